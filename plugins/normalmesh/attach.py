"""Output on the target's own vertices: each vertex attached to the finest normal-mesh level.

A target vertex is attached by its closest point on the finest level of the target's neutral
normal mesh (triangle + barycentric coordinates) and its offset from that point. A vertex
on the normal mesh (offset at most ``LEVER`` times the longest edge of its triangle: the
chord error of the finest level) keeps its offset in that triangle's frame and turns with
it. A vertex beyond the normal mesh's border (outside the feature points' hull: forehead,
temples, neck) keeps its offset in head coordinates and follows its closest point's
translation only: turning a long lever arm with a small border triangle swings it with
every wrinkle and jaw rotation (measured on the synthetic faces and ICT: translation only
is 10-30% closer to ground truth). Each frame, a vertex is the carried barycentric point
plus its offset.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from faceretarget.geometry.raycast import closest_points

#: Largest offset, in longest edges of the finest triangle, that turns with that triangle.
LEVER = 1.0
#: Largest offset, in longest edges of the finest triangle, of a point on the normal mesh
#: (see :func:`coverage`).
COVERED = 0.25


@dataclass(frozen=True)
class Attachment:
    """triangle (P,), barycentric (P, 3) on the finest level; turns (P,) whether the offset
    ``local (P, 3)`` is in the triangle's frame (e1, e2, n coordinates) or in head coordinates.

    corners, frame_corners (P, 3): vertex ids of the triangle in the finest level's positions,
    and of the frame triangle (-1 for offsets that do not turn), for :func:`carry`.
    """

    triangle: np.ndarray
    barycentric: np.ndarray
    turns: np.ndarray
    local: np.ndarray
    corners: np.ndarray
    frame_corners: np.ndarray


def triangle_frames(X: np.ndarray, triangles: np.ndarray, tri: np.ndarray) -> np.ndarray:
    """(P, 3, 3) rows e1 = unit(b - a), e2 = n x e1, n = unit normal of triangles ``tri``."""
    a, b, c = (X[triangles[tri, k]] for k in range(3))
    e1 = b - a
    n = np.cross(e1, c - a)
    e1 = e1 / np.maximum(np.linalg.norm(e1, axis=1, keepdims=True), np.finfo(float).tiny)
    n = n / np.maximum(np.linalg.norm(n, axis=1, keepdims=True), np.finfo(float).tiny)
    return np.stack([e1, np.cross(n, e1), n], axis=1)


def _longest_edges(X: np.ndarray, triangles: np.ndarray) -> np.ndarray:
    a, b, c = (X[triangles[:, k]] for k in range(3))
    return np.sqrt(
        np.max(
            np.stack([np.sum((b - a) ** 2, 1), np.sum((c - b) ** 2, 1), np.sum((a - c) ** 2, 1)]),
            axis=0,
        )
    )


def _lowest_tied_triangle(
    triangles: np.ndarray, tri: np.ndarray, bary: np.ndarray, n_vertices: int
) -> tuple[np.ndarray, np.ndarray]:
    """A closest point on an edge or a corner lies on every triangle sharing that edge or corner;
    which one the query returns depends on rounding (so on where the mesh is placed). Take
    the lowest-numbered of them, with the point's barycentric weights in it."""
    tri, bary = tri.copy(), bary.copy()
    on = bary <= 1e-12
    n_t = len(triangles)
    ids = np.repeat(np.arange(n_t), 3)
    # corners: the lowest triangle at each vertex
    at_vertex = np.full(n_vertices, n_t, dtype=np.int64)
    np.minimum.at(at_vertex, triangles.ravel(), ids)
    # edges: the lowest triangle at each (sorted) edge, by key a * V + b
    pairs = np.sort(
        np.stack([triangles, np.roll(triangles, -1, axis=1)], axis=2).reshape(-1, 2), axis=1
    ).astype(np.int64)
    keys, inverse = np.unique(pairs[:, 0] * n_vertices + pairs[:, 1], return_inverse=True)
    at_edge = np.full(len(keys), n_t, dtype=np.int64)
    np.minimum.at(at_edge, inverse.ravel(), ids)
    corners = triangles[tri]
    rows = np.flatnonzero(on.sum(axis=1) == 2)  # at a corner
    if rows.size:
        k = np.argmax(~on[rows], axis=1)
        v = corners[rows, k]
        tri[rows] = at_vertex[v]
        bary[rows] = (triangles[tri[rows]] == v[:, None]).astype(float)
    rows = np.flatnonzero(on.sum(axis=1) == 1)  # on an edge
    if rows.size:
        k = np.argmax(on[rows], axis=1)  # the corner off the edge
        a, b = corners[rows, (k + 1) % 3], corners[rows, (k + 2) % 3]
        wa, wb = bary[rows, (k + 1) % 3], bary[rows, (k + 2) % 3]
        key = np.sort(np.stack([a, b], axis=1), axis=1).astype(np.int64)
        pos = np.searchsorted(keys, key[:, 0] * n_vertices + key[:, 1])
        tri[rows] = at_edge[pos]
        t = triangles[tri[rows]]
        bary[rows] = (t == a[:, None]) * wa[:, None] + (t == b[:, None]) * wb[:, None]
    return tri, bary


def attach(points: np.ndarray, finest: np.ndarray, triangles: np.ndarray) -> Attachment:
    """Attach ``points (P, 3)`` to the finest level ``finest (V, 3)``, ``triangles (T, 3)``."""
    hits = closest_points(finest, triangles, points)
    tri, bary = _lowest_tied_triangle(
        np.asarray(triangles), hits.triangle, hits.barycentric, len(finest)
    )
    offset = points - np.einsum("pk,pkd->pd", bary, finest[triangles[tri]])
    turns = np.linalg.norm(offset, axis=1) <= LEVER * _longest_edges(finest, triangles)[tri]
    local = offset.copy()
    frames = triangle_frames(finest, triangles, tri[turns])
    local[turns] = np.einsum("pkd,pd->pk", frames, offset[turns])
    corners = triangles[tri]
    frame_corners = np.where(turns[:, None], corners, -1)
    return Attachment(tri, np.ascontiguousarray(bary), turns, local, corners, frame_corners)


def carry(att: Attachment, finest: np.ndarray) -> np.ndarray:
    """(P, 3) attached points on the finest level with positions ``finest (V, 3)``."""
    from . import _kernels as k

    out = np.empty((len(att.triangle), 3))
    k.carry_points(finest, att.corners, att.barycentric, att.frame_corners, att.local, out)
    return out


def coverage(
    points: np.ndarray, att: Attachment, finest: np.ndarray, triangles: np.ndarray, band: float
) -> np.ndarray:
    """(P,) weight of the normal mesh in the output of each attached point: 0 off the normal
    mesh, 1 on it farther than ``band`` from any point off it, a smoothstep in between.

    A point is on the normal mesh when its offset from its closest point there is at most
    ``COVERED`` times the longest edge of that triangle (the finest level's chord error);
    distances are straight-line distances between the points (the target neutral's vertices).
    """
    from scipy.spatial import cKDTree

    offset = np.linalg.norm(
        np.einsum("pk,pkd->pd", att.barycentric, finest[att.corners]) - points, axis=1
    )
    on = offset <= COVERED * _longest_edges(finest, triangles)[att.triangle]
    weight = np.zeros(len(points))
    if not on.any():
        return weight
    if on.all() or band <= 0:
        return on.astype(float)
    d, _ = cKDTree(points[~on]).query(points[on], distance_upper_bound=band)
    s = np.clip(d / band, 0.0, 1.0)  # inf (nothing within the band) -> 1
    weight[on] = s * s * (3.0 - 2.0 * s)
    return weight
