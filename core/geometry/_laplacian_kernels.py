"""numba kernels for Laplacians, Taubin smoothing and per-vertex frames.

Compiled lazily (imported inside the functions that use them) and cached. No kernel
uses ``fastmath`` or a parallel reduction, so results do not depend on the number of
threads or on how many frames are batched together.
"""
from __future__ import annotations

import numba as nb
import numpy as np


@nb.njit(cache=True)
def fill_cotangent(vertices, triangles, slots, data):
    """Refill the values of a cotangent Laplacian whose CSR pattern is fixed.

    vertices : (V, 3) float64; triangles : (T, 3) int64
    slots : (T, 3, 4) int64 positions in ``data`` of (i, j), (j, i), (i, i), (j, j) for the
        edge (i, j) opposite corner k of triangle t
    data : (nnz,) float64, overwritten. L_ij = -(cot a + cot b) / 2, L_ii = -sum_j L_ij.
    """
    data[:] = 0.0
    for t in range(triangles.shape[0]):
        for k in range(3):
            c = triangles[t, k]
            i = triangles[t, (k + 1) % 3]
            j = triangles[t, (k + 2) % 3]
            ux = vertices[i, 0] - vertices[c, 0]
            uy = vertices[i, 1] - vertices[c, 1]
            uz = vertices[i, 2] - vertices[c, 2]
            vx = vertices[j, 0] - vertices[c, 0]
            vy = vertices[j, 1] - vertices[c, 1]
            vz = vertices[j, 2] - vertices[c, 2]
            dot = ux * vx + uy * vy + uz * vz
            cx = uy * vz - uz * vy
            cy = uz * vx - ux * vz
            cz = ux * vy - uy * vx
            half_cot = 0.5 * dot / np.sqrt(cx * cx + cy * cy + cz * cz)
            data[slots[t, k, 0]] -= half_cot
            data[slots[t, k, 1]] -= half_cot
            data[slots[t, k, 2]] += half_cot
            data[slots[t, k, 3]] += half_cot


@nb.njit(cache=True)
def _umbrella_step(indptr, indices, weights, x, out, lam):
    """out = x + lam * (W x - x) for a row-stochastic W (CSR)."""
    n, c = x.shape
    keep = 1.0 - lam
    for i in range(n):
        for k in range(c):
            out[i, k] = keep * x[i, k]
        for p in range(indptr[i], indptr[i + 1]):
            j = indices[p]
            w = lam * weights[p]
            for k in range(c):
                out[i, k] += w * x[j, k]


@nb.njit(parallel=True, cache=True)
def taubin(indptr, indices, weights, x, iterations, lam, mu, n_blocks):
    """Taubin lambda|mu smoothing of the columns of ``x : (V, C)`` in place.

    ``iterations`` pairs of a shrinking step (lam > 0) and an inflating step (mu < 0).
    The columns are split into ``n_blocks`` blocks, each smoothed through all iterations
    by one thread on a contiguous copy (one parallel region, no barrier per step: a
    barrier per step stalls badly on a busy machine).
    """
    n, c = x.shape
    lam_t = x.dtype.type(lam)
    mu_t = x.dtype.type(mu)
    w = weights.astype(x.dtype)
    step = (c + n_blocks - 1) // n_blocks
    for b in nb.prange(n_blocks):
        c0 = b * step
        c1 = min(c, c0 + step)
        if c1 <= c0:
            continue
        a = np.ascontiguousarray(x[:, c0:c1])
        buf = np.empty_like(a)
        for _ in range(iterations):
            _umbrella_step(indptr, indices, w, a, buf, lam_t)
            _umbrella_step(indptr, indices, w, buf, a, mu_t)
        x[:, c0:c1] = a


@nb.njit(cache=True)
def _face_cross(points, f, triangles, cross):
    """Unnormalised face normals (edge cross products) of mesh ``f`` into ``cross (T, 3)``."""
    for t in range(triangles.shape[0]):
        a = triangles[t, 0]
        b = triangles[t, 1]
        c = triangles[t, 2]
        ux = points[f, b, 0] - points[f, a, 0]
        uy = points[f, b, 1] - points[f, a, 1]
        uz = points[f, b, 2] - points[f, a, 2]
        wx = points[f, c, 0] - points[f, a, 0]
        wy = points[f, c, 1] - points[f, a, 1]
        wz = points[f, c, 2] - points[f, a, 2]
        cross[t, 0] = uy * wz - uz * wy
        cross[t, 1] = uz * wx - ux * wz
        cross[t, 2] = ux * wy - uy * wx


@nb.njit(cache=True, inline="always")
def _vertex_frame(points, f, v, cross, vt_ptr, vt_tri, neighbors):
    """Frame of vertex ``v`` in mesh ``f``: (tangent, bitangent, normal) as 9 numbers + ok."""
    nx = 0.0
    ny = 0.0
    nz = 0.0
    for p in range(vt_ptr[v], vt_ptr[v + 1]):
        t = vt_tri[p]
        nx += cross[t, 0]
        ny += cross[t, 1]
        nz += cross[t, 2]
    norm = np.sqrt(nx * nx + ny * ny + nz * nz)
    tx = 0.0
    ty = 0.0
    tz = 0.0
    ok = False
    if norm > 0.0:
        nx /= norm
        ny /= norm
        nz /= norm
        for q in range(2):
            j = neighbors[v, q]
            ex = points[f, j, 0] - points[f, v, 0]
            ey = points[f, j, 1] - points[f, v, 1]
            ez = points[f, j, 2] - points[f, v, 2]
            elen = np.sqrt(ex * ex + ey * ey + ez * ez)
            d = ex * nx + ey * ny + ez * nz
            tx = ex - d * nx
            ty = ey - d * ny
            tz = ez - d * nz
            tlen = np.sqrt(tx * tx + ty * ty + tz * tz)
            if tlen > 1e-6 * elen:
                tx /= tlen
                ty /= tlen
                tz /= tlen
                ok = True
                break
    if not ok:
        return 1.0, 0.0, 0.0, 0.0, 1.0, 0.0, 0.0, 0.0, 1.0, False
    bx = ny * tz - nz * ty
    by = nz * tx - nx * tz
    bz = nx * ty - ny * tx
    return tx, ty, tz, bx, by, bz, nx, ny, nz, True


@nb.njit(parallel=True, cache=True)
def vertex_frames(points, triangles, vt_ptr, vt_tri, neighbors, out):
    """Per-vertex orthonormal frames of a batch of meshes.

    points : (F, V, 3) float; triangles : (T, 3) int64
    vt_ptr, vt_tri : CSR list of the triangles around each vertex
    neighbors : (V, 2) int64 preferred and fallback neighbour for the tangent
    out : (F, V, 3, 3) float64, columns (tangent, bitangent, normal)

    The normal is the area-weighted average of the incident face normals; the tangent is
    the edge to the preferred neighbour projected onto the tangent plane (the fallback
    neighbour when that projection is shorter than 1e-6 of the edge). Returns, per mesh,
    the number of vertices whose normal or tangent is undefined (identity frame there).
    """
    n_frames, n_vertices = points.shape[0], points.shape[1]
    bad = np.zeros(n_frames, dtype=np.int64)
    for f in nb.prange(n_frames):
        cross = np.empty((triangles.shape[0], 3))
        _face_cross(points, f, triangles, cross)
        count = 0
        for v in range(n_vertices):
            tx, ty, tz, bx, by, bz, nx, ny, nz, ok = _vertex_frame(points, f, v, cross, vt_ptr, vt_tri, neighbors)
            if not ok:
                count += 1
            out[f, v, 0, 0] = tx
            out[f, v, 1, 0] = ty
            out[f, v, 2, 0] = tz
            out[f, v, 0, 1] = bx
            out[f, v, 1, 1] = by
            out[f, v, 2, 1] = bz
            out[f, v, 0, 2] = nx
            out[f, v, 1, 2] = ny
            out[f, v, 2, 2] = nz
        bad[f] = count
    return bad


@nb.njit(parallel=True, cache=True)
def frame_apply(points, triangles, vt_ptr, vt_tri, neighbors, vectors, out, inverse):
    """Apply each vertex's frame (computed on the fly) to ``vectors : (F, V, 3)``.

    ``inverse``: world -> local (``F^T d``), else local -> world (``F c``). Same frames as
    :func:`vertex_frames` without storing them. Returns the per-mesh count of undefined frames.
    """
    n_frames, n_vertices = points.shape[0], points.shape[1]
    bad = np.zeros(n_frames, dtype=np.int64)
    for f in nb.prange(n_frames):
        cross = np.empty((triangles.shape[0], 3))
        _face_cross(points, f, triangles, cross)
        count = 0
        for v in range(n_vertices):
            tx, ty, tz, bx, by, bz, nx, ny, nz, ok = _vertex_frame(points, f, v, cross, vt_ptr, vt_tri, neighbors)
            if not ok:
                count += 1
            a = vectors[f, v, 0]
            b = vectors[f, v, 1]
            c = vectors[f, v, 2]
            if inverse:
                out[f, v, 0] = tx * a + ty * b + tz * c
                out[f, v, 1] = bx * a + by * b + bz * c
                out[f, v, 2] = nx * a + ny * b + nz * c
            else:
                out[f, v, 0] = tx * a + bx * b + nx * c
                out[f, v, 1] = ty * a + by * b + ny * c
                out[f, v, 2] = tz * a + bz * b + nz * c
        bad[f] = count
    return bad
