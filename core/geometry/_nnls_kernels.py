"""numba kernels for small dense SPD systems and quadratic programs (compiled lazily, cached).

The one place for these jobs; plugins import them rather than keep their own copies:

- dense Cholesky (:func:`cholesky`, with a pivot test and an optional ridge; :func:`factor`
  escalates the ridge until it succeeds) and the triangular solves (:func:`forward`,
  :func:`backward`, :func:`chol_solve`), on the leading ``n x n`` block of preallocated
  arrays so callers in loops allocate nothing;
- one primal active-set method (Lawson & Hanson 1974, ch. 23, generalised to two-sided
  bounds and to "sum to s" groups), :func:`active_set_qp`, which serves
  :mod:`faceretarget.geometry.nnls` (NNLS and bounded least squares on the Gram matrix) and
  :mod:`faceretarget.geometry.simplex` (quadratic programs over products of probability
  simplices)::

    minimise 1/2 x^T G x - c^T x
    subject to lo <= x <= hi,  sum_{i in group g} x_i = s_g  (groups optional)

  Groups are only used with ``lo = 0, hi = inf`` (simplices), so every group keeps at
  least one free variable and its multiplier is defined by the free ones;
- two loops over it: :func:`active_set_qp_many` (one ``G``, many right-hand sides) and
  :func:`active_set_qp_frames` (a sequence of frames, each warm-started from the previous
  solution, with ``G`` downdated at frames where some row blocks are missing).
"""

from __future__ import annotations

import numba as nb
import numpy as np

FREE, LOWER, UPPER = 0, 1, 2
#: Reassociation lets LLVM vectorise the dot products; NaN/inf semantics are kept (the
#: bounds use +-inf), so results stay deterministic and exact up to rounding.
FASTMATH = {"reassoc", "nsz", "arcp", "contract"}
_RIDGE_START = 1e-13  # relative ridge tried first when a free block is singular


@nb.njit(cache=True, fastmath=FASTMATH)
def cholesky(
    a: np.ndarray, n: int | np.integer, ridge: float, pivot_min: float, out: np.ndarray
) -> bool:
    """Lower Cholesky factor of ``a[:n, :n] + ridge * I`` into ``out[:n, :n]`` (upper part
    untouched). False, with ``out`` partly written, if a pivot is not above ``pivot_min``
    (0: not positive definite; ``rtol * max(diag)``: numerically singular) or is NaN."""
    for j in range(n):
        rj = out[j]
        s = a[j, j] + ridge
        for k in range(j):
            s -= rj[k] * rj[k]
        if not s > pivot_min:
            return False
        d = np.sqrt(s)
        out[j, j] = d
        for i in range(j + 1, n):
            ri = out[i]
            t = a[i, j]
            for k in range(j):
                t -= ri[k] * rj[k]
            out[i, j] = t / d
    return True


@nb.njit(cache=True, fastmath=FASTMATH)
def forward(fac: np.ndarray, n: int | np.integer, rhs: np.ndarray) -> None:
    """``rhs <- L^-1 rhs`` for the lower factor ``L = fac[:n, :n]`` (in place)."""
    for i in range(n):
        fi = fac[i]
        s = rhs[i]
        for k in range(i):
            s -= fi[k] * rhs[k]
        rhs[i] = s / fi[i]


@nb.njit(cache=True, fastmath=FASTMATH)
def backward(fac: np.ndarray, n: int | np.integer, rhs: np.ndarray) -> None:
    """``rhs <- L^-T rhs`` (in place), reading L by rows."""
    for i in range(n - 1, -1, -1):
        fi = fac[i]
        x = rhs[i] / fi[i]
        rhs[i] = x
        for k in range(i):
            rhs[k] -= fi[k] * x


@nb.njit(cache=True, fastmath=FASTMATH)
def chol_solve(fac: np.ndarray, n: int | np.integer, rhs: np.ndarray) -> None:
    """Solve ``fac fac^T y = rhs`` in place (first ``n`` entries)."""
    forward(fac, n, rhs)
    backward(fac, n, rhs)


@nb.njit(cache=True, fastmath=FASTMATH)
def factor(a: np.ndarray, n: int | np.integer, scale: float, out: np.ndarray) -> None:
    """Cholesky with an escalating ridge (relative to ``scale``) for singular blocks."""
    ridge = 0.0
    for _ in range(40):
        if cholesky(a, n, ridge, 0.0, out):
            return
        ridge = _RIDGE_START * scale if ridge == 0.0 else ridge * 10.0


@nb.njit(cache=True, fastmath=FASTMATH)
def active_set_qp(
    G: np.ndarray,
    c: np.ndarray,
    lo: np.ndarray,
    hi: np.ndarray,
    group: np.ndarray,
    sums: np.ndarray,
    x: np.ndarray,
    max_iter: int,
    tol: float,
) -> int:
    """Solve the QP above in place, starting from the feasible ``x : (n,)``.

    ``group[i]`` is the group of variable i (-1: none); ``sums[g]`` its total. Returns
    the number of iterations, negated when ``max_iter`` was reached first.
    """
    n = x.shape[0]
    n_groups = sums.shape[0]
    status = np.zeros(n, np.int64)
    scale = 0.0
    for i in range(n):
        scale = max(scale, abs(G[i, i]), abs(c[i]))
    if scale == 0.0:
        scale = 1.0
    for i in range(n):
        if x[i] <= lo[i]:
            x[i] = lo[i]
            status[i] = LOWER
        elif x[i] >= hi[i]:
            x[i] = hi[i]
            status[i] = UPPER
    free = np.empty(n, np.int64)
    gf = np.empty((n, n))
    fac = np.empty((n, n))
    z = np.empty(n)
    y = np.empty((n_groups, n))
    mu = np.zeros(n_groups)
    schur = np.empty((n_groups, n_groups))
    sfac = np.empty((n_groups, n_groups))
    target = np.empty(n_groups)
    has_free = np.zeros(n_groups, np.bool_)
    grad = np.empty(n)
    tol_abs = tol * scale
    entered = -1
    for it in range(max_iter):
        nf = np.int64(0)  # not a literal 0: the calls below would compile a second specialization
        for i in range(n):
            if status[i] == FREE:
                free[nf] = i
                nf += 1
        if nf > 0:
            # equality-constrained subproblem on the free set (bounded variables fixed)
            for a in range(nf):
                ia = free[a]
                s = c[ia]
                for j in range(n):
                    if status[j] != FREE:
                        s -= G[ia, j] * x[j]
                z[a] = s
                for b in range(nf):
                    gf[a, b] = G[ia, free[b]]
            factor(gf, nf, scale, fac)
            forward(fac, nf, z)  # z = L^-1 r
            if n_groups > 0:
                # Schur complement on the group sums with V = L^-1 E (G = L L^T):
                # S = V^T V, S mu = V^T z - target, then z <- L^-T (z - V mu)
                for g in range(n_groups):
                    has_free[g] = False
                    target[g] = sums[g]
                for j in range(n):
                    if group[j] >= 0:
                        if status[j] == FREE:
                            has_free[group[j]] = True
                        else:
                            target[group[j]] -= x[j]
                for g in range(n_groups):
                    yg = y[g]
                    for a in range(nf):
                        yg[a] = 1.0 if group[free[a]] == g else 0.0
                    if has_free[g]:
                        forward(fac, nf, yg)
                for g in range(n_groups):
                    yg = y[g]
                    for h in range(n_groups):
                        s = 0.0
                        if has_free[g] and has_free[h]:
                            yh = y[h]
                            for a in range(nf):
                                s += yg[a] * yh[a]
                        schur[g, h] = s if (g != h or has_free[g]) else 1.0
                    s = 0.0
                    if has_free[g]:
                        for a in range(nf):
                            s += yg[a] * z[a]
                        mu[g] = s - target[g]
                    else:
                        mu[g] = 0.0
                sscale = 0.0
                for g in range(n_groups):
                    sscale = max(sscale, abs(schur[g, g]))
                factor(schur, n_groups, sscale if sscale > 0.0 else 1.0, sfac)
                chol_solve(sfac, n_groups, mu)
                for g in range(n_groups):
                    if has_free[g]:
                        yg = y[g]
                        for a in range(nf):
                            z[a] -= yg[a] * mu[g]
            backward(fac, nf, z)
            # feasibility of the subproblem's solution
            step = 1.0
            blocking = -1
            for a in range(nf):
                i = free[a]
                if z[a] < lo[i]:
                    # (a free variable rounded onto or past its bound cannot move: step 0)
                    t = (x[i] - lo[i]) / (x[i] - z[a]) if x[i] > z[a] else 0.0
                    if t < step:
                        step, blocking = t, a
                elif z[a] > hi[i]:
                    t = (hi[i] - x[i]) / (z[a] - x[i]) if z[a] > x[i] else 0.0
                    if t < step:
                        step, blocking = t, a
            if blocking >= 0:
                if step <= 0.0:
                    step = 0.0
                    if free[blocking] == entered:
                        # the variable just released cannot move: optimal to working precision
                        _finish(x, lo, hi, group, sums)
                        return it + 1
                for a in range(nf):
                    i = free[a]
                    x[i] += step * (z[a] - x[i])
                for a in range(nf):
                    i = free[a]
                    if z[a] < lo[i] and (a == blocking or x[i] <= lo[i] + tol * (1.0 + abs(lo[i]))):
                        x[i] = lo[i]
                        status[i] = LOWER
                    elif z[a] > hi[i] and (
                        a == blocking or x[i] >= hi[i] - tol * (1.0 + abs(hi[i]))
                    ):
                        x[i] = hi[i]
                        status[i] = UPPER
                continue
            for a in range(nf):
                x[free[a]] = z[a]
        # optimality: multipliers of the bounds, nu_i = grad_i + mu_g(i)
        for i in range(n):
            s = -c[i]
            for j in range(n):
                s += G[i, j] * x[j]
            grad[i] = s
        best = tol_abs
        enter = -1
        for i in range(n):
            if status[i] == FREE:
                continue
            nu = grad[i]
            if group[i] >= 0:
                nu += mu[group[i]]
            if status[i] == LOWER and -nu > best and lo[i] < hi[i]:
                best, enter = -nu, i
            elif status[i] == UPPER and nu > best and lo[i] < hi[i]:
                best, enter = nu, i
        if enter < 0:
            _finish(x, lo, hi, group, sums)
            return it + 1
        status[enter] = FREE
        entered = enter
    _finish(x, lo, hi, group, sums)
    return -max_iter


@nb.njit(cache=True)
def _finish(
    x: np.ndarray, lo: np.ndarray, hi: np.ndarray, group: np.ndarray, sums: np.ndarray
) -> None:
    """Clip to the bounds and rescale each (non-negative) group to its exact total."""
    n = x.shape[0]
    for i in range(n):
        if x[i] < lo[i]:
            x[i] = lo[i]
        elif x[i] > hi[i]:
            x[i] = hi[i]
    for g in range(sums.shape[0]):
        total = 0.0
        for i in range(n):
            if group[i] == g:
                total += x[i]
        if total > 0.0:
            f = sums[g] / total
            for i in range(n):
                if group[i] == g:
                    x[i] *= f


@nb.njit(cache=True)
def active_set_qp_many(
    G: np.ndarray,
    C: np.ndarray,
    lo: np.ndarray,
    hi: np.ndarray,
    group: np.ndarray,
    sums: np.ndarray,
    X: np.ndarray,
    max_iter: int,
    tol: float,
    iterations: np.ndarray,
) -> None:
    """:func:`active_set_qp` for each row of ``C : (k, n)`` (one shared ``G``), in place on ``X``."""
    for r in range(C.shape[0]):
        iterations[r] = active_set_qp(G, C[r], lo, hi, group, sums, X[r], max_iter, tol)


@nb.njit(cache=True)
def active_set_qp_frames(
    G: np.ndarray,
    block_grams: np.ndarray,
    dropped: np.ndarray,
    C: np.ndarray,
    lo: np.ndarray,
    hi: np.ndarray,
    x0: np.ndarray,
    ridge: float,
    pivot_rtol: float,
    X: np.ndarray,
    max_iter: int,
    tol: float,
    iterations: np.ndarray,
) -> None:
    """:func:`active_set_qp` without groups for each frame ``t`` (row ``C[t]``), in order,
    each warm-started from the previous frame's solution (frame 0 from ``x0``), into ``X[t]``.

    ``G : (n, n)`` is the Gram of all row blocks; at a frame where some blocks are missing
    (``dropped[t, b]``) their Grams ``block_grams[b] : (n, n)`` are subtracted, and if that
    leaves a matrix whose Cholesky pivots fall to ``pivot_rtol`` times its largest diagonal
    entry, ``ridge`` is added to its diagonal (shapes unseen at this frame go to the bound
    nearest zero instead of anywhere). ``iterations[t]`` as :func:`active_set_qp`.
    """
    n_frames, n = C.shape
    n_blocks = dropped.shape[1]
    no_group = np.full(n, -1, np.int64)
    no_sums = np.zeros(0)
    H = np.empty((n, n))
    fac = np.empty((n, n))
    for t in range(n_frames):
        x = X[t]
        for i in range(n):
            x[i] = x0[i] if t == 0 else X[t - 1, i]
        any_dropped = False
        for b in range(n_blocks):
            any_dropped = any_dropped or dropped[t, b]
        if not any_dropped:
            iterations[t] = active_set_qp(G, C[t], lo, hi, no_group, no_sums, x, max_iter, tol)
            continue
        for i in range(n):  # H = G - the dropped blocks (loops: an array slice assignment
            for j in range(n):  # compiles numba's shape-message machinery)
                s = G[i, j]
                for b in range(n_blocks):
                    if dropped[t, b]:
                        s -= block_grams[b, i, j]
                H[i, j] = s
        top = 0.0
        for i in range(n):
            top = max(top, H[i, i])
        if not cholesky(H, n, 0.0, pivot_rtol * top, fac):
            for i in range(n):
                H[i, i] += ridge
        iterations[t] = active_set_qp(H, C[t], lo, hi, no_group, no_sums, x, max_iter, tol)
