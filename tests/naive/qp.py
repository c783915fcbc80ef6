"""Brute-force references for the non-negative QP ``min 1/2 x^T H x - r^T x, x >= 0``."""

from __future__ import annotations

import itertools

import numpy as np
import scipy.optimize
import scipy.sparse as sp


def nonneg_qp_enumerate(hessian, rhs):
    """Try every free set (2^n of them, n <= 12): the feasible stationary point of least
    objective is the optimum of the convex problem."""
    h = np.asarray(hessian, dtype=np.float64)
    r = np.asarray(rhs, dtype=np.float64)
    n = r.size
    assert n <= 12, "2^n free sets"
    best, best_x = np.inf, np.zeros(n)
    for mask in itertools.product((False, True), repeat=n):
        free = np.flatnonzero(mask)
        x = np.zeros(n)
        if free.size:
            x[free] = np.linalg.lstsq(h[np.ix_(free, free)], r[free], rcond=None)[0]
        if (x < -1e-12).any():
            continue
        value = 0.5 * x @ h @ x - r @ x
        if value < best:
            best, best_x = value, np.maximum(x, 0.0)
    return best_x


def nonneg_qp_scipy(hessian, rhs):
    """The same problem as least squares on the Cholesky factor ``H = L L^T``: ``min |L^T x -
    L^-1 r|^2`` by scipy's NNLS (Lawson & Hanson). Needs ``H`` positive definite."""
    h = np.asarray(hessian, dtype=np.float64)
    lower = np.linalg.cholesky(h)
    b = np.linalg.solve(lower, np.asarray(rhs, dtype=np.float64))
    return scipy.optimize.nnls(lower.T, b, maxiter=50 * h.shape[0])[0]


def block_tridiagonal(seed, n, k, decades, ridge=0.0):
    """``kron(Laplacian, G)`` as in a knot problem of the coating edit, with a metric ``G`` whose
    scales span ``decades`` (not an M-matrix; ill-conditioned for large ``decades``)."""
    rng = np.random.default_rng(seed)
    b = rng.normal(size=(k, k)) * np.logspace(0, -decades, k)
    lap = sp.diags([2 * np.ones(n), -np.ones(n - 1), -np.ones(n - 1)], [0, -1, 1])
    h = sp.kron(lap, sp.csr_matrix(b.T @ b)).tocsc()
    h = h + ridge * float(h.diagonal().mean()) * sp.identity(n * k, format="csc")
    return h.tocsc(), rng.normal(size=n * k) * rng.uniform(0.1, 100)


def blocks_of(hessian, n, k):
    """The diagonal ``(n, K, K)`` and upper ``(n - 1, K, K)`` blocks of a block-tridiagonal
    matrix of ``n x n`` blocks, read off its dense form."""
    dense = hessian.toarray() if sp.issparse(hessian) else np.asarray(hessian)
    diagonal = np.stack([dense[t * k : (t + 1) * k, t * k : (t + 1) * k] for t in range(n)])
    upper = np.zeros((max(n - 1, 0), k, k))
    for t in range(n - 1):
        upper[t] = dense[t * k : (t + 1) * k, (t + 1) * k : (t + 2) * k]
    return diagonal, upper


def block_tridiagonal_dense(diagonal, upper):
    """The dense ``(n K, n K)`` matrix of the blocks (``upper[t]`` at block ``(t, t + 1)``,
    its transpose at ``(t + 1, t)``)."""
    n, k = diagonal.shape[0], diagonal.shape[1]
    dense = np.zeros((n * k, n * k))
    for t in range(n):
        dense[t * k : (t + 1) * k, t * k : (t + 1) * k] = diagonal[t]
    for t in range(n - 1):
        dense[t * k : (t + 1) * k, (t + 1) * k : (t + 2) * k] = upper[t]
        dense[(t + 1) * k : (t + 2) * k, t * k : (t + 1) * k] = upper[t].T
    return dense
