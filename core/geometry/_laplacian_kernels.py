"""numba kernels for Laplacians, Taubin smoothing and per-vertex frames.

Compiled lazily (imported inside the functions that use them) and cached. The kernels are
serial and ``nogil``: callers run blocks of columns or frames side by side on Python
threads (``_threads.in_blocks``). No kernel uses ``fastmath`` or a reduction across
blocks, so results do not depend on the number of threads or on how many frames are
batched together.
"""

from __future__ import annotations

import numba as nb
import numpy as np

from ._mesh_ops_kernels import vertex_normal_sums

#: Columns per block of :func:`taubin_frames` are a multiple of this when a block has more
#: (whole SIMD vectors: a block of 21 float32 columns ran 1.6x slower per column than one
#: of 24).
SIMD_COLUMNS = 8


@nb.njit(cache=True)
def fill_cotangent(
    vertices: np.ndarray, triangles: np.ndarray, slots: np.ndarray, data: np.ndarray
) -> None:
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
def _umbrella_step(
    indptr: np.ndarray,
    indices: np.ndarray,
    weights: np.ndarray,
    x: np.ndarray,
    out: np.ndarray,
    lam: float,
) -> None:
    """out = x + lam * (W x - x) for a row-stochastic W (CSR)."""
    n, c = x.shape
    keep = 1.0 - lam
    if c == 3:  # one mesh a block: the same operations, unrolled (a loop of 3 is scalar)
        for i in range(n):
            out[i, 0] = keep * x[i, 0]
            out[i, 1] = keep * x[i, 1]
            out[i, 2] = keep * x[i, 2]
            for p in range(indptr[i], indptr[i + 1]):
                j = indices[p]
                w = lam * weights[p]
                out[i, 0] += w * x[j, 0]
                out[i, 1] += w * x[j, 1]
                out[i, 2] += w * x[j, 2]
        return
    for i in range(n):
        for k in range(c):
            out[i, k] = keep * x[i, k]
        for p in range(indptr[i], indptr[i + 1]):
            j = indices[p]
            w = lam * weights[p]
            for k in range(c):
                out[i, k] += w * x[j, k]


@nb.njit(cache=True, nogil=True)
def taubin_frames(
    indptr: np.ndarray,
    indices: np.ndarray,
    weights: np.ndarray,
    points: np.ndarray,
    out: np.ndarray,
    iterations: int,
    lam: float,
    mu: float,
    c0: int,
    c1: int,
    proto: np.ndarray,
) -> None:
    """Taubin smoothing of meshes ``points : (C, V, 3)`` into ``out`` (float64, same shape),
    for the coordinate columns ``c0:c1`` of the ``3C`` (column ``k`` is coordinate ``k % 3``
    of mesh ``k // 3``).

    The block is gathered into a contiguous ``(V, c1 - c0)`` array of ``proto.dtype``
    (float32 halves the memory traffic), every iteration runs on it and the result is
    scattered: no per-step barrier, no transposed copies outside the kernel.
    """
    n = points.shape[1]
    if c1 <= c0:
        return
    w = weights.astype(proto.dtype)
    lam_t = proto.dtype.type(lam)
    mu_t = proto.dtype.type(mu)
    a = np.empty((n, c1 - c0), dtype=proto.dtype)
    for i in range(n):
        for k in range(c0, c1):
            a[i, k - c0] = points[k // 3, i, k % 3]
    buf = np.empty_like(a)
    for _ in range(iterations):
        _umbrella_step(indptr, indices, w, a, buf, lam_t)
        _umbrella_step(indptr, indices, w, buf, a, mu_t)
    for i in range(n):
        for k in range(c0, c1):
            out[k // 3, i, k % 3] = a[i, k - c0]


@nb.njit(cache=True, inline="always")
def _vertex_frame(
    points: np.ndarray,
    f: int,
    v: int,
    normals: np.ndarray,
    neighbors: np.ndarray,
) -> tuple[float, float, float, float, float, float, float, float, float, bool]:
    """Frame of vertex ``v`` in mesh ``f`` (``normals``: the area-weighted sums of
    :func:`._mesh_ops_kernels.vertex_normal_sums`):
    (tangent, bitangent, normal) as 9 numbers + ok."""
    nx = normals[v, 0]
    ny = normals[v, 1]
    nz = normals[v, 2]
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


@nb.njit(cache=True, inline="always")
def _rotate(
    tx: float,
    ty: float,
    tz: float,
    bx: float,
    by: float,
    bz: float,
    nx: float,
    ny: float,
    nz: float,
    a: float,
    b: float,
    c: float,
    inverse: bool,
) -> tuple[float, float, float]:
    """``F^T (a, b, c)`` (``inverse``: world -> local) or ``F (a, b, c)`` for ``F = [t, b, n]``."""
    if inverse:
        return tx * a + ty * b + tz * c, bx * a + by * b + bz * c, nx * a + ny * b + nz * c
    return tx * a + bx * b + nx * c, ty * a + by * b + ny * c, tz * a + bz * b + nz * c


@nb.njit(cache=True, nogil=True)
def vertex_frames(
    points: np.ndarray,
    triangles: np.ndarray,
    neighbors: np.ndarray,
    out: np.ndarray,
) -> np.ndarray:
    """Per-vertex orthonormal frames of a batch of meshes.

    points : (F, V, 3) float; triangles : (T, 3) int64
    neighbors : (V, 2) int64 preferred and fallback neighbour for the tangent
    out : (F, V, 3, 3) float64, columns (tangent, bitangent, normal)

    The normal is the area-weighted average of the incident face normals; the tangent is
    the edge to the preferred neighbour projected onto the tangent plane (the fallback
    neighbour when that projection is shorter than 1e-6 of the edge). Returns, per mesh,
    the number of vertices whose normal or tangent is undefined (identity frame there).
    """
    n_frames, n_vertices = points.shape[0], points.shape[1]
    bad = np.zeros(n_frames, dtype=np.int64)
    for f in range(n_frames):
        normals = np.empty((n_vertices, 3))
        vertex_normal_sums(points[f], triangles, normals)
        count = 0
        for v in range(n_vertices):
            tx, ty, tz, bx, by, bz, nx, ny, nz, ok = _vertex_frame(points, f, v, normals, neighbors)
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


@nb.njit(cache=True, nogil=True)
def frame_apply(
    points: np.ndarray,
    triangles: np.ndarray,
    neighbors: np.ndarray,
    vectors: np.ndarray,
    out: np.ndarray,
    inverse: bool,
    m_ptr: np.ndarray,
    m_ind: np.ndarray,
    m_val: np.ndarray,
) -> np.ndarray:
    """Apply each vertex's frame (computed on the fly from ``points``) to per-vertex vectors.

    ``inverse``: world -> local (``F^T d``), else local -> world (``F c``). The vectors are
    ``vectors : (F, V, 3)`` as given, or, when a CSR matrix ``M`` is passed (``m_ptr`` of
    length V + 1), ``M (vectors - points)`` computed on the fly: with ``points`` a smooth
    mesh and ``vectors`` the detailed one, this is the Laplacian coating
    ``F(smooth)^T M (detailed - smooth)`` in one pass. Same frames as
    :func:`vertex_frames` without storing them; returns the per-mesh count of undefined frames.
    """
    n_frames, n_vertices = points.shape[0], points.shape[1]
    matrix = m_ptr.shape[0] == n_vertices + 1
    bad = np.zeros(n_frames, dtype=np.int64)
    for f in range(n_frames):
        normals = np.empty((n_vertices, 3))
        vertex_normal_sums(points[f], triangles, normals)
        count = 0
        for v in range(n_vertices):
            tx, ty, tz, bx, by, bz, nx, ny, nz, ok = _vertex_frame(points, f, v, normals, neighbors)
            if not ok:
                count += 1
            if matrix:
                a = 0.0
                b = 0.0
                c = 0.0
                for p in range(m_ptr[v], m_ptr[v + 1]):
                    j = m_ind[p]
                    w = m_val[p]
                    a += w * (vectors[f, j, 0] - points[f, j, 0])
                    b += w * (vectors[f, j, 1] - points[f, j, 1])
                    c += w * (vectors[f, j, 2] - points[f, j, 2])
            else:
                a = vectors[f, v, 0]
                b = vectors[f, v, 1]
                c = vectors[f, v, 2]
            out[f, v, 0], out[f, v, 1], out[f, v, 2] = _rotate(
                tx, ty, tz, bx, by, bz, nx, ny, nz, a, b, c, inverse
            )
        bad[f] = count
    return bad


@nb.njit(cache=True)
def best_two(src: np.ndarray, dst: np.ndarray, score: np.ndarray, out: np.ndarray) -> None:
    """For each vertex ``i``, ``out[i] = (best, second)``: the ``dst`` of its two directed
    edges ``src == i`` ranked first by ``score`` (highest first, ties: lower ``dst``); the
    best twice for a vertex of one edge. The order of ``np.lexsort((dst, -score, src))``
    in one pass, for finite scores (the caller checks them); every vertex must have an edge."""
    n = out.shape[0]
    top = np.full(n, -np.inf)
    nxt = np.full(n, -np.inf)
    out[:, 0] = -1
    out[:, 1] = -1
    for e in range(src.shape[0]):
        i, j, s = src[e], dst[e], score[e]
        b = out[i, 0]
        if b < 0 or s > top[i] or (s == top[i] and j < b):
            out[i, 1] = b
            nxt[i] = top[i]
            out[i, 0] = j
            top[i] = s
        elif out[i, 1] < 0 or s > nxt[i] or (s == nxt[i] and j < out[i, 1]):
            out[i, 1] = j
            nxt[i] = s
    for i in range(n):
        if out[i, 1] < 0:
            out[i, 1] = out[i, 0]
