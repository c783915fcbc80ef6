"""numba kernels of :mod:`faceretarget.geometry.banded_qp` for block-tridiagonal matrices
(compiled lazily, cached).

A symmetric block-tridiagonal ``H`` has diagonal blocks ``diagonal (n, K, K)`` and blocks
``upper (n - 1, K, K)`` above them (block ``(t, t + 1)`` is ``upper[t]``); like LAPACK's
band storage (``block_tridiagonal_band``), only the upper triangle of a diagonal block is
read, so both forms see the same matrix. Its Cholesky factor ``H + diag(shift) = L L^T``
is block lower-bidiagonal: diagonal blocks ``low[t]`` (lower triangular) and below them
``L[t + 1, t] = offt[t]^T`` with ``offt[t] = low[t]^-1 upper[t]``. The Cholesky
recurrences by blocks::

    low[t] low[t]^T = diagonal[t] + diag(shift_t) - offt[t - 1]^T offt[t - 1]
    low[t] offt[t]  = upper[t]

LAPACK's banded Cholesky of the same matrix (``block_tridiagonal_band``, band ``2K - 1``)
fills its whole band in, although the last rows of each block reach fewer columns; these
work on the blocks alone. The loops run over contiguous rows so LLVM vectorises them.
"""

from __future__ import annotations

import math

import numba as nb
import numpy as np

from ._nnls_kernels import FASTMATH


@nb.njit(cache=True, nogil=True, fastmath=FASTMATH)
def block_cholesky(
    diagonal: np.ndarray, upper: np.ndarray, shift: np.ndarray, low: np.ndarray, offt: np.ndarray
) -> bool:
    """Factor ``H + diag(shift)`` into ``low (n, K, K)`` and ``offt (n - 1, K, K)`` (see the
    module; the diagonal blocks' upper triangles); ``shift : (n K,)``. False if a pivot is
    not positive or NaN (not positive definite to rounding); the factors are then partial."""
    n, k = diagonal.shape[0], diagonal.shape[1]
    for t in range(n):
        lt = low[t]  # the lower triangle of the shifted block, factored in place
        for j in range(k):  # the upper triangle of the block, transposed
            for i in range(j, k):
                lt[i, j] = diagonal[t, j, i]
            lt[j, j] += shift[t * k + j]
        if t > 0:  # minus L[t, t-1] L[t, t-1]^T = offt^T offt, a row of offt at a time
            c = offt[t - 1]
            for q in range(k):
                for i in range(k):
                    cqi = c[q, i]
                    for j in range(i + 1):
                        lt[i, j] -= cqi * c[q, j]
        for j in range(k):
            acc = lt[j, j]
            for q in range(j):
                acc -= lt[j, q] * lt[j, q]
            if not acc > 0.0:
                return False
            pivot = math.sqrt(acc)
            lt[j, j] = pivot
            for i in range(j + 1, k):
                acc = lt[i, j]
                for q in range(j):
                    acc -= lt[i, q] * lt[j, q]
                lt[i, j] = acc / pivot
        for i in range(k):
            for j in range(i + 1, k):
                lt[i, j] = 0.0
        if t < n - 1:  # offt[t] = low[t]^-1 upper[t]: forward substitution on whole rows
            u = upper[t]
            o = offt[t]
            for i in range(k):
                for j in range(k):
                    o[i, j] = u[i, j]
                for q in range(i):
                    liq = lt[i, q]
                    for j in range(k):
                        o[i, j] -= liq * o[q, j]
                inv = 1.0 / lt[i, i]
                for j in range(k):
                    o[i, j] *= inv
    return True


@nb.njit(cache=True, nogil=True, fastmath=FASTMATH)
def block_solve(low: np.ndarray, offt: np.ndarray, rhs: np.ndarray, out: np.ndarray) -> None:
    """``out = (L L^T)^-1 rhs`` for :func:`block_cholesky`'s factors; ``rhs, out : (n K,)``
    (``out`` may be ``rhs``)."""
    n, k = low.shape[0], low.shape[1]
    for i in range(n * k):
        out[i] = rhs[i]
    for t in range(n):  # L y = b: y_t = low_t^-1 (b_t - offt[t-1]^T y_{t-1})
        base = t * k
        if t > 0:
            c = offt[t - 1]
            prev = base - k
            for q in range(k):
                yq = out[prev + q]
                for i in range(k):
                    out[base + i] -= c[q, i] * yq
        lt = low[t]
        for i in range(k):
            acc = out[base + i]
            for q in range(i):
                acc -= lt[i, q] * out[base + q]
            out[base + i] = acc / lt[i, i]
    for t in range(n - 1, -1, -1):  # L^T x = y: x_t = low_t^-T (y_t - offt[t] x_{t+1})
        base = t * k
        if t < n - 1:
            c = offt[t]
            nxt = base + k
            for i in range(k):
                acc = 0.0
                for j in range(k):
                    acc += c[i, j] * out[nxt + j]
                out[base + i] -= acc
        lt = low[t]
        for i in range(k - 1, -1, -1):
            xi = out[base + i] / lt[i, i]
            out[base + i] = xi
            for q in range(i):
                out[base + q] -= lt[i, q] * xi


@nb.njit(cache=True, nogil=True, fastmath=FASTMATH)
def block_matvec(diagonal: np.ndarray, upper: np.ndarray, x: np.ndarray, out: np.ndarray) -> None:
    """``out = H x`` for the block-tridiagonal ``H`` (``x, out : (n K,)``, not aliased; the
    diagonal blocks' upper triangles)."""
    n, k = diagonal.shape[0], diagonal.shape[1]
    for t in range(n):
        base = t * k
        d = diagonal[t]
        for i in range(k):  # the upper triangle of the block and its transpose
            acc = 0.0
            for j in range(i):
                acc += d[j, i] * x[base + j]
            for j in range(i, k):
                acc += d[i, j] * x[base + j]
            if t < n - 1:
                u = upper[t]
                for j in range(k):
                    acc += u[i, j] * x[base + k + j]
            out[base + i] = acc
        if t > 0:  # upper[t - 1]^T x_{t-1}, a row of upper[t - 1] at a time
            u = upper[t - 1]
            prev = base - k
            for q in range(k):
                xq = x[prev + q]
                for i in range(k):
                    out[base + i] += u[q, i] * xq
