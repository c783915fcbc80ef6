"""Brute-force references for the simplex projection and simplex-constrained QPs."""

from __future__ import annotations

import numpy as np
from scipy.optimize import minimize


def project_simplex_bisection(v, radius=1.0, iters=200):
    """Projection of ``v (n,)`` onto ``{x >= 0, sum x = radius}`` by bisection on theta.

    The projection is ``max(v - theta, 0)`` with theta solving ``sum max(v - theta, 0) = radius``;
    the left side decreases in theta, so bisection finds it (no sorting involved).
    """
    v = np.asarray(v, dtype=np.float64)
    lo, hi = v.min() - radius, v.max()
    for _ in range(iters):
        mid = 0.5 * (lo + hi)
        if np.maximum(v - mid, 0.0).sum() > radius:
            lo = mid
        else:
            hi = mid
    return np.maximum(v - 0.5 * (lo + hi), 0.0)


def simplex_qp_slsqp(G, c, groups):
    """``argmin 1/2 x^T G x - c^T x`` with each group on the unit simplex, by SLSQP."""
    G, c, groups = np.asarray(G, float), np.asarray(c, float), np.asarray(groups)
    n = c.shape[0]
    cons = [
        {"type": "eq", "fun": (lambda x, g=g: x[groups == g].sum() - 1.0)}
        for g in np.unique(groups)
    ]
    x0 = np.zeros(n)
    for g in np.unique(groups):
        x0[groups == g] = 1.0 / np.count_nonzero(groups == g)
    res = minimize(
        lambda x: 0.5 * x @ G @ x - c @ x,
        x0,
        jac=lambda x: G @ x - c,
        method="SLSQP",
        bounds=[(0.0, None)] * n,
        constraints=cons,
        options={"ftol": 1e-14, "maxiter": 1000},
    )
    return res.x
