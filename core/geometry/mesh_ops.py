"""Basic per-triangle and per-vertex quantities of a triangle mesh (vectorized numpy).

All functions take ``vertices : (V, 3) float64`` and ``triangles : (T, 3) int``.
"""

from __future__ import annotations

import hashlib
import threading
from collections import OrderedDict

import numpy as np
import scipy.sparse as sp

from .._validate import readonly
from ..errors import ShapeError


def translated(points: np.ndarray, offset: np.ndarray) -> np.ndarray:
    """``points + offset`` for ``points : (..., V, 3)`` or ``(3,)`` and ``offset : (3,)`` -> float64, same shape.

    The same numbers as numpy's broadcast, in one pass over rows of ``3 V`` (the offset tiled
    once): broadcasting a ``(3,)`` vector runs an inner loop of three elements, ~3x slower
    on a chunk of 32 frames at 80K vertices.
    """
    p = np.asarray(points, dtype=np.float64)
    o = np.asarray(offset, dtype=np.float64)
    if p.shape[-1:] != (3,) or o.shape != (3,):
        raise ShapeError(
            f"translated: points must be (..., V, 3) or (3,) and offset (3,), got {p.shape} and {o.shape}"
        )
    if p.ndim == 1 or p.size == 0:
        return p + o
    rows = p.reshape(-1, p.shape[-2] * 3)
    return (rows + np.tile(o, p.shape[-2])).reshape(p.shape)


def triangle_cross(vertices: np.ndarray, triangles: np.ndarray) -> np.ndarray:
    """(T, 3) cross products (v1 - v0) x (v2 - v0); length = twice the area."""
    v = np.asarray(vertices, dtype=np.float64)
    a, b, c = v[triangles[:, 0]], v[triangles[:, 1]], v[triangles[:, 2]]
    return np.cross(b - a, c - a)


def face_areas(vertices: np.ndarray, triangles: np.ndarray) -> np.ndarray:
    """(T,) triangle areas."""
    return 0.5 * np.linalg.norm(triangle_cross(vertices, triangles), axis=1)


def unit_rows(vectors: np.ndarray) -> np.ndarray:
    """(N, 3) rows scaled to unit length; zero rows stay zero. Each row is first divided by
    its largest component, so tiny (subnormal) or huge rows come out unit length too."""
    scale = np.abs(vectors).max(axis=1, keepdims=True)
    scaled = np.divide(vectors, scale, out=np.zeros_like(vectors), where=scale > 0)
    norm = np.linalg.norm(scaled, axis=1, keepdims=True)
    return np.divide(scaled, norm, out=np.zeros_like(scaled), where=norm > 0)


def face_normals(vertices: np.ndarray, triangles: np.ndarray) -> np.ndarray:
    """(T, 3) unit triangle normals; zero rows for zero-area triangles."""
    return unit_rows(triangle_cross(vertices, triangles))


def vertex_normals(
    vertices: np.ndarray, triangles: np.ndarray, out: np.ndarray | None = None
) -> np.ndarray:
    """(V, 3) area-weighted unit vertex normals: each vertex's sum of its triangles'
    :func:`triangle_cross` products made unit length (as :func:`unit_rows` does, at any
    scale); zero for isolated vertices and for NaN or infinite sums.

    ``out``: a C-contiguous float64 ``(V, 3)`` array to fill and return (no allocation; a
    per-frame caller reuses it). One numba kernel (``_mesh_ops_kernels.vertex_normals``),
    which kernels and per-frame loops may also call directly on validated arrays.
    """
    from ._mesh_ops_kernels import vertex_normals as kernel

    v = np.ascontiguousarray(vertices, dtype=np.float64)
    t = np.asarray(triangles)
    if t.dtype.kind not in "iu":
        t = t.astype(np.int64)
    t = np.ascontiguousarray(t)
    if v.ndim != 2 or v.shape[1] != 3 or t.ndim != 2 or t.shape[1] != 3:
        raise ShapeError(
            f"vertex_normals: expected vertices (V, 3) and triangles (T, 3), got {v.shape} and {t.shape}"
        )
    n = v.shape[0]
    if t.size and (t.min() < -n or t.max() >= n):
        raise IndexError(f"vertex_normals: a triangle index is outside the {n} vertices")
    if out is None:
        out = np.empty((n, 3))
    elif out.shape != (n, 3) or out.dtype != np.float64 or not out.flags.c_contiguous:
        raise ShapeError(
            f"vertex_normals: out must be a C-contiguous float64 ({n}, 3) array, got {out.dtype} {out.shape}"
        )
    kernel(readonly(v), readonly(t), out)  # read-only: one compiled specialization
    return out


def directed_edges(triangles: np.ndarray) -> np.ndarray:
    """(3T, 2) directed half-edges (i -> j) of every triangle, in triangle order."""
    t = np.asarray(triangles)
    return np.concatenate([t[:, [0, 1]], t[:, [1, 2]], t[:, [2, 0]]])


def _undirected_keys(directed: np.ndarray) -> tuple[np.ndarray, int]:
    """1D keys ``a * n + b`` (``a < b`` the edge's ends, ``n`` the largest index + 1) of
    non-empty ``directed (E, 2)`` edges: sorted like the rows ``(a, b)``, and ~5x faster
    to ``np.unique`` than the rows (``axis=0``)."""
    e = np.sort(directed, axis=1).astype(np.int64, copy=False)
    n = int(e.max()) + 1
    return e[:, 0] * n + e[:, 1], n


#: Distinct triangle arrays whose edges :func:`unique_edges` keeps (by content).
_EDGE_MEMO_SIZE = 4
_edge_memo: OrderedDict[tuple, np.ndarray] = OrderedDict()
_edge_lock = threading.Lock()


def unique_edges(triangles: np.ndarray) -> np.ndarray:
    """(E, 2) unique undirected edges, smaller index first, sorted; read-only.

    Kept for the last few distinct triangle arrays, by content (a SHA-1 of the indices,
    2 ms at 160K triangles against 40 ms to sort the edges): one mesh-sequence fit asked nine
    times for the edges of one mesh, from the operators each builds.
    """
    t = np.ascontiguousarray(triangles)
    key = (t.shape, t.dtype.str, hashlib.sha1(t.data, usedforsecurity=False).digest())
    with _edge_lock:
        if key in _edge_memo:
            _edge_memo.move_to_end(key)
            return _edge_memo[key]
    edges = _unique_edges(t)
    edges.flags.writeable = False  # the array itself: a view's flag could be set back
    with _edge_lock:
        _edge_memo[key] = edges
        while len(_edge_memo) > _EDGE_MEMO_SIZE:
            _edge_memo.popitem(last=False)
    return edges


def _unique_edges(triangles: np.ndarray) -> np.ndarray:
    d = directed_edges(triangles)
    if len(d) == 0:
        return d.reshape(0, 2)
    keys, n = _undirected_keys(d)
    keys.sort()  # then the first of each run: 4x faster than np.unique's hash table here
    keys = keys[np.concatenate(([True], keys[1:] != keys[:-1]))]
    return np.stack([keys // n, keys % n], axis=1).astype(d.dtype, copy=False)


def boundary_edges(triangles: np.ndarray) -> np.ndarray:
    """(B, 2) directed boundary edges (used by exactly one triangle), in that triangle's order."""
    d = directed_edges(triangles)
    if len(d) == 0:
        return d.reshape(0, 2)
    _, inverse, counts = np.unique(_undirected_keys(d)[0], return_inverse=True, return_counts=True)
    return d[counts[inverse] == 1]


def vertex_adjacency(triangles: np.ndarray, n_vertices: int) -> sp.csr_matrix:
    """(V, V) symmetric CSR 0/1 adjacency matrix."""
    e = unique_edges(triangles)
    data = np.ones(2 * len(e))
    rows = np.concatenate([e[:, 0], e[:, 1]])
    cols = np.concatenate([e[:, 1], e[:, 0]])
    return sp.csr_matrix((data, (rows, cols)), shape=(n_vertices, n_vertices))


def barycentric_matrix(
    corners: np.ndarray, barycentric: np.ndarray, n_vertices: int
) -> sp.csr_matrix:
    """``(P, V)`` CSR interpolation matrix: row ``p`` holds ``barycentric[p] (3,)`` at the
    vertices ``corners[p] (3,)`` (points on triangles: ``matrix @ vertices`` gives them)."""
    c = np.asarray(corners)
    rows = np.repeat(np.arange(len(c)), 3)
    return sp.csr_matrix(
        (np.asarray(barycentric, dtype=np.float64).ravel(), (rows, c.ravel())),
        shape=(len(c), n_vertices),
    )
