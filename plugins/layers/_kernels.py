"""numba kernels of the layered-model parameter extraction (Kholgade et al. 2011, sec. 4).

Notation (see ``solver.py`` for the derivation): m regions, J layers, K = sum_j K_j
poses in all; ``alpha (K,)`` the stacked simplex coefficients (pose a belongs to layer
``layer_of[a]``), ``W (m, J)`` the mask weights ``w_jl`` stored region-major (row l sums
to 1 over the layers). The data term of Eq. 7 in reduced form is

    |x_hat - sum_l sum_j w_jl M_l B_j alpha_j|^2
        = xx - 2 sum_{l,a} W[l, j(a)] alpha_a g[l, a]
          + sum_{l,l',a,b} W[l, j(a)] W[l', j(b)] alpha_a alpha_b H[l, l', a, b]

with ``g[l, a] = b_a^T M_l x_hat`` and ``H[l, l', a, b] = b_a^T M_l M_l' b_b``, so an
iteration never touches the D_A marker coordinates. Each frame minimises

    E = c_d * data + c_b * (|W[mouth] - e_speech|^2 + |alpha_speech - e_closed|^2)
        + c_s * (|W - W_prev|^2 + |alpha - alpha_prev|^2)

by Levenberg-Marquardt steps on the joint variables (alpha, W): each step minimises a
convex model of E (Gauss-Newton for the bilinear data term, the quadratic penalties
exact) over the product of simplices, exactly, with the active-set method of
``faceretarget.geometry._nnls_kernels``; a step is kept only if E decreases.
"""
from __future__ import annotations

import numba as nb
import numpy as np

from faceretarget.geometry._nnls_kernels import FASTMATH, active_set_qp

_QP_TOL = 1e-13
_QP_MAX_ITER = 400


@nb.njit(cache=True, fastmath=FASTMATH)
def _downdate(H, Bt, Mc, miss, Ht):
    """``Ht = H`` minus the contribution of the missing coordinates ``miss (C,) bool``."""
    m, K = H.shape[0], H.shape[2]
    Ht[:] = H
    for c in range(Bt.shape[0]):
        if not miss[c]:
            continue
        for l in range(m):
            ml = Mc[c, l]
            if ml == 0.0:
                continue
            for l2 in range(m):
                w = ml * Mc[c, l2]
                if w == 0.0:
                    continue
                for a in range(K):
                    wa = w * Bt[c, a]
                    if wa == 0.0:
                        continue
                    for b in range(K):
                        Ht[l, l2, a, b] -= wa * Bt[c, b]



@nb.njit(cache=True, fastmath=FASTMATH)
def _evaluate(H, used, alpha, W, g, layer_of, beta, h):
    """``beta[l, a] = W[l, j(a)] alpha_a``, ``h = H beta``; returns (sum beta g, sum beta h)."""
    m, K = H.shape[0], H.shape[2]
    for l in range(m):
        for a in range(K):
            beta[l, a] = W[l, layer_of[a]] * alpha[a]
    lin = 0.0
    quad = 0.0
    for l in range(m):
        for a in range(K):
            s = 0.0
            for l2 in range(m):
                if not used[l, l2]:
                    continue
                row = H[l, l2, a]
                b2 = beta[l2]
                for b in range(K):
                    s += row[b] * b2[b]
            h[l, a] = s
            lin += beta[l, a] * g[l, a]
            quad += beta[l, a] * s
    return lin, quad


@nb.njit(cache=True, fastmath=FASTMATH)
def _penalties(alpha, W, layer_of, c_b, c_s, mouth, speech, closed, a_prev, w_prev):
    """Bias and smoothing terms of E (zero where their weights are zero)."""
    e = 0.0
    if c_b > 0.0:
        for j in range(W.shape[1]):
            t = W[mouth, j] - (1.0 if j == speech else 0.0)
            e += c_b * t * t
        for a in range(alpha.shape[0]):
            if layer_of[a] == speech:
                t = alpha[a] - (1.0 if a == closed else 0.0)
                e += c_b * t * t
    if c_s > 0.0:
        s = 0.0
        for a in range(alpha.shape[0]):
            t = alpha[a] - a_prev[a]
            s += t * t
        for l in range(W.shape[0]):
            for j in range(W.shape[1]):
                t = W[l, j] - w_prev[l, j]
                s += t * t
        e += c_s * s
    return e


@nb.njit(cache=True, fastmath=FASTMATH)
def _gauss_newton_system(H, used, alpha, W, g, h, offsets, layer_of, c_d, c_b, c_s, mouth, speech, closed, a_prev, w_prev,
                         G, c):
    """Convex model of E around (alpha, W): ``1/2 y^T G y - c^T y``, y = (alpha, W row-major).

    The data term is linearised as f(y) ~ J y - f(x) (f is bilinear, so J x = 2 f(x));
    bias and smoothing are quadratic already and enter exactly. The layers are
    contiguous pose ranges ``offsets[j]:offsets[j + 1]``, so the inner loops are dense.
    """
    m, K = H.shape[0], H.shape[2]
    J = W.shape[1]
    n = K + m * J
    G[:] = 0.0
    c[:] = 0.0
    acc = np.empty(J)
    for l in range(m):
        for a in range(K):
            ja = layer_of[a]
            r = K + l * J + ja
            gh = g[l, a] + h[l, a]
            c[a] += c_d * W[l, ja] * gh
            c[r] += c_d * alpha[a] * gh
        for l2 in range(m):
            if not used[l, l2]:
                continue
            for a in range(K):
                ja = layer_of[a]
                ua = c_d * W[l, ja]
                aa = c_d * alpha[a]
                r = K + l * J + ja
                row = H[l, l2, a]
                Ga = G[a]
                for j in range(J):
                    f = ua * W[l2, j]
                    s = 0.0
                    for b in range(offsets[j], offsets[j + 1]):
                        Ga[b] += f * row[b]  # d f / d alpha_a . d f / d alpha_b
                        s += alpha[b] * row[b]
                    acc[j] = s
                for j in range(J):
                    col = K + l2 * J + j
                    Ga[col] += ua * acc[j]  # d f / d alpha_a . d f / d W[l2, j]
                    G[r, col] += aa * acc[j]  # d f / d W[l, j(a)] . d f / d W[l2, j]
    for a in range(K):  # the (weights, alpha) block mirrors (alpha, weights)
        for r in range(K, n):
            G[r, a] = G[a, r]
    for a in range(K):
        G[a, a] += c_s
        c[a] += c_s * a_prev[a]
        if c_b > 0.0 and layer_of[a] == speech:
            G[a, a] += c_b
            if a == closed:
                c[a] += c_b
    for l in range(m):
        for j in range(J):
            r = K + l * J + j
            G[r, r] += c_s
            c[r] += c_s * w_prev[l, j]
            if c_b > 0.0 and l == mouth:
                G[r, r] += c_b
                if j == speech:
                    c[r] += c_b


@nb.njit(cache=True)
def _unpack(y, K, alpha, W):
    m, J = W.shape
    for a in range(K):
        alpha[a] = y[a]
    for l in range(m):
        for j in range(J):
            W[l, j] = y[K + l * J + j]


@nb.njit(cache=True, fastmath=FASTMATH)
def solve_frames(H, used, Bt, Mc, g, xx, miss, any_miss, c_d, c_b, c_s, layer_of, n_layers, mouth, speech, closed,
                 w_init, a_init, has_prev, max_iter, tol, out_w, out_a, out_obj, out_iter):
    """Extract (W, alpha) for every frame in order, each warm-started from the previous.

    Levenberg-Marquardt on the joint variables: each step minimises the Gauss-Newton
    model (+ mu |y - x|^2) exactly over the product of simplices (active set), and is
    kept only if E decreases (else mu grows), so E is monotone and every iterate is
    feasible. ``w_init (m, J)``, ``a_init (K,)``: the start of frame 0, and also its
    smoothing target when ``has_prev`` (streaming continues a sequence). Writes
    ``out_w (F, m, J)``, ``out_a (F, K)``, the objective ``out_obj (F,)`` and the
    number of model solves ``out_iter (F,)``.
    """
    n_frames = g.shape[0]
    m, K = H.shape[0], H.shape[2]
    J = n_layers
    n = K + m * J
    G = np.empty((n, n))
    Gm = np.empty((n, n))
    c = np.empty(n)
    cm = np.empty(n)
    y = np.empty(n)
    lo, hi = np.zeros(n), np.full(n, np.inf)
    group = np.empty(n, np.int64)
    for a in range(K):
        group[a] = layer_of[a]
    for l in range(m):
        for j in range(J):
            group[K + l * J + j] = J + l
    sums = np.ones(J + m)
    offsets = np.zeros(J + 1, np.int64)
    for a in range(K):
        offsets[layer_of[a] + 1] += 1
    for j in range(J):
        offsets[j + 1] += offsets[j]
    Ht = np.empty_like(H)
    beta = np.empty((m, K))
    h = np.empty((m, K))
    beta_y = np.empty((m, K))
    h_y = np.empty((m, K))
    W = w_init.copy()
    alpha = a_init.copy()
    W_y = np.empty_like(W)
    alpha_y = np.empty_like(alpha)
    w_prev = w_init.copy()
    a_prev = a_init.copy()
    for t in range(n_frames):
        Hf = H
        if any_miss[t]:
            _downdate(H, Bt, Mc, miss[t], Ht)
            Hf = Ht
        cd = c_d[t]
        cs = c_s[t] if (t > 0 or has_prev) else 0.0
        cb = c_b[t] if (mouth >= 0 and speech >= 0) else 0.0
        lin, quad = _evaluate(Hf, used, alpha, W, g[t], layer_of, beta, h)
        energy = cd * (xx[t] - 2.0 * lin + quad) + _penalties(alpha, W, layer_of, cb, cs, mouth, speech, closed, a_prev, w_prev)
        floor = tol * 1e-3 * (cd * xx[t] + cb + cs) + 1e-300  # exact fits: accuracy relative to |x_hat|
        mu = 0.0
        it = 0
        while it < max_iter:
            it += 1
            _gauss_newton_system(Hf, used, alpha, W, g[t], h, offsets, layer_of, cd, cb, cs, mouth, speech, closed, a_prev,
                                 w_prev, G, c)
            scale = 0.0
            for i in range(n):
                scale += G[i, i]
            scale = max(scale / n, 1e-300)
            accepted = False
            while True:
                for i in range(n):
                    for k in range(n):
                        Gm[i, k] = G[i, k]
                    Gm[i, i] += mu
                for a in range(K):
                    y[a] = alpha[a]
                    cm[a] = c[a] + mu * alpha[a]
                for l in range(m):
                    for j in range(J):
                        r = K + l * J + j
                        y[r] = W[l, j]
                        cm[r] = c[r] + mu * W[l, j]
                active_set_qp(Gm, cm, lo, hi, group, sums, y, _QP_MAX_ITER, _QP_TOL)
                _unpack(y, K, alpha_y, W_y)
                lin, quad = _evaluate(Hf, used, alpha_y, W_y, g[t], layer_of, beta_y, h_y)
                e_y = cd * (xx[t] - 2.0 * lin + quad) + _penalties(alpha_y, W_y, layer_of, cb, cs, mouth, speech, closed, a_prev, w_prev)
                if e_y <= energy:
                    accepted = True
                    break
                mu = max(4.0 * mu, 1e-6 * scale)
                if mu > 1e12 * scale:
                    break
            if not accepted:
                break
            decrease = energy - e_y
            energy = e_y
            alpha[:] = alpha_y
            W[:] = W_y
            beta, beta_y = beta_y, beta
            h, h_y = h_y, h
            mu = mu / 3.0 if mu > 1e-9 * scale else 0.0
            if decrease <= tol * energy or decrease <= floor:
                break
        out_w[t] = W
        out_a[t] = alpha
        out_obj[t] = max(energy, 0.0)
        out_iter[t] = it
        w_prev[:] = W
        a_prev[:] = alpha


@nb.njit(cache=True, fastmath=FASTMATH)
def project(xhat, projector_t, g, xx):
    """``g[f] = projector_t @ xhat[f]`` and ``xx[f] = |xhat[f]|^2`` for ``xhat (F, C)``.

    Row by row with one fixed summation order, so a frame gives bitwise the same numbers
    alone (streaming) as inside a batch; BLAS would round a GEMM and a GEMV differently,
    and the per-frame solver's stopping test can amplify such last-bit differences.
    """
    for f in range(xhat.shape[0]):
        x = xhat[f]
        s = 0.0
        for c in range(x.shape[0]):
            s += x[c] * x[c]
        xx[f] = s
        for k in range(projector_t.shape[0]):
            p = projector_t[k]
            s = 0.0
            for c in range(x.shape[0]):
                s += p[c] * x[c]
            g[f, k] = s


@nb.njit(cache=True, fastmath=FASTMATH)
def assemble(products, offsets, n_frames, neutral, vertex_ptr, entry_region, entry_col, motion, out):
    """Eq. 5 per vertex: ``out[f, v] = R_f (neutral_v + sum of its region products) + t_f``.

    ``products`` is flat: region l's ``(n_frames, w_l)`` product ``beta_l @ block_l`` starts
    at ``n_frames * offsets[l]`` (row-major); vertex v's 3-vectors sit in regions
    ``entry_region[e]`` at columns ``entry_col[e]`` for e in ``vertex_ptr[v]:vertex_ptr[v + 1]``.
    ``motion (F, 4, 4)``; writes ``out (F, V, 3)`` once.
    """
    for f in range(n_frames):
        r = motion[f]
        for v in range(neutral.shape[0]):
            x, y, z = neutral[v, 0], neutral[v, 1], neutral[v, 2]
            for e in range(vertex_ptr[v], vertex_ptr[v + 1]):
                l = entry_region[e]
                k = n_frames * offsets[l] + f * (offsets[l + 1] - offsets[l]) + entry_col[e]
                x += products[k]
                y += products[k + 1]
                z += products[k + 2]
            o = out[f, v]
            o[0] = r[0, 0] * x + r[0, 1] * y + r[0, 2] * z + r[0, 3]
            o[1] = r[1, 0] * x + r[1, 1] * y + r[1, 2] * z + r[1, 3]
            o[2] = r[2, 0] * x + r[2, 1] * y + r[2, 2] * z + r[2, 3]
