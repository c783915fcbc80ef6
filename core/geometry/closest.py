"""Closest points on segments and polylines (plain arrays).

Closest points on a triangle mesh are answered by :mod:`faceretarget.geometry.raycast`
(a numba BVH, :meth:`RayCaster.closest`); this module adds the polyline case that
correspondence needs for open boundaries (eye, mouth and outline loops).
"""

from __future__ import annotations

import numpy as np

#: Point-segment pairs evaluated per block in :func:`closest_on_polyline`.
_PAIRS_PER_BLOCK = 1 << 18


def closest_on_segments(
    points: np.ndarray, p0: np.ndarray, p1: np.ndarray
) -> tuple[np.ndarray, np.ndarray]:
    """Closest point of each segment ``p0 -> p1`` to each point (broadcast).

    Returns ``closest (..., 3)`` and ``t (...)`` in [0, 1] with ``closest = p0 + t (p1 - p0)``.
    """
    p, a, b = (np.asarray(x, dtype=np.float64) for x in (points, p0, p1))
    ab = b - a
    den = np.einsum("...i,...i->...", ab, ab)
    t = np.clip(np.einsum("...i,...i->...", p - a, ab) / np.where(den > 0, den, np.inf), 0.0, 1.0)
    return a + t[..., None] * ab, t


def closest_on_polyline(
    points: np.ndarray, vertices: np.ndarray, edges: np.ndarray
) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """Closest points on the segments ``edges (B, 2)`` (vertex ids into ``vertices (V, 3)``).

    Brute force over the segments, in blocks of points (boundary polylines are short).

    Returns
    -------
    edge_ids : (P,) int64
    t : (P,) float64
        The point is ``(1 - t) * vertices[edges[i, 0]] + t * vertices[edges[i, 1]]``.
    closest : (P, 3) float64
    distances : (P,) float64
    """
    pts = np.asarray(points, dtype=np.float64)
    v = np.asarray(vertices, dtype=np.float64)
    e = np.asarray(edges, dtype=np.int64)
    n = len(pts)
    out_e = np.zeros(n, dtype=np.int64)
    out_t = np.zeros(n)
    out_c = np.zeros((n, 3))
    out_d = np.zeros(n)
    a, b = v[e[:, 0]], v[e[:, 1]]
    step = max(1, _PAIRS_PER_BLOCK // max(len(e), 1))
    for start in range(0, n, step):
        sl = slice(start, min(start + step, n))
        c, t = closest_on_segments(pts[sl, None], a[None], b[None])
        d = np.linalg.norm(c - pts[sl, None], axis=2)
        best = np.argmin(d, axis=1)
        rows = np.arange(len(best))
        out_e[sl], out_t[sl], out_c[sl], out_d[sl] = (
            best,
            t[rows, best],
            c[rows, best],
            d[rows, best],
        )
    return out_e, out_t, out_c, out_d
