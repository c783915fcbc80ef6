"""Ray and closest-point queries on triangle meshes through a bounding-volume hierarchy.

Two backends answer line queries (rays in both directions, nearest hit by ``|t|``):

- ``"embree"``: Intel Embree through the maintained ``embreex`` package (x86_64), in float32,
  each hit then re-intersected with its triangle in float64;
- ``"bvh"``: a numba BVH (``_raycast_kernels``), float64, which can be *refitted* to new vertex
  positions of the same topology in O(T) (animation frames).

Closest-point queries always use the numba BVH. Results give, per query, the triangle id
(-1 = nothing within ``max_distance``), barycentric coordinates ``(R, 3)`` of the hit in
that triangle and a signed distance: the ray parameter ``t`` along the unit direction, or
for closest points the distance signed by the side of the triangle's normal.

The brute-force O(N*M) references the tests compare against live in ``tests/naive/raycast.py``.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any

import numpy as np
import numpy.typing as npt

from .._threads import in_blocks, worker_count
from .._validate import check_finite, readonly
from ..errors import ShapeError

__all__ = [
    "BVH",
    "RayHits",
    "RayCaster",
    "build_bvh",
    "cast_rays",
    "closest_points",
    "embree_available",
    "triangle_neighbors",
    "walk_rays",
]

#: Fewest queries for which the kernels run on several threads (below, starting them costs more).
PARALLEL_MIN = 2048
#: Most triangles a walk (:func:`walk_rays`) crosses before giving up.
WALK_STEPS = 64

#: Triangles per BVH leaf.
LEAF_SIZE = 4
#: Bits per axis of the Morton codes ordering the triangles (3 x 21 = 63 bits).
_MORTON_BITS = 21


def embree_available() -> bool:
    """Whether the Embree backend (package ``embreex``) can be imported."""
    try:
        import embreex.mesh_construction  # noqa: F401
        import embreex.rtcore_scene  # noqa: F401
    except Exception:
        return False
    return True


@dataclass(frozen=True)
class RayHits:
    """Answer of a line or closest-point query over R queries.

    triangle : (R,) int64, -1 where nothing was found
    barycentric : (R, 3) float64 weights of the triangle's corners (NaN on a miss)
    distance : (R,) float64 signed distance (NaN on a miss)
    points : (R, 3) float64 the hit / closest points (NaN on a miss)
    """

    triangle: np.ndarray
    barycentric: np.ndarray
    distance: np.ndarray
    points: np.ndarray

    @property
    def hit(self) -> np.ndarray:
        """(R,) bool: where something was found."""
        return self.triangle >= 0


def _morton_codes(centroids: np.ndarray) -> np.ndarray:
    lo = centroids.min(axis=0)
    span = np.maximum(centroids.max(axis=0) - lo, np.finfo(float).tiny)
    q = ((centroids - lo) / span * ((1 << _MORTON_BITS) - 1)).astype(np.int64)
    codes = np.zeros(len(centroids), dtype=np.int64)
    for bit in range(_MORTON_BITS):
        for axis in range(3):
            codes |= ((q[:, axis] >> bit) & 1) << (3 * bit + (2 - axis))
    return codes


@dataclass(frozen=True)
class BVH:
    """A bounding-volume hierarchy over ``triangles`` (flat arrays; picklable).

    node_lo, node_hi : (N, 3) boxes; left, right : (N,) children (-1 for leaves);
    start, count : (N,) leaf ranges into ``order`` : (T,) triangle ids.
    """

    vertices: np.ndarray
    triangles: np.ndarray
    node_lo: np.ndarray
    node_hi: np.ndarray
    left: np.ndarray
    right: np.ndarray
    start: np.ndarray
    count: np.ndarray
    order: np.ndarray

    def __post_init__(self) -> None:
        # read-only views: the kernels then see one array type whatever the caller passed
        # (a writable and a read-only argument are two numba specializations, compiled apart)
        for name in self.__dataclass_fields__:
            object.__setattr__(self, name, readonly(getattr(self, name)))

    def refit(self, vertices: np.ndarray) -> BVH:
        """The same tree with boxes recomputed for new ``vertices : (V, 3)`` (same topology)."""
        from . import _raycast_kernels as k

        v = _as_points(vertices, "BVH.refit vertices")
        if v.shape != self.vertices.shape:
            raise ShapeError(
                f"BVH.refit: expected vertices of shape {self.vertices.shape}, got {v.shape}"
            )
        lo = np.empty_like(self.node_lo)
        hi = np.empty_like(self.node_hi)
        k.refit_bounds(
            self.left,
            self.right,
            self.start,
            self.count,
            self.order,
            readonly(v),
            self.triangles,
            lo,
            hi,
        )
        return BVH(
            v, self.triangles, lo, hi, self.left, self.right, self.start, self.count, self.order
        )

    @property
    def arrays(
        self,
    ) -> tuple[
        np.ndarray,
        np.ndarray,
        np.ndarray,
        np.ndarray,
        np.ndarray,
        np.ndarray,
        np.ndarray,
        np.ndarray,
        np.ndarray,
    ]:
        """The hierarchy as the kernels take it (the leading arguments of each)."""
        return (
            self.node_lo,
            self.node_hi,
            self.left,
            self.right,
            self.start,
            self.count,
            self.order,
            self.vertices,
            self.triangles,
        )


def _as_points(x: npt.ArrayLike, name: str) -> np.ndarray:
    a = np.ascontiguousarray(np.asarray(x, dtype=np.float64))
    if a.ndim != 2 or a.shape[1] != 3:
        raise ShapeError(f"{name}: expected shape (N, 3), got {a.shape}")
    check_finite(a, name)
    return a


def _as_triangles(t: npt.ArrayLike, n_vertices: int) -> np.ndarray:
    a = np.ascontiguousarray(np.asarray(t, dtype=np.int64))
    if a.ndim != 2 or a.shape[1] != 3 or a.shape[0] == 0:
        raise ShapeError(f"triangles: expected shape (T, 3) with T >= 1, got {a.shape}")
    if a.min() < 0 or a.max() >= n_vertices:
        from ..errors import IndexRangeError

        raise IndexRangeError(f"triangles: indices must lie in 0..{n_vertices - 1}")
    return a


def build_bvh(vertices: np.ndarray, triangles: np.ndarray, *, leaf_size: int = LEAF_SIZE) -> BVH:
    """Build a BVH over ``triangles (T, 3)`` of ``vertices (V, 3)``."""
    from . import _raycast_kernels as k

    v = _as_points(vertices, "vertices")
    t = _as_triangles(triangles, len(v))
    codes = _morton_codes(v[t].mean(axis=1))
    order = np.argsort(codes, kind="stable").astype(np.int64)
    left, right, start, count = k.build_topology(codes[order], int(leaf_size))
    lo = np.empty((len(left), 3))
    hi = np.empty((len(left), 3))
    # read-only, as BVH.refit passes them: one specialization
    k.refit_bounds(
        readonly(left),
        readonly(right),
        readonly(start),
        readonly(count),
        readonly(order),
        readonly(v),
        readonly(t),
        lo,
        hi,
    )
    return BVH(v, t, lo, hi, left, right, start, count, order)


def _unit_directions(directions: npt.ArrayLike, n: int) -> tuple[np.ndarray, np.ndarray]:
    d = _as_points(directions, "directions")
    if d.shape[0] != n:
        raise ShapeError(
            f"origins and directions must have the same length, got {n} and {d.shape[0]}"
        )
    norm = np.linalg.norm(d, axis=1)
    ok = norm > 0
    unit = np.zeros_like(d)
    unit[ok] = d[ok] / norm[ok, None]
    return unit, ok


def _limits(max_distance: float | npt.ArrayLike, n: int) -> np.ndarray:
    m = np.broadcast_to(np.asarray(max_distance, dtype=np.float64), (n,)).copy()
    if np.isnan(m).any() or (m < 0).any():
        raise ShapeError("max_distance must be >= 0 (inf for unlimited)")
    return m


def _hits(
    vertices: np.ndarray, triangles: np.ndarray, tri: np.ndarray, bary: np.ndarray, dist: np.ndarray
) -> RayHits:
    miss = tri < 0
    bary = np.where(miss[:, None], np.nan, bary)
    dist = np.where(miss, np.nan, dist)
    safe = np.where(miss, 0, tri)
    pts = np.einsum("rk,rkd->rd", np.nan_to_num(bary), vertices[triangles[safe]])
    pts[miss] = np.nan
    return RayHits(tri, bary, dist, pts)


def _refine_lines(
    vertices: np.ndarray,
    triangles: np.ndarray,
    tri: np.ndarray,
    origins: np.ndarray,
    directions: np.ndarray,
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Exact float64 line/triangle intersection ``(t, u, v)`` with the given triangles."""
    p0 = vertices[triangles[tri, 0]]
    e1 = vertices[triangles[tri, 1]] - p0
    e2 = vertices[triangles[tri, 2]] - p0
    pv = np.cross(directions, e2)
    det = np.einsum("ij,ij->i", e1, pv)
    inv = np.divide(1.0, det, out=np.zeros_like(det), where=det != 0)
    tv = origins - p0
    u = np.einsum("ij,ij->i", tv, pv) * inv
    qv = np.cross(tv, e1)
    v = np.einsum("ij,ij->i", directions, qv) * inv
    t = np.einsum("ij,ij->i", e2, qv) * inv
    return t, u, v


def _parts(n: int) -> int:
    """Blocks of ``n`` queries: one below :data:`PARALLEL_MIN`, else a thread's each."""
    return 1 if n < PARALLEL_MIN else worker_count(n)


class RayCaster:
    """Repeated queries on one mesh: builds the BVH / Embree scene once, on first use.

    Parameters
    ----------
    vertices : (V, 3) float
    triangles : (T, 3) int
    backend : "auto" | "embree" | "bvh" | "brute"
        Line queries: "auto" uses Embree when ``embreex`` imports, else the numba BVH;
        "brute" tests every triangle (no set-up; for a handful of lines).
    """

    def __init__(
        self,
        vertices: npt.ArrayLike,
        triangles: npt.ArrayLike,
        *,
        backend: str = "auto",
        bvh: BVH | None = None,
    ) -> None:
        self.vertices = _as_points(vertices, "vertices")
        self.triangles = _as_triangles(triangles, len(self.vertices))
        if backend not in ("auto", "embree", "bvh", "brute"):
            raise ShapeError(
                f"RayCaster backend must be 'auto', 'embree', 'bvh' or 'brute', got {backend!r}"
            )
        if backend == "embree" and not embree_available():
            from ..errors import CapabilityError

            raise CapabilityError(
                "the Embree backend needs the package embreex (pip install embreex, x86_64 only); use backend='bvh'"
            )
        if backend == "auto":
            backend = "embree" if embree_available() else "bvh"
        self.backend = backend
        self._bvh = bvh
        self._scene = None

    @property
    def bvh(self) -> BVH:
        if self._bvh is None:
            self._bvh = build_bvh(self.vertices, self.triangles)
        return self._bvh

    def _embree_scene(self) -> Any:
        if self._scene is None:
            from embreex import rtcore_scene
            from embreex.mesh_construction import TriangleMesh

            scene = rtcore_scene.EmbreeScene()
            TriangleMesh(
                scene=scene,
                vertices=self.vertices.astype(np.float32),
                indices=self.triangles.astype(np.int32),
            )
            self._scene = scene
        return self._scene

    def cast(
        self,
        origins: npt.ArrayLike,
        directions: npt.ArrayLike,
        *,
        both_directions: bool = True,
        max_distance: float | npt.ArrayLike = np.inf,
    ) -> RayHits:
        """Nearest hit (by |t|) of lines ``origins + t * directions`` with |t| <= ``max_distance``.

        ``directions`` need not be unit length (they are normalised, so ``distance`` is in
        mesh units); zero directions miss. With ``both_directions=False`` only t >= 0 counts.
        """
        o = _as_points(origins, "origins")
        d, ok = _unit_directions(directions, len(o))
        limit = _limits(max_distance, len(o))
        if self.backend == "embree":
            tri, t, u, v = self._cast_embree(o, d, limit, both_directions)
        elif self.backend == "brute":
            tri, t, u, v = self._cast_brute(o, d, limit, both_directions)
        else:
            tri, t, u, v = self._cast_bvh(o, d, limit, both_directions)
        tri = np.where(ok, tri, -1)
        bary = np.stack([1.0 - u - v, u, v], axis=1)
        return _hits(self.vertices, self.triangles, tri, bary, t)

    def _cast_bvh(
        self, o: np.ndarray, d: np.ndarray, limit: np.ndarray, both: bool
    ) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
        from . import _raycast_kernels as k

        n = len(o)
        tri = np.empty(n, np.int64)
        t, u, v = np.empty(n), np.empty(n), np.empty(n)
        bvh, both = self.bvh.arrays, bool(both)
        in_blocks(
            k.cast_lines,
            n,
            lambda a, b: (*bvh, o[a:b], d[a:b], limit[a:b], both, tri[a:b], t[a:b], u[a:b], v[a:b]),
            parts=_parts(n),
        )
        return tri, t, u, v

    def _cast_brute(
        self, o: np.ndarray, d: np.ndarray, limit: np.ndarray, both: bool
    ) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
        from . import _raycast_kernels as k

        n = len(o)
        tri = np.empty(n, np.int64)
        t, u, v = np.empty(n), np.empty(n), np.empty(n)
        k.cast_lines_brute(self.vertices, self.triangles, o, d, limit, bool(both), tri, t, u, v)
        return tri, t, u, v

    def _cast_embree(
        self, o: np.ndarray, d: np.ndarray, limit: np.ndarray, both: bool
    ) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
        scene = self._embree_scene()
        o32, d32 = o.astype(np.float32), d.astype(np.float32)
        far = np.minimum(limit, np.finfo(np.float32).max).astype(np.float32)
        fwd = scene.run(o32, d32, dists=far.copy(), output=1)
        tri = fwd["primID"].astype(np.int64)
        dist = np.where(tri >= 0, fwd["tfar"].astype(np.float64), np.inf)
        if both:
            bwd = scene.run(o32, -d32, dists=far.copy(), output=1)
            btri = bwd["primID"].astype(np.int64)
            bdist = np.where(btri >= 0, bwd["tfar"].astype(np.float64), np.inf)
            take = bdist < dist
            tri = np.where(take, btri, tri)
        hit = np.flatnonzero(tri >= 0)
        n = len(o)
        t, u, v = np.full(n, np.nan), np.zeros(n), np.zeros(n)
        th, uh, vh = _refine_lines(self.vertices, self.triangles, tri[hit], o[hit], d[hit])
        # float32 hits close to an edge can land just outside their triangle: clamp onto it
        uh, vh = np.clip(uh, 0.0, 1.0), np.clip(vh, 0.0, 1.0)
        over = uh + vh > 1.0
        s = np.where(over, uh + vh, 1.0)
        t[hit], u[hit], v[hit] = th, uh / s, vh / s
        beyond = hit[np.abs(th) > limit[hit]]
        tri[beyond] = -1
        return tri, t, u, v

    def closest(
        self, points: npt.ArrayLike, *, max_distance: float | npt.ArrayLike = np.inf
    ) -> RayHits:
        """Closest surface point of each of ``points (P, 3)`` within ``max_distance``.

        ``distance`` is signed: positive on the side the triangle's normal points to.
        """
        from . import _raycast_kernels as k

        p = _as_points(points, "points")
        n = len(p)
        limit = _limits(max_distance, n)
        tri = np.empty(n, np.int64)
        bary = np.empty((n, 3))
        d2 = np.empty(n)
        bvh, p, limit2 = self.bvh.arrays, readonly(p), limit * limit
        in_blocks(
            k.closest_points,
            n,
            lambda a, b: (*bvh, p[a:b], limit2[a:b], tri[a:b], bary[a:b], d2[a:b]),
            parts=_parts(n),
        )
        hits = _hits(self.vertices, self.triangles, tri, bary, np.sqrt(d2))
        found = tri >= 0
        a = self.vertices[self.triangles[tri[found], 0]]
        normal = np.cross(
            self.vertices[self.triangles[tri[found], 1]] - a,
            self.vertices[self.triangles[tri[found], 2]] - a,
        )
        side = np.einsum("ij,ij->i", p[found] - hits.points[found], normal)
        hits.distance[found] *= np.where(side < 0, -1.0, 1.0)
        return hits


def cast_rays(
    vertices: npt.ArrayLike,
    triangles: npt.ArrayLike,
    origins: npt.ArrayLike,
    directions: npt.ArrayLike,
    *,
    both_directions: bool = True,
    max_distance: float | npt.ArrayLike = np.inf,
    backend: str = "auto",
) -> RayHits:
    """One-off line query (see :meth:`RayCaster.cast`)."""
    return RayCaster(vertices, triangles, backend=backend).cast(
        origins, directions, both_directions=both_directions, max_distance=max_distance
    )


def closest_points(
    vertices: npt.ArrayLike,
    triangles: npt.ArrayLike,
    points: npt.ArrayLike,
    *,
    max_distance: float | npt.ArrayLike = np.inf,
) -> RayHits:
    """One-off closest-point query (see :meth:`RayCaster.closest`)."""
    return RayCaster(vertices, triangles, backend="bvh").closest(points, max_distance=max_distance)


def triangle_neighbors(triangles: np.ndarray) -> np.ndarray:
    """(T, 3) int64: the triangle across the edge opposite corner k of each triangle (-1 if none).

    Edges shared by more than two triangles get -1 (no unique neighbour).
    """
    t = np.asarray(triangles, dtype=np.int64)
    n = len(t)
    # edge opposite corner k: (corner k+1, corner k+2)
    a = np.concatenate([t[:, 1], t[:, 2], t[:, 0]])
    b = np.concatenate([t[:, 2], t[:, 0], t[:, 1]])
    owner = np.tile(np.arange(n), 3)
    corner = np.repeat(np.arange(3), n)
    key = np.minimum(a, b) * (t.max() + 1) + np.maximum(a, b)
    order = np.argsort(key, kind="stable")
    ks = key[order]
    out = np.full((n, 3), -1, dtype=np.int64)
    same = ks[1:] == ks[:-1]
    unique_pair = same.copy()
    unique_pair[1:] &= ~same[:-1]  # not part of a run of three or more
    unique_pair[:-1] &= ~same[1:]
    i = np.flatnonzero(unique_pair)
    first, second = order[i], order[i + 1]
    out[owner[first], corner[first]] = owner[second]
    out[owner[second], corner[second]] = owner[first]
    return out


def walk_rays(
    vertices: npt.ArrayLike,
    triangles: npt.ArrayLike,
    neighbors: npt.ArrayLike,
    origins: npt.ArrayLike,
    directions: npt.ArrayLike,
    start: npt.ArrayLike,
    *,
    max_distance: float | npt.ArrayLike = np.inf,
    max_steps: int = WALK_STEPS,
) -> RayHits:
    """Hits of lines ``origins + t * directions`` (both directions) found by walking the mesh.

    ``start (R,)`` gives a triangle to start from per line (-1: skip). Meant for frames of a
    fixed topology, started from the previous frame's hits: O(steps) per line, and the hit
    found is the crossing reached continuously from the start, not necessarily the nearest.
    ``neighbors`` is :func:`triangle_neighbors` of ``triangles``. Lines that fail (boundary,
    too many steps, farther than ``max_distance``) miss (triangle -1).
    """
    from . import _raycast_kernels as k

    v = _as_points(vertices, "vertices")
    tri_arr = _as_triangles(triangles, len(v))
    o = _as_points(origins, "origins")
    d, ok = _unit_directions(directions, len(o))
    s = np.ascontiguousarray(np.where(ok, np.asarray(start, dtype=np.int64), -1))
    if s.shape != (len(o),):
        raise ShapeError(f"walk_rays: start must have shape ({len(o)},), got {s.shape}")
    limit = _limits(max_distance, len(o))
    n = len(o)
    tri = np.empty(n, np.int64)
    t, u, w = np.empty(n), np.empty(n), np.empty(n)
    k.walk_lines(
        v,
        tri_arr,
        np.ascontiguousarray(neighbors, dtype=np.int64),
        o,
        d,
        s,
        limit,
        int(max_steps),
        tri,
        t,
        u,
        w,
    )
    bary = np.stack([1.0 - u - w, u, w], axis=1)
    return _hits(v, tri_arr, tri, bary, t)
