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

over ``alpha`` on each layer's simplex and ``W`` either convex per region (the paper:
row l on the simplex) or, ``additive``, each ``W[l, j]`` in [0, 1] (the layers add; the
bias then pulls only the speech coefficients to the closed viseme and leaves the weights
to the data: an emotion may stay on closed lips, and a closed neutral mouth stays neutral)

by Levenberg-Marquardt steps on the joint variables (alpha, W): each step minimises a
convex model of E (Gauss-Newton for the bilinear data term, the quadratic penalties
exact) over the product of simplices, exactly, with the active-set method of
``faceretarget.geometry._nnls_kernels``; a step is kept only if E decreases.

Alignment passes measure the data modulo the alignment's own small motions (see
``solver.py``): with ``Jr (C, r)`` the derivative of ``x_hat`` with respect to the r
rigid / similarity parameters and ``L L^T = Jr^T Jr``, the data term is
``|P (x_hat - f)|^2`` with ``P = I - Jr (Jr^T Jr)^-1 Jr^T``, i.e. in reduced form
``H' = H - U^T U``, ``g' = g - U^T q``, ``xx' = xx - |q|^2`` with ``U = L^-1 Jr^T M_l B``
and ``q = L^-1 Jr^T x_hat`` (restricted to the observed coordinates of each frame).
"""

from __future__ import annotations

import numba as nb
import numpy as np

from faceretarget.geometry._nnls_kernels import FASTMATH, active_set_qp, factor, forward

_QP_TOL = 1e-13
_QP_MAX_ITER = 400


@nb.njit(cache=True)
def _copy(dst, src):
    """``dst[...] = src`` for C-contiguous arrays of one size, as a loop: numba's slice
    assignment compiles a broadcasting implementation (with its error-message string
    machinery) per pair of array types, seconds of a cold start each."""
    d, s = dst.reshape(dst.size), src.reshape(src.size)
    for i in range(s.size):
        d[i] = s[i]


@nb.njit(cache=True, fastmath=FASTMATH)
def _downdate(H, Bt, Mc, miss, Ht):
    """``Ht = H`` minus the contribution of the missing coordinates ``miss (C,) bool``."""
    m, K = H.shape[0], H.shape[2]
    _copy(Ht, H)
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
def _penalties(alpha, W, layer_of, c_b, c_s, mouth, speech, closed, a_prev, w_prev, additive):
    """Bias and smoothing terms of E (zero where their weights are zero)."""
    e = 0.0
    if c_b > 0.0:
        for j in range(W.shape[1]):
            if additive:  # the bias picks the viseme; the data say how much of each layer
                break
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
def _gauss_newton_system(
    H,
    used,
    alpha,
    W,
    g,
    h,
    offsets,
    layer_of,
    c_d,
    c_b,
    c_s,
    mouth,
    speech,
    closed,
    a_prev,
    w_prev,
    additive,
    G,
    c,
):
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
            if c_b > 0.0 and l == mouth and not additive:
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
def _rigid_frame(miss, any_miss, Jr, JtJ, Uraw, qraw, Bt, Mc, Lf, Uf, Lt, JtJ_t, Ut, q):
    """The projection of one frame: returns ``U~ = L^-1 Jr^T M_l B`` (``Uf`` for a complete
    frame, else ``Ut`` restricted to the observed coordinates) and writes ``q = L^-1 qraw``."""
    nr = Jr.shape[1]
    m, K = Uraw.shape[1], Uraw.shape[2]
    if any_miss:
        _copy(JtJ_t, JtJ)
        _copy(Ut, Uraw)
        for c in range(Jr.shape[0]):
            if not miss[c]:
                continue
            for i in range(nr):
                ji = Jr[c, i]
                if ji == 0.0:
                    continue
                for k in range(nr):
                    JtJ_t[i, k] -= ji * Jr[c, k]
                for l in range(m):
                    ml = Mc[c, l] * ji
                    if ml == 0.0:
                        continue
                    for a in range(K):
                        Ut[i, l, a] -= ml * Bt[c, a]
        jscale = 0.0
        for i in range(nr):
            jscale = max(jscale, JtJ[i, i])
        Lt[:] = 0.0
        factor(JtJ_t, nr, jscale, Lt)
        col = np.empty(nr)
        for l in range(m):
            for a in range(K):
                for i in range(nr):
                    col[i] = Ut[i, l, a]
                forward(Lt, nr, col)
                for i in range(nr):
                    Ut[i, l, a] = col[i]
        U = Ut
        L = Lt
    else:
        U = Uf
        L = Lf
    for i in range(nr):
        q[i] = qraw[i]
    forward(L, nr, q)
    return U


@nb.njit(cache=True, fastmath=FASTMATH)
def _sq(v):
    e = 0.0
    for i in range(v.shape[0]):
        e += v[i] * v[i]
    return e


@nb.njit(cache=True, fastmath=FASTMATH)
def _rigid_part(U, beta, q, s):
    """``s = U~ beta`` and returns ``|q - s|^2``: the data's part along the alignment's motions."""
    nr, m, K = U.shape
    e = 0.0
    for i in range(nr):
        t = 0.0
        for l in range(m):
            for a in range(K):
                t += U[i, l, a] * beta[l, a]
        s[i] = t
        d = q[i] - t
        e += d * d
    return e


@nb.njit(cache=True, fastmath=FASTMATH)
def _rigid_system(G, c, U, alpha, W, layer_of, offsets, cd, q, s, Vt):
    """Project the Gauss-Newton model: ``G -= cd V V^T``, ``c -= cd V (q + s)`` with
    ``V = J_f^T Jr L^-T`` (``J_f``: the layered output's Jacobian in (alpha, W)); ``Vt (r, n)``
    is scratch for ``V^T``."""
    nr, m, K = U.shape
    J = W.shape[1]
    n = G.shape[0]
    Vt[:] = 0.0
    for i in range(nr):
        vi = Vt[i]
        for l in range(m):
            ul = U[i, l]
            for a in range(K):
                u = ul[a]
                vi[a] += W[l, layer_of[a]] * u
                vi[K + l * J + layer_of[a]] += alpha[a] * u
    for k in range(nr):
        vk = Vt[k]
        w = cd * (q[k] + s[k])
        for i in range(n):
            c[i] -= w * vk[i]
    G -= cd * np.dot(Vt.T, Vt)


@nb.njit(cache=True, fastmath=FASTMATH, nogil=True)
def solve_frames(
    H,
    used,
    Bt,
    Mc,
    g,
    xx,
    miss,
    any_miss,
    c_d,
    c_b,
    c_s,
    layer_of,
    n_layers,
    mouth,
    speech,
    closed,
    w_init,
    a_init,
    has_prev,
    additive,
    start_w,
    start_a,
    use_start,
    Jr,
    JtJ,
    Uraw,
    qraw,
    max_iter,
    tol,
    out_w,
    out_a,
    out_obj,
    out_iter,
):
    """Extract (W, alpha) for every frame in order, each warm-started from the previous.

    Levenberg-Marquardt on the joint variables: each step minimises the Gauss-Newton
    model (+ mu |y - x|^2) exactly over the feasible set (simplices; the weights on
    simplices too, or in [0, 1] when ``additive``) with the active-set QP, and is
    kept only if E decreases (else mu grows), so E is monotone and every iterate is
    feasible. ``w_init (m, J)``, ``a_init (K,)``: the start of frame 0, and also its
    smoothing target when ``has_prev`` (streaming continues a sequence). With
    ``use_start``, frame t starts from ``start_w[t], start_a[t]`` instead (a solution of
    the same frame from a previous alignment pass); the smoothing target stays the
    previous frame's result. Writes ``out_w (F, m, J)``, ``out_a (F, K)``, the
    objective ``out_obj (F,)`` and the number of model solves ``out_iter (F,)``.

    Projected data term (alignment passes) when ``r = Jr.shape[1] > 0``: ``JtJ (r, r)``
    and ``Uraw (r, m, K) = Jr^T M_l b_a`` over all coordinates, ``qraw (F, r) = Jr^T
    x_hat`` (``x_hat`` is zero where missing); frames with missing coordinates get their
    own ``U`` and ``q``. The projection is applied as a rank-r correction of the energy
    and of the Gauss-Newton model, so the Gram tensor keeps its block sparsity.
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
            if additive:
                group[K + l * J + j] = -1
                hi[K + l * J + j] = 1.0
            else:
                group[K + l * J + j] = J + l
    sums = np.ones(J) if additive else np.ones(J + m)
    offsets = np.zeros(J + 1, np.int64)
    for a in range(K):
        offsets[layer_of[a] + 1] += 1
    for j in range(J):
        offsets[j + 1] += offsets[j]
    Ht = np.empty_like(H)
    nr = Jr.shape[1]
    Lf = np.zeros((nr, nr))
    Uf = np.empty((nr, m, K))
    Ut = np.empty((nr, m, K))
    Lt = np.zeros((nr, nr))
    JtJ_t = np.empty((nr, nr))
    q = np.empty(nr)
    srig = np.empty(nr)
    V = np.empty((nr, n))
    U = Uf
    if nr > 0:
        jscale = 0.0
        for i in range(nr):
            jscale = max(jscale, JtJ[i, i])
        factor(JtJ, nr, jscale, Lf)
        for l in range(m):
            for a in range(K):
                for i in range(nr):
                    q[i] = Uraw[i, l, a]
                forward(Lf, nr, q)
                for i in range(nr):
                    Uf[i, l, a] = q[i]
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
    best_w = np.empty_like(W)
    best_a = np.empty_like(alpha)
    for t in range(n_frames):
        if use_start:
            _copy(W, start_w[t])
            _copy(alpha, start_a[t])
        if additive:
            # A layer whose weight is 0 in every region has coefficients the data cannot see:
            # from there the bilinear steps cannot bring it back (its weights and coefficients
            # must change together). Start such a layer afresh: weight 1, uniform coefficients.
            for j in range(J):
                dead = True
                for l in range(m):
                    if W[l, j] > 1e-9:
                        dead = False
                if dead:
                    for l in range(m):
                        W[l, j] = 1.0
                    for a in range(offsets[j], offsets[j + 1]):
                        alpha[a] = 1.0 / (offsets[j + 1] - offsets[j])
        Hf = H
        if any_miss[t]:
            _downdate(H, Bt, Mc, miss[t], Ht)
            Hf = Ht
        xt = xx[t]
        if nr > 0:
            U = _rigid_frame(
                miss[t], any_miss[t], Jr, JtJ, Uraw, qraw[t], Bt, Mc, Lf, Uf, Lt, JtJ_t, Ut, q
            )
            for i in range(nr):
                xt -= q[i] * q[i]
        gt = g[t]
        cd = c_d[t]
        cs = c_s[t] if (t > 0 or has_prev) else 0.0
        cb = c_b[t] if (mouth >= 0 and speech >= 0) else 0.0
        best_e = np.inf
        it_total = 0
        energy = 0.0
        it = 0
        for attempt in range(2):
            if attempt == 1:
                # Additive composition, lip bias on, speech off in the mouth: the bias then
                # pins the speech coefficients to the closed viseme although they do not act,
                # a stationary point the bilinear steps cannot leave (the viseme and the weight
                # must change together). Try again with the mouth's speech weight on.
                if not (additive and cb > 0.0 and W[mouth, speech] <= 1e-6):
                    break
                _copy(best_w, W)
                _copy(best_a, alpha)
                best_e = energy
                W[mouth, speech] = 1.0
            lin, quad = _evaluate(Hf, used, alpha, W, gt, layer_of, beta, h)
            if nr > 0:
                quad -= _rigid_part(U, beta, q, srig) - _sq(q)
            energy = cd * (xt - 2.0 * lin + quad) + _penalties(
                alpha, W, layer_of, cb, cs, mouth, speech, closed, a_prev, w_prev, additive
            )
            floor = (
                tol * 1e-3 * (cd * xt + cb + cs) + 1e-300
            )  # exact fits: accuracy relative to |x_hat|
            mu = 0.0
            it = 0
            while it < max_iter:
                it += 1
                _gauss_newton_system(
                    Hf,
                    used,
                    alpha,
                    W,
                    gt,
                    h,
                    offsets,
                    layer_of,
                    cd,
                    cb,
                    cs,
                    mouth,
                    speech,
                    closed,
                    a_prev,
                    w_prev,
                    additive,
                    G,
                    c,
                )
                if nr > 0:
                    _rigid_part(U, beta, q, srig)
                    _rigid_system(G, c, U, alpha, W, layer_of, offsets, cd, q, srig, V)
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
                    # np.int64: a literal argument is a specialization of its own
                    active_set_qp(Gm, cm, lo, hi, group, sums, y, np.int64(_QP_MAX_ITER), _QP_TOL)
                    _unpack(y, K, alpha_y, W_y)
                    lin, quad = _evaluate(Hf, used, alpha_y, W_y, gt, layer_of, beta_y, h_y)
                    if nr > 0:
                        quad -= _rigid_part(U, beta_y, q, srig) - _sq(q)
                    e_y = cd * (xt - 2.0 * lin + quad) + _penalties(
                        alpha_y,
                        W_y,
                        layer_of,
                        cb,
                        cs,
                        mouth,
                        speech,
                        closed,
                        a_prev,
                        w_prev,
                        additive,
                    )
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
                _copy(alpha, alpha_y)
                _copy(W, W_y)
                beta, beta_y = beta_y, beta
                h, h_y = h_y, h
                mu = mu / 3.0 if mu > 1e-9 * scale else 0.0
                if decrease <= tol * energy or decrease <= floor:
                    break

            it_total += it
        if energy > best_e:
            energy = best_e
            _copy(W, best_w)
            _copy(alpha, best_a)
        _copy(out_w[t], W)
        _copy(out_a[t], alpha)
        out_obj[t] = max(energy, 0.0)
        out_iter[t] = it_total
        _copy(w_prev, W)
        _copy(a_prev, alpha)


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


@nb.njit(cache=True, fastmath=FASTMATH, nogil=True)
def assemble(
    products, offsets, n_frames, neutral, vertex_ptr, entry_region, entry_col, motion, out
):
    """Eq. 5 per vertex: ``out[f, v] = R_f (neutral_v + sum of its region products) + t_f``.

    ``products`` is flat: region l's ``(n_frames, w_l)`` product ``beta_l @ block_l`` starts
    at ``n_frames * offsets[l]`` (row-major); vertex v's 3-vectors sit in regions
    ``entry_region[e]`` at columns ``entry_col[e]`` for e in ``vertex_ptr[v]:vertex_ptr[v + 1]``.
    ``motion (F, 4, 4)``; writes ``out (F, V, 3)`` once.
    """
    n_regions = offsets.shape[0] - 1
    base = np.empty(n_regions, np.int64)
    for f in range(n_frames):
        r = motion[f]
        r00, r01, r02, r03 = r[0, 0], r[0, 1], r[0, 2], r[0, 3]
        r10, r11, r12, r13 = r[1, 0], r[1, 1], r[1, 2], r[1, 3]
        r20, r21, r22, r23 = r[2, 0], r[2, 1], r[2, 2], r[2, 3]
        for l in range(n_regions):
            base[l] = n_frames * offsets[l] + f * (offsets[l + 1] - offsets[l])
        of = out[f]
        for v in range(neutral.shape[0]):
            x, y, z = neutral[v, 0], neutral[v, 1], neutral[v, 2]
            for e in range(vertex_ptr[v], vertex_ptr[v + 1]):
                k = base[entry_region[e]] + entry_col[e]
                x += products[k]
                y += products[k + 1]
                z += products[k + 2]
            of[v, 0] = r00 * x + r01 * y + r02 * z + r03
            of[v, 1] = r10 * x + r11 * y + r12 * z + r13
            of[v, 2] = r20 * x + r21 * y + r22 * z + r23
