"""numba kernels for deformation gradients (compiled lazily, cached)."""

from __future__ import annotations

import numba as nb
import numpy as np


@nb.njit(cache=True, nogil=True)
def gradient_columns(
    points: np.ndarray,
    triangles: np.ndarray,
    inv_ref: np.ndarray,
    out: np.ndarray,
    bad: np.ndarray,
    start: int,
    stop: int,
) -> None:
    """Deformation gradients of a batch of meshes, laid out as least-squares columns.

    points : (C, V, 3) deformed meshes; triangles : (T, 3); inv_ref : (T, 3, 3) inverse
    reference frames ``V^-1``. Writes ``out[3j + c, 3f + d] = Q_fj[d, c]`` with
    ``Q = [v2 - v1, v3 - v1, n / sqrt|n|] V^-1`` (Sumner & Popovic eq. 1-4), and
    ``bad[f, j] = True`` where triangle ``j`` of mesh ``f`` has (near) zero area
    (``|n| <= 1e-12 (|e1|^2 + |e2|^2)``), for the items ``i = f T + j`` in ``start:stop``
    (serial, ``nogil``: callers run blocks of items on threads).
    """
    n_tri = triangles.shape[0]
    e = np.empty((3, 3))
    for i in range(start, stop):
        f = i // n_tri
        j = i - f * n_tri
        a = triangles[j, 0]
        b = triangles[j, 1]
        c = triangles[j, 2]
        scale = 0.0
        for d in range(3):
            e[d, 0] = points[f, b, d] - points[f, a, d]
            e[d, 1] = points[f, c, d] - points[f, a, d]
            scale += e[d, 0] * e[d, 0] + e[d, 1] * e[d, 1]
        nx = e[1, 0] * e[2, 1] - e[2, 0] * e[1, 1]
        ny = e[2, 0] * e[0, 1] - e[0, 0] * e[2, 1]
        nz = e[0, 0] * e[1, 1] - e[1, 0] * e[0, 1]
        nn = np.sqrt(nx * nx + ny * ny + nz * nz)
        if nn <= 1e-12 * scale:
            bad[f, j] = True
            nn = 1.0
        s = 1.0 / np.sqrt(nn)
        e[0, 2] = nx * s
        e[1, 2] = ny * s
        e[2, 2] = nz * s
        for col in range(3):
            for d in range(3):
                out[3 * j + col, 3 * f + d] = (
                    e[d, 0] * inv_ref[j, 0, col]
                    + e[d, 1] * inv_ref[j, 1, col]
                    + e[d, 2] * inv_ref[j, 2, col]
                )
