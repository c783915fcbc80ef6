"""Landmark-guided non-rigid ICP: resample a target surface into the source topology.

The preprocessing Xu et al. 2014 (sec. 3) rely on: the source mesh is first warped onto
the target by an RBF through the landmark pairs (phi(r) = r, Seol et al. 2012 sec. 3.2),
then fitted to the target surface by iterated closest points with a Laplacian
(membrane) regulariser on the displacement from that warp, whose stiffness decreases
stage by stage (the schedule of Amberg et al. 2007), and a landmark term:

    min_x  sum_i w_i |x_i - c_i|^2 + alpha (x - x0)^T L (x - x0) + beta sum_l |P_l x - t_l|^2

with c_i the closest target point of x_i (boundary vertices: the closest point on the
matched target boundary loop), w_i in {0, 1} rejecting matches that face away, lie on
the target's border or are far outliers, L the uniform graph Laplacian of the source
and x0 the warped source. Each solve factorizes the sparse SPD system once for the three
coordinates (SuperLU through :class:`~faceretarget.geometry.factorized.SPDFactor`).
"""
from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np
import scipy.sparse as sp

from ..errors import DegenerateGeometryError, InputError
from ..geometry.closest import closest_on_polyline
from ..geometry.factorized import SPDFactor
from ..geometry.laplacian import uniform_laplacian
from ..model import Landmarks, Mesh
from .landmarks import paired_positions, to_barycentric
from .topology import boundary_loops
from .warp import rbf_warp

__all__ = ["QualityReport", "resample_to_topology", "DEFAULT_STIFFNESS"]

#: Stiffness schedule (membrane weight relative to a unit closest-point weight).
DEFAULT_STIFFNESS = (30.0, 10.0, 3.0, 1.0, 0.3, 0.1)
#: Closest-point iterations per stiffness stage.
DEFAULT_ITERATIONS = 3
#: Landmark weight (relative to a unit closest-point weight).
DEFAULT_LANDMARK_WEIGHT = 10.0
#: Matches whose surface normals disagree more than this (cosine) are rejected.
_NORMAL_COS = 0.2
#: Matches farther than this many times the median match distance are rejected.
_OUTLIER_FACTOR = 6.0
#: Barycentric weight below which a closest point counts as lying on an edge / vertex.
_ON_EDGE = 1e-9


@dataclass(frozen=True)
class QualityReport:
    """How well a resampled mesh fits the target surface.

    Lengths are relative to the target's bounding-box diagonal (``scale``).

    residual_mean, residual_max : float
        Distance of the resampled vertices to the target surface.
    coverage_max : float
        Largest distance of a target vertex to the resampled surface (uncovered parts).
    landmark_error : float
        Largest distance between a resampled source landmark and its target landmark.
    flipped_triangles : int
        Resampled triangles whose normal points against the target surface normal.
    rejected : int
        Vertices without an accepted closest-point match in the last iteration.
    iterations : int
    scale : float
    """

    residual_mean: float
    residual_max: float
    coverage_max: float
    landmark_error: float
    flipped_triangles: int
    rejected: int
    iterations: int
    scale: float
    details: dict = field(default_factory=dict, repr=False)

    def as_dict(self) -> dict:
        """The scalar fields as a plain (JSON-friendly) dict."""
        return {k: getattr(self, k) for k in ("residual_mean", "residual_max", "coverage_max", "landmark_error",
                                              "flipped_triangles", "rejected", "iterations", "scale")}


def _edge_keys(edges: np.ndarray, n: int) -> np.ndarray:
    e = np.sort(np.asarray(edges, dtype=np.int64), axis=1)
    return e[:, 0] * n + e[:, 1]


def _on_boundary(tri_ids, bary, triangles, boundary_vertex, boundary_keys, n_vertices) -> np.ndarray:
    """(P,) bool: the closest point lies on a boundary edge or boundary vertex of the mesh."""
    corners = triangles[tri_ids]
    inside = bary > _ON_EDGE
    n_in = inside.sum(axis=1)
    out = np.zeros(len(tri_ids), dtype=bool)
    one = n_in == 1
    if one.any():
        out[one] = boundary_vertex[corners[one][inside[one]]]
    two = n_in == 2
    if two.any():
        pair = corners[two][inside[two]].reshape(-1, 2)
        out[two] = np.isin(_edge_keys(pair, n_vertices), boundary_keys)
    return out


def _match_loops(src_points, src_loops, tgt_vertices, tgt_loops):
    """For each source loop, the target loop nearest on average (index into ``tgt_loops``)."""
    out = []
    for loop in src_loops:
        best, best_d = -1, np.inf
        for j, tl in enumerate(tgt_loops):
            seg = np.stack([tl, np.roll(tl, -1)], axis=1)
            d = closest_on_polyline(src_points[loop], tgt_vertices, seg)[3].mean()
            if d < best_d:
                best, best_d = j, d
        out.append(best)
    return out


def resample_to_topology(
    source_mesh: Mesh,
    source_landmarks: Landmarks,
    target_mesh: Mesh,
    target_landmarks: Landmarks,
    *,
    stiffness=DEFAULT_STIFFNESS,
    iterations: int = DEFAULT_ITERATIONS,
    landmark_weight: float = DEFAULT_LANDMARK_WEIGHT,
    match_boundaries: bool = True,
    snap: bool = True,
) -> tuple[Mesh, QualityReport]:
    """Fit the source mesh onto the target surface: the target resampled in the source topology.

    Parameters
    ----------
    source_mesh, target_mesh : Mesh
        Any topologies; the source's vertex order and triangles are kept.
    source_landmarks, target_landmarks : Landmarks
        Corresponding points (paired by order; vertex ids or barycentric), at least 4 not
        in one plane.
    stiffness : sequence of float
        Decreasing membrane weights, one stage each (see :data:`DEFAULT_STIFFNESS`).
    iterations : int
        Closest-point iterations per stage.
    landmark_weight : float
    match_boundaries : bool
        Pull each source boundary loop onto the nearest target boundary loop (open
        surfaces: eye, mouth and outline loops).
    snap : bool
        Finally move every accepted vertex exactly onto its closest target point, unless
        that would flip a triangle.

    Returns
    -------
    mesh : Mesh
        Source topology, vertices on the target surface.
    report : QualityReport
    """
    stiffness = tuple(float(a) for a in np.atleast_1d(stiffness))
    if not stiffness or any(a <= 0 or not np.isfinite(a) for a in stiffness):
        raise InputError(f"resample_to_topology: stiffness must be positive numbers, got {stiffness}")
    if int(iterations) < 1:
        raise InputError(f"resample_to_topology: iterations must be >= 1, got {iterations}")
    if not landmark_weight > 0:
        raise InputError(f"resample_to_topology: landmark_weight must be > 0, got {landmark_weight}")
    src_pos, tgt_pos = paired_positions(source_mesh, source_landmarks, target_mesh, target_landmarks)
    if np.linalg.matrix_rank(src_pos - src_pos.mean(axis=0), tol=1e-9 * source_mesh.scale) < 3:
        raise DegenerateGeometryError(
            "resample_to_topology: the landmarks lie in a plane (or on a line); give at least 4 landmarks spread over the face"
        )
    n = source_mesh.n_vertices
    tri_s = source_mesh.triangles
    x0 = rbf_warp(src_pos, tgt_pos)(source_mesh.vertices)
    lap = uniform_laplacian(tri_s, n)
    lm = to_barycentric(source_landmarks, source_mesh)
    corners = tri_s[lm.triangle_ids]
    p = sp.csr_matrix((lm.barycentric.ravel(), (np.repeat(np.arange(len(lm)), 3), corners.ravel())), shape=(len(lm), n))
    ptp = (p.T @ p) * landmark_weight
    pt_t = (p.T @ tgt_pos) * landmark_weight

    matcher = _Matcher(target_mesh, source_mesh, match_boundaries)
    x = x0.copy()
    lx0 = lap @ x0
    total = 0
    for alpha in stiffness:
        matcher.pair_loops(x)
        for _ in range(int(iterations)):
            total += 1
            targets, weights = matcher(x)
            a = sp.diags(weights) + alpha * lap + ptp
            b = weights[:, None] * targets + alpha * lx0 + pt_t
            x = SPDFactor(a, what="the non-rigid ICP system").solve(b)
    targets, weights = matcher(x)
    if snap:
        x = _snap(x, targets, weights > 0, tri_s)
    mesh = Mesh(x, tri_s, name=(target_mesh.name or "target") + " resampled", _trusted=True)
    return mesh, quality_report(mesh, source_landmarks, target_mesh, tgt_pos, rejected=int((weights == 0).sum()), iterations=total)


class _Matcher:
    """Closest-point targets and acceptance weights on one target mesh."""

    def __init__(self, target: Mesh, source: Mesh, match_boundaries: bool):
        from ..geometry.mesh_ops import boundary_edges
        from ..geometry.raycast import RayCaster

        self.target = target
        self.caster = RayCaster(target.vertices, target.triangles, backend="bvh")
        self.t_boundary = np.zeros(target.n_vertices, dtype=bool)
        self.t_boundary[target.boundary_vertices] = True
        self.t_keys = np.sort(_edge_keys(boundary_edges(target.triangles), target.n_vertices))
        self.source_triangles = source.triangles
        self.tgt_loops = boundary_loops(target.triangles) if match_boundaries else []
        self.src_loops = boundary_loops(source.triangles) if (match_boundaries and self.tgt_loops) else []
        self.pairs: list[int] = []
        edges = target.edges
        # a match within one mean edge length of the surface is never an outlier
        self.floor = float(np.linalg.norm(target.vertices[edges[:, 0]] - target.vertices[edges[:, 1]], axis=1).mean())

    def pair_loops(self, x: np.ndarray) -> None:
        """Pair each source boundary loop with the nearest target loop at the current fit."""
        self.pairs = _match_loops(x, self.src_loops, self.target.vertices, self.tgt_loops) if self.src_loops else []

    def __call__(self, x: np.ndarray):
        """Targets ``(V, 3)`` and weights ``(V,)`` in {0, 1} for the current fit ``x``."""
        from ..geometry.mesh_ops import vertex_normals

        hits = self.caster.closest(x)
        targets = hits.points.copy()
        normals = vertex_normals(x, self.source_triangles)
        agree = np.einsum("ij,ij->i", normals, self.target.face_normals[hits.triangle]) > _NORMAL_COS
        border = _on_boundary(hits.triangle, hits.barycentric, self.target.triangles, self.t_boundary, self.t_keys, self.target.n_vertices)
        ok = agree & ~border
        dist = np.abs(hits.distance)
        if ok.any():
            ok &= dist <= _OUTLIER_FACTOR * max(float(np.median(dist[ok])), self.floor / _OUTLIER_FACTOR)
        for loop, j in zip(self.src_loops, self.pairs):
            tl = self.tgt_loops[j]
            targets[loop] = closest_on_polyline(x[loop], self.target.vertices, np.stack([tl, np.roll(tl, -1)], axis=1))[2]
            ok[loop] = True
        return targets, ok.astype(np.float64)


def _snap(x, targets, accepted, triangles):
    """Move accepted vertices onto their targets, keeping the old position around any triangle that would flip."""
    from ..geometry.mesh_ops import face_normals

    before = face_normals(x, triangles)
    y = np.where(accepted[:, None], targets, x)
    for _ in range(5):
        after = face_normals(y, triangles)
        bad = np.einsum("ij,ij->i", before, after) <= 0.0
        if not bad.any():
            break
        revert = np.unique(triangles[bad])
        y[revert] = x[revert]
    return y


def quality_report(resampled: Mesh, source_landmarks: Landmarks, target_mesh: Mesh, target_landmark_positions, *, rejected: int = 0,
                   iterations: int = 0) -> QualityReport:
    """Measure how well ``resampled`` (source topology) fits ``target_mesh``."""
    from ..geometry.raycast import RayCaster

    scale = target_mesh.scale
    on_target = RayCaster(target_mesh.vertices, target_mesh.triangles, backend="bvh")
    res = np.abs(on_target.closest(resampled.vertices).distance)
    back = RayCaster(resampled.vertices, resampled.triangles, backend="bvh").closest(target_mesh.vertices)
    # triangle normals against the target normal at each centroid's closest point
    at = on_target.closest(resampled.vertices[resampled.triangles].mean(axis=1))
    flipped = int((np.einsum("ij,ij->i", resampled.face_normals, target_mesh.face_normals[at.triangle]) < 0).sum())
    lm_err = np.linalg.norm(source_landmarks.positions(resampled.vertices, resampled.triangles) - target_landmark_positions, axis=1)
    return QualityReport(
        residual_mean=float(res.mean() / scale),
        residual_max=float(res.max() / scale),
        coverage_max=float(np.abs(back.distance).max() / scale),
        landmark_error=float(lm_err.max() / scale),
        flipped_triangles=flipped,
        rejected=rejected,
        iterations=iterations,
        scale=scale,
        details={"residuals": res, "coverage": np.abs(back.distance)},
    )
