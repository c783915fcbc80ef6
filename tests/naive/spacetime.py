"""Brute-force references for the spacetime plugin (Seol et al. 2012).

Everything here is written from the energy, row by row, with dense or assembled sparse
matrices; nothing is shared with the plugin's structured solver. Small sizes only
(the assembled Kronecker system is what the paper solved with Matlab: 47 s at 1,500 frames).
"""

from __future__ import annotations

import numpy as np
import scipy.optimize
import scipy.sparse as sp
import scipy.sparse.linalg as spla


def energy_rows(
    basis,
    deltas,
    *,
    prior_factor=None,
    prior_offset=None,
    alpha=0.0,
    beta=0.0,
    marker_weights=None,
    ridge=0.0,
):
    """Least-squares rows ``A x - b`` of the whole energy, unknowns ``x = vec(W)`` frame-major.

    basis (3N, M); deltas (F, N, 3) with NaN rows for missing samples; prior_factor (h, M),
    prior_offset (h,): prior residual ``sqrt(alpha) (A w_t + a)``; marker_weights (N,) or
    (F, N) Sobolev weights (default ones); ridge: scalar (``ridge * I``) or PSD (M, M) matrix
    per frame. Velocity rows exist only for markers seen at both frames; position rows only
    where the marker is seen.
    """
    b = np.asarray(basis, dtype=float)
    s = np.asarray(deltas, dtype=float).reshape(len(deltas), -1)
    n_frames, m = s.shape[0], b.shape[1]
    n_markers = b.shape[0] // 3
    weights = (
        np.ones((n_frames, n_markers))
        if marker_weights is None
        else np.broadcast_to(np.asarray(marker_weights, float), (n_frames, n_markers))
    )
    rows, cols, vals, rhs = [], [], [], []
    row = 0

    def add(coeffs: dict, value: float):
        nonlocal row
        for frame, vec in coeffs.items():
            for j in range(m):
                if vec[j] != 0.0:
                    rows.append(row)
                    cols.append(frame * m + j)
                    vals.append(vec[j])
        rhs.append(value)
        row += 1

    for t in range(1, n_frames):
        for r in range(3 * n_markers):
            if np.isnan(s[t, r]) or np.isnan(s[t - 1, r]):
                continue
            add({t: b[r], t - 1: -b[r]}, s[t, r] - s[t - 1, r])
    if alpha and prior_factor is not None:
        for t in range(n_frames):
            for k in range(prior_factor.shape[0]):
                add({t: np.sqrt(alpha) * prior_factor[k]}, -np.sqrt(alpha) * prior_offset[k])
    if beta:
        for t in range(n_frames):
            for r in range(3 * n_markers):
                if np.isnan(s[t, r]) or weights[t, r // 3] == 0.0:
                    continue
                c = np.sqrt(beta * weights[t, r // 3])
                add({t: c * b[r]}, c * s[t, r])
    for t in range(n_frames):
        for row_vec in _ridge_rows(ridge, m):
            add({t: row_vec}, 0.0)
    a = sp.csr_matrix((vals, (rows, cols)), shape=(row, n_frames * m))
    return a, np.asarray(rhs)


def _ridge_rows(ridge, m):
    """Rows ``R^{1/2}`` of a ridge given as a scalar (``ridge * I``) or a PSD (m, m) matrix."""
    if np.ndim(ridge) == 0:
        return np.sqrt(ridge) * np.eye(m) if ridge else np.zeros((0, m))
    lam, vec = np.linalg.eigh(ridge)
    keep = lam > 0
    return (np.sqrt(lam[keep]) * vec[:, keep]).T


def _ridge_matrix(ridge, m):
    return ridge * np.eye(m) if np.ndim(ridge) == 0 else np.asarray(ridge, float)


def _eliminate_known(basis, deltas, known, known_weights, **energy):
    """The energy's rows with the known frames moved to the right-hand side: ``x`` (F*M,)
    with the known values set, the ``fixed`` mask, the rows of the unknowns and their rhs."""
    a, rhs = energy_rows(basis, deltas, **energy)
    n_frames, m = len(deltas), np.asarray(basis).shape[1]
    known = np.asarray(known, bool)
    fixed = np.repeat(known, m)
    x = np.zeros(n_frames * m)
    x[fixed] = np.asarray(known_weights, float)[known].ravel()
    return x, fixed, a[:, ~fixed], rhs - a[:, fixed] @ x[fixed]


def solve_rows(basis, deltas, known, known_weights, **energy):
    """Minimize the energy with known frames fixed: assemble rows, eliminate, normal equations + spsolve."""
    x, fixed, au, r = _eliminate_known(basis, deltas, known, known_weights, **energy)
    if (~fixed).any():
        x[~fixed] = spla.spsolve((au.T @ au).tocsc(), au.T @ r)
    return x.reshape(len(deltas), -1)


def kronecker_system(
    basis, deltas, known, known_weights, *, prior_matrix, prior_vector, beta=0.0, ridge=0.0
):
    """The paper's assembled sparse system (Eq. 5 normal equations), complete data only.

    ``((D^T D) kron (B^T B) + I kron (alpha Q + beta B^T B + ridge I)) vec(W) = rhs`` with
    ``prior_matrix = alpha Q`` and ``prior_vector = alpha q``; known frames eliminated.
    Returns (matrix over unknowns (CSC), right-hand side, unknown mask (F*M,), full x with knowns set).
    """
    b = np.asarray(basis, dtype=float)
    s = np.asarray(deltas, dtype=float).reshape(len(deltas), -1)
    n_frames, m = s.shape[0], b.shape[1]
    d = sp.diags(
        [-np.ones(n_frames - 1), np.ones(n_frames - 1)], [0, 1], shape=(n_frames - 1, n_frames)
    )
    lap = (d.T @ d).tocsr()
    gram = b.T @ b
    k = prior_matrix + beta * gram + _ridge_matrix(ridge, m)
    mat = (
        sp.kron(lap, sp.csr_matrix(gram)) + sp.kron(sp.identity(n_frames), sp.csr_matrix(k))
    ).tocsr()
    rhs = ((lap @ s) @ b + prior_vector[None] + beta * (s @ b)).ravel()
    fixed = np.repeat(np.asarray(known, bool), m)
    x = np.zeros(n_frames * m)
    x[fixed] = np.asarray(known_weights, float)[np.asarray(known, bool)].ravel()
    sub = mat[~fixed][:, ~fixed].tocsc()
    r = rhs[~fixed] - mat[~fixed][:, fixed] @ x[fixed]
    return sub, r, ~fixed, x


def solve_kronecker(basis, deltas, known, known_weights, **kw):
    """Solve :func:`kronecker_system` with ``spsolve`` -> (F, M)."""
    sub, r, unknown, x = kronecker_system(basis, deltas, known, known_weights, **kw)
    x[unknown] = spla.spsolve(sub, r)
    return x.reshape(len(deltas), -1)


def kronecker_residual(weights, basis, deltas, known, known_weights, **kw) -> float:
    """Relative normal-equation residual ``||A x - r|| / ||r||`` of ``weights (F, M)``."""
    sub, r, unknown, _ = kronecker_system(basis, deltas, known, known_weights, **kw)
    x = np.asarray(weights, float).ravel()[unknown]
    return float(np.linalg.norm(sub @ x - r) / np.linalg.norm(r))


def _frame_systems(basis, deltas, ridge, extra_rows=None, extra_rhs=None):
    """Per frame: the stacked rows ``[B (seen markers); extra; ridge]`` and their right-hand side."""
    b = np.asarray(basis, dtype=float)
    s = np.asarray(deltas, dtype=float).reshape(len(deltas), -1)
    ridge_rows = _ridge_rows(ridge, b.shape[1])
    for t in range(len(s)):
        ok = ~np.isnan(s[t])
        rows = [b[ok]] + ([extra_rows] if extra_rows is not None else []) + [ridge_rows]
        rhs = (
            [s[t, ok]]
            + ([extra_rhs] if extra_rhs is not None else [])
            + [np.zeros(len(ridge_rows))]
        )
        yield np.vstack(rows), np.concatenate(rhs)


def per_frame(basis, deltas, *, prior_factor=None, prior_offset=None, alpha=0.0, ridge=0.0):
    """Per-frame least squares with dense ``lstsq`` on the stacked rows (missing rows dropped)."""
    extra = (
        (np.sqrt(alpha) * prior_factor, -np.sqrt(alpha) * prior_offset)
        if alpha and prior_factor is not None
        else (None, None)
    )
    return np.array(
        [
            np.linalg.lstsq(a, r, rcond=None)[0]
            for a, r in _frame_systems(basis, deltas, ridge, *extra)
        ]
    )


def bounded_per_frame(basis, deltas, lower, upper, *, ridge=0.0):
    """Per-frame bounded least squares with ``scipy.optimize.lsq_linear`` (BVLS), tight tolerance."""
    return np.array(
        [
            scipy.optimize.lsq_linear(a, r, bounds=(lower, upper), method="bvls", tol=1e-14).x
            for a, r in _frame_systems(basis, deltas, ridge)
        ]
    )


def pca_prior(samples, basis, neutral, center="neutral", rtol=1e-10):
    """PCA prior from the covariance matrix's eigendecomposition: returns (Q, q) with
    prior(w) = (B w + n - c)^T E Lambda^-1 E^T (B w + n - c), grad/2 = Q w - q."""
    x = np.asarray(samples, float)
    c = x.mean(axis=0) if center == "mean" else np.asarray(neutral, float)
    cov = (x - c).T @ (x - c) / len(x)
    lam, e = np.linalg.eigh(cov)
    keep = lam > rtol * lam.max()
    precision = e[:, keep] @ np.diag(1.0 / lam[keep]) @ e[:, keep].T
    b = np.asarray(basis, float)
    q_mat = b.T @ precision @ b
    q_vec = -b.T @ precision @ (np.asarray(neutral, float) - c)
    return q_mat, q_vec


def procrustes_rotation(reference, points):
    """Rotation of sec. 3.1 for one frame: SVD of Y^T X (both centred), R = V U^T (det fixed)."""
    y = np.asarray(reference, float) - np.mean(reference, axis=0)
    x = np.asarray(points, float) - np.mean(points, axis=0)
    u, _, vt = np.linalg.svd(y.T @ x)
    r = vt.T @ u.T
    if np.linalg.det(r) < 0:
        vt[-1] *= -1
        r = vt.T @ u.T
    return r


def solve_rows_bounded(basis, deltas, known, known_weights, lower, upper, l1=0.0, **energy):
    """:func:`solve_rows` with ``lower <= w <= upper`` on the unknown frames and ``2 * l1 * sum(w)``
    added to the energy (the L1 norm, valid for ``lower >= 0``; ``l1`` a scalar or (M,)), by BVLS (``lsq_linear``) on the
    assembled rows. The linear term is moved into the right-hand side: with ``A`` of full column
    rank, ``||A x - b||^2 + c^T x = ||A x - (b + d)||^2 + const`` for ``d = -A (A^T A)^-1 c / 2``.
    """
    x, fixed, au, r = _eliminate_known(basis, deltas, known, known_weights, **energy)
    au = au.toarray()
    n_frames, m = len(deltas), np.asarray(basis).shape[1]
    n_free = int((~fixed).sum())
    if np.any(l1):  # a scalar or one weight per shape
        c = np.tile(np.broadcast_to(2.0 * np.asarray(l1, dtype=np.float64), (m,)), n_free // m)
        r = r - 0.5 * au @ np.linalg.solve(au.T @ au, c)
    lo = np.tile(np.broadcast_to(lower, (m,)), n_free // m)
    hi = np.tile(np.broadcast_to(upper, (m,)), n_free // m)
    x[~fixed] = scipy.optimize.lsq_linear(au, r, bounds=(lo, hi), method="bvls", tol=1e-14).x
    return x.reshape(n_frames, m)
