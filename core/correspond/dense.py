"""Dense point pairs between two faces of different topology, guided by landmarks.

For fitting a blendshape rig to a dense source (a mesh sequence), every interior target
vertex (optionally a subsample) is paired with a point on the source surface: the target
neutral is carried into the source's space by the landmark RBF warp (phi(r) = r plus a
linear part, :func:`~faceretarget.correspond.rbf_warp`) and projected onto the source
neutral (closest point). Pairs that land far from the source surface (a mouth bag or an
eyeball the source does not have) or on a surface facing another way are dropped.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from ..errors import CorrespondenceError, ShapeError
from ..model import Mesh
from .topology import boundary_loops
from .transfer import Correspondence, closest_point_transfer
from .warp import rbf_warp

__all__ = ["DensePairs", "dense_pairs", "interior_vertices", "farthest_points"]

#: A pair is dropped when the warped target point lies farther than this fraction of the
#: source's face size (RMS landmark radius) from the source surface.
MAX_DISTANCE = 0.05
#: ... or when the source surface normal and the target normal disagree (cosine below this).
MIN_NORMAL_COSINE = 0.0
#: A dense fit needs at least this many pairs.
MIN_PAIRS = 20


@dataclass(frozen=True)
class DensePairs:
    """Target vertices paired with points on the source surface.

    target_ids : (P,) int64         target vertex ids
    source : Correspondence         P points on the source mesh (triangle + barycentric)
    dropped : int                   candidate vertices dropped (too far, facing away)
    candidates : int                interior target vertices considered
    """

    target_ids: np.ndarray
    source: Correspondence
    dropped: int
    candidates: int

    def __len__(self) -> int:
        return len(self.target_ids)


def interior_vertices(mesh: Mesh, skip_rings: int = 2) -> np.ndarray:
    """Vertex ids of ``mesh`` more than ``skip_rings`` edge rings from its outer boundary.

    The outer boundary is the longest boundary loop; inner loops (eye and mouth rims) are
    kept, since they carry blinks and lip closures. Returns sorted (P,) int64.
    """
    n = mesh.n_vertices
    loops = boundary_loops(mesh.triangles)
    if not loops or skip_rings <= 0:
        return np.arange(n, dtype=np.int64)
    drop = np.zeros(n, dtype=bool)
    drop[loops[0]] = True
    adjacency = mesh.adjacency
    for _ in range(skip_rings - 1 if skip_rings > 0 else 0):
        drop |= (adjacency @ drop.astype(np.float64)) > 0
    return np.flatnonzero(~drop).astype(np.int64)


def farthest_points(points: np.ndarray, count: int, start: int = 0) -> np.ndarray:
    """Indices of ``count`` of ``points (P, 3)`` spread evenly by farthest-point sampling
    (deterministic, from index ``start``); all indices when ``count >= P``."""
    p = np.asarray(points, dtype=np.float64)
    if count >= len(p):
        return np.arange(len(p), dtype=np.int64)
    chosen = np.empty(count, dtype=np.int64)
    chosen[0] = start
    dist = np.sum((p - p[start]) ** 2, axis=1)
    for k in range(1, count):
        chosen[k] = i = int(np.argmax(dist))
        np.minimum(dist, np.sum((p - p[i]) ** 2, axis=1), out=dist)
    return np.sort(chosen)


def dense_pairs(
    target: Mesh,
    target_landmarks: np.ndarray,
    source: Mesh,
    source_landmarks: np.ndarray,
    *,
    max_points: int | None = 1000,
    skip_rings: int = 2,
    candidates: np.ndarray | None = None,
) -> DensePairs:
    """Pair interior target vertices with points on the source surface.

    Parameters
    ----------
    target, source : Mesh
        Neutral target and source faces (any topologies, any units).
    target_landmarks, source_landmarks : (N, 3) float
        Corresponding landmark positions on the two neutrals (same order).
    max_points : int or None
        Keep at most this many target vertices, spread by farthest-point sampling.
    skip_rings : int
        Target vertices this many rings or fewer from the outer boundary are left out.
    candidates : (K,) int, optional
        Target vertex ids to consider instead of the interior vertices.

    Raises :class:`CorrespondenceError` when fewer than ``MIN_PAIRS`` pairs survive.
    """
    tl = np.asarray(target_landmarks, dtype=np.float64)
    sl = np.asarray(source_landmarks, dtype=np.float64)
    if tl.ndim != 2 or tl.shape[1] != 3 or tl.shape != sl.shape:
        raise ShapeError(
            f"dense_pairs: landmarks must be two (N, 3) arrays of the same shape, got {tl.shape} and {sl.shape}"
        )
    ids = (
        interior_vertices(target, skip_rings)
        if candidates is None
        else np.asarray(candidates, dtype=np.int64)
    )
    n_candidates = len(ids)
    warp = rbf_warp(tl, sl)
    points = warp(target.vertices[ids])
    hits = closest_point_transfer(points, source)
    size = float(np.sqrt(np.mean(np.sum((sl - sl.mean(axis=0)) ** 2, axis=1))))
    # the source normal at each closest point: the barycentric blend of its vertex normals,
    # the same whichever triangle meeting at an edge or vertex the search returned
    blend = np.einsum(
        "pk,pkd->pd", hits.barycentric, source.vertex_normals[source.triangles[hits.triangle_ids]]
    )
    source_normals = blend / np.maximum(
        np.linalg.norm(blend, axis=1, keepdims=True), np.finfo(float).tiny
    )
    cosine = np.einsum("pk,pk->p", source_normals, target.vertex_normals[ids])
    keep = (hits.distances <= MAX_DISTANCE * size) & (cosine > MIN_NORMAL_COSINE)
    if max_points is not None and keep.sum() > max_points:
        sub = np.flatnonzero(keep)
        chosen = sub[farthest_points(target.vertices[ids[sub]], int(max_points))]
        keep = np.zeros_like(keep)
        keep[chosen] = True
    if keep.sum() < MIN_PAIRS:
        raise CorrespondenceError(
            f"dense correspondence: only {int(keep.sum())} of {n_candidates} target vertices found a source surface point "
            f"within {MAX_DISTANCE:.0%} of the face size; check that the landmarks of source and target correspond, "
            "or fit on the landmarks only"
        )
    corr = Correspondence(
        hits.triangle_ids[keep],
        hits.barycentric[keep],
        hits.distances[keep],
        hits.triangles,
        hits.n_vertices,
    )
    dropped = int(
        n_candidates
        - np.count_nonzero((hits.distances <= MAX_DISTANCE * size) & (cosine > MIN_NORMAL_COSINE))
    )
    return DensePairs(ids[keep], corr, dropped, n_candidates)
