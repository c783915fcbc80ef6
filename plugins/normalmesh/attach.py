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
    return np.sqrt(np.max(np.stack([np.sum((b - a) ** 2, 1), np.sum((c - b) ** 2, 1), np.sum((a - c) ** 2, 1)]), axis=0))


def attach(points: np.ndarray, finest: np.ndarray, triangles: np.ndarray) -> Attachment:
    """Attach ``points (P, 3)`` to the finest level ``finest (V, 3)``, ``triangles (T, 3)``."""
    hits = closest_points(finest, triangles, points)
    offset = points - hits.points
    turns = np.linalg.norm(offset, axis=1) <= LEVER * _longest_edges(finest, triangles)[hits.triangle]
    local = offset.copy()
    frames = triangle_frames(finest, triangles, hits.triangle[turns])
    local[turns] = np.einsum("pkd,pd->pk", frames, offset[turns])
    corners = triangles[hits.triangle]
    frame_corners = np.where(turns[:, None], corners, -1)
    return Attachment(hits.triangle, np.ascontiguousarray(hits.barycentric), turns, local, corners, frame_corners)


def carry(att: Attachment, finest: np.ndarray) -> np.ndarray:
    """(P, 3) attached points on the finest level with positions ``finest (V, 3)``."""
    from . import _kernels as k

    out = np.empty((len(att.triangle), 3))
    k.carry_points(finest, att.corners, att.barycentric, att.frame_corners, att.local, out)
    return out
