"""Brute-force references for Loop subdivision and normal-mesh construction.

Plain Python loops over vertices, edges and triangles; ray casting by testing every
triangle (``naive.raycast``). Small meshes only.
"""

from __future__ import annotations

import math

import numpy as np

from naive.raycast import cast_rays, closest_points


def _edges_in_order(triangles):
    """Sorted unique undirected edges (the odd-vertex order of the fast implementation)."""
    return sorted(
        {tuple(sorted((int(t[i]), int(t[(i + 1) % 3])))) for t in triangles for i in range(3)}
    )


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
        ab, bc, ca = (
            index[tuple(sorted((a, b)))],
            index[tuple(sorted((b, c)))],
            index[tuple(sorted((c, a)))],
        )
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


def _folded(pred, Y, tri):
    before = np.cross(pred[tri[1]] - pred[tri[0]], pred[tri[2]] - pred[tri[0]])
    after = np.cross(Y[tri[1]] - Y[tri[0]], Y[tri[2]] - Y[tri[0]])
    return np.dot(before, after) < 0


def normal_mesh_naive(
    vertices,
    triangles,
    base,
    base_triangles,
    levels,
    max_offset,
    sweeps=3,
    repair="surface",
    fold_rounds=8,
):
    """Level positions of the normal mesh (no boundary displacements: use a closed mesh).

    Odd vertices: unlifted Loop prediction, line along the predicted mesh's vertex normal,
    nearest hit (both directions) within ``max_offset`` x coarse edge length on a triangle
    facing the same way; otherwise the vertex is a piercing error. Then, triangle by
    triangle (in order), a triangle of the new level that flips while none of its new
    vertices is flagged flags the new vertex that moved farthest from its prediction
    relative to its edge (back to its prediction), for up to ``fold_rounds`` passes.
    Flagged vertices become the mean of their neighbours (``sweeps`` Jacobi sweeps) and,
    with ``repair="surface"``, then their closest surface point if it is within the limit
    and under them (offset along that triangle's normal, |cos| >= 0.7), unless that flips a
    triangle. Returns (levels, pierced count).
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
        for _ in range(fold_rounds):
            new = False
            for face in T1:
                odd = [i for i in face if i >= n0]
                if not _folded(pred, Y, face) or any(flagged[i - n0] for i in odd):
                    continue
                scores = []
                for i in odd:
                    a, b = edges[i - n0]
                    length = np.sum((X[b] - X[a]) ** 2)
                    moved = np.sum((Y[i] - pred[i]) ** 2)
                    scores.append(moved / length if length > 0 else np.inf)
                culprit = odd[int(np.argmax(scores))]
                flagged[culprit - n0] = True
                new = True
            for e in np.flatnonzero(flagged):
                Y[n0 + e] = pred[n0 + e]
            if not new:
                break
        bad = [n0 + e for e in np.flatnonzero(flagged)]
        ring = _rings(T1, len(Y))
        for _ in range(sweeps):
            new = {i: np.mean([Y[j] for j in ring[i]], axis=0) for i in bad}
            for i in bad:
                Y[i] = new[i]
        if repair == "surface" and bad:
            average = {i: Y[i].copy() for i in bad}
            k, d, q = closest_points(v, tri, np.array([Y[i] for i in bad]))
            placed = []
            for j, i in enumerate(bad):
                a, b, c = v[tri[k[j]]]
                n = np.cross(b - a, c - a)
                off = Y[i] - q[j]
                length = np.linalg.norm(off)
                cos = abs(np.dot(off, n)) / max(length * np.linalg.norm(n), np.finfo(float).tiny)
                if d[j] <= limit[i - n0] and (cos >= 0.7 or length <= 1e-9 * limit[i - n0]):
                    Y[i] = q[j]
                    placed.append(i)
            folded_odd = {i for face in T1 if _folded(pred, Y, face) for i in face if i >= n0}
            for i in placed:
                if i in folded_odd:
                    Y[i] = average[i]
        pierced += len(bad)
        X, T = Y, T1
        out.append(X)
    return out, pierced
