"""numba triangular solves with many right-hand sides (compiled lazily, cached).

The factors are CSC matrices from SuperLU; right-hand sides are row-major ``(n, k)``
blocks so each factor entry updates a contiguous run of ``k`` values. Columns are split
into blocks solved in parallel; each column's arithmetic is the same whatever the
split, so results do not depend on the number of threads.
"""
from __future__ import annotations

import numba as nb


@nb.njit(parallel=True, cache=True)
def lu_solve(l_ptr, l_ind, l_val, u_ptr, u_ind, u_val, u_diag, x, n_blocks):
    """Solve ``L U z = x`` in place; L unit lower (strict part stored), U upper (strict part
    stored, diagonal in ``u_diag``), both CSC; ``x : (n, k)``."""
    n, k = x.shape
    step = (k + n_blocks - 1) // n_blocks
    for b in nb.prange(n_blocks):
        c0 = b * step
        c1 = min(k, c0 + step)
        for j in range(n):
            for p in range(l_ptr[j], l_ptr[j + 1]):
                i = l_ind[p]
                w = l_val[p]
                for c in range(c0, c1):
                    x[i, c] -= w * x[j, c]
        for j in range(n - 1, -1, -1):
            d = u_diag[j]
            for c in range(c0, c1):
                x[j, c] /= d
            for p in range(u_ptr[j], u_ptr[j + 1]):
                i = u_ind[p]
                w = u_val[p]
                for c in range(c0, c1):
                    x[i, c] -= w * x[j, c]


@nb.njit(parallel=True, cache=True)
def lu_solve_ordered(order, l_ptr, l_ind, l_val, u_ptr, u_ind, u_val, u_diag, x, n_blocks):
    """As :func:`lu_solve` for a symmetric permutation, in the original row order.

    ``order[i]`` is the original index of pivot ``i``; the factors' row indices are already
    original indices, so ``x : (n, k)`` is solved in place without permuted copies.
    """
    n, k = x.shape
    step = (k + n_blocks - 1) // n_blocks
    for b in nb.prange(n_blocks):
        c0 = b * step
        c1 = min(k, c0 + step)
        for j in range(n):
            oj = order[j]
            for p in range(l_ptr[j], l_ptr[j + 1]):
                i = l_ind[p]
                w = l_val[p]
                for c in range(c0, c1):
                    x[i, c] -= w * x[oj, c]
        for j in range(n - 1, -1, -1):
            oj = order[j]
            d = u_diag[j]
            for c in range(c0, c1):
                x[oj, c] /= d
            for p in range(u_ptr[j], u_ptr[j + 1]):
                i = u_ind[p]
                w = u_val[p]
                for c in range(c0, c1):
                    x[i, c] -= w * x[oj, c]
