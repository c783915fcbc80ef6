"""Brute-force references for Loop subdivision and normal-mesh construction.

Plain Python loops over vertices, edges and triangles; ray casting by testing every
triangle (``naive.raycast``). Small meshes only.
"""
from __future__ import annotations

import math

import numpy as np

from naive.raycast import cast_rays


def _edges_in_order(triangles):
    """Sorted unique undirected edges (the odd-vertex order of the fast implementation)."""
    return sorted({tuple(sorted((int(t[i]), int(t[(i + 1) % 3])))) for t in triangles for i in range(3)})


def loop_subdivide_naive(vertices, triangles, even="loop"):
    """One Loop step with boundary rules (see faceretarget.geometry.subdivision), by loops."""
    v = [np.asarray(p, float) for p in vertices]
    tris = [tuple(int(i) for i in t) for t in triangles]
    edges = _edges_in_order(tris)
    edge_tris = {e: [] for e in edges}
    for t in tris:
        for i in range(3):
            a, b = t[i], t[(i + 1) % 3]
            edge_tris[tuple(sorted((a, b)))].append(t[(i + 2) % 3])
    neighbours = {i: set() for i in range(len(v))}
    boundary_nb = {i: set() for i in range(len(v))}
    for (a, b), opp in edge_tris.items():
        neighbours[a].add(b)
        neighbours[b].add(a)
        if len(opp) == 1:
            boundary_nb[a].add(b)
            boundary_nb[b].add(a)
    new = []
    for i, p in enumerate(v):
        if even == "keep" or not neighbours[i]:
            new.append(p.copy())
        elif boundary_nb[i]:
            nb = sorted(boundary_nb[i])
            new.append(0.75 * p + 0.125 * (v[nb[0]] + v[nb[1]]) if len(nb) == 2 else p.copy())
        else:
            n = len(neighbours[i])
            beta = (5 / 8 - (3 / 8 + math.cos(2 * math.pi / n) / 4) ** 2) / n
            new.append((1 - n * beta) * p + beta * sum(v[j] for j in neighbours[i]))
    index = {}
    for e in edges:
        a, b = e
        opp = edge_tris[e]
        if len(opp) == 2:
            new.append(3 / 8 * (v[a] + v[b]) + 1 / 8 * (v[opp[0]] + v[opp[1]]))
        else:
            new.append(0.5 * (v[a] + v[b]))
        index[e] = len(new) - 1
    out_tris = []
    for a, b, c in tris:
        ab, bc, ca = index[tuple(sorted((a, b)))], index[tuple(sorted((b, c)))], index[tuple(sorted((c, a)))]
        out_tris += [(a, ab, ca), (ab, b, bc), (ca, bc, c), (ab, bc, ca)]
    return np.array(new), np.array(out_tris)


def vertex_normals_naive(vertices, triangles):
    acc = np.zeros((len(vertices), 3))
    for a, b, c in triangles:
        n = np.cross(vertices[b] - vertices[a], vertices[c] - vertices[a])
        for i in (a, b, c):
            acc[i] += n
    return acc / np.linalg.norm(acc, axis=1, keepdims=True)


def _rings(triangles, n_vertices):
    edge_count = {}
    for t in triangles:
        for i in range(3):
            e = tuple(sorted((int(t[i]), int(t[(i + 1) % 3]))))
            edge_count[e] = edge_count.get(e, 0) + 1
    on_boundary = {i for e, c in edge_count.items() if c == 1 for i in e}
    ring = {i: [] for i in range(n_vertices)}
    for (a, b), c in edge_count.items():
        for x, y in ((a, b), (b, a)):
            if x not in on_boundary or c == 1:
                ring[x].append(y)
    return ring


def normal_mesh_naive(vertices, triangles, base, base_triangles, levels, max_offset, sweeps=3):
    """Level positions of the normal mesh (no boundary displacements: use a closed mesh).

    Odd vertices: unlifted Loop prediction, line along the predicted mesh's vertex normal,
    nearest hit (both directions) within ``max_offset`` x coarse edge length on a triangle
    facing the same way; otherwise, or when a triangle of the new level flips, the vertex is
    the mean of its neighbours (``sweeps`` Jacobi sweeps). Returns (levels, pierced count).
    """
    v = np.asarray(vertices, float)
    tri = np.asarray(triangles)
    X = np.asarray(base, float)
    T = np.asarray(base_triangles)
    out = [X]
    pierced = 0
    for _ in range(levels):
        n0 = len(X)
        edges = _edges_in_order(T)
        pred, T1 = loop_subdivide_naive(X, T, even="keep")
        normals = vertex_normals_naive(pred, T1)
        origins = pred[n0:]
        dirs = normals[n0:]
        limit = np.array([max_offset * np.linalg.norm(X[b] - X[a]) for a, b in edges])
        hit_tri, t, _ = cast_rays(v, tri, origins, dirs, max_distance=limit)
        Y = pred.copy()
        flagged = np.zeros(len(edges), bool)
        for e in range(len(edges)):
            k = hit_tri[e]
            if k < 0:
                flagged[e] = True
                continue
            a, b, c = v[tri[k]]
            if np.dot(np.cross(b - a, c - a), dirs[e]) <= 0:
                flagged[e] = True
                continue
            Y[n0 + e] = origins[e] + t[e] * dirs[e]
        for a, b, c in T1:
            before = np.cross(pred[b] - pred[a], pred[c] - pred[a])
            after = np.cross(Y[b] - Y[a], Y[c] - Y[a])
            if np.dot(before, after) < 0:
                for i in (a, b, c):
                    if i >= n0:
                        flagged[i - n0] = True
        bad = [n0 + e for e in np.flatnonzero(flagged)]
        ring = _rings(T1, len(Y))
        for i in bad:
            Y[i] = pred[i]
        for _ in range(sweeps):
            new = {i: np.mean([Y[j] for j in ring[i]], axis=0) for i in bad}
            for i in bad:
                Y[i] = new[i]
        pierced += len(bad)
        X, T = Y, T1
        out.append(X)
    return out, pierced
