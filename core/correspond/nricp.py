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
coordinates (an LDL^T factorization through :class:`~faceretarget.geometry.factorized.SPDFactor`).

The fit does not depend on units or placement: both meshes are first brought into one
canonical frame (each centred on its landmarks' centroid and scaled to unit RMS landmark
radius, the source turned to its landmarks' principal axes and the target rotated onto it
by Procrustes), every tolerance is relative (to the median match distance, the mean edge
length or the landmark radius) or dimensionless, the landmark warp takes exact distances
(:func:`~faceretarget.correspond.rbf_warp`), and the result is mapped back into the
target's frame and units. Every
accept / reject decision is a continuous function of the geometry (the target normal at a
closest point is the barycentric blend of its vertex normals, the same whichever of the
triangles meeting at an edge or a vertex the search returns), so rounding differences
(scaling by 0.01 is not exact in binary) cannot flip a decision and be amplified
iteration after iteration: either face scaled x0.01 .. x1000 or moved rigidly gives the
same resampling to ~5e-15 of the face height (before: 1e-4 RMS, up to 6e-3, from matches
accepted or rejected on the face normal of whichever triangle a tie picked, at creases).
"""

from __future__ import annotations

import warnings
from collections.abc import Iterable, Sequence
from dataclasses import dataclass, field
from typing import TYPE_CHECKING

import numpy as np
import numpy.typing as npt
import scipy.sparse as sp

from ..config import (
    CORRESPONDENCE_FLIPPED_ERROR,
    CORRESPONDENCE_FLIPPED_WARN,
    CORRESPONDENCE_LANDMARK_ERROR,
    CORRESPONDENCE_LANDMARK_WARN,
    CORRESPONDENCE_LOOP_MATCH,
    CORRESPONDENCE_OUTLINE_RINGS,
    CORRESPONDENCE_RESIDUAL_ERROR,
    CORRESPONDENCE_RESIDUAL_WARN,
    CORRESPONDENCE_RIM_RINGS,
    CORRESPONDENCE_UNCOVERED_EDGES,
    CORRESPONDENCE_UNCOVERED_ERROR,
    CORRESPONDENCE_UNCOVERED_WARN,
)
from ..errors import CorrespondenceError, CorrespondenceWarning, DegenerateGeometryError, InputError
from ..geometry.closest import closest_on_polyline
from ..geometry.factorized import SPDFactor
from ..geometry.laplacian import uniform_laplacian
from ..geometry.mesh_ops import barycentric_matrix, unit_rows
from ..model import Landmarks, Mesh
from .landmarks import paired_positions, to_barycentric
from .topology import boundary_loops
from .warp import rbf_warp

if TYPE_CHECKING:
    from ..geometry.raycast import RayCaster, RayHits

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
#: Rounds of untangling (drop the matches around flipped interior triangles, re-solve).
_UNTANGLE_ROUNDS = 6
#: Edge rings around a flipped triangle whose matches are dropped.
_UNTANGLE_RINGS = 1


@dataclass(frozen=True)
class QualityReport:
    """How well a resampled mesh fits the target surface.

    Lengths are relative to the target's bounding-box diagonal (``scale``, in the target's
    units; from :func:`resample_to_topology` the box is taken in its canonical frame, the
    principal axes of the source's landmarks, so the report does not depend on how either
    face is turned or scaled).

    residual_mean, residual_max : float
        Distance of the resampled vertices to the target surface.
    coverage_max : float
        Largest distance of a target vertex to the resampled surface (uncovered parts).
    landmark_error : float
        Largest distance between a resampled source landmark and its target landmark.
    flipped_triangles : int
        Triangles of the *face interior* (all three corners matched on the target) whose
        normal points against the target surface normal. Source parts with no
        counterpart on the target (a filled eye over an eye hole, a mouth bag, a skirt
        beyond the target's outline) are not interior; ``details["flipped_all"]`` counts
        every triangle.
    rejected : int
        Vertices without a counterpart on the target (no accepted closest-point match).
    iterations : int
    scale : float
    details : dict
        Per-vertex ``residuals`` (V_s,), ``coverage`` (V_t,: distance of each target vertex
        to the matched part of the resampled surface), ``matched`` (V_s,) bool,
        ``interior_triangles``, ``flipped_all``, ``flipped_ids``,
        ``matched_residual_mean`` / ``_max`` (relative to ``scale``), ``uncovered_share``
        (target vertices farther than
        :data:`~faceretarget.config.CORRESPONDENCE_UNCOVERED_EDGES` mean edges from the
        matched surface) and ``uncovered_inner_share`` (those more than
        :data:`~faceretarget.config.CORRESPONDENCE_OUTLINE_RINGS` rings inside the
        target's outline), ``released`` / ``untangle_rounds`` (untangling), ``loops_paired``
        and ``regions``: ``{"flipped" | "landmarks" | "uncovered" | "residual": {region: count}}``,
        regions named from the landmark names (eyes, mouth, brows, nose, jaw, cheeks,
        boundary).
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
        """The scalar fields (and the problems found, as text) as a plain (JSON-friendly) dict."""
        out = {
            k: getattr(self, k)
            for k in (
                "residual_mean",
                "residual_max",
                "coverage_max",
                "landmark_error",
                "flipped_triangles",
                "rejected",
                "iterations",
                "scale",
            )
        }
        for k in (
            "interior_triangles",
            "flipped_all",
            "matched_residual_mean",
            "uncovered_share",
            "uncovered_inner_share",
        ):
            if k in self.details:
                out[k] = self.details[k]
        out["problems"] = [f"{level}: {text}" for level, text in self.problems()]
        return out

    def problems(self) -> list[tuple[str, str]]:
        """``[(level, text)]``, level "error" (past a hard limit) or "warning", for every quality
        measure past its threshold in :mod:`faceretarget.config` (``CORRESPONDENCE_*``); each
        text names the regions concerned."""
        d = self.details
        out: list[tuple[str, str]] = []
        regions = d.get("regions", {})

        def where(key: str) -> str:
            r = regions.get(key) or {}
            return " (" + ", ".join(f"{k}: {v}" for k, v in list(r.items())[:5]) + ")" if r else ""

        interior = max(int(d.get("interior_triangles", 0)), 1)
        share = self.flipped_triangles / interior
        if self.flipped_triangles > CORRESPONDENCE_FLIPPED_WARN:
            level = "error" if share > CORRESPONDENCE_FLIPPED_ERROR else "warning"
            out.append(
                (
                    level,
                    f"{self.flipped_triangles} triangles of the face interior ({100 * share:.2f}%) point against "
                    f"the target surface{where('flipped')}",
                )
            )
        if self.landmark_error > CORRESPONDENCE_LANDMARK_WARN:
            level = "error" if self.landmark_error > CORRESPONDENCE_LANDMARK_ERROR else "warning"
            out.append(
                (
                    level,
                    f"a landmark ends {100 * self.landmark_error:.2f}% of the target's size from its target "
                    f"landmark{where('landmarks')}",
                )
            )
        res = d.get("matched_residual_mean")
        if res is not None and res > CORRESPONDENCE_RESIDUAL_WARN:
            level = "error" if res > CORRESPONDENCE_RESIDUAL_ERROR else "warning"
            out.append(
                (
                    level,
                    f"matched vertices lie {100 * res:.2f}% of the target's size off its surface on average{where('residual')}",
                )
            )
        unc = d.get("uncovered_inner_share")
        if unc is not None and unc > CORRESPONDENCE_UNCOVERED_WARN:
            level = "error" if unc > CORRESPONDENCE_UNCOVERED_ERROR else "warning"
            out.append(
                (
                    level,
                    f"{100 * unc:.1f}% of the target's vertices inside its outline are not reached by the "
                    f"source surface{where('uncovered')}",
                )
            )
        return out

    def check(self, what: str = "correspondence") -> QualityReport:
        """Raise :class:`~faceretarget.errors.CorrespondenceError` past a hard limit, else warn
        (:class:`~faceretarget.errors.CorrespondenceWarning`) below a warning threshold;
        returns self."""
        found = self.problems()
        if not found:
            return self
        text = "; ".join(t for _, t in found)
        hint = (
            "check that source and target landmarks correspond (same order, same points: the upper lid on both "
            "faces, not on a closed lid's fold), or give more landmarks around the regions named"
        )
        if any(level == "error" for level, _ in found):
            raise CorrespondenceError(
                f"{what}: the source and target surfaces could not be put in correspondence: {text}; {hint}"
            )
        warnings.warn(
            f"{what}: poor correspondence between source and target: {text}; results there may be wrong; {hint}",
            CorrespondenceWarning,
            stacklevel=3,
        )
        return self


def _edge_keys(edges: np.ndarray, n: int) -> np.ndarray:
    e = np.sort(np.asarray(edges, dtype=np.int64), axis=1)
    return e[:, 0] * n + e[:, 1]


def _on_boundary(
    tri_ids: np.ndarray,
    bary: np.ndarray,
    triangles: np.ndarray,
    boundary_vertex: np.ndarray,
    boundary_keys: np.ndarray,
    n_vertices: int,
) -> np.ndarray:
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


def _match_loops(
    src_points: np.ndarray,
    src_loops: Sequence[np.ndarray],
    tgt_vertices: np.ndarray,
    tgt_loops: Sequence[np.ndarray],
    src_triangles: np.ndarray | None = None,
    max_distance: float = np.inf,
) -> list[int]:
    """For each source loop, the target loop nearest on average (index into ``tgt_loops``),
    or -1 when even that one does not follow it: the mean distance from the source loop to
    the target loop, or back, exceeds ``max_distance`` (a closed-eye source's outline cut
    elsewhere than the target's, a skirt beyond it)."""
    out = []
    for loop in src_loops:
        best, best_d = -1, np.inf
        for j, tl in enumerate(tgt_loops):
            seg = np.stack([tl, np.roll(tl, -1)], axis=1)
            d = closest_on_polyline(src_points[loop], tgt_vertices, seg)[3].mean()
            if d < best_d:
                best, best_d = j, d
        if best >= 0 and np.isfinite(max_distance):
            tl = tgt_loops[best]
            back = closest_on_polyline(
                tgt_vertices[tl], src_points, np.stack([loop, np.roll(loop, -1)], axis=1)
            )[3].mean()
            if max(best_d, back) > max_distance:
                best = -1
        out.append(best)
    return out


@dataclass(frozen=True)
class _Frame:
    """A similarity ``canonical = R (p - centre) / scale`` and its inverse."""

    centre: np.ndarray
    scale: float
    rotation: np.ndarray

    def to_canonical(self, points: np.ndarray) -> np.ndarray:
        return ((np.asarray(points, dtype=np.float64) - self.centre) @ self.rotation.T) / self.scale

    def from_canonical(self, points: np.ndarray) -> np.ndarray:
        return (np.asarray(points, dtype=np.float64) * self.scale) @ self.rotation + self.centre


def _landmark_radius(positions: np.ndarray) -> float:
    """RMS distance of landmark positions to their centroid (the face size of the fit)."""
    return float(np.sqrt(np.mean(np.sum((positions - positions.mean(axis=0)) ** 2, axis=1))))


def canonical_frames(
    source_positions: npt.ArrayLike, target_positions: npt.ArrayLike
) -> tuple[_Frame, _Frame]:
    """The frames in which :func:`resample_to_topology` works: each face centred on its
    landmarks' centroid and scaled to unit RMS landmark radius; the source turned to the
    principal axes of its landmarks (each axis signed by the third moment along it), the
    target rotated onto the source (the Procrustes rotation of its landmarks onto the
    source's). All depend on the landmarks only, so a face given in other units or placed
    elsewhere lands on the same canonical coordinates (up to rounding, or up to an exact
    sign flip of an axis where a third moment vanishes)."""
    src = np.asarray(source_positions, dtype=np.float64)
    tgt = np.asarray(target_positions, dtype=np.float64)
    rs, rt = _landmark_radius(src), _landmark_radius(tgt)
    if not (rs > 0 and rt > 0 and np.isfinite(rs) and np.isfinite(rt)):
        raise DegenerateGeometryError(
            "resample_to_topology: the landmarks of one face all coincide; give at least 4 landmarks spread over the face"
        )
    b = (src - src.mean(axis=0)) / rs
    _, axes = np.linalg.eigh(b.T @ b)
    axes = axes[:, ::-1]
    skew = np.mean((b @ axes) ** 3, axis=0)
    axes = axes * np.where(skew < 0, -1.0, 1.0)
    if np.linalg.det(axes) < 0:
        axes[:, int(np.argmin(np.abs(skew)))] *= -1.0
    b = b @ axes
    a = (tgt - tgt.mean(axis=0)) / rt
    # target rotation r minimising sum |r a_i - b_i|^2 (Kabsch): a^T b = u s vt -> r = vt^T d u^T
    u, _, vt = np.linalg.svd(a.T @ b)
    d = np.diag([1.0, 1.0, np.sign(np.linalg.det(vt.T @ u.T)) or 1.0])
    rotation = vt.T @ d @ u.T
    return _Frame(src.mean(axis=0), rs, axes.T), _Frame(tgt.mean(axis=0), rt, rotation)


def resample_to_topology(
    source_mesh: Mesh,
    source_landmarks: Landmarks,
    target_mesh: Mesh,
    target_landmarks: Landmarks,
    *,
    stiffness: Sequence[float] = DEFAULT_STIFFNESS,
    iterations: int = DEFAULT_ITERATIONS,
    landmark_weight: float = DEFAULT_LANDMARK_WEIGHT,
    match_boundaries: bool = True,
    snap: bool = True,
    check: bool = True,
    what: str = "resample_to_topology",
) -> tuple[Mesh, QualityReport]:
    """Fit the source mesh onto the target surface: the target resampled in the source topology.

    The two faces may differ in more than triangulation: eyes closed (no eye holes) in one
    and open in the other, a mouth bag or none, outlines cut elsewhere (a head onto a
    face). Source parts with no counterpart on the target (a filled eye over the target's
    eye hole, a mouth bag, a skirt beyond the target's outline) find no accepted closest
    point and follow their matched neighbours through the membrane; a boundary loop is
    pulled onto a target loop only where the two follow each other (mean distance both
    ways below :data:`~faceretarget.config.CORRESPONDENCE_LOOP_MATCH` of the face size).
    Triangles of the *face interior* (every corner matched) that still point against the
    target surface are untangled: their corners' matches are dropped and the membrane
    re-solved, a few rounds.

    Parameters
    ----------
    source_mesh, target_mesh : Mesh
        Any topologies; the source's vertex order and triangles are kept.
    source_landmarks, target_landmarks : Landmarks
        Corresponding points (paired by order; vertex ids or barycentric), at least 4 not
        in one plane. Their names (e.g. ``eye_L_inner``, ``lip_upper_2``) name the regions
        in quality messages.
    stiffness : sequence of float
        Decreasing membrane weights, one stage each (see :data:`DEFAULT_STIFFNESS`).
    iterations : int
        Closest-point iterations per stage.
    landmark_weight : float
    match_boundaries : bool
        Pull each source boundary loop onto the target boundary loop that follows it
        (open surfaces: eye, mouth and outline loops).
    snap : bool
        Finally move every accepted vertex exactly onto its closest target point, unless
        that would flip a triangle.
    check : bool
        Judge the result (:meth:`QualityReport.check`): a
        :class:`~faceretarget.errors.CorrespondenceWarning` naming the regions below the
        warning thresholds of :mod:`faceretarget.config`, a
        :class:`~faceretarget.errors.CorrespondenceError` past the hard limits. False: only
        return the report.
    what : str
        Who is asking (a method's name), for the messages.

    Returns
    -------
    mesh : Mesh
        Source topology, vertices on the target surface.
    report : QualityReport
    """
    stiffness = tuple(float(a) for a in np.atleast_1d(stiffness))
    if not stiffness or any(a <= 0 or not np.isfinite(a) for a in stiffness):
        raise InputError(
            f"resample_to_topology: stiffness must be positive numbers, got {stiffness}"
        )
    if int(iterations) < 1:
        raise InputError(f"resample_to_topology: iterations must be >= 1, got {iterations}")
    if not landmark_weight > 0:
        raise InputError(
            f"resample_to_topology: landmark_weight must be > 0, got {landmark_weight}"
        )
    src_pos, tgt_pos = paired_positions(
        source_mesh, source_landmarks, target_mesh, target_landmarks
    )
    if np.linalg.matrix_rank(src_pos - src_pos.mean(axis=0), tol=1e-9 * source_mesh.scale) < 3:
        raise DegenerateGeometryError(
            "resample_to_topology: the landmarks lie in a plane (or on a line); give at least 4 landmarks spread over the face"
        )
    # work in the canonical frame (unit landmark radius, target rotated onto the source):
    # the same numbers whatever the units and placement of either face
    frame_s, frame_t = canonical_frames(src_pos, tgt_pos)
    target_original = target_mesh
    source_mesh = Mesh(
        frame_s.to_canonical(source_mesh.vertices),
        source_mesh.triangles,
        name=source_mesh.name,
        _trusted=True,
    )
    target_mesh = Mesh(
        frame_t.to_canonical(target_mesh.vertices),
        target_mesh.triangles,
        name=target_mesh.name,
        _trusted=True,
    )
    src_pos, tgt_pos = paired_positions(
        source_mesh, source_landmarks, target_mesh, target_landmarks
    )
    n = source_mesh.n_vertices
    tri_s = source_mesh.triangles
    x0 = rbf_warp(src_pos, tgt_pos)(source_mesh.vertices)
    lap = uniform_laplacian(tri_s, n)
    lm = to_barycentric(source_landmarks, source_mesh)
    assert lm.barycentric is not None  # to_barycentric returns barycentric landmarks
    p = barycentric_matrix(tri_s[lm.triangle_ids], lm.barycentric, n)
    ptp = (p.T @ p) * landmark_weight
    pt_t = (p.T @ tgt_pos) * landmark_weight
    size = _landmark_radius(tgt_pos)  # 1 in the canonical frame

    matcher = _Matcher(target_mesh, source_mesh, match_boundaries, CORRESPONDENCE_LOOP_MATCH * size)
    x = x0.copy()
    lx0 = lap @ x0

    def solve(alpha: float, targets: np.ndarray, weights: np.ndarray) -> np.ndarray:
        a = sp.diags(weights) + alpha * lap + ptp
        b = weights[:, None] * targets + alpha * lx0 + pt_t
        return SPDFactor(a, what="the non-rigid ICP system").solve(b)

    total = 0
    for alpha in stiffness:
        matcher.pair_loops(x)
        for _ in range(int(iterations)):
            total += 1
            targets, weights = matcher(x)
            x = solve(alpha, targets, weights)
    # untangle: drop the matches around interior triangles that point against the target
    # (a released vertex that had a match still belongs to the face interior: releasing it
    # does not take its triangles out of the count)
    released = np.zeros(n, dtype=bool)
    released_matched = np.zeros(n, dtype=bool)
    rounds = 0
    for _ in range(_UNTANGLE_ROUNDS):
        targets, weights = matcher(x)
        matched = (weights > 0) | released_matched
        bad = _flipped(x, tri_s, matcher.caster, target_mesh) & matched[tri_s].all(axis=1)
        if not bad.any():
            break
        rounds += 1
        grow = np.zeros(n, dtype=bool)
        grow[tri_s[bad]] = True
        for _ in range(_UNTANGLE_RINGS):
            grow |= (source_mesh.adjacency @ grow.astype(np.float64)) > 0
        released_matched |= grow & (weights > 0)
        released |= grow
        weights = np.where(released, 0.0, weights)
        # a middle stiffness: stiff enough to carry the released vertices smoothly over the
        # gap, soft enough to keep the matched ones near the surface (snapped below)
        x = solve(stiffness[len(stiffness) // 2], targets, weights)
        total += 1
    targets, weights = matcher(x)
    matched = (weights > 0) | released_matched
    accepted = (weights > 0) & ~released
    if snap:
        x = _snap(x, targets, accepted, tri_s)
    name = (target_original.name or "target") + " resampled"
    report = quality_report(
        Mesh(x, tri_s, name=name, _trusted=True),
        source_landmarks,
        target_mesh,
        tgt_pos,
        rejected=int((~matched).sum()),
        iterations=total,
        matched=matched,
        target_landmarks=target_landmarks,
        released=int(released.sum()),
        untangle_rounds=rounds,
        loops_paired=[int(j) for j in matcher.pairs],
    )
    report = _in_units(report, frame_t.scale)
    mesh = Mesh(frame_t.from_canonical(x), tri_s, name=name, _trusted=True)
    if check:
        report.check(what)
    return mesh, report


def _in_units(report: QualityReport, scale: float) -> QualityReport:
    """A report measured in the canonical frame, its lengths in the target's units (the
    relative measures are unchanged; ``scale`` is the target's bounding-box diagonal taken
    in the canonical orientation, so that it does not depend on how either face is turned)."""
    import dataclasses

    details = dict(report.details)
    for key in ("residuals", "coverage"):
        details[key] = np.asarray(details[key]) * scale
    return dataclasses.replace(report, scale=report.scale * scale, details=details)


class _Matcher:
    """Closest-point targets and acceptance weights on one target mesh."""

    def __init__(
        self, target: Mesh, source: Mesh, match_boundaries: bool, loop_distance: float = np.inf
    ) -> None:
        from ..geometry.mesh_ops import boundary_edges
        from ..geometry.raycast import RayCaster

        self.target = target
        self.caster = RayCaster(target.vertices, target.triangles, backend="bvh")
        self.t_boundary = np.zeros(target.n_vertices, dtype=bool)
        self.t_boundary[target.boundary_vertices] = True
        self.t_keys = np.sort(_edge_keys(boundary_edges(target.triangles), target.n_vertices))
        self.source_triangles = source.triangles
        self.tgt_loops = boundary_loops(target.triangles) if match_boundaries else []
        self.src_loops = (
            boundary_loops(source.triangles) if (match_boundaries and self.tgt_loops) else []
        )
        self.loop_distance = loop_distance
        self.pairs: list[int] = []
        self.t_normals = target.vertex_normals
        edges = target.edges
        # a match within one mean edge length of the surface is never an outlier
        self.floor = float(
            np.linalg.norm(
                target.vertices[edges[:, 0]] - target.vertices[edges[:, 1]], axis=1
            ).mean()
        )

    def pair_loops(self, x: np.ndarray) -> None:
        """Pair each source boundary loop with the target loop that follows it at the current fit (-1: none)."""
        self.pairs = (
            _match_loops(
                x,
                self.src_loops,
                self.target.vertices,
                self.tgt_loops,
                max_distance=self.loop_distance,
            )
            if self.src_loops
            else []
        )

    def __call__(self, x: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Targets ``(V, 3)`` and weights ``(V,)`` in {0, 1} for the current fit ``x``."""
        from ..geometry.mesh_ops import vertex_normals

        hits = self.caster.closest(x)
        targets = hits.points.copy()
        normals = vertex_normals(x, self.source_triangles)
        agree = (
            np.einsum("ij,ij->i", normals, _normals_at(self.t_normals, self.target.triangles, hits))
            > _NORMAL_COS
        )
        border = _on_boundary(
            hits.triangle,
            hits.barycentric,
            self.target.triangles,
            self.t_boundary,
            self.t_keys,
            self.target.n_vertices,
        )
        ok = agree & ~border
        dist = np.abs(hits.distance)
        if ok.any():
            gate = _OUTLIER_FACTOR * max(float(np.median(dist[ok])), self.floor / _OUTLIER_FACTOR)
            ok &= dist <= gate
            # the target must lie under the vertex too, not only beside it: a line along the
            # vertex normal that meets no target surface nearby crosses a hole (a filled eye
            # over an open one, a mouth bag behind the lips)
            idx = np.flatnonzero(ok)
            along = self.caster.cast(x[idx], normals[idx], max_distance=2.0 * gate + self.floor)
            ok[idx[~along.hit]] = False
        for loop, j in zip(self.src_loops, self.pairs):
            if j < 0:
                continue
            tl = self.tgt_loops[j]
            targets[loop] = closest_on_polyline(
                x[loop], self.target.vertices, np.stack([tl, np.roll(tl, -1)], axis=1)
            )[2]
            ok[loop] = True
        return targets, ok.astype(np.float64)


def _normals_at(vertex_normals: np.ndarray, triangles: np.ndarray, hits: RayHits) -> np.ndarray:
    """(P, 3) unit target normals at closest points: the barycentric blend of the vertex
    normals, continuous over the surface. (The face normal of the triangle found is not: a
    closest point on an edge or a vertex belongs to every triangle meeting there and the
    search returns any of them, by rounding; at a crease their normals differ widely.)"""
    blend = np.einsum("pk,pkd->pd", hits.barycentric, vertex_normals[triangles[hits.triangle]])
    return unit_rows(blend)


def _flipped(x: np.ndarray, triangles: np.ndarray, caster: RayCaster, target: Mesh) -> np.ndarray:
    """(T,) bool: triangles of the fit ``x`` whose normal points against the target surface
    under them: the sum of the target normals at the closest points of the centroid and of
    the three corners (a triangle straddling a sharp crease, a lip or lid margin, is judged
    against both sides, not against whichever side its centroid happens to be nearest)."""
    from ..geometry.mesh_ops import face_normals

    vn, tri_t = target.vertex_normals, target.triangles
    at = _normals_at(vn, tri_t, caster.closest(x[triangles].mean(axis=1)))
    corner = _normals_at(vn, tri_t, caster.closest(x))
    ref = at + corner[triangles].sum(axis=1)
    return np.einsum("ij,ij->i", face_normals(x, triangles), ref) < 0


def _snap(
    x: np.ndarray, targets: np.ndarray, accepted: np.ndarray, triangles: np.ndarray
) -> np.ndarray:
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


#: Landmark-name keywords -> region named in quality messages (first match wins).
_REGION_WORDS = (
    ("eye", "eyes"),
    ("lid", "eyes"),
    ("brow", "brows"),
    ("lip", "mouth"),
    ("mouth", "mouth"),
    ("nose", "nose"),
    ("jaw", "jaw"),
    ("chin", "jaw"),
    ("cheek", "cheeks"),
    ("forehead", "forehead"),
)


def _region_of(name: str | None, index: int) -> str:
    low = (name or "").lower()
    for word, region in _REGION_WORDS:
        if word in low:
            return region
    return f"near landmark {name or index}"


def _regions(
    points: np.ndarray,
    landmark_points: np.ndarray,
    names: Sequence[str],
    boundary: np.ndarray | None = None,
) -> dict[str, int]:
    """Count ``points (P, 3)`` per named region (nearest landmark's name; "boundary" where ``boundary``)."""
    if len(points) == 0:
        return {}
    nearest = np.argmin(((points[:, None, :] - landmark_points[None]) ** 2).sum(axis=-1), axis=1)
    labels = [_region_of(names[i] if names is not None else None, int(i)) for i in nearest]
    if boundary is not None:
        labels = ["boundary" if b else lab for lab, b in zip(labels, boundary)]
    out: dict[str, int] = {}
    for lab in labels:
        out[lab] = out.get(lab, 0) + 1
    return dict(sorted(out.items(), key=lambda kv: -kv[1]))


def quality_report(
    resampled: Mesh,
    source_landmarks: Landmarks,
    target_mesh: Mesh,
    target_landmark_positions: npt.ArrayLike,
    *,
    rejected: int = 0,
    iterations: int = 0,
    matched: np.ndarray | None = None,
    target_landmarks: Landmarks | None = None,
    released: int = 0,
    untangle_rounds: int = 0,
    loops_paired: Iterable[int] | None = None,
) -> QualityReport:
    """Measure how well ``resampled`` (source topology) fits ``target_mesh``.

    ``matched (V_s,)``: the source vertices that have a counterpart on the target (the
    face interior is the triangles with three matched corners; default: all vertices).
    """
    from ..geometry.raycast import RayCaster

    scale = target_mesh.scale
    tri = resampled.triangles
    n = resampled.n_vertices
    matched = np.ones(n, dtype=bool) if matched is None else np.asarray(matched, dtype=bool)
    on_target = RayCaster(target_mesh.vertices, target_mesh.triangles, backend="bvh")
    hits = on_target.closest(resampled.vertices)
    res = np.abs(hits.distance)
    # the face interior: every corner matched, and none on the rim band of a target hole or
    # outline (where a closed lid meets an open one, or an outline cut elsewhere, the two
    # surfaces do not correspond vertex for vertex; flips there are reported apart)
    rim_band = _rings_from(target_mesh, target_mesh.boundary_vertices, CORRESPONDENCE_RIM_RINGS)
    # (the corners the closest point lies between, not every corner of whichever triangle
    # a tie on an edge returned)
    on_rim = (rim_band[target_mesh.triangles[hits.triangle]] & (hits.barycentric > _ON_EDGE)).any(
        axis=1
    )
    interior = matched[tri].all(axis=1) & ~on_rim[tri].any(axis=1)
    # target coverage by the matched (interior) part of the resampled surface
    covering = matched[tri].all(axis=1)
    if covering.any():
        back = RayCaster(resampled.vertices, tri[covering], backend="bvh").closest(
            target_mesh.vertices
        )
        coverage = np.abs(back.distance)
    else:
        coverage = np.full(target_mesh.n_vertices, np.inf)
    # triangle normals against the target normal at each centroid's closest point
    flipped_all = _flipped(resampled.vertices, tri, on_target, target_mesh)
    flipped = flipped_all & interior
    tgt_lm = np.asarray(target_landmark_positions, dtype=np.float64)
    lm_err = np.linalg.norm(source_landmarks.positions(resampled.vertices, tri) - tgt_lm, axis=1)
    names = None
    if target_landmarks is not None and target_landmarks.names is not None:
        names = list(target_landmarks.names)
    elif source_landmarks.names is not None:
        names = list(source_landmarks.names)
    edges = target_mesh.edges
    edge = float(
        np.linalg.norm(
            target_mesh.vertices[edges[:, 0]] - target_mesh.vertices[edges[:, 1]], axis=1
        ).mean()
    )
    uncovered = coverage > CORRESPONDENCE_UNCOVERED_EDGES * edge
    t_boundary = np.zeros(target_mesh.n_vertices, dtype=bool)
    t_boundary[target_mesh.boundary_vertices] = True
    near_outline = _rings_from(target_mesh, _outline(target_mesh), CORRESPONDENCE_OUTLINE_RINGS)
    centroids = resampled.vertices[tri[flipped]].mean(axis=1)
    s_boundary = np.zeros(n, dtype=bool)
    s_boundary[resampled.boundary_vertices] = True
    details = {
        "residuals": res,
        "coverage": coverage,
        "matched": matched,
        "interior_triangles": int(interior.sum()),
        "flipped_all": int(flipped_all.sum()),
        "flipped_rim": int((flipped_all & matched[tri].all(axis=1) & ~interior).sum()),
        "flipped_ids": np.flatnonzero(flipped),
        "matched_residual_mean": float(res[matched].mean() / scale)
        if matched.any()
        else float("inf"),
        "matched_residual_max": float(res[matched].max() / scale)
        if matched.any()
        else float("inf"),
        "uncovered_share": float(uncovered.mean()),
        "uncovered_inner_share": float((uncovered & ~near_outline).mean()),
        "released": int(released),
        "untangle_rounds": int(untangle_rounds),
        "loops_paired": list(loops_paired or []),
        "regions": {
            "flipped": _regions(centroids, tgt_lm, names, s_boundary[tri[flipped]].any(axis=1)),
            "landmarks": _regions(
                tgt_lm[lm_err > CORRESPONDENCE_LANDMARK_WARN * scale], tgt_lm, names
            ),
            "uncovered": _regions(target_mesh.vertices[uncovered & ~near_outline], tgt_lm, names),
            "residual": _regions(
                resampled.vertices[matched & (res > CORRESPONDENCE_RESIDUAL_WARN * scale)],
                tgt_lm,
                names,
            ),
        },
    }
    return QualityReport(
        residual_mean=float(res.mean() / scale),
        residual_max=float(res.max() / scale),
        coverage_max=float(coverage.max() / scale),
        landmark_error=float(lm_err.max() / scale),
        flipped_triangles=int(flipped.sum()),
        rejected=int(rejected),
        iterations=iterations,
        scale=scale,
        details=details,
    )


def _outline(mesh: Mesh) -> np.ndarray:
    loops = boundary_loops(mesh.triangles)
    return loops[0] if loops else np.zeros(0, dtype=np.int64)


def _rings_from(mesh: Mesh, seeds: np.ndarray, rings: int) -> np.ndarray:
    """(V,) bool: vertices within ``rings`` edge rings of ``seeds``."""
    out = np.zeros(mesh.n_vertices, dtype=bool)
    out[seeds] = True
    adjacency = mesh.adjacency
    for _ in range(int(rings)):
        out |= (adjacency @ out.astype(np.float64)) > 0
    return out
