"""Numba kernels of the spacetime solver (compiled lazily on first use, ``cache=True``).

Imported only inside the functions that call them, never at plugin import time.

- :func:`modal_sweep`: the structured movement-matching solve. After the generalized
  eigendecomposition (``solver.System.modal``) the normal equations of Eq. 4 split into one
  tridiagonal system in time per mode; this projects the data, runs all of them in one
  Thomas sweep and maps back to weights.
- :func:`modal_energies`: the residual energies of that solve from its modal quantities.
- :func:`admm_box`: movement matching with box bounds and an L1 term (ADMM whose w-step
  is the same sweep).
- :func:`block_thomas`: the exact general solve (block tridiagonal in time) used when
  frames differ (missing markers, per-frame Sobolev weights).

Dense Cholesky and the per-frame bounded least squares ("Range PF") are not here: they are
the shared kernels of :mod:`faceretarget.geometry._nnls_kernels` (through
``geometry.nnls.bounded_lsq_frames`` for the latter).
"""

from __future__ import annotations

import numba as nb
import numpy as np

from faceretarget.geometry._nnls_kernels import FASTMATH, chol_solve, cholesky


@nb.njit(cache=True)
def modal_sweep(s, bphi, pbphi, beta, c0, lam, known, phi_t, z, y, scratch, out):
    """Structured movement-matching solve: project, one Thomas sweep per mode, back to weights.

    For every mode j solves ``((1 - lam_j) L + lam_j I) y_j = L z_j + beta zpos_j + c0_j`` and
    returns ``out = y Phi^T``.

    Parameters
    ----------
    s : (F, 3N) float64
        Source marker deltas (no missing samples).
    bphi, pbphi : (3N, m) float64
        ``B Phi`` and ``P B Phi`` (Sobolev marker weights P; used when beta != 0). An empty
        (0, m) ``pbphi`` means uniform weights ``P = p_0 I``, with ``p_0`` folded into ``beta``.
    beta : float
    c0 : (m,) float64
        Prior term ``Phi^T alpha q`` (same every frame).
    lam : (m,) float64
        Generalized eigenvalues in [0, 1].
    known : (F,) bool
        Frames whose value is given (boundary / user constraints): their row is identity.
    phi_t : (m, m) float64
        ``Phi^T``, C-contiguous (the generalized eigenvectors are its rows; weights = Phi y).
    z : (F, m) float64
        Receives the projection ``s B Phi`` (may be ``out`` when it is not needed after).
    y : (F, m) float64
        Receives the modal solution ``y`` (``out = y Phi^T``).
    scratch : (F, m) float64
        On entry, the modal values of the known frames in their rows (other rows unused);
        work array.
    out : (F, m) float64
        Receives the weights.

    ``L`` is the path-graph Laplacian in time (Neumann ends), ``D^T D`` of the paper's
    appendix; rows of known frames are replaced by the identity, which moves the known values
    to the right-hand side of their neighbours. The three products are BLAS calls (4x the
    plain loops on this machine); callers run them single-threaded
    (``faceretarget._threads``), so they do not fight numba for the cores.
    """
    np.dot(s, bphi, z)
    if beta != 0.0 and pbphi.shape[0] > 0:
        np.dot(s, pbphi, y)
        laplacian_rhs(z, y, beta, c0, known, y)  # y: P B Phi projection in, right-hand side out
    else:  # no Sobolev term, or uniform marker weights (beta already includes p_0)
        laplacian_rhs(z, z, beta, c0, known, y)
    tridiagonal_modes(y, lam, known, scratch, y, out)  # out takes the factor until the end
    np.dot(y, phi_t, out)


@nb.njit(cache=True, fastmath=FASTMATH)
def modal_energies(s, y, z, lam, velocity, position):
    """:func:`residual_energies` of a structured solve from its modal quantities, without
    ``B w``: with ``Phi^T (G + K) Phi = I`` and ``Phi^T K Phi = diag(lam)``, ``w_t = Phi y_t``
    and ``z_t = Phi^T B^T s_t``,

        ||B w_t - s_t||^2 = sum_j (1 - lam_j) y_tj^2 - 2 y_t . z_t + ||s_t||^2

    and the same for the differences ``t - 1 -> t`` (``velocity[0] = 0``). O(F (m + 3N))
    instead of the O(F m 3N) product; ``s`` (F, 3N) complete. The subtraction leaves an
    absolute error of a few ulps of ``||s_t||^2`` (an exact fit reports a tiny positive
    energy instead of 0); clamped at 0.
    """
    n_frames, k_rows = s.shape
    m = y.shape[1]
    for t in range(n_frames):
        pos = 0.0
        for j in range(m):
            pos += ((1.0 - lam[j]) * y[t, j] - 2.0 * z[t, j]) * y[t, j]
        for k in range(k_rows):
            pos += s[t, k] * s[t, k]
        position[t] = max(pos, 0.0)
        if t == 0:
            velocity[0] = 0.0
            continue
        vel = 0.0
        for j in range(m):
            dy = y[t, j] - y[t - 1, j]
            vel += ((1.0 - lam[j]) * dy - 2.0 * (z[t, j] - z[t - 1, j])) * dy
        for k in range(k_rows):
            ds = s[t, k] - s[t - 1, k]
            vel += ds * ds
        velocity[t] = max(vel, 0.0)


@nb.njit(cache=True)
def laplacian_rhs(z, zpos, beta, c0, known, out):
    """``out_t = L z_t + beta zpos_t + c0`` for the unknown frames (rows of known frames: 0).

    ``L`` is the path-graph Laplacian in time with Neumann ends (a frame's degree is its
    number of neighbours). ``out`` may alias ``zpos`` (read only at the entry it writes),
    not ``z``.
    """
    n_frames, m = z.shape
    for t in range(n_frames):
        if known[t]:
            for j in range(m):
                out[t, j] = 0.0
            continue
        has_prev = t > 0
        has_next = t < n_frames - 1
        deg = (1.0 if has_prev else 0.0) + (1.0 if has_next else 0.0)
        for j in range(m):
            r = deg * z[t, j] + c0[j]
            if beta != 0.0:
                r += beta * zpos[t, j]
            if has_prev:
                r -= z[t - 1, j]
            if has_next:
                r -= z[t + 1, j]
            out[t, j] = r


@nb.njit(cache=True)
def thomas_factor(lam, known, inv):
    """Factor ``((1 - lam_j) L + lam_j I)`` for every mode j (Thomas algorithm, forward part).

    ``inv[t, j]`` receives ``1 / d_t`` for the pivots ``d_t = b_t - g_j^2 / d_{t-1}``
    (``g_j = 1 - lam_j``, ``b_t = g_j deg_t + lam_j``); rows of known frames are the identity
    and get 0, so they cut the recurrence. Depends on ``lam`` and ``known`` only: ADMM factors
    once per step size and then runs :func:`thomas_apply` every iteration, without divisions.
    """
    n_frames, m = inv.shape
    for t in range(n_frames):
        if known[t]:
            for j in range(m):
                inv[t, j] = 0.0
            continue
        has_prev = t > 0
        deg = (1.0 if has_prev else 0.0) + (1.0 if t < n_frames - 1 else 0.0)
        for j in range(m):
            g = 1.0 - lam[j]
            pivot = g * deg + lam[j]
            if has_prev:
                pivot -= g * g * inv[t - 1, j]
            inv[t, j] = 1.0 / pivot


@nb.njit(cache=True)
def thomas_apply(r, lam, known, yk, inv, y):
    """Solve with the factor of :func:`thomas_factor`: ``y_j = ((1 - lam_j) L + lam_j I)^-1 r_j``.

    Rows of known frames are ``y_t = yk_t``; their neighbours see the known value on the
    right-hand side. ``y`` may alias ``r``; ``yk`` must not alias ``inv``.
    """
    n_frames, m = r.shape
    for t in range(n_frames):
        if known[t]:
            for j in range(m):
                y[t, j] = yk[t, j]
        elif t > 0:
            for j in range(m):
                y[t, j] = (r[t, j] + (1.0 - lam[j]) * y[t - 1, j]) * inv[t, j]
        else:
            for j in range(m):
                y[t, j] = r[t, j] * inv[t, j]
    for t in range(n_frames - 2, -1, -1):
        if not known[t]:
            for j in range(m):
                y[t, j] += (1.0 - lam[j]) * inv[t, j] * y[t + 1, j]


@nb.njit(cache=True)
def steady_pivots(lam, known, inv, limit, steady):
    """The interior pivots of :func:`thomas_factor` converge geometrically to the fixed point of
    ``x = 1 / (2 g + lam - g^2 x)`` (``g = 1 - lam``), ``limit[j] = 2 / (b + sqrt(b^2 - 4 g^2))``
    with ``b = 2 g + lam``; ``steady[t]`` is True where every pivot of row t is within
    ``1e-10 lam_j`` (relative) of it, so that the ADMM sweeps read ``limit`` (m values) in place of
    row t of ``inv``. The mode's matrix has condition number about ``4 / lam_j``, so the solution
    moves by at most ~4e-10 relative: far below the float32 w-step's 1e-6."""
    n_frames, m = inv.shape
    for j in range(m):
        g = 1.0 - lam[j]
        b = 2.0 * g + lam[j]
        limit[j] = 2.0 / (b + np.sqrt(max(b * b - 4.0 * g * g, 0.0)))
    for t in range(n_frames):
        ok = (not known[t]) and 0 < t < n_frames - 1
        if ok:
            for j in range(m):
                if abs(inv[t, j] - limit[j]) > 1e-10 * lam[j] * limit[j]:
                    ok = False
                    break
        steady[t] = ok


@nb.njit(cache=True)
def _thomas_steady(y, lam, known, yk, inv, limit, steady, sweep, carry):
    """:func:`thomas_apply` of ``y`` in place (``y`` may be float32): rows flagged ``steady``
    (:func:`steady_pivots`) take their pivots from ``limit``; the recurrences run in float64
    (``carry``, (m,)), ``sweep`` (F, m) float64 keeps the forward pass."""
    n_frames, m = y.shape
    for t in range(n_frames):
        if known[t]:
            for j in range(m):
                carry[j] = yk[t, j]
                sweep[t, j] = carry[j]
        elif t == 0:
            for j in range(m):
                carry[j] = y[t, j] * inv[t, j]
                sweep[t, j] = carry[j]
        elif steady[t]:
            for j in range(m):
                carry[j] = (y[t, j] + (1.0 - lam[j]) * carry[j]) * limit[j]
                sweep[t, j] = carry[j]
        else:
            for j in range(m):
                carry[j] = (y[t, j] + (1.0 - lam[j]) * carry[j]) * inv[t, j]
                sweep[t, j] = carry[j]
    for j in range(m):
        y[n_frames - 1, j] = carry[j]
    for t in range(n_frames - 2, -1, -1):
        if known[t]:
            for j in range(m):
                carry[j] = sweep[t, j]
                y[t, j] = carry[j]
        elif steady[t]:
            for j in range(m):
                carry[j] = sweep[t, j] + (1.0 - lam[j]) * limit[j] * carry[j]
                y[t, j] = carry[j]
        else:
            for j in range(m):
                carry[j] = sweep[t, j] + (1.0 - lam[j]) * inv[t, j] * carry[j]
                y[t, j] = carry[j]


@nb.njit(cache=True)
def tridiagonal_modes(r, lam, known, yk, y, scratch):
    """Solve ``((1 - lam_j) L + lam_j I) y_j = r_j`` for every mode j by one Thomas sweep.

    Rows of known frames are the identity (``y_t = yk_t``). ``y`` may alias ``r``; ``scratch``
    (F, m) receives the factor and must not alias ``yk``.
    """
    thomas_factor(lam, known, scratch)
    thomas_apply(r, lam, known, yk, scratch, y)


@nb.njit(cache=True)
def admm_box(
    r_w,
    lam,
    known,
    yk,
    inv,
    limit,
    steady,
    phi,
    phi_t,
    rho,
    scale,
    relax,
    lo,
    hi,
    l1,
    z,
    u,
    max_iter,
    eps_abs,
    eps_rel,
    dual_unit,
    ex,
    y,
    sweep,
):
    """ADMM for movement matching with box bounds and an L1 term on the weights.

    Minimizes ``1/2 w^T H w - r^T w + sum_j l1_j |w_j|`` subject to ``lo <= w <= hi`` over the unknown
    frames, where ``H = L kron G + I kron K`` is the movement-matching normal matrix. Split
    ``w = z`` with the penalty ``rho/2 ||D^1/2 (w - z + u)||^2`` (``D = diag(scale)``): the w-step
    solves ``(H + rho I kron D) w = r + rho D (z - u)``, which keeps the Kronecker structure
    (``phi``/``lam`` are the generalized eigenpairs of ``(K + rho D, G + K + rho D)``), so it is one
    tridiagonal sweep per mode, factored once per step size (``inv``, ``limit``, ``steady``:
    :func:`thomas_factor`, :func:`steady_pivots`); the z-step is the prox of the box + L1 term,
    ``clip(soft(v, l1_j / (rho d_j)), lo_j, hi_j)``, element by element (Boyd et al. 2011,
    sec. 5-6, with over-relaxation ``relax``).

    The w-step's right-hand side ``r + rho D (z - u)`` is formed in ``ex`` by the z-step and taken
    to modal coordinates by one product, ``(F, m) x (m, m)``; that product and the one back,
    most of an iteration's time, run in the dtype of ``phi`` (float32 by default,
    ``solver.ADMM_SINGLE``: twice the float64 speed): an inexact w-step whose relative error,
    about 1e-6, is far below the stopping tolerance. The sweep, the prox, the iterates ``z``,
    ``u`` and the residuals are float64. ``ex`` holds the w-step's result and is overwritten
    by the next right-hand side row by row (one work array fewer).

    scale, l1, lo, hi : (m,) the penalty's diagonal ``D``, per-shape L1 weights and bounds.
    r_w : (F, m) right-hand side ``r`` of the unknown frames (dtype of ``phi``); known frames
    keep ``yk`` (modal) and their ``z`` rows. ``z``, ``u`` (scaled dual) are updated in place;
    ``ex``, ``y`` (the dtype of ``phi``) and ``sweep`` (float64) are (F, m) work arrays. The
    dual residual has the units of the system's matrices: its absolute tolerance is
    ``eps_abs * dual_unit`` (a typical diagonal entry), so the iterations do not depend on the
    length unit of the data. Returns ``(iterations, primal, dual, eps_primal, eps_dual)`` of the
    last iteration; iterations is negative if the tolerance was not reached within ``max_iter``.
    """
    n_frames, m = z.shape
    n_free = 0
    for t in range(n_frames):
        if not known[t]:
            n_free += m
    root = np.sqrt(max(n_free, 1))
    penalty = rho * scale  # (m,) rho d_j
    thresh = l1 / penalty  # soft threshold of the prox, per shape
    scale2 = scale * scale
    acc = np.zeros((5, m))  # per-shape sums (vectorized): primal, dual, |w|, |z|, |D u| squared
    carry = np.empty(m)
    for t in range(n_frames):
        for j in range(m):
            ex[t, j] = 0.0 if known[t] else penalty[j] * (z[t, j] - u[t, j]) + r_w[t, j]
    primal = dual = eps_p = eps_d = 0.0
    for it in range(max_iter):
        np.dot(ex, phi, y)  # BLAS (sgemm)
        _thomas_steady(y, lam, known, yk, inv, limit, steady, sweep, carry)
        np.dot(y, phi_t, ex)  # ex = w
        acc[:] = 0.0
        for t in range(n_frames):
            if known[t]:
                for j in range(m):
                    ex[t, j] = 0.0
                continue
            for j in range(m):
                wt = np.float64(ex[t, j])
                wr = relax * wt + (1.0 - relax) * z[t, j]
                v = wr + u[t, j]
                v -= min(max(v, -thresh[j]), thresh[j])  # soft threshold, branch-free
                zn_ = min(max(v, lo[j]), hi[j])
                ut = u[t, j] + wr - zn_
                diff = wt - zn_
                dz = zn_ - z[t, j]
                acc[0, j] += diff * diff
                acc[1, j] += scale2[j] * dz * dz
                acc[2, j] += wt * wt
                acc[3, j] += zn_ * zn_
                acc[4, j] += scale2[j] * ut * ut
                u[t, j] = ut
                z[t, j] = zn_
                ex[t, j] = penalty[j] * (zn_ - ut) + r_w[t, j]
        primal = np.sqrt(acc[0].sum())
        dual = rho * np.sqrt(acc[1].sum())
        eps_p = eps_abs * root + eps_rel * np.sqrt(max(acc[2].sum(), acc[3].sum()))
        eps_d = eps_abs * root * dual_unit + eps_rel * rho * np.sqrt(acc[4].sum())
        if primal <= eps_p and dual <= eps_d:
            return it + 1, primal, dual, eps_p, eps_d
    return -max_iter, primal, dual, eps_p, eps_d


@nb.njit(cache=True, fastmath=FASTMATH)
def residual_energies(s, basis_t, w, velocity, position):
    """Per-frame ``position[t] = ||B w_t - s_t||^2`` and ``velocity[t] = ||r_t - r_{t-1}||^2``
    (``r_t = B w_t - s_t``; ``velocity[0] = 0``). Missing samples (NaN in ``s``) are dropped
    from both; a velocity entry needs the sample at both frames. ``basis_t`` is ``B^T``
    (m, 3N), C-contiguous. ``B w`` is a BLAS product over blocks of ``ENERGY_BLOCK`` frames
    (the scratch stays in cache, whatever the sequence's length).
    """
    n_frames, k_rows = s.shape
    block = min(ENERGY_BLOCK, n_frames)
    cur = np.empty((block, k_rows))
    prev = np.zeros(k_rows)
    prev_ok = np.zeros(k_rows, dtype=np.bool_)
    for start in range(0, n_frames, block):
        stop = min(start + block, n_frames)
        rows = cur[: stop - start]
        np.dot(w[start:stop], basis_t, rows)
        for t in range(start, stop):
            pos = 0.0
            vel = 0.0
            for k in range(k_rows):
                x = s[t, k]
                ok = x == x  # not NaN (FASTMATH keeps NaN semantics: no 'nnan')
                r = rows[t - start, k] - x if ok else 0.0
                pos += r * r
                d = r - prev[k] if (ok and prev_ok[k]) else 0.0
                vel += d * d
                prev[k] = r
                prev_ok[k] = ok
            position[t] = pos
            velocity[t] = vel if t > 0 else 0.0


#: Frames per BLAS block of :func:`residual_energies`.
ENERGY_BLOCK = 128


@nb.njit(cache=True)
def _edge_gram(gram, marker_grams, miss_a, miss_b):
    """``B^T M_e B``: the full Gram minus the blocks of markers missing at either end."""
    m = gram.shape[0]
    out = np.empty((m, m))
    for a in range(m):
        for b in range(m):
            out[a, b] = gram[a, b]
    for i in range(miss_a.shape[0]):
        if miss_a[i] or miss_b[i]:
            for a in range(m):
                for b in range(m):
                    out[a, b] -= marker_grams[i, a, b]
    return out


@nb.njit(cache=True)
def block_thomas(
    gram,
    marker_grams,
    k0,
    missing,
    pos_weights,
    use_pos,
    rhs,
    known,
    wk,
    ridge,
    pivot_rtol,
    out,
    coupling,
):
    """Exact block-tridiagonal solve of the movement-matching normal equations.

    Parameters
    ----------
    gram : (m, m)              B^T B over all markers
    marker_grams : (N, m, m)   B_i^T B_i per marker (3 rows each)
    k0 : (m, m)                alpha Q + ridge (position-type terms common to all frames)
    missing : (F, N) bool      missing marker samples
    pos_weights : (F, N)       Sobolev weight beta * p_{t,i} (0 where missing); used if use_pos
    use_pos : bool
    rhs : (F, m)               normal-equation right-hand side (original coordinates)
    known : (F,) bool, wk : (F, m)   constrained frames and their values
    ridge : float              added to the diagonal of a block that is singular
    pivot_rtol : float         a Cholesky pivot below this times the block's largest diagonal
                               entry counts as singular (``config.PIVOT_RTOL``)
    out : (F, m)               receives the weights
    coupling : (F, m, m)       work memory, F m^2 doubles

    Velocity edge (t-1, t) uses only markers present at both frames; the frame block of an
    unknown frame is the sum of its two edge Grams plus the position terms. Known frames
    are identity rows, so the Schur complements stay symmetric positive definite
    (block Cholesky-Thomas). A singular block (some shape unseen at this frame, no prior)
    gets ``ridge`` on its diagonal. Returns False if a block is still not positive definite.
    """
    n_frames, m = rhs.shape
    n_markers = marker_grams.shape[0]
    ext = np.empty(
        (m + 1, m)
    )  # rows: the columns of -A[t, t+1] = -g_next, then the right-hand side
    fac = np.empty((m, m))
    g_prev = np.zeros((m, m))
    for t in range(n_frames):
        has_next = t < n_frames - 1
        if has_next:
            g_next = _edge_gram(gram, marker_grams, missing[t], missing[t + 1])
        else:
            g_next = np.zeros((m, m))
        if known[t]:
            for a in range(m):
                out[t, a] = wk[t, a]
                for b in range(m):
                    coupling[t, a, b] = 0.0
            g_prev = g_next
            continue
        block = np.empty((m, m))
        for a in range(m):
            for b in range(m):
                block[a, b] = k0[a, b] + g_prev[a, b] + g_next[a, b]
        if use_pos:
            for i in range(n_markers):
                p = pos_weights[t, i]
                if p != 0.0:
                    for a in range(m):
                        for b in range(m):
                            block[a, b] += p * marker_grams[i, a, b]
        for a in range(m):
            ext[m, a] = rhs[t, a]
        if t > 0:
            # lower coupling A[t, t-1] = -g_prev: S_t = A_tt - A[t, t-1] X_{t-1}, y_t = r_t - A[t, t-1] x_{t-1}
            for a in range(m):
                for c in range(m):
                    ga = g_prev[a, c]
                    if ga != 0.0:
                        ext[m, a] += ga * out[t - 1, c]
                        for b in range(m):
                            block[a, b] += ga * coupling[t - 1, c, b]
        for a in range(m):
            for b in range(m):
                ext[b, a] = -g_next[a, b]
        top = 0.0
        for a in range(m):
            top = max(top, block[a, a])
        if not cholesky(block, m, 0.0, pivot_rtol * top, fac):
            for a in range(m):
                block[a, a] += ridge
            if not cholesky(block, m, 0.0, pivot_rtol * (top + ridge), fac):
                return False
        for r in range(m + 1):
            chol_solve(fac, m, ext[r])
        for a in range(m):
            for b in range(m):
                coupling[t, a, b] = ext[b, a]
            out[t, a] = ext[m, a]
        g_prev = g_next
    for t in range(n_frames - 2, -1, -1):
        if not known[t]:
            for a in range(m):
                v = 0.0
                for b in range(m):
                    v += coupling[t, a, b] * out[t + 1, b]
                out[t, a] -= v
    return True
