"""numba triangular solves with many right-hand sides (compiled lazily, cached).

The factors are the strict triangles of an LDL^T factorization as CSC matrices (unit lower
``L``, upper ``U = D L^T`` with its diagonal apart); right-hand sides are row-major ``(n, k)``
blocks so each factor entry updates a contiguous run of ``k`` values. Each call solves
the columns ``c0:c1``; callers run blocks of columns side by side on Python threads
(``_threads.in_blocks``: the kernels are serial and ``nogil``). Each column's arithmetic
is the same whatever the split, so results do not depend on the number of threads.
"""

from __future__ import annotations

import numba as nb
import numpy as np


@nb.njit(cache=True, nogil=True)
def lu_solve(
    l_ptr: np.ndarray,
    l_ind: np.ndarray,
    l_val: np.ndarray,
    u_ptr: np.ndarray,
    u_ind: np.ndarray,
    u_val: np.ndarray,
    u_diag: np.ndarray,
    x: np.ndarray,
    c0: int,
    c1: int,
) -> None:
    """Solve ``L U z = x[:, c0:c1]`` in place; L unit lower (strict part stored), U upper
    (strict part stored, diagonal in ``u_diag``), both CSC; ``x : (n, k)``."""
    n = x.shape[0]
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


@nb.njit(cache=True, nogil=True)
def lu_solve_frames(
    order: np.ndarray,
    l_ptr: np.ndarray,
    l_ind: np.ndarray,
    l_val: np.ndarray,
    u_ptr: np.ndarray,
    u_ind: np.ndarray,
    u_val: np.ndarray,
    u_diag: np.ndarray,
    rhs: np.ndarray,
    add: np.ndarray,
    out: np.ndarray,
    c0: int,
    c1: int,
) -> None:
    """Solve ``A x = rhs`` for per-frame right-hand sides ``rhs : (C, n, 3)`` and write
    ``out = add + x`` (``(C, n, 3)``) for a symmetric pivoting (``order[i]``: the original
    index of pivot ``i``), in the precision of ``l_val`` (float32 or float64; ``u_val`` and
    ``u_diag`` alike), for the columns ``c0:c1`` of the ``3C`` (column ``c`` is coordinate
    ``c % 3`` of frame ``c // 3``). The block is gathered into a contiguous array in pivot
    order (so the factors are walked with good locality), solved and scattered back to
    the original order."""
    n = rhs.shape[1]
    if c1 <= c0:
        return
    w = c1 - c0
    x = np.empty((n, w), dtype=l_val.dtype)  # the factor's precision
    for i in range(n):
        o = order[i]
        for c in range(c0, c1):
            x[i, c - c0] = rhs[c // 3, o, c % 3]
    for j in range(n):
        for p in range(l_ptr[j], l_ptr[j + 1]):
            i = l_ind[p]
            v = l_val[p]
            for c in range(w):
                x[i, c] -= v * x[j, c]
    for j in range(n - 1, -1, -1):
        d = u_diag[j]
        for c in range(w):
            x[j, c] /= d
        for p in range(u_ptr[j], u_ptr[j + 1]):
            i = u_ind[p]
            v = u_val[p]
            for c in range(w):
                x[i, c] -= v * x[j, c]
    for i in range(n):
        o = order[i]
        for c in range(c0, c1):
            out[c // 3, o, c % 3] = add[c // 3, o, c % 3] + x[i, c - c0]


@nb.njit(cache=True, nogil=True)
def permute_rows(x: np.ndarray, source: np.ndarray) -> None:
    """``x[i] = x[source[i]]`` for every row ``i`` of ``x : (n, k)`` at once, in place
    (``source``: a permutation of ``range(n)``), one cycle of the permutation at a time:
    every row is moved once, through one row of scratch."""
    n = x.shape[0]
    done = np.zeros(n, dtype=np.bool_)
    held = np.empty(x.shape[1], dtype=x.dtype)
    for start in range(n):
        if done[start]:
            continue
        held[:] = x[start]
        i = start
        while True:
            done[i] = True
            j = source[i]
            if j == start:
                x[i] = held
                break
            x[i] = x[j]
            i = j
