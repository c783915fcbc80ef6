"""numba kernels for deformation gradients (compiled lazily, cached)."""

from __future__ import annotations

import numba as nb
import numpy as np


@nb.njit(parallel=True, cache=True)
def gradient_columns(
    points: np.ndarray, triangles: np.ndarray, inv_ref: np.ndarray, out: np.ndarray, bad: np.ndarray
) -> None:
    """Deformation gradients of a batch of meshes, laid out as least-squares columns.

    points : (C, V, 3) deformed meshes; triangles : (T, 3); inv_ref : (T, 3, 3) inverse
    reference frames ``V^-1``. Writes ``out[3j + c, 3f + d] = Q_fj[d, c]`` with
    ``Q = [v2 - v1, v3 - v1, n / sqrt|n|] V^-1`` (Sumner & Popovic eq. 1-4), and
    ``bad[f, j] = True`` where triangle ``j`` of mesh ``f`` has (near) zero area
    (``|n| <= 1e-12 (|e1|^2 + |e2|^2)``).
    """
    n_frames = points.shape[0]
    n_tri = triangles.shape[0]
    for i in nb.prange(n_frames * n_tri):
        f = i // n_tri
        j = i - f * n_tri
        a = triangles[j, 0]
        b = triangles[j, 1]
        c = triangles[j, 2]
        e = np.empty((3, 3))
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


@nb.njit(cache=True)
def inverse_frames(vertices: np.ndarray, triangles: np.ndarray, out: np.ndarray) -> None:
    """``out[j] = V_j^-1`` for the frames ``V = [v2 - v1, v3 - v1, n / sqrt|n|]`` (columns) of
    ``vertices : (V, 3)``, ``triangles : (T, 3)``, by the adjugate: the rows of ``V^-1`` are
    ``(e2 x c, c x e1, e1 x e2) / det V``. Zero-area triangles give non-finite rows (the
    caller checks the triangles first)."""
    for j in range(triangles.shape[0]):
        a = triangles[j, 0]
        b = triangles[j, 1]
        c = triangles[j, 2]
        e1x = vertices[b, 0] - vertices[a, 0]
        e1y = vertices[b, 1] - vertices[a, 1]
        e1z = vertices[b, 2] - vertices[a, 2]
        e2x = vertices[c, 0] - vertices[a, 0]
        e2y = vertices[c, 1] - vertices[a, 1]
        e2z = vertices[c, 2] - vertices[a, 2]
        nx = e1y * e2z - e1z * e2y
        ny = e1z * e2x - e1x * e2z
        nz = e1x * e2y - e1y * e2x
        s = np.sqrt(np.sqrt(nx * nx + ny * ny + nz * nz))
        cx = nx / s
        cy = ny / s
        cz = nz / s
        # rows: e2 x c, c x e1, e1 x e2 (= n), over det = e1 . (e2 x c)
        r0x = e2y * cz - e2z * cy
        r0y = e2z * cx - e2x * cz
        r0z = e2x * cy - e2y * cx
        det = e1x * r0x + e1y * r0y + e1z * r0z
        out[j, 0, 0] = r0x / det
        out[j, 0, 1] = r0y / det
        out[j, 0, 2] = r0z / det
        out[j, 1, 0] = (cy * e1z - cz * e1y) / det
        out[j, 1, 1] = (cz * e1x - cx * e1z) / det
        out[j, 1, 2] = (cx * e1y - cy * e1x) / det
        out[j, 2, 0] = nx / det
        out[j, 2, 1] = ny / det
        out[j, 2, 2] = nz / det
