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
