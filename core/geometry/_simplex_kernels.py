"""numba kernels for :mod:`faceretarget.geometry.simplex` (compiled lazily, cached)."""

from __future__ import annotations

import numba as nb
import numpy as np


@nb.njit(cache=True)
def project_row(v: np.ndarray, radius: float, out: np.ndarray) -> None:
    """Euclidean projection of ``v : (n,)`` onto ``{x >= 0, sum x = radius}`` into ``out``.

    Sort-based (Held, Wolfe & Crowder 1974; Duchi et al. 2008): with ``u`` sorted in
    decreasing order, ``rho = max{j : u_j - (sum_{i<=j} u_i - radius) / j > 0}`` and
    ``theta = (sum_{i<=rho} u_i - radius) / rho``; then ``x = max(v - theta, 0)``.
    """
    n = v.shape[0]
    u = np.sort(v)[::-1]
    cumulative = 0.0
    theta = 0.0
    for j in range(n):
        cumulative += u[j]
        t = (cumulative - radius) / (j + 1)
        if u[j] - t > 0.0:
            theta = t
    total = 0.0
    for i in range(n):
        x = v[i] - theta
        out[i] = x if x > 0.0 else 0.0
        total += out[i]
    # rounding: rescale so the sum is radius to the last bit the data allows
    if total > 0.0:
        scale = radius / total
        for i in range(n):
            out[i] *= scale


@nb.njit(cache=True)
def project_rows(values: np.ndarray, radius: float, out: np.ndarray) -> None:
    """Row-wise :func:`project_row` of ``values : (B, n)``."""
    for b in range(values.shape[0]):
        project_row(values[b], radius, out[b])
