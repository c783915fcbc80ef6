"""Base meshes from feature points (Na & Jung 2004 sec. 3.1-3.2).

The base mesh connects the feature points (landmarks) with one triangulation shared by source
and target. The paper builds it by hand; given no ``base_triangles`` we build it
automatically: the source's neutral feature points are projected onto the plane of the two
main axes of its face mesh (a shared 2D parameterization, oriented so that counter-clockwise
means the mesh's outward normal), Delaunay-triangulated, and then

- sliver triangles on the hull (an angle above ``HULL_SLIVER_DEGREES`` opposite a hull edge)
  are peeled off, repeatedly;
- triangles with an edge that bridges a hole or a fold of either mesh (over the mesh, its ends
  are more than ``BRIDGE_RATIO`` times farther apart than in space: across a closed mouth
  whose lips roll inward, across an eye) are dropped;
- triangles that do not lie over the surface of *both* meshes (a sample of the triangle whose
  closest surface point is on a rim, reached sideways rather than along the normal: eye and
  mouth holes, outside the border) are dropped, and so are triangles facing against the
  surface normals at their corners on either mesh (lips rolling inward).

Every base triangle, given or built, must be non-degenerate and face the same way as the
surface at its corners on both meshes, else :class:`DegenerateGeometryError` names it.
"""

from __future__ import annotations

import numpy as np

from faceretarget.errors import DegenerateGeometryError, IndexRangeError, ShapeError
from faceretarget.geometry.mesh_ops import unique_edges
from faceretarget.geometry.raycast import RayCaster

#: Fewest feature points accepted (a base mesh of at least two triangles).
MIN_FEATURE_POINTS = 4
#: A base triangle with 2 * area / longest_edge^2 below this is degenerate (sin of ~0.006 deg).
DEGENERATE_RATIO = 1e-4
#: Hull triangles with an angle above this opposite a hull edge are peeled off (automatic base).
HULL_SLIVER_DEGREES = 130.0
#: A sample whose offset to the closest surface point makes a cosine below this with the
#: surface normal there lies beside the surface (over a hole or beyond the border).
OVER_SURFACE_COS = 0.7
#: A base edge whose ends are more than this times farther apart over the mesh than in space
#: bridges a hole or a fold (automatic base mesh; see :func:`bridging_edges`).
BRIDGE_RATIO = 2.0
#: Fraction of automatic base triangles allowed to face out on one mesh but not the other.
MISMATCH_FRACTION = 0.1
#: Barycentric samples of a base triangle tested for lying over the surface: the centroid, one
#: towards each corner, and one near each edge midpoint (pulled 10% towards the opposite
#: corner, so an edge along the rim of a convex hole still counts as over the surface while
#: an edge across the hole does not).
_SAMPLES = np.array(
    [
        [1 / 3, 1 / 3, 1 / 3],
        [2 / 3, 1 / 6, 1 / 6],
        [1 / 6, 2 / 3, 1 / 6],
        [1 / 6, 1 / 6, 2 / 3],
        [0.45, 0.45, 0.1],
        [0.1, 0.45, 0.45],
        [0.45, 0.1, 0.45],
    ]
)


def point_normals(landmarks, vertex_normals: np.ndarray, triangles: np.ndarray) -> np.ndarray:
    """(N, 3) unit surface normals at landmarks (interpolated vertex normals)."""
    n = landmarks.positions(vertex_normals, triangles)
    length = np.linalg.norm(n, axis=1, keepdims=True)
    return np.divide(n, length, out=np.zeros_like(n), where=length > 0)


def median_edge(points: np.ndarray, triangles: np.ndarray) -> float:
    """Median length of the triangles' edges (an interior edge counted twice, a border edge once)."""
    t = np.asarray(triangles)
    return float(np.median(np.linalg.norm(points[t] - points[np.roll(t, -1, axis=1)], axis=-1)))


def nearest_vertices(landmarks, vertices: np.ndarray, triangles: np.ndarray) -> np.ndarray:
    """(N,) the mesh vertex nearest each landmark (itself for vertex-id landmarks)."""
    if landmarks.vertex_ids is not None:
        return np.asarray(landmarks.vertex_ids, dtype=np.int64)
    corners = np.asarray(triangles)[landmarks.triangle_ids]
    return corners[np.arange(len(corners)), np.argmax(landmarks.barycentric, axis=1)].astype(
        np.int64
    )


def flatten(points: np.ndarray, mesh_vertices: np.ndarray, mesh_normals: np.ndarray) -> np.ndarray:
    """(N, 2) coordinates of ``points`` in the plane of the mesh's two main axes.

    The plane's normal (least-variance axis) is oriented along the mesh's mean vertex normal,
    and the 2D axes are right-handed around it, so a counter-clockwise 2D triangle faces out.
    """
    v = np.asarray(mesh_vertices, dtype=np.float64)
    centre = v.mean(axis=0)
    _, _, vt = np.linalg.svd(v - centre, full_matrices=False)
    e1, e2, n = vt[0], vt[1], vt[2]
    if np.dot(n, np.asarray(mesh_normals).mean(axis=0)) < 0:
        n = -n
    e2 = np.cross(n, e1)
    p = np.asarray(points, dtype=np.float64) - centre
    return np.stack([p @ e1, p @ e2], axis=1)


def _angles(p: np.ndarray, tri: np.ndarray) -> np.ndarray:
    """(K, 3) interior angles (radians) at each corner of 2D or 3D triangles."""
    a, b, c = p[tri[:, 0]], p[tri[:, 1]], p[tri[:, 2]]
    out = []
    for x, y, z in ((a, b, c), (b, c, a), (c, a, b)):
        u, w = y - x, z - x
        cos = np.einsum("ij,ij->i", u, w) / np.maximum(
            np.linalg.norm(u, axis=1) * np.linalg.norm(w, axis=1), np.finfo(float).tiny
        )
        out.append(np.arccos(np.clip(cos, -1.0, 1.0)))
    return np.stack(out, axis=1)


def _hull_edges(tri: np.ndarray) -> set:
    e = np.concatenate([tri[:, [1, 2]], tri[:, [2, 0]], tri[:, [0, 1]]])
    key = np.sort(e, axis=1)
    uniq, counts = np.unique(key, axis=0, return_counts=True)
    return {tuple(x) for x in uniq[counts == 1]}


def peel_slivers(
    tri: np.ndarray, p2: np.ndarray, max_degrees: float = HULL_SLIVER_DEGREES
) -> np.ndarray:
    """Drop hull triangles whose angle opposite a hull edge exceeds ``max_degrees``, repeatedly."""
    limit = np.deg2rad(max_degrees)
    while len(tri) > 1:
        hull = _hull_edges(tri)
        ang = _angles(p2, tri)
        bad = np.zeros(len(tri), dtype=bool)
        for k in range(3):  # edge opposite corner k
            e = np.sort(tri[:, [(k + 1) % 3, (k + 2) % 3]], axis=1)
            on_hull = np.array([tuple(x) in hull for x in e])
            bad |= on_hull & (ang[:, k] > limit)
        if not bad.any() or bad.all():
            break
        tri = tri[~bad]
    return tri


def _cross2(p: np.ndarray, tri: np.ndarray) -> np.ndarray:
    """(K,) z of (b - a) x (c - a) for 2D triangles (twice the signed area)."""
    a, b, c = p[tri[:, 0]], p[tri[:, 1]], p[tri[:, 2]]
    return (b[:, 0] - a[:, 0]) * (c[:, 1] - a[:, 1]) - (b[:, 1] - a[:, 1]) * (c[:, 0] - a[:, 0])


def shape_ratio(points: np.ndarray, tri: np.ndarray) -> np.ndarray:
    """(K,) 2 * area / longest_edge^2 of each triangle (0 for collinear or coincident corners)."""
    a, b, c = points[tri[:, 0]], points[tri[:, 1]], points[tri[:, 2]]
    area2 = (
        np.abs(_cross2(points, tri))
        if points.shape[1] == 2
        else np.linalg.norm(np.cross(b - a, c - a), axis=-1)
    )
    longest = np.max(
        np.stack([np.sum((b - a) ** 2, -1), np.sum((c - b) ** 2, -1), np.sum((a - c) ** 2, -1)]),
        axis=0,
    )
    return np.divide(area2, longest, out=np.zeros_like(area2), where=longest > 0)


def over_surface(tri: np.ndarray, points: np.ndarray, caster: RayCaster) -> np.ndarray:
    """(K,) whether every sample of each triangle lies over the surface.

    A sample lies over the surface when the offset to its closest surface point runs along
    that point's normal (|cos| >= ``OVER_SURFACE_COS``) or is negligible; over a hole or
    beyond the border the closest point is on the rim and the offset runs sideways.
    """
    a, b, c = points[tri[:, 0]], points[tri[:, 1]], points[tri[:, 2]]
    samples = np.einsum("sk,tkd->tsd", _SAMPLES, np.stack([a, b, c], axis=1)).reshape(-1, 3)
    hits = caster.closest(samples)
    v, t = caster.vertices, caster.triangles
    corner = v[t[hits.triangle, 0]]
    normal = np.cross(v[t[hits.triangle, 1]] - corner, v[t[hits.triangle, 2]] - corner)
    offset = samples - hits.points
    length = np.linalg.norm(offset, axis=1)
    cos = np.abs(np.einsum("ij,ij->i", offset, normal)) / np.maximum(
        length * np.linalg.norm(normal, axis=1), np.finfo(float).tiny
    )
    size = np.linalg.norm(np.ptp(v, axis=0))
    ok = (cos >= OVER_SURFACE_COS) | (length <= 1e-9 * size)
    return ok.reshape(len(tri), len(_SAMPLES)).all(axis=1)


def automatic_base_triangles(
    src_points,
    src_vertices,
    src_normals,
    src_caster,
    tgt_points,
    tgt_caster,
    src_point_normals=None,
    tgt_point_normals=None,
    names=None,
    surfaces=None,
) -> np.ndarray:
    """Base connectivity over the feature points, shared by source and target (see module doc).

    ``src_normals`` are the source mesh's vertex normals (orienting the projection);
    ``*_point_normals (N, 3)``, when given, drop triangles facing against the surface at their
    corners on either mesh (an inward-rolling lip). A triangle facing out on one mesh and
    against the surface on the other means the feature points do not correspond (e.g. left
    and right swapped); more than ``MISMATCH_FRACTION`` of them raise DegenerateGeometryError.
    ``surfaces``, when given, is a list of ``(points (N, 3), nearest vertex ids (N,), mesh
    vertices, mesh triangles)`` (one per mesh): triangles with an edge bridging a hole or a
    fold of either mesh are dropped (see :func:`bridging_edges`).
    """
    from scipy.spatial import Delaunay, QhullError

    p2 = flatten(src_points, src_vertices, src_normals)
    try:
        tri = Delaunay(p2).simplices.astype(np.int64)
    except (QhullError, ValueError) as exc:
        raise DegenerateGeometryError(
            f"normalmesh: the feature points could not be triangulated ({str(exc).splitlines()[0]}); "
            "they must not all lie on one line seen from the front; pass base_triangles= to give the connectivity"
        ) from None
    cw = _cross2(p2, tri) < 0
    tri[cw] = tri[cw][:, [0, 2, 1]]
    tri = tri[shape_ratio(p2, tri) > DEGENERATE_RATIO]
    tri = peel_slivers(tri, p2)
    for points, caster in ((src_points, src_caster), (tgt_points, tgt_caster)):
        tri = tri[over_surface(tri, points, caster)]
    for points, ids, verts, faces in surfaces or ():
        tri = tri[~bridging_edges(tri, points, ids, verts, faces)]
    if src_point_normals is not None and tgt_point_normals is not None:
        src_out = _facing(tri, src_points, src_point_normals) > 0
        tgt_out = _facing(tri, tgt_points, tgt_point_normals) > 0
        if (src_out != tgt_out).sum() > max(2, MISMATCH_FRACTION * len(tri)):
            names = names if names is not None else [str(i) for i in range(len(src_points))]
            check_base_triangles(tri[src_out], tgt_points, tgt_point_normals, "target", names)
            check_base_triangles(tri[tgt_out], src_points, src_point_normals, "source", names)
        tri = tri[src_out & tgt_out]
    if len(tri) == 0:
        raise DegenerateGeometryError(
            "normalmesh: no triangle of the feature points lies over both faces' surfaces; check that the "
            "landmarks sit on the meshes, or pass base_triangles= to give the base connectivity"
        )
    return canonical_triangles(tri)


def canonical_triangles(tri: np.ndarray) -> np.ndarray:
    """Each triangle rotated to start at its smallest index (orientation kept), rows sorted: the
    same connectivity in the same order however it was found (Delaunay's order depends on the
    projection, which moves with the source)."""
    tri = np.asarray(tri, dtype=np.int64)
    first = np.argmin(tri, axis=1)
    tri = np.stack([tri[np.arange(len(tri)), (first + k) % 3] for k in range(3)], axis=1)
    return tri[np.lexsort(tri.T[::-1])]


def bridging_edges(
    tri: np.ndarray,
    points: np.ndarray,
    point_vertices: np.ndarray,
    vertices: np.ndarray,
    triangles: np.ndarray,
    ratio: float = BRIDGE_RATIO,
) -> np.ndarray:
    """(K,) whether a triangle has an edge that bridges a gap of the surface: the shortest path
    over the mesh's edges between its ends (from their nearest vertices ``point_vertices``) is
    more than ``ratio`` times their straight distance (or there is none). Such an edge jumps
    across a hole or a fold: an upper and a lower inner-lip point over a closed mouth whose
    lips roll inward, two eyelid points across the eye. Measured: the bridging edges of ICT's
    68-landmark base mesh have ratios 2.1 (eye) to 51 (lips); all others at most 1.45."""
    import scipy.sparse as sp
    from scipy.sparse.csgraph import dijkstra

    tri = np.asarray(tri, dtype=np.int64)
    if len(tri) == 0:
        return np.zeros(0, dtype=bool)
    pairs = np.concatenate([tri[:, [0, 1]], tri[:, [1, 2]], tri[:, [2, 0]]])
    straight = np.linalg.norm(points[pairs[:, 0]] - points[pairs[:, 1]], axis=1)
    e = unique_edges(np.asarray(triangles, dtype=np.int64))
    w = np.linalg.norm(vertices[e[:, 0]] - vertices[e[:, 1]], axis=1)
    n = len(vertices)
    graph = sp.csr_matrix(
        (
            np.concatenate([w, w]),
            (np.concatenate([e[:, 0], e[:, 1]]), np.concatenate([e[:, 1], e[:, 0]])),
        ),
        shape=(n, n),
    )
    path = np.full(len(pairs), np.inf)
    # one search per feature point, only as far as its longest base edge needs
    for a in np.unique(pairs[:, 0]):
        rows = np.flatnonzero(pairs[:, 0] == a)
        reach = dijkstra(
            graph,
            indices=point_vertices[a],
            limit=float(ratio) * float(straight[rows].max()) * (1 + 1e-9),
        )
        path[rows] = reach[point_vertices[pairs[rows, 1]]]
    bridge = ~(path <= ratio * straight)
    return bridge.reshape(3, len(tri)).any(axis=0)


def as_base_triangles(value, n_points: int) -> np.ndarray:
    """Validate user-given base connectivity ``(K, 3)`` over ``n_points`` feature points."""
    arr = np.asarray(value)
    if arr.ndim != 2 or arr.shape[1] != 3 or arr.shape[0] == 0 or arr.dtype.kind not in "iu":
        raise ShapeError(
            f"normalmesh: base_triangles must be a (K, 3) integer array with K >= 1, got shape {arr.shape} dtype {arr.dtype}"
        )
    arr = arr.astype(np.int64)
    if arr.min() < 0 or arr.max() >= n_points:
        raise IndexRangeError(
            f"normalmesh: base_triangles index the {n_points} feature points (0..{n_points - 1}); got {arr.min()}..{arr.max()}"
        )
    if ((arr[:, 0] == arr[:, 1]) | (arr[:, 1] == arr[:, 2]) | (arr[:, 0] == arr[:, 2])).any():
        raise DegenerateGeometryError("normalmesh: a base triangle repeats a feature point")
    return arr


def _facing(tri: np.ndarray, points: np.ndarray, normals: np.ndarray) -> np.ndarray:
    """(K,) dot of each triangle's normal with the sum of the surface normals at its corners."""
    a, b, c = points[tri[:, 0]], points[tri[:, 1]], points[tri[:, 2]]
    return np.einsum("ij,ij->i", np.cross(b - a, c - a), normals[tri].sum(axis=1))


def check_base_triangles(
    tri: np.ndarray, points: np.ndarray, normals: np.ndarray, what: str, names
) -> None:
    """Raise DegenerateGeometryError for degenerate base triangles or ones facing against the surface."""

    def label(k):
        return f"#{k} ({', '.join(names[i] for i in tri[k])})"

    ratio = shape_ratio(points, tri)
    bad = np.flatnonzero(ratio <= DEGENERATE_RATIO)
    if bad.size:
        raise DegenerateGeometryError(
            f"normalmesh: {bad.size} base triangle(s) on the {what} are degenerate (corners coincident or in a line), "
            f"first {label(bad[0])}; move the feature points apart or give other base_triangles"
        )
    bad = np.flatnonzero(_facing(tri, points, normals) <= 0)
    if bad.size:
        raise DegenerateGeometryError(
            f"normalmesh: {bad.size} base triangle(s) are flipped on the {what} (they face against the surface), "
            f"first {label(bad[0])}; list base triangle corners counter-clockwise seen from outside, and check "
            "that source and target feature points correspond in order"
        )
