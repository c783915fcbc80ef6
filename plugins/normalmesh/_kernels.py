"""Numba kernels of the normal-mesh plugin (per level, per frame). Imported lazily.

Serial on purpose (per frame each kernel takes a fraction of a millisecond at 69K vertices,
less than waking numba's thread pool costs) and ``nogil``: the retargeter runs chunks of
frames in Python threads instead.

Shapes: ``X (V, 3)`` positions of one level; ``edges (E, 2)`` endpoints of the coarse edge
each odd vertex ``n_coarse + e`` lies on; ``tangent (E, 2)``, ``offset (E,)`` an odd vertex's
displacement from its predicted position in the local frame (t1, t2, n) of the predicted
mesh: n the vertex normal, t1 the coarse edge direction made perpendicular to n, t2 = n x t1.
"""

from __future__ import annotations

import numba as nb
import numpy as np

from faceretarget.geometry._raycast_kernels import walk_one

#: trace_level status of an odd vertex
TRACE_HIT, TRACE_PIERCED, TRACE_LOST, TRACE_SKIPPED = 0, 1, 2, 3


@nb.njit(cache=True, inline="always")
def _cross(P, a, b, c):
    u0, u1, u2 = P[b, 0] - P[a, 0], P[b, 1] - P[a, 1], P[b, 2] - P[a, 2]
    v0, v1, v2 = P[c, 0] - P[a, 0], P[c, 1] - P[a, 1], P[c, 2] - P[a, 2]
    return u1 * v2 - u2 * v1, u2 * v0 - u0 * v2, u0 * v1 - u1 * v0


@nb.njit(cache=True, inline="always")
def _frame(X, normals, edges, n_coarse, e):
    """(t1, t2, n) at odd vertex ``n_coarse + e``, each as three floats."""
    v = n_coarse + e
    n0, n1, n2 = normals[v, 0], normals[v, 1], normals[v, 2]
    a, b = edges[e, 0], edges[e, 1]
    d0, d1, d2 = X[b, 0] - X[a, 0], X[b, 1] - X[a, 1], X[b, 2] - X[a, 2]
    dn = d0 * n0 + d1 * n1 + d2 * n2
    d0, d1, d2 = d0 - dn * n0, d1 - dn * n1, d2 - dn * n2
    s = np.sqrt(d0 * d0 + d1 * d1 + d2 * d2)
    if s == 0.0:  # edge along the normal (or no normal): any perpendicular direction
        if abs(n0) < 0.9:
            d0, d1, d2 = 1.0 - n0 * n0, -n0 * n1, -n0 * n2
        else:
            d0, d1, d2 = -n1 * n0, 1.0 - n1 * n1, -n1 * n2
        s = np.sqrt(d0 * d0 + d1 * d1 + d2 * d2)
        if s == 0.0:
            d0, d1, d2, s = 1.0, 0.0, 0.0, 1.0
    t10, t11, t12 = d0 / s, d1 / s, d2 / s
    t20 = n1 * t12 - n2 * t11
    t21 = n2 * t10 - n0 * t12
    t22 = n0 * t11 - n1 * t10
    return t10, t11, t12, t20, t21, t22, n0, n1, n2


@nb.njit(cache=True, nogil=True)
def place_odd(X, normals, edges, n_coarse, tangent, offset, out):
    """out[n_coarse + e] = X[n_coarse + e] + t1 tangent[e, 0] + t2 tangent[e, 1] + n offset[e]."""
    for e in range(edges.shape[0]):
        t10, t11, t12, t20, t21, t22, n0, n1, n2 = _frame(X, normals, edges, n_coarse, e)
        v = n_coarse + e
        a, b, c = tangent[e, 0], tangent[e, 1], offset[e]
        out[v, 0] = X[v, 0] + a * t10 + b * t20 + c * n0
        out[v, 1] = X[v, 1] + a * t11 + b * t21 + c * n1
        out[v, 2] = X[v, 2] + a * t12 + b * t22 + c * n2


@nb.njit(cache=True, nogil=True)
def local_coords(X, normals, edges, n_coarse, Y, tangent, offset):
    """Inverse of :func:`place_odd`: coordinates of ``Y[odd] - X[odd]`` in the local frames."""
    for e in range(edges.shape[0]):
        t10, t11, t12, t20, t21, t22, n0, n1, n2 = _frame(X, normals, edges, n_coarse, e)
        v = n_coarse + e
        d0, d1, d2 = Y[v, 0] - X[v, 0], Y[v, 1] - X[v, 1], Y[v, 2] - X[v, 2]
        tangent[e, 0] = d0 * t10 + d1 * t11 + d2 * t12
        tangent[e, 1] = d0 * t20 + d1 * t21 + d2 * t22
        offset[e] = d0 * n0 + d1 * n1 + d2 * n2


@nb.njit(cache=True, nogil=True)
def flipped_odd(Y, X, triangles, n_coarse, flags):
    """Set ``flags[e]`` for odd vertices of triangles whose normal in ``Y`` opposes that in ``X``."""
    for t in range(triangles.shape[0]):
        a, b, c = triangles[t, 0], triangles[t, 1], triangles[t, 2]
        p0, p1, p2 = _cross(X, a, b, c)
        m0, m1, m2 = _cross(Y, a, b, c)
        if p0 * m0 + p1 * m1 + p2 * m2 < 0.0:
            for v in (a, b, c):
                if v >= n_coarse:
                    flags[v - n_coarse] = True


@nb.njit(cache=True, nogil=True)
def fold_culprits(Y, X, triangles, n_coarse, edges, flags):
    """For each triangle whose normal in ``Y`` opposes that in ``X`` and none of whose odd
    vertices is flagged yet, flag the odd vertex that moved farthest from ``X`` relative to the
    length of the coarse edge it splits (its culprit). Triangles are visited in order and a
    flag counts at once. Returns the number of folded triangles."""
    folded = 0
    for t in range(triangles.shape[0]):
        a, b, c = triangles[t, 0], triangles[t, 1], triangles[t, 2]
        p0, p1, p2 = _cross(X, a, b, c)
        m0, m1, m2 = _cross(Y, a, b, c)
        if p0 * m0 + p1 * m1 + p2 * m2 >= 0.0:
            continue
        folded += 1
        best, worst = -1, -1.0
        for v in (a, b, c):
            if v < n_coarse:
                continue
            e = v - n_coarse
            if flags[e]:
                best = -2
                break
            i, j = edges[e, 0], edges[e, 1]
            length = (X[j, 0] - X[i, 0]) ** 2 + (X[j, 1] - X[i, 1]) ** 2 + (X[j, 2] - X[i, 2]) ** 2
            moved = (Y[v, 0] - X[v, 0]) ** 2 + (Y[v, 1] - X[v, 1]) ** 2 + (Y[v, 2] - X[v, 2]) ** 2
            score = moved / length if length > 0.0 else np.inf
            if score > worst:
                best, worst = e, score
        if best >= 0:
            flags[best] = True
    return folded


@nb.njit(cache=True, nogil=True)
def neighbour_average(Y, vertices, indptr, indices, iterations):
    """Replace ``Y[vertices]`` by the mean of their ring neighbours (Jacobi sweeps, in place)."""
    tmp = np.empty((vertices.shape[0], 3))
    for _ in range(iterations):
        for i in range(vertices.shape[0]):
            v = vertices[i]
            lo, hi = indptr[v], indptr[v + 1]
            if hi == lo:
                tmp[i, 0], tmp[i, 1], tmp[i, 2] = Y[v, 0], Y[v, 1], Y[v, 2]
                continue
            s0 = s1 = s2 = 0.0
            for j in range(lo, hi):
                w = indices[j]
                s0 += Y[w, 0]
                s1 += Y[w, 1]
                s2 += Y[w, 2]
            k = hi - lo
            tmp[i, 0], tmp[i, 1], tmp[i, 2] = s0 / k, s1 / k, s2 / k
        for i in range(vertices.shape[0]):
            v = vertices[i]
            Y[v, 0], Y[v, 1], Y[v, 2] = tmp[i, 0], tmp[i, 1], tmp[i, 2]


@nb.njit(cache=True, nogil=True)
def carry_points(X, corners, bary, frame_corners, local, out):
    """Points attached to a mesh: ``bary``-weighted ``X[corners]`` plus ``local (P, 3)`` in the
    frame of the triangle ``X[frame_corners]`` (``corners``, ``frame_corners`` (P, 3) vertex ids),
    or as it is where ``frame_corners`` is -1.

    Frame of triangle (a, b, c): e1 = unit(b - a), n = unit((b - a) x (c - a)), e2 = n x e1.
    """
    for p in range(corners.shape[0]):
        a, b, c = corners[p, 0], corners[p, 1], corners[p, 2]
        fa, fb, fc = frame_corners[p, 0], frame_corners[p, 1], frame_corners[p, 2]
        if fa < 0:
            for k in range(3):
                out[p, k] = (
                    bary[p, 0] * X[a, k] + bary[p, 1] * X[b, k] + bary[p, 2] * X[c, k] + local[p, k]
                )
            continue
        u0, u1, u2 = X[fb, 0] - X[fa, 0], X[fb, 1] - X[fa, 1], X[fb, 2] - X[fa, 2]
        n0, n1, n2 = _cross(X, fa, fb, fc)
        sn = np.sqrt(n0 * n0 + n1 * n1 + n2 * n2)
        su = np.sqrt(u0 * u0 + u1 * u1 + u2 * u2)
        if sn > 0.0 and su > 0.0:
            n0, n1, n2 = n0 / sn, n1 / sn, n2 / sn
            u0, u1, u2 = u0 / su, u1 / su, u2 / su
        else:
            n0 = n1 = n2 = u0 = u1 = u2 = 0.0
        w0 = n1 * u2 - n2 * u1
        w1 = n2 * u0 - n0 * u2
        w2 = n0 * u1 - n1 * u0
        l0, l1, l2 = local[p, 0], local[p, 1], local[p, 2]
        out[p, 0] = (
            bary[p, 0] * X[a, 0]
            + bary[p, 1] * X[b, 0]
            + bary[p, 2] * X[c, 0]
            + l0 * u0
            + l1 * w0
            + l2 * n0
        )
        out[p, 1] = (
            bary[p, 0] * X[a, 1]
            + bary[p, 1] * X[b, 1]
            + bary[p, 2] * X[c, 1]
            + l0 * u1
            + l1 * w1
            + l2 * n1
        )
        out[p, 2] = (
            bary[p, 0] * X[a, 2]
            + bary[p, 1] * X[b, 2]
            + bary[p, 2] * X[c, 2]
            + l0 * u2
            + l1 * w2
            + l2 * n2
        )


@nb.njit(cache=True, nogil=True)
def trace_level(
    vertices,
    triangles,
    neighbors,
    X,
    pred,
    normals,
    edges,
    n_coarse,
    skip,
    start,
    max_offset,
    max_steps,
    Y,
    status,
    found,
):
    """One level of a frame's normal mesh: each odd vertex's line along its normal, walked
    over the frame's mesh from ``start`` (the triangle the neutral's line hit).

    ``status[e]``: TRACE_HIT (``Y`` set to the hit), TRACE_PIERCED (no start, a walk out across
    the mesh border, a crossing farther than allowed, a line grazing a crease, or a hit on a
    triangle facing away), TRACE_LOST (step limit or a parallel line: retry with a global
    query) or
    TRACE_SKIPPED (``skip[e]``: boundary vertices, handled by the caller). A hit must lie
    within ``max_offset`` x the length of the coarse edge the vertex splits. ``found[e]`` is
    the triangle the walk ended on (-1 if none).
    """
    for e in range(edges.shape[0]):
        found[e] = -1
        if skip[e]:
            status[e] = TRACE_SKIPPED
            continue
        if start[e] < 0:
            status[e] = TRACE_PIERCED
            continue
        v = n_coarse + e
        a, b = edges[e, 0], edges[e, 1]
        length = np.sqrt(
            (X[b, 0] - X[a, 0]) ** 2 + (X[b, 1] - X[a, 1]) ** 2 + (X[b, 2] - X[a, 2]) ** 2
        )
        n0, n1, n2 = normals[v, 0], normals[v, 1], normals[v, 2]
        tri, t, _, _ = walk_one(
            vertices,
            triangles,
            neighbors,
            pred[v, 0],
            pred[v, 1],
            pred[v, 2],
            n0,
            n1,
            n2,
            start[e],
            max_offset * length,
            max_steps,
        )
        if tri <= -2:  # left the mesh across its border, crossing too far away, or grazing a crease
            status[e] = TRACE_PIERCED
            continue
        if tri < 0:
            status[e] = TRACE_LOST
            continue
        found[e] = tri
        c0, c1, c2 = _cross(vertices, triangles[tri, 0], triangles[tri, 1], triangles[tri, 2])
        if c0 * n0 + c1 * n1 + c2 * n2 <= 0.0:
            status[e] = TRACE_PIERCED
            continue
        Y[v, 0] = pred[v, 0] + t * n0
        Y[v, 1] = pred[v, 1] + t * n1
        Y[v, 2] = pred[v, 2] + t * n2
        status[e] = TRACE_HIT


@nb.njit(cache=True, inline="always")
def _vertex_frame(X, normals, neighbour, v):
    """(t1, t2, n) at vertex ``v``: n its unit normal, t1 the direction to ``neighbour[v]`` made
    perpendicular to n, t2 = n x t1 (each as three floats)."""
    n0, n1, n2 = normals[v, 0], normals[v, 1], normals[v, 2]
    w = neighbour[v]
    d0, d1, d2 = X[w, 0] - X[v, 0], X[w, 1] - X[v, 1], X[w, 2] - X[v, 2]
    dn = d0 * n0 + d1 * n1 + d2 * n2
    d0, d1, d2 = d0 - dn * n0, d1 - dn * n1, d2 - dn * n2
    s = np.sqrt(d0 * d0 + d1 * d1 + d2 * d2)
    if s > 0.0:
        d0, d1, d2 = d0 / s, d1 / s, d2 / s
    return d0, d1, d2, n1 * d2 - n2 * d1, n2 * d0 - n0 * d2, n0 * d1 - n1 * d0, n0, n1, n2


@nb.njit(cache=True, nogil=True)
def local_frames(X, normals, neighbour, out):
    """``out (V, 3, 3)``: rows t1, t2, n of :func:`_vertex_frame` at every vertex."""
    for v in range(X.shape[0]):
        f = _vertex_frame(X, normals, neighbour, v)
        for r in range(3):
            for c in range(3):
                out[v, r, c] = f[3 * r + c]


@nb.njit(cache=True, nogil=True)
def slide(source, source_normals, material, target, target_normals, neighbour, slide0, delta, out):
    """``out = target + delta * F_t^T (F_s (material - source) - slide0)`` per vertex, with F_s,
    F_t the vertex frames (:func:`_vertex_frame`) of the source's and the target's finest
    level: the source's sliding of its material points past its normal-mesh vertices, carried
    to the target in local coordinates."""
    for v in range(source.shape[0]):
        s = _vertex_frame(source, source_normals, neighbour, v)
        t = _vertex_frame(target, target_normals, neighbour, v)
        d0, d1, d2 = (
            material[v, 0] - source[v, 0],
            material[v, 1] - source[v, 1],
            material[v, 2] - source[v, 2],
        )
        l0 = s[0] * d0 + s[1] * d1 + s[2] * d2 - slide0[v, 0]
        l1 = s[3] * d0 + s[4] * d1 + s[5] * d2 - slide0[v, 1]
        l2 = s[6] * d0 + s[7] * d1 + s[8] * d2 - slide0[v, 2]
        for k in range(3):
            out[v, k] = target[v, k] + delta * (l0 * t[k] + l1 * t[3 + k] + l2 * t[6 + k])


@nb.njit(cache=True, nogil=True)
def multiquadric_maps(x, centers, weights, constant, c, linear, out):
    """Per point ``i``: ``out[i] = sum_j weights[i, j] sqrt(|x[i] - centers[i, j]|^2 + c[i]^2)
    + constant[i] + linear @ x[i]`` (the per-point maps of ``base_retarget.BaseMap``)."""
    for i in range(x.shape[0]):
        x0, x1, x2 = x[i, 0], x[i, 1], x[i, 2]
        cc = c[i] * c[i]
        for k in range(3):
            out[i, k] = constant[i, k] + linear[k, 0] * x0 + linear[k, 1] * x1 + linear[k, 2] * x2
        for j in range(centers.shape[1]):
            w0, w1, w2 = weights[i, j, 0], weights[i, j, 1], weights[i, j, 2]
            if w0 == 0.0 and w1 == 0.0 and w2 == 0.0:
                continue
            r2 = (
                (x0 - centers[i, j, 0]) ** 2
                + (x1 - centers[i, j, 1]) ** 2
                + (x2 - centers[i, j, 2]) ** 2
            )
            h = np.sqrt(r2 + cc)
            out[i, 0] += w0 * h
            out[i, 1] += w1 * h
            out[i, 2] += w2 * h
