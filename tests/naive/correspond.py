"""Brute-force closest points on a triangle mesh: every triangle, by plane projection or edges.

An independent method from the production kernel (Ericson's Voronoi-region test): the
closest point of a triangle is its plane projection when that falls inside, else the
best of the closest points on its three edges.
"""

import numpy as np


def _segment_points(p, x, y):
    d = y - x
    dd = np.einsum("ij,ij->i", d, d)
    t = np.clip(np.einsum("ij,ij->i", p - x, d) / np.where(dd > 0, dd, np.inf), 0.0, 1.0)
    return x + t[:, None] * d


def closest_points_brute(points, vertices, triangles):
    """(closest (P, 3), distances (P,), triangle ids (P,)), checking every triangle for every point."""
    a, b, c = (vertices[triangles[:, k]] for k in range(3))
    n = np.cross(b - a, c - a)
    nn = np.einsum("ij,ij->i", n, n)
    out_c, out_d, out_t = [], [], []
    for p in points:
        cands = [_segment_points(p[None], x, y) for x, y in ((a, b), (b, c), (c, a))]
        q = p - (np.einsum("ij,ij->i", p - a, n) / np.where(nn > 0, nn, np.inf))[:, None] * n
        inside = nn > 0
        for x, y in ((a, b), (b, c), (c, a)):
            inside &= np.einsum("ij,ij->i", np.cross(y - x, q - x), n) >= 0
        cands.append(np.where(inside[:, None], q, np.inf))
        pts = np.stack(cands)  # (4, T, 3)
        d = np.linalg.norm(pts - p, axis=2)
        d = np.where(np.isfinite(d), d, np.inf)
        k, t = np.unravel_index(np.argmin(d), d.shape)
        out_c.append(pts[k, t])
        out_d.append(d[k, t])
        out_t.append(t)
    return np.array(out_c), np.array(out_d), np.array(out_t)
