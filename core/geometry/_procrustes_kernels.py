"""numba kernel of :mod:`faceretarget.geometry.procrustes` (compiled lazily, cached)."""

from __future__ import annotations

import numba as nb


@nb.njit(cache=True)
def remove_affine(transforms, points, reference, out):
    """``out[f, i] = A_f^-1 (x_fi - t_f) - reference[i]`` for ``transforms (F, 4, 4) = [[A, t], [0, 1]]``.

    ``points (F, P, 3)``, ``reference (P, 3)`` (zeros to get the positions themselves), ``out
    (F, P, 3)`` (may alias ``points``). ``A^-1`` by cofactors (Cramer's rule), once a frame;
    NaN points stay NaN. Returns the index of the first frame whose ``A`` is singular, or -1.
    """
    n_frames, n_points = points.shape[0], points.shape[1]
    for f in range(n_frames):
        a = transforms[f]
        c00 = a[1, 1] * a[2, 2] - a[1, 2] * a[2, 1]
        c01 = a[0, 2] * a[2, 1] - a[0, 1] * a[2, 2]
        c02 = a[0, 1] * a[1, 2] - a[0, 2] * a[1, 1]
        det = a[0, 0] * c00 + a[1, 0] * c01 + a[2, 0] * c02
        if det == 0.0 or det != det:
            return f
        inv = 1.0 / det
        i00, i01, i02 = c00 * inv, c01 * inv, c02 * inv
        i10 = (a[1, 2] * a[2, 0] - a[1, 0] * a[2, 2]) * inv
        i11 = (a[0, 0] * a[2, 2] - a[0, 2] * a[2, 0]) * inv
        i12 = (a[0, 2] * a[1, 0] - a[0, 0] * a[1, 2]) * inv
        i20 = (a[1, 0] * a[2, 1] - a[1, 1] * a[2, 0]) * inv
        i21 = (a[0, 1] * a[2, 0] - a[0, 0] * a[2, 1]) * inv
        i22 = (a[0, 0] * a[1, 1] - a[0, 1] * a[1, 0]) * inv
        t0, t1, t2 = a[0, 3], a[1, 3], a[2, 3]
        for i in range(n_points):
            d0 = points[f, i, 0] - t0
            d1 = points[f, i, 1] - t1
            d2 = points[f, i, 2] - t2
            out[f, i, 0] = i00 * d0 + i01 * d1 + i02 * d2 - reference[i, 0]
            out[f, i, 1] = i10 * d0 + i11 * d1 + i12 * d2 - reference[i, 1]
            out[f, i, 2] = i20 * d0 + i21 * d1 + i22 * d2 - reference[i, 2]
    return -1
