"""numba kernels of :mod:`faceretarget.geometry.procrustes` (compiled lazily, cached).

The one place for these jobs; plugins call them (through :mod:`~faceretarget.geometry.procrustes`
or, inside their own kernels, directly) rather than keep their own copies:

- :func:`kabsch`: weighted rigid or similarity Procrustes fits, frame by frame (the whole of
  :func:`~faceretarget.geometry.procrustes.fit_rigid`);
- :func:`transform_points`: apply or undo per-frame affine transforms on points (the whole of
  :func:`~faceretarget.geometry.procrustes.apply` and :func:`~faceretarget.geometry.procrustes.remove`
  in 3D).
"""

from __future__ import annotations

import numba as nb
import numpy as np

from ._nnls_kernels import FASTMATH

#: Most Jacobi sweeps of :func:`_rotation_3d` (a 4 x 4 converges in 4-6).
_JACOBI_SWEEPS = 30


@nb.njit(cache=True, nogil=True)
def transform_points(
    transforms: np.ndarray,
    points: np.ndarray,
    reference: np.ndarray,
    inverse: bool,
    out: np.ndarray,
) -> int:
    """Apply per-frame affine ``transforms (F, 4, 4) = [[A, t], [0, 1]]`` to ``points (F, P, 3)``
    (any float type) into ``out (F, P, 3)`` (float64; may alias ``points``):
    ``out[f, i] = A_f x_fi + t_f``, or with ``inverse`` ``A_f^-1 (x_fi - t_f)``; minus
    ``reference[i]`` when ``reference (P, 3)`` has rows (give ``(0, 3)`` for none).

    ``A^-1`` by cofactors (Cramer's rule), once a frame. NaN points stay NaN. Returns the
    index of the first frame whose ``A`` is singular (or NaN) when ``inverse``, else -1.
    Serial and ``nogil`` (memory-bound: faster than numba's thread pool on a few cores).
    """
    n_frames, n_points = points.shape[0], points.shape[1]
    subtract = reference.shape[0] > 0
    for f in range(n_frames):
        a = transforms[f]
        t0, t1, t2 = a[0, 3], a[1, 3], a[2, 3]
        if inverse:
            c00 = a[1, 1] * a[2, 2] - a[1, 2] * a[2, 1]
            c01 = a[0, 2] * a[2, 1] - a[0, 1] * a[2, 2]
            c02 = a[0, 1] * a[1, 2] - a[0, 2] * a[1, 1]
            det = a[0, 0] * c00 + a[1, 0] * c01 + a[2, 0] * c02
            if det == 0.0 or det != det:
                return f
            inv = 1.0 / det
            m00, m01, m02 = c00 * inv, c01 * inv, c02 * inv
            m10 = (a[1, 2] * a[2, 0] - a[1, 0] * a[2, 2]) * inv
            m11 = (a[0, 0] * a[2, 2] - a[0, 2] * a[2, 0]) * inv
            m12 = (a[0, 2] * a[1, 0] - a[0, 0] * a[1, 2]) * inv
            m20 = (a[1, 0] * a[2, 1] - a[1, 1] * a[2, 0]) * inv
            m21 = (a[0, 1] * a[2, 0] - a[0, 0] * a[2, 1]) * inv
            m22 = (a[0, 0] * a[1, 1] - a[0, 1] * a[1, 0]) * inv
            for i in range(n_points):
                d0 = points[f, i, 0] - t0
                d1 = points[f, i, 1] - t1
                d2 = points[f, i, 2] - t2
                x = m00 * d0 + m01 * d1 + m02 * d2
                y = m10 * d0 + m11 * d1 + m12 * d2
                z = m20 * d0 + m21 * d1 + m22 * d2
                if subtract:
                    x, y, z = x - reference[i, 0], y - reference[i, 1], z - reference[i, 2]
                out[f, i, 0], out[f, i, 1], out[f, i, 2] = x, y, z
        else:
            m00, m01, m02 = a[0, 0], a[0, 1], a[0, 2]
            m10, m11, m12 = a[1, 0], a[1, 1], a[1, 2]
            m20, m21, m22 = a[2, 0], a[2, 1], a[2, 2]
            for i in range(n_points):
                p0, p1, p2 = points[f, i, 0], points[f, i, 1], points[f, i, 2]
                x = m00 * p0 + m01 * p1 + m02 * p2 + t0
                y = m10 * p0 + m11 * p1 + m12 * p2 + t1
                z = m20 * p0 + m21 * p1 + m22 * p2 + t2
                if subtract:
                    x, y, z = x - reference[i, 0], y - reference[i, 1], z - reference[i, 2]
                out[f, i, 0], out[f, i, 1], out[f, i, 2] = x, y, z
    return -1


@nb.njit(cache=True, inline="always")
def _missing(x: np.ndarray, p: int, dim: int) -> bool:
    """Whether point ``p`` of ``x`` has a NaN coordinate (one test: a NaN makes the sum NaN)."""
    total = 0.0
    for d in range(dim):
        total += x[p, d]
    return np.isnan(total)


@nb.njit(cache=True)
def _rotation_2d(cov: np.ndarray, rot: np.ndarray) -> None:
    """The rotation ``R`` maximising ``tr(R^T cov)`` for a 2 x 2 ``cov``, in closed form:
    ``(cos, sin)`` along ``(cov00 + cov11, cov10 - cov01)`` (the identity for a zero one)."""
    a = cov[0, 0] + cov[1, 1]
    b = cov[1, 0] - cov[0, 1]
    norm = np.sqrt(a * a + b * b)
    c, s = (a / norm, b / norm) if norm > 0.0 else (1.0, 0.0)
    rot[0, 0], rot[0, 1], rot[1, 0], rot[1, 1] = c, -s, s, c


@nb.njit(cache=True)
def _rotation_3d(cov: np.ndarray, n: np.ndarray, v: np.ndarray, rot: np.ndarray) -> None:
    """The proper rotation ``R`` maximising ``tr(R^T cov)`` for a 3 x 3 ``cov = sum w x r^T``
    (Horn 1987, closed-form absolute orientation with unit quaternions): the unit
    eigenvector ``q`` of the largest eigenvalue of the symmetric 4 x 4 ``N`` built from
    ``S = cov^T`` (Horn's eq. for N), by cyclic Jacobi rotations; ``R = R(q)``. The same
    rotation as Kabsch's SVD with its reflection fix, without LAPACK in the kernel (which
    took 1-1.5 s more to compile in every fresh process). ``n``, ``v``: (4, 4) scratch."""
    sxx, sxy, sxz = cov[0, 0], cov[1, 0], cov[2, 0]
    syx, syy, syz = cov[0, 1], cov[1, 1], cov[2, 1]
    szx, szy, szz = cov[0, 2], cov[1, 2], cov[2, 2]
    n[0, 0], n[1, 1] = sxx + syy + szz, sxx - syy - szz
    n[2, 2], n[3, 3] = -sxx + syy - szz, -sxx - syy + szz
    n[0, 1] = n[1, 0] = syz - szy
    n[0, 2] = n[2, 0] = szx - sxz
    n[0, 3] = n[3, 0] = sxy - syx
    n[1, 2] = n[2, 1] = sxy + syx
    n[1, 3] = n[3, 1] = szx + sxz
    n[2, 3] = n[3, 2] = syz + szy
    total = 0.0
    for i in range(4):
        for j in range(4):
            v[i, j] = 1.0 if i == j else 0.0
            total += n[i, j] * n[i, j]
    for _ in range(_JACOBI_SWEEPS):
        off = 0.0
        for p in range(3):
            for q in range(p + 1, 4):
                off += n[p, q] * n[p, q]
        if off <= 1e-32 * total:
            break
        for p in range(3):
            for q in range(p + 1, 4):
                apq = n[p, q]
                if apq == 0.0:
                    continue
                theta = (n[q, q] - n[p, p]) / (2.0 * apq)  # Jacobi rotation zeroing n[p, q]
                t = 1.0 / (abs(theta) + np.sqrt(theta * theta + 1.0))
                if theta < 0.0:
                    t = -t
                c = 1.0 / np.sqrt(t * t + 1.0)
                s = t * c
                for k in range(4):
                    akp, akq = n[k, p], n[k, q]
                    n[k, p], n[k, q] = c * akp - s * akq, s * akp + c * akq
                for k in range(4):
                    apk, aqk = n[p, k], n[q, k]
                    n[p, k], n[q, k] = c * apk - s * aqk, s * apk + c * aqk
                for k in range(4):
                    vkp, vkq = v[k, p], v[k, q]
                    v[k, p], v[k, q] = c * vkp - s * vkq, s * vkp + c * vkq
    best = 0
    for i in range(1, 4):
        if n[i, i] > n[best, best]:
            best = i
    q0, q1, q2, q3 = v[0, best], v[1, best], v[2, best], v[3, best]
    norm = np.sqrt(q0 * q0 + q1 * q1 + q2 * q2 + q3 * q3)
    q0, q1, q2, q3 = q0 / norm, q1 / norm, q2 / norm, q3 / norm
    rot[0, 0] = q0 * q0 + q1 * q1 - q2 * q2 - q3 * q3
    rot[0, 1] = 2.0 * (q1 * q2 - q0 * q3)
    rot[0, 2] = 2.0 * (q1 * q3 + q0 * q2)
    rot[1, 0] = 2.0 * (q2 * q1 + q0 * q3)
    rot[1, 1] = q0 * q0 - q1 * q1 + q2 * q2 - q3 * q3
    rot[1, 2] = 2.0 * (q2 * q3 - q0 * q1)
    rot[2, 0] = 2.0 * (q3 * q1 - q0 * q2)
    rot[2, 1] = 2.0 * (q3 * q2 + q0 * q1)
    rot[2, 2] = q0 * q0 - q1 * q1 - q2 * q2 + q3 * q3


@nb.njit(cache=True, fastmath=FASTMATH)
def kabsch(
    reference: np.ndarray,
    frames: np.ndarray,
    weights: np.ndarray,
    with_scale: bool,
    min_points: int,
    rotation: np.ndarray,
    translation: np.ndarray,
    scale: np.ndarray,
) -> int:
    """Weighted rigid (or similarity) Procrustes of a reference onto each frame (Kabsch /
    Umeyama): ``frame ~ s R ref + t`` with ``R`` a proper rotation, frame by frame (a frame
    alone gives the same numbers as inside a batch). ``R`` maximises ``tr(R^T cov)`` for the
    weighted cross-covariance ``cov``: :func:`_rotation_2d` or :func:`_rotation_3d`, the
    rotation of the SVD with its reflection fix; ``s = tr(R^T cov) / var(ref)``.

    ``reference (R, N, D)`` and ``weights (W, N)`` (non-negative): one for every frame (R = 1,
    W = 1) or one a frame (R = F, W = F); ``frames (F, N, D)``, a point with a NaN
    coordinate missing. Writes ``rotation (F, D, D)``, ``translation (F, D)`` and ``scale
    (F,)`` (one unless ``with_scale``). A frame with fewer than ``min_points`` present points
    of non-zero weight gets the identity; returns the first such frame, or -1.
    """
    n_frames, n_points, dim = frames.shape
    cov = np.empty((dim, dim))
    rot = np.empty((dim, dim))
    quartic = np.empty((4, 4))
    vecs = np.empty((4, 4))
    mu_r = np.empty(dim)
    mu_x = np.empty(dim)
    first_skipped = -1
    for f in range(n_frames):
        ref = reference[f if reference.shape[0] > 1 else 0]
        w_f = weights[f if weights.shape[0] > 1 else 0]
        x = frames[f]
        total = 0.0
        count = 0
        for d in range(dim):
            mu_r[d] = 0.0
            mu_x[d] = 0.0
        for p in range(n_points):
            if _missing(x, p, dim):
                continue
            w = w_f[p]
            count += w != 0.0
            total += w
            for d in range(dim):
                mu_r[d] += w * ref[p, d]
                mu_x[d] += w * x[p, d]
        if count < min_points or total <= 0.0:  # the identity
            rotation[f] = 0.0
            for d in range(dim):
                rotation[f, d, d] = 1.0
                translation[f, d] = 0.0
            scale[f] = 1.0
            if first_skipped < 0:
                first_skipped = f
            continue
        for d in range(dim):
            mu_r[d] /= total
            mu_x[d] /= total
        cov[:] = 0.0
        var_r = 0.0
        for p in range(n_points):
            if _missing(x, p, dim):
                continue
            w = w_f[p] / total
            for i in range(dim):
                bi = x[p, i] - mu_x[i]
                for j in range(dim):
                    cov[i, j] += w * bi * (ref[p, j] - mu_r[j])
            for j in range(dim):
                a = ref[p, j] - mu_r[j]
                var_r += w * a * a
        if dim == 2:
            _rotation_2d(cov, rot)
        else:
            _rotation_3d(cov, quartic, vecs, rot)
        s = 1.0
        if with_scale:
            tr = 0.0  # tr(R^T cov): the sum of the singular values, the last one signed
            for i in range(dim):
                for j in range(dim):
                    tr += rot[i, j] * cov[i, j]
            s = tr / max(var_r, 1e-300)
        scale[f] = s
        for i in range(dim):
            t = 0.0
            for j in range(dim):
                rotation[f, i, j] = rot[i, j]
                t += rot[i, j] * mu_r[j]
            translation[f, i] = mu_x[i] - s * t
    return first_skipped
