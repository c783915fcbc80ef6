"""Brute-force references for the coating method's numerics (small sizes only).

Dense per-vertex / per-triangle loops, written for obviousness: cotangent weights from
angles, Taubin smoothing with a dense averaging matrix, vertex frames and coatings one
vertex at a time, deformation transfer with the fourth vertices kept as unknowns and
solved by dense least squares, and the editing problems assembled in full.
"""

from __future__ import annotations

import math

import numpy as np


def neighbours(triangles, n_vertices):
    nb = [set() for _ in range(n_vertices)]
    for a, b, c in np.asarray(triangles).tolist():
        nb[a] |= {b, c}
        nb[b] |= {a, c}
        nb[c] |= {a, b}
    return [sorted(s) for s in nb]


def cotangent_laplacian(vertices, triangles):
    """Dense L with L_ij = -(cot a + cot b)/2 from the opposite angles (acos)."""
    v = np.asarray(vertices, dtype=float)
    n = len(v)
    lap = np.zeros((n, n))
    for tri in np.asarray(triangles).tolist():
        for k in range(3):
            c, i, j = tri[k], tri[(k + 1) % 3], tri[(k + 2) % 3]
            u, w = v[i] - v[c], v[j] - v[c]
            angle = math.acos(
                max(-1.0, min(1.0, float(u @ w) / (np.linalg.norm(u) * np.linalg.norm(w))))
            )
            half = 0.5 / math.tan(angle)
            lap[i, j] -= half
            lap[j, i] -= half
            lap[i, i] += half
            lap[j, j] += half
    return lap


def uniform_laplacian(triangles, n_vertices):
    lap = np.zeros((n_vertices, n_vertices))
    for i, nb in enumerate(neighbours(triangles, n_vertices)):
        lap[i, i] = len(nb)
        for j in nb:
            lap[i, j] = -1.0
    return lap


def taubin(points, triangles, iterations=40, lam=0.5, mu=-0.53):
    """Taubin smoothing with explicit neighbour averages, one vertex at a time."""
    x = np.array(points, dtype=float)
    nb = neighbours(triangles, len(x))
    for _ in range(iterations):
        for factor in (lam, mu):
            y = x.copy()
            for i in range(len(x)):
                if nb[i]:
                    y[i] = x[i] + factor * (np.mean(x[nb[i]], axis=0) - x[i])
            x = y
    return x


def vertex_frame(points, triangles, vertex, neighbor):
    """[t, b, n] columns of one vertex: area-weighted normal, projected edge tangent."""
    p = np.asarray(points, dtype=float)
    n = np.zeros(3)
    for tri in np.asarray(triangles).tolist():
        if vertex in tri:
            a, b, c = tri
            n += np.cross(p[b] - p[a], p[c] - p[a])
    n /= np.linalg.norm(n)
    e = p[neighbor] - p[vertex]
    t = e - (e @ n) * n
    t /= np.linalg.norm(t)
    return np.stack([t, np.cross(n, t), n], axis=1)


def coating(points, smooth, triangles, poisson, neighbors):
    """Local coating F^T (M (S - S~)) one vertex at a time; ``poisson`` dense (V, V)."""
    d = np.asarray(points, float) - np.asarray(smooth, float)
    xi = np.asarray(poisson) @ d
    out = np.zeros_like(xi)
    for v in range(len(xi)):
        out[v] = vertex_frame(smooth, triangles, v, neighbors[v, 0]).T @ xi[v]
    return out


def deformation_transfer(source_ref, source_def, target_ref, triangles, anchor=0):
    """Sumner & Popovic with the fourth vertices as unknowns, dense lstsq, ``anchor`` pinned."""
    tri = np.asarray(triangles)
    n, t = len(target_ref), len(tri)

    def frame(p, a, b, c):
        e1, e2 = p[b] - p[a], p[c] - p[a]
        nn = np.cross(e1, e2)
        return np.stack([e1, e2, nn / math.sqrt(np.linalg.norm(nn))], axis=1)

    rows, rhs = [], []
    for j, (a, b, c) in enumerate(tri.tolist()):
        q = frame(source_def, a, b, c) @ np.linalg.inv(frame(source_ref, a, b, c))
        w = np.linalg.inv(frame(target_ref, a, b, c))
        for col in range(3):
            row = np.zeros(n + t)
            row[b] += w[0, col]
            row[c] += w[1, col]
            row[n + j] += w[2, col]
            row[a] -= w[0, col] + w[1, col] + w[2, col]
            rows.append(row)
            rhs.append(q[:, col])
    a_mat = np.delete(np.array(rows), anchor, axis=1)
    sol = np.linalg.lstsq(a_mat, np.array(rhs), rcond=None)[0]
    return np.insert(sol, anchor, 0.0, axis=0)[:n]


def bases_edit(normal, gauge, bases0, center, weights, constraints, mu, lambda_b, free):
    """Bases step of the large-scale edit assembled in full: unknowns are every basis's
    anchored displacement; the gauge projection ``P`` removes the weighted mean."""
    k, n, _ = bases0.shape
    proj = np.eye(n) - np.outer(np.ones(n), gauge)
    nf = free.size
    hess = np.kron(np.eye(k), lambda_b * normal[np.ix_(free, free)])
    out = np.empty_like(bases0)
    for d in range(3):
        h = hess.copy()
        g = np.zeros(k * nf)
        for con in constraints:
            f = np.zeros(n)
            np.add.at(f, con.vertices, con.coeffs)
            u = (proj.T @ f)[free]
            row = np.kron(weights[con.frame], u)
            cur = con.coeffs @ (
                center[d]
                + np.einsum("k,kv->v", weights[con.frame], bases0[:, con.vertices, d] - center[d])
            )
            h += mu * np.outer(row, row)
            g += mu * row * (con.value[d] - cur)
        sol = np.linalg.solve(h, g).reshape(k, nf)
        full = np.zeros((k, n))
        full[:, free] = sol
        out[:, :, d] = bases0[:, :, d] + full @ proj.T
    return out


def propagate(change, edges, key, n_frames, lambda_key, lambda_gradient, lambda_boundary):
    """Eq. 18 assembled as one dense system over (frames x vertices), per coordinate."""
    p = change.shape[0]
    size = n_frames * p
    h = np.zeros((size, size))

    def idx(t, i):
        return t * p + i

    for t in range(n_frames - 1):
        for i in range(p):
            a, b = idx(t, i), idx(t + 1, i)
            h[a, a] += lambda_gradient
            h[b, b] += lambda_gradient
            h[a, b] -= lambda_gradient
            h[b, a] -= lambda_gradient
    for t in range(n_frames):
        for i, j in edges:
            a, b = idx(t, i), idx(t, j)
            h[a, a] += lambda_gradient
            h[b, b] += lambda_gradient
            h[a, b] -= lambda_gradient
            h[b, a] -= lambda_gradient
    for i in range(p):
        h[idx(key, i), idx(key, i)] += lambda_key
        if key != 0:
            h[idx(0, i), idx(0, i)] += lambda_boundary
        if key != n_frames - 1:
            h[idx(n_frames - 1, i), idx(n_frames - 1, i)] += lambda_boundary
    out = np.zeros((n_frames, p, 3))
    for d in range(3):
        g = np.zeros(size)
        for i in range(p):
            g[idx(key, i)] = lambda_key * change[i, d]
        out[:, :, d] = np.linalg.solve(h, g).reshape(n_frames, p)
    return out


def grid_mesh(n=8, seed=0, jitter=0.2):
    """A small open, bumpy, jittered grid surface: ``(vertices (n*n, 3), triangles)``."""
    rng = np.random.default_rng(seed)
    xs, ys = np.meshgrid(np.linspace(0.0, 1.0, n), np.linspace(0.0, 1.0, n))
    h = 1.0 / (n - 1)
    x = xs.ravel() + jitter * h * rng.uniform(-1, 1, n * n)
    y = ys.ravel() + jitter * h * rng.uniform(-1, 1, n * n)
    z = 0.3 * np.sin(2.5 * x) * np.cos(2.0 * y)
    idx = np.arange(n * n).reshape(n, n)
    a, b, c, d = (
        idx[:-1, :-1].ravel(),
        idx[:-1, 1:].ravel(),
        idx[1:, :-1].ravel(),
        idx[1:, 1:].ravel(),
    )
    tri = np.concatenate([np.stack([a, b, d], 1), np.stack([a, d, c], 1)])
    return np.stack([x, y, z], axis=1), tri


def weights_edit(bases, center, weights, constraints, window, mu, lambda_w, metric):
    """The weight step of a large-scale edit assembled in full: every window frame's weights
    unknown and bounded below by 0, velocity terms (in ``metric``) between consecutive frames
    including the zero change just outside both window ends (virtual frames past a sequence
    end), point constraints at their frames; solved by scipy's NNLS. Returns the window's
    new weights ``(w1 - w0 + 1, K)``."""
    from scipy.optimize import nnls

    k = weights.shape[1]
    w0, w1 = window
    frames = np.arange(w0, w1 + 1)
    n = frames.size * k
    root = np.linalg.cholesky(metric).T  # metric = root^T root
    rows, rhs = [], []
    for t in range(w0 - 1, w1 + 1):  # velocity change between t and t + 1
        block = np.zeros((k, n))
        target = np.zeros(k)
        for s, sign in ((t + 1, 1.0), (t, -1.0)):
            if w0 <= s <= w1:
                block[:, (s - w0) * k : (s - w0 + 1) * k] += sign * root
                target += sign * (root @ weights[s])
        rows.append(np.sqrt(lambda_w) * block)
        rhs.append(np.sqrt(lambda_w) * target)
    for c in constraints:
        if not w0 <= c.frame <= w1:
            continue
        a = np.einsum("v,kvd->kd", c.coeffs, bases[:, c.vertices] - center)  # (K, 3)
        block = np.zeros((3, n))
        block[:, (c.frame - w0) * k : (c.frame - w0 + 1) * k] = a.T
        rows.append(np.sqrt(mu) * block)
        rhs.append(np.sqrt(mu) * (c.value - center * c.coeffs.sum()))
    return nnls(np.vstack(rows), np.concatenate(rhs), maxiter=50 * n)[0].reshape(frames.size, k)


def frame_neighbors(vertices, triangles):
    """Tangent neighbours by sorting every directed edge (vertex, best score first, ties:
    lower id) with ``np.lexsort``: the first two of each vertex (the best twice for one edge).
    The scores are the library's (``local_frames.tangent_scores``); the selection is checked."""
    from faceretarget.geometry.local_frames import tangent_scores

    src, dst, score = tangent_scores(vertices, triangles)
    order = np.lexsort((dst, -score, src))
    out = np.empty((np.asarray(vertices).shape[0], 2), dtype=np.int64)
    for i in range(out.shape[0]):
        mine = order[src[order] == i]
        out[i] = dst[mine[0]], dst[mine[1] if len(mine) > 1 else mine[0]]
    return out
