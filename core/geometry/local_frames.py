"""Per-vertex local frames (normal + projected edge tangent), as used to transfer a Laplacian coating.

The frame of vertex ``i`` is the orthonormal matrix ``F_i = [t_i, b_i, n_i]`` (columns):
``n_i`` the area-weighted vertex normal, ``t_i`` the edge from ``i`` to a fixed
neighbour projected onto the tangent plane and normalised, ``b_i = n_i x t_i``
(Sorkine et al. 2004, sec. 4). Because the tangent comes from a mesh edge, the frame
moves with the surface: vectors expressed in it (``F_i^T d``) are invariant to rigid
motions and, approximately, to smooth large-scale deformation.

The neighbour of each vertex is chosen once per topology, on a reference mesh, as the
one whose projected edge best follows a global direction, so that neighbouring frames
are roughly aligned.
"""

from __future__ import annotations

from collections.abc import Callable
from typing import TYPE_CHECKING, Any

import numpy as np
import numpy.typing as npt

from .._validate import readonly
from ..errors import DegenerateGeometryError, NonFiniteError, ShapeError
from .mesh_ops import unique_edges, vertex_normals

if TYPE_CHECKING:
    import scipy.sparse as sp

__all__ = ["frame_neighbors", "VertexFrames", "vertex_frames", "to_local", "to_world"]


def frame_neighbors(vertices: np.ndarray, triangles: np.ndarray) -> np.ndarray:
    """(V, 2) int64: for each vertex, the preferred and a fallback neighbour for its tangent.

    Chosen on ``vertices : (V, 3)`` (the reference mesh): the neighbour whose edge,
    projected onto the tangent plane, is best aligned with the global x axis (y where
    the normal is nearly along x). Raises DegenerateGeometryError for isolated vertices.
    """
    from ._laplacian_kernels import best_two

    src, dst, score = tangent_scores(vertices, triangles)
    out = np.empty((np.asarray(vertices).shape[0], 2), dtype=np.int64)
    best_two(src, dst, score, out)  # by vertex, best score first (ties: lower id)
    return out


def tangent_scores(
    vertices: np.ndarray, triangles: np.ndarray
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Every directed edge ``src -> dst`` (E2,) and its ``score`` (E2,): the cosine between the
    edge projected onto ``src``'s tangent plane and the global x axis (y where the normal is
    nearly along x), as :func:`frame_neighbors` ranks them."""
    v = np.asarray(vertices, dtype=np.float64)
    t = np.asarray(triangles, dtype=np.int64)
    n_vertices = v.shape[0]
    if not np.isfinite(v).all():
        raise NonFiniteError(
            f"local frames: {int(np.count_nonzero(~np.isfinite(v).all(axis=1)))} vertex/vertices "
            "are NaN or infinite; give a finite reference mesh"
        )
    normals = vertex_normals(v, t)
    e = unique_edges(t)
    src = np.concatenate([e[:, 0], e[:, 1]])
    dst = np.concatenate([e[:, 1], e[:, 0]])
    degree = np.bincount(src, minlength=n_vertices)
    if np.any(degree == 0):
        bad = np.flatnonzero(degree == 0)
        raise DegenerateGeometryError(
            f"local frames: {bad.size} vertex/vertices belong to no triangle (first: {bad[:5].tolist()}); remove unused vertices"
        )
    n = normals[src]
    axis = np.where(
        np.abs(n[:, :1]) > 0.9, np.array([[0.0, 1.0, 0.0]]), np.array([[1.0, 0.0, 0.0]])
    )
    axis = axis - np.einsum("ij,ij->i", axis, n)[:, None] * n
    edge = v[dst] - v[src]
    edge = edge - np.einsum("ij,ij->i", edge, n)[:, None] * n
    length = np.linalg.norm(edge, axis=1) * np.maximum(np.linalg.norm(axis, axis=1), 1e-300)
    score = np.einsum("ij,ij->i", edge, axis) / np.maximum(length, 1e-300)
    if not np.isfinite(score).all():  # coordinates so large that the products overflow
        raise NonFiniteError(
            "local frames: the reference mesh's coordinates overflow (above ~1e150); rescale it"
        )
    return src, dst, score


def _by_frames(kernel: Any, n_frames: int, args: Callable[[int, int], tuple]) -> np.ndarray:
    """A frames kernel (``vertex_frames`` or ``frame_apply``: serial, ``nogil``, returning
    the per-mesh count of undefined frames) run on blocks of frames side by side; the
    counts of all ``n_frames`` meshes."""
    from .._threads import in_blocks

    counts = in_blocks(kernel, n_frames, args)
    return np.concatenate(counts) if counts else np.zeros(0, dtype=np.int64)


class VertexFrames:
    """Computes per-vertex frames of meshes of one topology (numba, batched over frames).

    Parameters
    ----------
    triangles : (T, 3) int
    neighbors : (V, 2) int
        From :func:`frame_neighbors` on the reference mesh.
    """

    def __init__(self, triangles: np.ndarray, neighbors: np.ndarray):
        t = np.ascontiguousarray(triangles, dtype=np.int64)
        nb_ = np.ascontiguousarray(neighbors, dtype=np.int64)
        if nb_.ndim != 2 or nb_.shape[1] != 2:
            raise ShapeError(f"VertexFrames: neighbors must be (V, 2), got {nb_.shape}")
        n_vertices = nb_.shape[0]
        if t.ndim != 2 or t.shape[1] != 3:
            raise ShapeError(f"VertexFrames: triangles must be (T, 3), got {t.shape}")
        if t.size and (t.min() < 0 or t.max() >= n_vertices):  # the kernels index unchecked
            raise ShapeError(
                f"VertexFrames: triangle indices must be in 0..{n_vertices - 1}, got {t.min()}..{t.max()}"
            )
        # read-only whatever the caller passed: one compiled specialization of the kernels
        self.triangles = readonly(t)
        self.neighbors = readonly(nb_)
        self.n_vertices = n_vertices

    def _points(self, points: npt.ArrayLike, what: str) -> tuple[np.ndarray, bool]:
        p = np.asarray(points)
        single = p.ndim == 2
        if single:
            p = p[None]
        if p.ndim != 3 or p.shape[1:] != (self.n_vertices, 3):
            raise ShapeError(
                f"VertexFrames: {what} must be (V, 3) or (F, V, 3) with V={self.n_vertices}, got {np.shape(points)}"
            )
        if p.dtype not in (np.float32, np.float64):
            p = p.astype(np.float64)
        return np.ascontiguousarray(p), single

    @staticmethod
    def _check(bad: np.ndarray) -> None:
        if bad.any():
            f = int(np.flatnonzero(bad)[0])
            raise DegenerateGeometryError(
                f"local frames: {int(bad[f])} vertex/vertices of mesh {f} have no defined normal or tangent "
                "(all incident triangles have zero area); repair the mesh"
            )

    def __call__(self, points: np.ndarray) -> np.ndarray:
        """Frames of ``points : (V, 3)`` or ``(F, V, 3)`` -> ``(V, 3, 3)`` or ``(F, V, 3, 3)``.

        Raises DegenerateGeometryError if a vertex has no defined normal or tangent.
        """
        from ._laplacian_kernels import vertex_frames as kernel

        p, single = self._points(points, "points")
        out = np.empty(p.shape[:2] + (3, 3), dtype=np.float64)
        self._check(
            _by_frames(
                kernel, len(p), lambda a, b: (p[a:b], self.triangles, self.neighbors, out[a:b])
            )
        )
        return out[0] if single else out

    def apply(
        self,
        points: np.ndarray,
        vectors: np.ndarray,
        *,
        inverse: bool,
        overwrite_vectors: bool = False,
    ) -> np.ndarray:
        """Frames of ``points`` applied to ``vectors`` (same shape, (…, V, 3)) without storing them.

        ``inverse=True``: world -> local (``F^T d``); ``False``: local -> world (``F c``).
        ``overwrite_vectors``: write the result into ``vectors`` when they are C-contiguous
        float64 (each vertex's vector is read before it is written; they must not share
        memory with ``points``), else into a new array.
        """
        from ._laplacian_kernels import frame_apply

        p, single = self._points(points, "points")
        vec = np.ascontiguousarray(np.asarray(vectors, dtype=np.float64).reshape(p.shape))
        out = vec if overwrite_vectors else np.empty(p.shape)  # vec: theirs, or a copy
        none, empty = np.zeros(1, dtype=np.int64), np.zeros(1)
        tri, nbr, inv = self.triangles, self.neighbors, bool(inverse)
        self._check(
            _by_frames(
                frame_apply,
                len(p),
                lambda a, b: (p[a:b], tri, nbr, vec[a:b], out[a:b], inv, none, none, empty),
            )
        )
        return out[0] if single else out

    def coating(self, points: np.ndarray, smooth: np.ndarray, matrix: sp.spmatrix) -> np.ndarray:
        """Laplacian coating ``F(smooth)^T (M (points - smooth))`` of meshes ``(…, V, 3)``.

        ``matrix`` : (V, V) scipy sparse ``M`` (a Laplacian, possibly screened). One fused
        pass: Laplacian coordinates of the detail, expressed in the smooth mesh's frames
        (Sorkine et al. 2004's coating).
        """
        import scipy.sparse as sp

        from ._laplacian_kernels import frame_apply

        s, single = self._points(smooth, "smooth")
        p = np.ascontiguousarray(np.asarray(points, dtype=np.float64).reshape(s.shape))
        m = sp.csr_matrix(matrix)
        out = np.empty(s.shape, dtype=np.float64)
        ptr, ind, val = (
            m.indptr.astype(np.int64),
            m.indices.astype(np.int64),
            m.data.astype(np.float64),
        )
        tri, nbr = self.triangles, self.neighbors
        self._check(
            _by_frames(
                frame_apply,
                len(s),
                lambda a, b: (s[a:b], tri, nbr, p[a:b], out[a:b], True, ptr, ind, val),
            )
        )
        return out[0] if single else out


def vertex_frames(
    points: np.ndarray, triangles: np.ndarray, neighbors: np.ndarray | None = None
) -> np.ndarray:
    """Frames ``(…, V, 3, 3)`` (columns tangent, bitangent, normal) of ``points : (…, V, 3)``.

    ``neighbors`` default: :func:`frame_neighbors` of the first mesh.
    """
    p = np.asarray(points, dtype=np.float64)
    if neighbors is None:
        neighbors = frame_neighbors(p if p.ndim == 2 else p[0], triangles)
    return VertexFrames(triangles, neighbors)(p)


def to_local(frames: np.ndarray, vectors: np.ndarray) -> np.ndarray:
    """Express world ``vectors (…, V, 3)`` in ``frames (…, V, 3, 3)``: ``F^T d``."""
    d = np.asarray(vectors, dtype=np.float64)
    return (
        frames[..., 0, :] * d[..., 0:1]
        + frames[..., 1, :] * d[..., 1:2]
        + frames[..., 2, :] * d[..., 2:3]
    )


def to_world(frames: np.ndarray, coords: np.ndarray) -> np.ndarray:
    """World vectors from local ``coords (…, V, 3)`` in ``frames (…, V, 3, 3)``: ``F c``."""
    c = np.asarray(coords, dtype=np.float64)
    return (
        frames[..., :, 0] * c[..., 0:1]
        + frames[..., :, 1] * c[..., 1:2]
        + frames[..., :, 2] * c[..., 2:3]
    )
