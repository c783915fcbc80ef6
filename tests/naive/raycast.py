"""Brute-force O(N*M) ray and closest-point queries (the references for geometry.raycast).

Every query is tested against every triangle; no acceleration structure. Only for small
meshes (a few thousand queries x a few thousand triangles).
"""

from __future__ import annotations

import numpy as np


def cast_rays(
    vertices, triangles, origins, directions, *, both_directions=True, max_distance=np.inf
):
    """Nearest hit by |t| of each line; returns (triangle (R,), t (R,), barycentric (R, 3)).

    Misses give triangle -1, t NaN and NaN barycentrics. Directions are normalised.
    ``max_distance`` is a number or one per ray.
    """
    v = np.asarray(vertices, float)
    t = np.asarray(triangles)
    a, b, c = v[t[:, 0]], v[t[:, 1]], v[t[:, 2]]
    normal = np.cross(b - a, c - a)
    n_rays = len(origins)
    limit = np.broadcast_to(np.asarray(max_distance, float), (n_rays,))
    out_tri = np.full(n_rays, -1)
    out_t = np.full(n_rays, np.nan)
    out_bary = np.full((n_rays, 3), np.nan)
    for r in range(n_rays):
        o = np.asarray(origins[r], float)
        d = np.asarray(directions[r], float)
        length = np.linalg.norm(d)
        if length == 0:
            continue
        d = d / length
        # plane intersection, then inside test by sub-triangle areas (Cramer's rule)
        denom = normal @ d
        with np.errstate(divide="ignore", invalid="ignore"):
            s = np.einsum("ij,ij->i", normal, a - o) / denom
        p = o + s[:, None] * d
        area = np.einsum("ij,ij->i", normal, normal)
        w0 = np.einsum("ij,ij->i", np.cross(c - b, p - b), normal) / area
        w1 = np.einsum("ij,ij->i", np.cross(a - c, p - c), normal) / area
        w2 = 1.0 - w0 - w1
        eps = 1e-9
        inside = (denom != 0) & (w0 >= -eps) & (w1 >= -eps) & (w2 >= -eps) & np.isfinite(s)
        inside &= np.abs(s) <= limit[r]
        if not both_directions:
            inside &= s >= 0
        if not inside.any():
            continue
        cand = np.flatnonzero(inside)
        k = cand[np.argmin(np.abs(s[cand]))]
        out_tri[r], out_t[r] = k, s[k]
        out_bary[r] = (w0[k], w1[k], w2[k])
    return out_tri, out_t, out_bary


def _closest_on_segment(p, a, b):
    ab = b - a
    denom = np.einsum("ij,ij->i", ab, ab)
    s = np.clip(np.einsum("ij,ij->i", p - a, ab) / np.where(denom > 0, denom, 1.0), 0.0, 1.0)
    return a + s[:, None] * ab


def closest_points(vertices, triangles, points):
    """Closest surface point of each point; returns (triangle (P,), distance (P,), point (P, 3)).

    For every triangle: the projection on its plane if it falls inside, else the closest
    point on its three edges; then the minimum over triangles.
    """
    v = np.asarray(vertices, float)
    t = np.asarray(triangles)
    a, b, c = v[t[:, 0]], v[t[:, 1]], v[t[:, 2]]
    normal = np.cross(b - a, c - a)
    area = np.einsum("ij,ij->i", normal, normal)
    out_tri = np.zeros(len(points), int)
    out_d = np.zeros(len(points))
    out_p = np.zeros((len(points), 3))
    for q, x in enumerate(np.asarray(points, float)):
        xs = np.broadcast_to(x, a.shape)
        proj = xs - (np.einsum("ij,ij->i", xs - a, normal) / area)[:, None] * normal
        w0 = np.einsum("ij,ij->i", np.cross(c - b, proj - b), normal) / area
        w1 = np.einsum("ij,ij->i", np.cross(a - c, proj - c), normal) / area
        inside = (w0 >= 0) & (w1 >= 0) & (w0 + w1 <= 1)
        cands = [np.where(inside[:, None], proj, np.inf)]
        for p0, p1 in ((a, b), (b, c), (c, a)):
            cands.append(_closest_on_segment(xs, p0, p1))
        stack = np.stack(cands)  # (4, T, 3)
        d = np.linalg.norm(stack - x, axis=2)
        d = np.where(np.isfinite(d), d, np.inf)
        flat = np.argmin(d.min(axis=0))
        out_tri[q] = flat
        out_d[q] = d[:, flat].min()
        out_p[q] = stack[np.argmin(d[:, flat]), flat]
    return out_tri, out_d, out_p
