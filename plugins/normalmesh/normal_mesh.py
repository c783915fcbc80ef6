"""Normal meshes (Guskov et al. 2000) over a base mesh of feature points (Na & Jung 2004 sec. 3).

A normal mesh is the base mesh plus, per level, one displacement per new vertex: the level
``l + 1`` mesh is the *unlifted* Loop prediction of level ``l`` (even vertices kept, odd
vertices by Loop's edge rule) with each odd vertex moved to where the line along the
predicted surface normal meets the original mesh (both directions, nearest hit). A vertex is
stored in its local frame (t1, t2, n) (see :mod:`._kernels`) as ``tangent (2,)`` and ``offset``:
for a ray hit the tangent part is zero and the offset is the paper's scalar normal offset.

Special cases (sec. 4.4):

- boundary: an odd vertex on a base-boundary edge whose two ends lie on one boundary loop of
  the original mesh gets the displacement to the closest point of that loop (perpendicular
  to the original boundary edge it lands on); a base-boundary vertex whose ray misses is
  moved the same way onto the nearest boundary when that is close enough;
- piercing errors: a miss, a hit farther than ``max_offset`` x the length of the coarse edge
  the vertex splits, a hit on a triangle facing away from the ray's normal (a flipped hit),
  or a hit that folds a triangle of the new level over (of a folded triangle's new vertices,
  the one that moved farthest from its prediction, relative to its edge); such a vertex is
  replaced by the average of its neighbours (boundary vertices: of their boundary
  neighbours) and counted. With ``repair="surface"`` (default)
  the average is then moved to its closest point on the original mesh (within the same
  distance limit, unless that folds a triangle): a repaired vertex lies on the surface, so
  the finer levels above it find their hits instead of inheriting the error (on ICT the
  cascade made up 80% of the count). ``repair="average"`` is the paper's rule.

Frames of a fixed-topology sequence (temporal correspondence, sec. 3.1) reuse the neutral's
choices: the same vertices are boundary vertices, and each ray starts a walk over the frame's
mesh from the triangle it hit on the neutral (:func:`faceretarget.geometry.raycast.walk_rays`),
with a BVH (refitted to the frame) for walks that fail. A piercing error in a frame is
repaired (``repair="surface"``) by the material point of the vertex's place on the neutral
(its hit, or its repaired closest point: ``anchor``), carried by the frame's triangle.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import scipy.sparse as sp
from scipy.sparse.csgraph import connected_components

from faceretarget._validate import readonly
from faceretarget.geometry.mesh_ops import directed_edges, face_areas
from faceretarget.geometry.raycast import BVH, RayCaster, build_bvh, triangle_neighbors
from faceretarget.geometry.subdivision import LoopStep, edge_table, loop_hierarchy

KIND_RAY, KIND_BOUNDARY, KIND_REPAIRED = 0, 1, 2
#: Repair rules of a piercing error: neighbour average then closest surface point, or the
#: neighbour average alone (the paper).
REPAIRS = ("surface", "average")
#: Rounds of the fold check (each flags one odd vertex per folded triangle: the one that moved
#: farthest from its prediction relative to its edge).
FOLD_ROUNDS = 8
#: A repaired vertex is moved to its closest surface point only if the offset makes at least
#: this cosine with the surface normal there (it lies over the surface, not beside a hole).
OVER_SURFACE_COS = 0.7
#: Jacobi sweeps of the neighbour average that repairs a piercing error.
REPAIR_SWEEPS = 3
#: Boundary segments kept per boundary vertex (nearest on the neutral) for the frames.
BOUNDARY_CANDIDATES = 8
#: A feature point within this fraction of the mesh size of a boundary edge lies on the boundary.
ON_BOUNDARY_TOL = 1e-6


@dataclass(frozen=True)
class Hierarchy:
    """Topology of a normal mesh: base triangles and one unlifted Loop step per level.

    rings[l] : (indptr, indices) neighbour lists of the level ``l + 1`` mesh used by the repair
    (a boundary vertex lists only its boundary neighbours).
    """

    base_triangles: np.ndarray
    n_base: int
    steps: tuple[LoopStep, ...]
    rings: tuple[tuple[np.ndarray, np.ndarray], ...]

    @property
    def levels(self) -> int:
        return len(self.steps)

    def triangles(self, level: int) -> np.ndarray:
        """(T_l, 3) triangles of level ``level`` (0 = base)."""
        return self.base_triangles if level == 0 else self.steps[level - 1].triangles

    def n_vertices(self, level: int) -> int:
        return self.n_base if level == 0 else self.steps[level - 1].n_fine


def make_hierarchy(base_triangles: np.ndarray, n_base: int, levels: int) -> Hierarchy:
    """The subdivision operators (sparse, built once) and repair rings of ``levels`` levels."""
    tri = np.asarray(base_triangles, dtype=np.int64)
    steps = tuple(loop_hierarchy(tri, n_base, levels, even="keep"))
    return Hierarchy(tri, int(n_base), steps, tuple(_repair_ring(s) for s in steps))


def _repair_ring(step: LoopStep) -> tuple[np.ndarray, np.ndarray]:
    edges, _, counts = edge_table(step.triangles)
    n = step.n_fine
    pairs = np.concatenate([edges, edges[:, ::-1]])
    on_boundary_edge = np.concatenate([counts == 1, counts == 1])
    keep = ~step.boundary_vertex[pairs[:, 0]] | on_boundary_edge
    pairs = pairs[keep]
    m = sp.csr_matrix((np.ones(len(pairs)), (pairs[:, 0], pairs[:, 1])), shape=(n, n))
    return m.indptr.astype(np.int64), m.indices.astype(np.int64)


@dataclass(frozen=True)
class Surface:
    """Topology of an original mesh used by the queries: neighbours and boundary loops.

    segments : (S, 2) boundary edges; loops : (S,) boundary loop id of each segment.
    """

    triangles: np.ndarray
    neighbors: np.ndarray
    segments: np.ndarray
    loops: np.ndarray

    @classmethod
    def of(cls, triangles: np.ndarray, n_vertices: int) -> Surface:
        tri = np.asarray(triangles, dtype=np.int64)
        _, inverse, counts = edge_table(tri)
        seg = directed_edges(tri)[counts[inverse] == 1]  # in the triangle's orientation
        loops = np.zeros(len(seg), dtype=np.int64)
        if len(seg):
            g = sp.csr_matrix(
                (np.ones(len(seg)), (seg[:, 0], seg[:, 1])), shape=(n_vertices, n_vertices)
            )
            _, label = connected_components(g, directed=False)
            loops = label[seg[:, 0]].astype(np.int64)
        return cls(tri, triangle_neighbors(tri), seg, loops)


@dataclass(frozen=True)
class NormalMesh:
    """One mesh as a normal mesh. Per level ``l = 1..L`` (index ``l - 1``), per odd vertex:

    tangent (E, 2), offset (E,) : displacement in the local frame (offset = normal offset)
    kind (E,) int8 : KIND_RAY, KIND_BOUNDARY or KIND_REPAIRED
    hit (E,) int64 : original triangle the ray hit (-1: none, boundary or miss)
    candidates (E, K) int64 : nearest boundary segments of boundary vertices (-1 elsewhere)
    anchor (E,) int64, anchor_bary (E, 3) : the original triangle and barycentric point the
        vertex lies on (its hit, or a repaired vertex's closest point; -1: off the surface or
        a boundary vertex), which repairs the vertex's piercing errors in animation frames
    positions : level 0..L vertex positions
    """

    positions: tuple[np.ndarray, ...]
    tangent: tuple[np.ndarray, ...]
    offset: tuple[np.ndarray, ...]
    kind: tuple[np.ndarray, ...]
    hit: tuple[np.ndarray, ...]
    candidates: tuple[np.ndarray, ...]
    anchor: tuple[np.ndarray, ...]
    anchor_bary: tuple[np.ndarray, ...]

    @property
    def n_pierced(self) -> int:
        """Vertices whose piercing error was repaired (paper Table 1)."""
        return int(sum(int((k == KIND_REPAIRED).sum()) for k in self.kind))


def base_triangle_of_vertices(hierarchy: Hierarchy) -> np.ndarray:
    """(V_L,) a base triangle each finest-level vertex lies on (a vertex shared by several
    triangles is given to one of them; -1: a feature point in no base triangle)."""
    L = hierarchy.levels
    tri = hierarchy.triangles(L)
    owner = np.full(hierarchy.n_vertices(L), -1, dtype=np.int64)
    for c in range(3):
        owner[tri[:, c]] = np.arange(len(tri)) >> (2 * L)  # children 4t..4t+3 of triangle t
    return owner


def piercing_share(hierarchy: Hierarchy, kinds) -> np.ndarray:
    """(K,) share of the vertices of each base triangle's patch (all levels) that are piercing
    errors, for per-level odd-vertex kinds ``kinds`` (a NormalMesh's ``kind``, or a frame's)."""
    owner = base_triangle_of_vertices(hierarchy)
    n_base = len(hierarchy.base_triangles)
    repaired = np.concatenate(
        [np.zeros(hierarchy.n_base, dtype=bool)] + [np.asarray(k) == KIND_REPAIRED for k in kinds]
    )
    used = owner >= 0
    total = np.bincount(owner[used], minlength=n_base).astype(float)
    bad = np.bincount(owner[used & repaired], minlength=n_base).astype(float)
    return bad / np.maximum(total, 1.0)


def normal_mesh_area(nm: NormalMesh, hierarchy: Hierarchy) -> float:
    """Total area of the finest level."""
    return float(face_areas(nm.positions[-1], hierarchy.triangles(hierarchy.levels)).sum())


# ----------------------------------------------------------------------------------------
# shared steps of one level
# ----------------------------------------------------------------------------------------
def _predict(step: LoopStep, X: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Unlifted Loop prediction ``(V1, 3)`` and its unit vertex normals."""
    from faceretarget.geometry._mesh_ops_kernels import vertex_normals

    pred = np.ascontiguousarray(step.matrix @ X)
    normals = np.empty_like(pred)
    vertex_normals(readonly(pred), readonly(step.triangles), normals)  # one kernel (read-only)
    return pred, normals


def _max_offsets(step: LoopStep, X: np.ndarray, ratio: float) -> np.ndarray:
    a, b = step.edges[:, 0], step.edges[:, 1]
    return ratio * np.linalg.norm(X[b] - X[a], axis=1)


def _hit_faces_agree(vertices, triangles, tri, normals) -> np.ndarray:
    """Whether each hit triangle faces the same way as the ray's normal (not a flipped hit)."""
    a = vertices[triangles[tri, 0]]
    n = np.cross(vertices[triangles[tri, 1]] - a, vertices[triangles[tri, 2]] - a)
    return np.einsum("ij,ij->i", n, normals) > 0


def cast_agreeing(caster: RayCaster, origins: np.ndarray, normals: np.ndarray, limit: np.ndarray):
    """Lines along ``normals`` through ``origins`` (both directions): the nearest hit within
    ``limit``, kept if its triangle faces the same way as the normal (else none). Returns
    (triangle (-1: none), points, barycentric)."""
    hits = caster.cast(origins, normals, max_distance=limit)
    good = hits.hit.copy()
    good[good] = _hit_faces_agree(
        caster.vertices, caster.triangles, hits.triangle[good], normals[good]
    )
    return np.where(good, hits.triangle, -1), hits.points, hits.barycentric


def _segment_closest(
    points: np.ndarray, p0: np.ndarray, p1: np.ndarray
) -> tuple[np.ndarray, np.ndarray]:
    """Closest points on segments (broadcast) and squared distances."""
    d = p1 - p0
    den = np.einsum("...j,...j->...", d, d)
    s = np.clip(np.einsum("...j,...j->...", points - p0, d) / np.where(den > 0, den, 1.0), 0.0, 1.0)
    q = p0 + s[..., None] * d
    return q, np.einsum("...j,...j->...", points - q, points - q)


def boundary_candidates(
    points, vertices, surface: Surface, loops: np.ndarray, k: int = BOUNDARY_CANDIDATES
) -> np.ndarray:
    """(P, k) ids of the boundary segments nearest each point, nearest first (-1 pads).

    Only segments of loop ``loops[p]`` count where that is >= 0. Segments are preselected by
    their midpoints (KD-tree, ``4 k`` of them), then ranked by exact distance; a point whose
    preselection holds no segment of its loop is searched exhaustively.
    """
    from scipy.spatial import cKDTree

    points = np.asarray(points, dtype=np.float64)
    out = np.full((len(points), k), -1, dtype=np.int64)
    n_seg = len(surface.segments)
    if len(points) == 0 or n_seg == 0:
        return out
    p0 = vertices[surface.segments[:, 0]]
    p1 = vertices[surface.segments[:, 1]]
    loops = np.asarray(loops, dtype=np.int64)

    def rank(rows, cand):
        _, d2 = _segment_closest(points[rows, None, :], p0[cand], p1[cand])
        d2 = np.where(
            (loops[rows, None] >= 0) & (surface.loops[cand] != loops[rows, None]), np.inf, d2
        )
        order = np.argsort(d2, axis=1, kind="stable")[:, :k]
        best = np.take_along_axis(cand, order, axis=1)
        best[np.isinf(np.take_along_axis(d2, order, axis=1))] = -1
        out[rows, : best.shape[1]] = best

    m = min(4 * k, n_seg)
    _, near = cKDTree(0.5 * (p0 + p1)).query(points, k=m)
    near = near.reshape(len(points), m)
    rank(np.arange(len(points)), near)
    missing = np.flatnonzero(out[:, 0] < 0)
    for lo in range(0, len(missing), 64):
        rows = missing[lo : lo + 64]
        rank(rows, np.broadcast_to(np.arange(n_seg), (len(rows), n_seg)))
    return out


def closest_on_candidates(
    points, vertices, surface: Surface, candidates: np.ndarray
) -> tuple[np.ndarray, np.ndarray]:
    """Closest point of each point on its candidate boundary segments, and the distance."""
    if len(points) == 0:
        return np.zeros((0, 3)), np.zeros(0)
    valid = candidates >= 0
    seg = surface.segments[np.where(valid, candidates, 0)]
    q, d2 = _segment_closest(points[:, None, :], vertices[seg[..., 0]], vertices[seg[..., 1]])
    d2 = np.where(valid, d2, np.inf)
    best = np.argmin(d2, axis=1)
    rows = np.arange(len(points))
    return q[rows, best], np.sqrt(d2[rows, best])


def _finish(step: LoopStep, ring, pred, normals, Y, flagged, place=None):
    """Fold check, neighbour-average repair, local coordinates. Modifies ``Y``, ``flagged``.

    While a triangle of the new level is folded over (its normal opposes the prediction's)
    and none of its odd vertices is flagged yet, the one that moved farthest from its
    prediction (relative to its edge) is flagged. Flagged vertices (piercing errors) are
    then repaired: the average of their neighbours, moved onto the surface by
    ``place(e, points)`` when given (returning the new positions, whether each was placed,
    and their triangle and barycentric point on the surface) unless that folds a triangle.
    Returns tangent, offset and the anchors (triangle (-1: none), barycentric) of the
    repaired vertices left on the surface.
    """
    from . import _kernels as k

    n0 = step.n_coarse
    bad = n0 + np.flatnonzero(flagged)
    Y[bad] = pred[bad]
    for _ in range(FOLD_ROUNDS):
        before = flagged.copy()
        k.fold_culprits(Y, pred, step.triangles, n0, step.edges, flagged)
        new = n0 + np.flatnonzero(flagged & ~before)
        if new.size == 0:
            break
        Y[new] = pred[new]
    bad = n0 + np.flatnonzero(flagged)
    anchor = np.full(step.n_odd, -1, dtype=np.int64)
    anchor_bary = np.zeros((step.n_odd, 3))
    if bad.size:
        k.neighbour_average(Y, bad, ring[0], ring[1], REPAIR_SWEEPS)
        if place is not None:
            e = bad - n0
            average = Y[bad].copy()
            pos, ok, tri, bary = place(e, average)
            Y[bad[ok]] = pos[ok]
            again = np.zeros(step.n_odd, dtype=bool)
            k.flipped_odd(Y, pred, step.triangles, n0, again)
            undo = ok & again[e]
            Y[bad[undo]] = average[undo]
            keep = ok & ~undo
            anchor[e[keep]], anchor_bary[e[keep]] = tri[keep], bary[keep]
    tangent = np.empty((step.n_odd, 2))
    offset = np.empty(step.n_odd)
    k.local_coords(pred, normals, step.edges, n0, Y, tangent, offset)
    return tangent, offset, anchor, anchor_bary


def _closest_placement(caster: RayCaster, limit: np.ndarray):
    """``place`` for :func:`_finish` on a neutral: the closest surface point within ``limit[e]``,
    if it lies under the point (the offset runs along the surface normal there, |cos| >=
    ``OVER_SURFACE_COS``): a point over a hole would be pulled onto the hole's rim."""

    def place(e, points):
        hits = caster.closest(points, max_distance=limit[e])
        ok = hits.hit.copy()
        t = caster.triangles[hits.triangle[ok]]
        v = caster.vertices
        normal = np.cross(v[t[:, 1]] - v[t[:, 0]], v[t[:, 2]] - v[t[:, 0]])
        offset = points[ok] - hits.points[ok]
        length = np.linalg.norm(offset, axis=1)
        cos = np.abs(np.einsum("ij,ij->i", offset, normal)) / np.maximum(
            length * np.linalg.norm(normal, axis=1), np.finfo(float).tiny
        )
        ok[ok] = (cos >= OVER_SURFACE_COS) | (length <= 1e-9 * limit[e][ok])
        return hits.points, ok, hits.triangle, hits.barycentric

    return place


def feature_point_loops(points: np.ndarray, vertices: np.ndarray, surface: Surface) -> np.ndarray:
    """(N,) boundary loop id of each feature point lying on an original boundary, else -1."""
    out = np.full(len(points), -1, dtype=np.int64)
    if len(surface.segments) == 0:
        return out
    tol = ON_BOUNDARY_TOL * float(np.linalg.norm(np.ptp(vertices, axis=0)))
    cand = boundary_candidates(points, vertices, surface, out, k=1)
    _, dist = closest_on_candidates(points, vertices, surface, cand)
    on = dist <= tol
    out[on] = surface.loops[cand[on, 0]]
    return out


# ----------------------------------------------------------------------------------------
# construction on a neutral mesh (full ray casting)
# ----------------------------------------------------------------------------------------
def build_normal_mesh(
    vertices: np.ndarray,
    surface: Surface,
    base: np.ndarray,
    base_loops: np.ndarray,
    hierarchy: Hierarchy,
    *,
    max_offset: float,
    caster: RayCaster | None = None,
    repair: str = "surface",
) -> NormalMesh:
    """Normal mesh of the original mesh ``vertices`` over ``base (N, 3)`` feature points.

    ``base_loops (N,)``: boundary loop of each feature point on the original mesh (-1: none).
    ``repair``: "surface" or "average" (see the module doc).
    """
    v = np.asarray(vertices, dtype=np.float64)
    caster = caster or RayCaster(v, surface.triangles)
    X = np.ascontiguousarray(base, dtype=np.float64)
    loops = np.asarray(base_loops, dtype=np.int64)
    keys = ("positions", "tangent", "offset", "kind", "hit", "candidates", "anchor", "anchor_bary")
    out = {k: [] for k in keys}
    out["positions"].append(X)
    for step, ring in zip(hierarchy.steps, hierarchy.rings):
        n0, n_odd = step.n_coarse, step.n_odd
        pred, normals = _predict(step, X)
        odd_pred, odd_n = pred[n0:], normals[n0:]
        a, b = step.edges[:, 0], step.edges[:, 1]
        odd_loops = np.where(
            step.boundary_edge & (loops[a] >= 0) & (loops[a] == loops[b]), loops[a], -1
        )
        kind = np.where(odd_loops >= 0, KIND_BOUNDARY, KIND_RAY).astype(np.int8)
        hit = np.full(n_odd, -1, dtype=np.int64)
        hit_bary = np.zeros((n_odd, 3))
        maxd = _max_offsets(step, X, max_offset)
        Y = pred.copy()
        ray = np.flatnonzero(kind == KIND_RAY)
        tri, pts, bary = cast_agreeing(caster, odd_pred[ray], odd_n[ray], maxd[ray])
        good = tri >= 0
        Y[n0 + ray[good]] = pts[good]
        hit[ray[good]] = tri[good]
        hit_bary[ray[good]] = bary[good]
        # a base-boundary vertex whose ray found nothing usable: onto the nearest boundary
        rescue = ray[~good & step.boundary_edge[ray]]
        cand = np.full((n_odd, BOUNDARY_CANDIDATES), -1, dtype=np.int64)
        if rescue.size:
            c = boundary_candidates(odd_pred[rescue], v, surface, np.full(rescue.size, -1))
            q, dist = closest_on_candidates(odd_pred[rescue], v, surface, c)
            near = dist <= maxd[rescue]
            kind[rescue[near]] = KIND_BOUNDARY
            odd_loops[rescue[near]] = surface.loops[c[near, 0]]
        bnd = np.flatnonzero(kind == KIND_BOUNDARY)
        cand[bnd] = boundary_candidates(odd_pred[bnd], v, surface, odd_loops[bnd])
        q, _ = closest_on_candidates(odd_pred[bnd], v, surface, cand[bnd])
        Y[n0 + bnd] = q
        flagged = (kind == KIND_RAY) & (hit < 0)
        flagged[bnd] = False
        place = _closest_placement(caster, maxd) if repair == "surface" else None
        tangent, offset, anchor, anchor_bary = _finish(step, ring, pred, normals, Y, flagged, place)
        kind[flagged] = KIND_REPAIRED
        anchor = np.where(kind == KIND_RAY, hit, anchor)
        anchor_bary = np.where((kind == KIND_RAY)[:, None], hit_bary, anchor_bary)
        X = Y
        loops = np.concatenate([loops, np.where(kind == KIND_BOUNDARY, odd_loops, -1)])
        for key, val in zip(keys, (X, tangent, offset, kind, hit, cand, anchor, anchor_bary)):
            out[key].append(val)
    return NormalMesh(**{k: tuple(v_) for k, v_ in out.items()})


# ----------------------------------------------------------------------------------------
# frames of a sequence with the neutral's topology (temporal correspondence, sec. 3.1)
# ----------------------------------------------------------------------------------------
class FrameDecomposer:
    """Normal offsets of frames of one original mesh topology, from its neutral normal mesh.

    Lines a walk loses are cast again against the whole frame: by brute force when few
    (``BRUTE_BUDGET`` line-triangle tests), else through the neutral's BVH refitted to the frame.
    """

    #: Most line x triangle tests done by brute force before refitting a BVH instead.
    BRUTE_BUDGET = 4_000_000

    def __init__(
        self,
        surface: Surface,
        reference: NormalMesh,
        hierarchy: Hierarchy,
        *,
        max_offset: float,
        neutral_vertices: np.ndarray,
        repair: str = "surface",
    ):
        self.surface = surface
        self.reference = reference
        self.hierarchy = hierarchy
        self.max_offset = float(max_offset)
        self.repair = repair
        self._neutral = np.asarray(neutral_vertices, dtype=np.float64)
        self._bvh: BVH | None = None
        self._boundary = [np.flatnonzero(k == KIND_BOUNDARY) for k in reference.kind]
        self._skip = [k == KIND_BOUNDARY for k in reference.kind]
        # walks start where the previous frame's lines hit (the neutral's at first)
        self._start = [h.copy() for h in reference.hit]

    def _global(self, vertices: np.ndarray, n_lines: int) -> RayCaster:
        if n_lines * len(self.surface.triangles) <= self.BRUTE_BUDGET:
            return RayCaster(vertices, self.surface.triangles, backend="brute")
        if self._bvh is None:
            self._bvh = build_bvh(self._neutral, self.surface.triangles)
        return RayCaster(
            vertices, self.surface.triangles, backend="bvh", bvh=self._bvh.refit(vertices)
        )

    def _anchor_placement(self, vertices: np.ndarray, level: int):
        """``place`` for :func:`_finish` in a frame: the material point of the neutral's anchor."""
        anchor, bary = self.reference.anchor[level], self.reference.anchor_bary[level]
        tri = self.surface.triangles

        def place(e, points):
            a = anchor[e]
            ok = a >= 0
            corners = tri[np.where(ok, a, 0)]
            pos = np.einsum("pk,pkd->pd", bary[e], vertices[corners])
            return pos, ok, a, bary[e]

        return place

    def __call__(self, vertices: np.ndarray, base: np.ndarray, *, keep_positions: bool = False):
        """Per-level local coordinates ``[(E_1, 3), ..., (E_L, 3)]`` (tangent t1, t2, normal offset)
        of one frame, the number of repaired piercing errors, and (``keep_positions``) the
        level positions. ``self.flagged`` keeps the frame's piercing errors per level."""
        from faceretarget.geometry.raycast import WALK_STEPS

        from . import _kernels as k

        v = np.ascontiguousarray(vertices, dtype=np.float64)
        surf, ref = self.surface, self.reference
        X = np.ascontiguousarray(base, dtype=np.float64)
        offsets, positions = [], [X]
        pierced = 0
        self.flagged = []
        for level, (step, ring) in enumerate(zip(self.hierarchy.steps, self.hierarchy.rings)):
            n0 = step.n_coarse
            pred, normals = _predict(step, X)
            Y = pred.copy()
            status = np.empty(step.n_odd, dtype=np.int8)
            found = np.empty(step.n_odd, dtype=np.int64)
            start = self._start[level]
            k.trace_level(  # read-only inputs: one compiled specialization, whatever the caller passed
                readonly(v),
                readonly(surf.triangles),
                readonly(surf.neighbors),
                readonly(X),
                readonly(pred),
                readonly(normals),
                readonly(step.edges),
                n0,
                self._skip[level],
                start,
                self.max_offset,
                WALK_STEPS,
                Y,
                status,
                found,
            )
            lost = np.flatnonzero(status == k.TRACE_LOST)
            if lost.size:
                odd = n0 + lost
                tri, pts, _ = cast_agreeing(
                    self._global(v, lost.size),
                    pred[odd],
                    normals[odd],
                    _max_offsets(step, X, self.max_offset)[lost],
                )
                good = tri >= 0
                Y[odd[good]] = pts[good]
                status[lost] = np.where(good, k.TRACE_HIT, k.TRACE_PIERCED)
                found[lost] = tri
            self._start[level] = np.where(found >= 0, found, start)
            bnd = self._boundary[level]
            if bnd.size:
                Y[n0 + bnd], _ = closest_on_candidates(
                    pred[n0 + bnd], v, surf, ref.candidates[level][bnd]
                )
            flagged = status == k.TRACE_PIERCED
            place = self._anchor_placement(v, level) if self.repair == "surface" else None
            tangent, offset, _, _ = _finish(step, ring, pred, normals, Y, flagged, place)
            pierced += int(flagged.sum())
            self.flagged.append(np.where(flagged, KIND_REPAIRED, KIND_RAY).astype(np.int8))
            offsets.append(np.column_stack([tangent, offset]))
            X = Y
            if keep_positions:
                positions.append(X)
        return offsets, pierced, positions


# ----------------------------------------------------------------------------------------
# reconstruction from base + local coordinates
# ----------------------------------------------------------------------------------------
def reconstruct(
    base: np.ndarray, hierarchy: Hierarchy, tangent, offset, *, levels: int | None = None
) -> list[np.ndarray]:
    """Level positions ``[X_0, ..., X_L]`` of the normal mesh with the given coordinates
    (per level ``tangent (E, 2)`` and ``offset (E,)``)."""
    from . import _kernels as k

    X = np.ascontiguousarray(base, dtype=np.float64)
    out = [X]
    n_levels = hierarchy.levels if levels is None else int(levels)
    for level in range(n_levels):
        step = hierarchy.steps[level]
        pred, normals = _predict(step, X)
        k.place_odd(
            pred,
            normals,
            step.edges,
            step.n_coarse,
            np.ascontiguousarray(tangent[level]),
            np.ascontiguousarray(offset[level]),
            pred,
        )
        X = pred
        out.append(X)
    return out
