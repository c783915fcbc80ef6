"""Mesh Laplacians: uniform (graph) and cotangent, as scipy CSR matrices.

Convention: ``L = D - W`` is symmetric positive semi-definite, so ``(L x)_i =
sum_j w_ij (x_i - x_j)`` are the Laplacian coordinates of vertex ``i`` (Sorkine et al.
2004, up to the sign and the normalisation by the degree). Constant vectors are in the
null space; add a small multiple of the identity (or anchors) before solving.

The cotangent Laplacian of many meshes of one topology (the frames of a sequence) is
built by refilling the values of a fixed CSR pattern with a numba kernel
(:class:`LaplacianPattern`), which costs a few milliseconds at 80K vertices.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import numpy.typing as npt
import scipy.sparse as sp

from ..errors import DegenerateGeometryError, ShapeError
from .mesh_ops import face_areas, unique_edges

__all__ = [
    "uniform_laplacian",
    "umbrella_operator",
    "cotangent_weights",
    "cotangent_laplacian",
    "LaplacianPattern",
    "laplacian_pattern",
]


def _check(vertices: npt.ArrayLike, triangles: npt.ArrayLike) -> tuple[np.ndarray, np.ndarray]:
    v = np.asarray(vertices, dtype=np.float64)
    t = np.asarray(triangles, dtype=np.int64)
    if v.ndim != 2 or v.shape[1] != 3:
        raise ShapeError(f"vertices: expected shape (V, 3), got {v.shape}")
    if t.ndim != 2 or t.shape[1] != 3:
        raise ShapeError(f"triangles: expected shape (T, 3), got {t.shape}")
    return v, t


def _adjacency_pattern(triangles: np.ndarray, n_vertices: int) -> sp.csr_matrix:
    """(V, V) CSR with ones on every edge and on the diagonal, sorted indices."""
    e = unique_edges(triangles)
    rows = np.concatenate([e[:, 0], e[:, 1], np.arange(n_vertices)])
    cols = np.concatenate([e[:, 1], e[:, 0], np.arange(n_vertices)])
    m = sp.csr_matrix((np.ones(rows.size), (rows, cols)), shape=(n_vertices, n_vertices))
    m.sum_duplicates()
    m.sort_indices()
    m.data[:] = 1.0
    return m


def uniform_laplacian(triangles: np.ndarray, n_vertices: int) -> sp.csr_matrix:
    """Graph Laplacian ``D - A`` (V, V): degree on the diagonal, -1 per edge."""
    t = np.asarray(triangles, dtype=np.int64)
    m = _adjacency_pattern(t, n_vertices)
    rows = np.repeat(np.arange(n_vertices), np.diff(m.indptr))
    off = m.indices != rows
    degree = np.bincount(rows[off], minlength=n_vertices).astype(np.float64)
    m.data = np.where(off, -1.0, degree[rows])
    return m


def umbrella_operator(triangles: np.ndarray, n_vertices: int) -> sp.csr_matrix:
    """Row-stochastic neighbour average ``W = D^-1 A`` (V, V), no diagonal.

    ``W x - x`` is the umbrella (uniform) Laplacian used by Taubin smoothing. Isolated
    vertices get an empty row (they stay where they are).
    """
    t = np.asarray(triangles, dtype=np.int64)
    e = unique_edges(t)
    rows = np.concatenate([e[:, 0], e[:, 1]])
    cols = np.concatenate([e[:, 1], e[:, 0]])
    degree = np.bincount(rows, minlength=n_vertices).astype(np.float64)
    m = sp.csr_matrix((1.0 / degree[rows], (rows, cols)), shape=(n_vertices, n_vertices))
    m.sort_indices()
    return m


def _check_areas(v: np.ndarray, t: np.ndarray, what: str) -> None:
    areas = face_areas(v, t)
    tiny = areas <= 1e-12 * max(float(areas.mean()), np.finfo(float).tiny)
    if tiny.any():
        bad = np.flatnonzero(tiny)
        raise DegenerateGeometryError(
            f"{what}: {bad.size} zero-area triangle(s) (first: {bad[:5].tolist()}) make the cotangent "
            "weights infinite; remove or repair them, or use the uniform Laplacian"
        )


def cotangent_weights(vertices: np.ndarray, triangles: np.ndarray) -> np.ndarray:
    """(T, 3) half cotangents of the angle at each corner (vectorized numpy).

    Entry ``[t, k]`` is ``cot(angle at corner k) / 2``, the weight the triangle adds to
    its edge opposite corner ``k``. Raises DegenerateGeometryError for zero-area triangles.
    """
    v, t = _check(vertices, triangles)
    _check_areas(v, t, "cotangent_weights")
    out = np.empty(t.shape, dtype=np.float64)
    for k in range(3):
        c = v[t[:, k]]
        u = v[t[:, (k + 1) % 3]] - c
        w = v[t[:, (k + 2) % 3]] - c
        out[:, k] = 0.5 * np.einsum("ij,ij->i", u, w) / np.linalg.norm(np.cross(u, w), axis=1)
    return out


@dataclass(frozen=True)
class LaplacianPattern:
    """The fixed CSR pattern of a Laplacian of one topology, for fast refills.

    indptr, indices : CSR structure (diagonal included, sorted)
    slots : (T, 3, 4) positions in the data array of (i, j), (j, i), (i, i), (j, j) for
        the edge (i, j) opposite each corner
    """

    n_vertices: int
    triangles: np.ndarray
    indptr: np.ndarray
    indices: np.ndarray
    slots: np.ndarray

    def matrix(self, data: np.ndarray) -> sp.csr_matrix:
        return sp.csr_matrix(
            (data, self.indices, self.indptr), shape=(self.n_vertices, self.n_vertices)
        )


def laplacian_pattern(triangles: np.ndarray, n_vertices: int) -> LaplacianPattern:
    """Build the CSR pattern (edges + diagonal) and the scatter slots of every triangle."""
    t = np.asarray(triangles, dtype=np.int64)
    m = _adjacency_pattern(t, n_vertices)
    indptr = m.indptr.astype(np.int64)
    indices = m.indices.astype(np.int64)
    rows = np.repeat(np.arange(n_vertices, dtype=np.int64), np.diff(indptr))
    keys = rows * n_vertices + indices  # increasing: CSR rows in order, sorted columns

    def slot(r: np.ndarray, c: np.ndarray) -> np.ndarray:
        return np.searchsorted(keys, r * n_vertices + c)

    slots = np.empty((t.shape[0], 3, 4), dtype=np.int64)
    for k in range(3):
        i = t[:, (k + 1) % 3]
        j = t[:, (k + 2) % 3]
        slots[:, k, 0] = slot(i, j)
        slots[:, k, 1] = slot(j, i)
        slots[:, k, 2] = slot(i, i)
        slots[:, k, 3] = slot(j, j)
    return LaplacianPattern(n_vertices, t, indptr, indices, slots)


def cotangent_laplacian(
    vertices: np.ndarray, triangles: np.ndarray, pattern: LaplacianPattern | None = None
) -> sp.csr_matrix:
    """Cotangent Laplacian (V, V): ``L_ij = -(cot a_ij + cot b_ij) / 2``, rows sum to zero.

    Parameters
    ----------
    vertices : (V, 3) float
    triangles : (T, 3) int
    pattern : LaplacianPattern, optional
        Reuse the pattern of this topology (built once by :func:`laplacian_pattern`).

    Raises
    ------
    DegenerateGeometryError
        Zero-area triangles (their cotangents are infinite); the message names them.
    """
    from ._laplacian_kernels import fill_cotangent

    v, t = _check(vertices, triangles)
    _check_areas(v, t, "cotangent_laplacian")
    if pattern is None:
        pattern = laplacian_pattern(t, v.shape[0])
    elif pattern.n_vertices != v.shape[0] or pattern.triangles.shape != t.shape:
        raise ShapeError(
            f"cotangent_laplacian: pattern is for {pattern.n_vertices} vertices / {pattern.triangles.shape[0]} "
            f"triangles, mesh has {v.shape[0]} / {t.shape[0]}"
        )
    data = np.empty(pattern.indices.shape[0], dtype=np.float64)
    fill_cotangent(np.ascontiguousarray(v), pattern.triangles, pattern.slots, data)
    return pattern.matrix(data)
