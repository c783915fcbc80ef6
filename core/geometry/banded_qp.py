"""Non-negative convex QP with a banded Hessian, by a primal-dual interior point method.

``nonneg_qp_banded(H, r)`` solves ``min 1/2 x^T H x - r^T x  s.t.  x >= 0`` for a sparse
symmetric positive (semi)definite ``H`` of small bandwidth ``u`` (e.g. block-tridiagonal
over time with dense ``K x K`` blocks: ``u = 2K - 1``). Mehrotra's predictor-corrector
(Nocedal & Wright 2006, alg. 16.4, here with bounds only): each step factors
``H + X^-1 Z`` once with LAPACK's banded Cholesky (``O(n u^2)``) and solves it twice. It
needs 15-40 steps whatever the conditioning; active-set methods may cycle when ``H`` is
not an M-matrix and first-order methods (ADMM) stall when it is ill-conditioned.

The answer is then *polished*: the variables the interior point leaves clearly positive
are taken as the free set and solved exactly; if that satisfies the optimality conditions
(free variables >= 0, gradient >= 0 on the others, each to rounding) it is returned, so
the result is the exact optimum up to rounding, not an interior iterate.
``nonneg_qp_band`` takes the upper band itself (e.g. from ``block_tridiagonal_band``), so
a caller that knows the structure never builds a sparse matrix;
``nonneg_qp_block_tridiagonal`` takes the blocks of a block-tridiagonal ``H`` and factors
each step by blocks (numba, :mod:`._banded_qp_kernels`), without the band's fill-in.
"""

from __future__ import annotations

from collections.abc import Callable
from typing import Any, Protocol

import numpy as np
import scipy.linalg as sla
import scipy.sparse as sp
from scipy.linalg.blas import dsbmv as sbmv

from .. import config
from .._threads import blas_single_threaded
from ..errors import ShapeError

__all__ = [
    "block_tridiagonal_band",
    "nonneg_qp_band",
    "nonneg_qp_banded",
    "nonneg_qp_block_tridiagonal",
    "sub_band",
    "to_upper_band",
]

#: Interior point steps at most; the relative tolerance on the residuals and on the duality
#: measure ``x . z / n`` at which it stops (times the scale of ``H`` and ``r``).
MAX_STEPS = 80
TOL = 1e-13
#: Fraction of the step to the boundary taken (keeps the iterates interior).
STEP_FRACTION = 0.995
#: Largest relative violation of the optimality conditions (``_free_set_solve``) an exact
#: free-set solve may show to be returned as the optimum, and the least scale of a row's
#: gradient there (a fraction of ``max |r|``: rows below the interior point's accuracy).
POLISH_TOL = 1e-9
ROW_FLOOR = 1e-8


def to_upper_band(matrix: sp.spmatrix) -> tuple[np.ndarray, int]:
    """``(ab, u)``: the upper triangle of symmetric ``matrix (n, n)`` in LAPACK's banded
    storage ``ab[u + i - j, j] = M[i, j]`` for ``i <= j`` (``ab : (u + 1, n)``)."""
    csc = sp.csc_matrix(matrix)
    if not csc.has_canonical_format:  # duplicates summed on a copy: the caller's arrays stay
        csc = csc.copy()
        csc.sum_duplicates()
    coo = csc.tocoo()  # each (row, col) once
    upper = coo.row <= coo.col
    row, col = coo.row[upper], coo.col[upper]
    n = matrix.shape[0]
    u = int((col - row).max()) if row.size else 0
    ab = np.zeros((u + 1, n))
    ab[u + row - col, col] = coo.data[upper]
    return ab, u


def sub_band(ab: np.ndarray, keep: np.ndarray) -> np.ndarray:
    """The upper band of ``M[keep][:, keep]`` (``keep`` increasing) from the upper band
    ``ab : (u + 1, n)`` of ``M``: entry ``(i', j')`` is ``M[keep[i'], keep[j']]``, zero
    where the two are more than ``u`` apart."""
    u = ab.shape[0] - 1
    out = np.zeros((u + 1, keep.size), order="F")
    for d in range(min(u, keep.size - 1) + 1):  # d: the offset in the kept indices
        j = np.arange(d, keep.size)
        gap = keep[j] - keep[j - d]
        near = gap <= u
        out[u - d, j[near]] = ab[u - gap[near], keep[j[near]]]
    return out


def _factor(ab: np.ndarray, d: np.ndarray | None = None) -> np.ndarray | None:
    """Banded Cholesky factor of ``H + diag(d)`` (``ab`` the upper band of ``H``; ``d``
    default 0); None if it is not positive definite to rounding."""
    m = ab.copy(order="F")
    if d is not None:
        m[-1] += d
    try:
        return sla.cholesky_banded(m, lower=False, check_finite=False, overwrite_ab=True)
    except np.linalg.LinAlgError:
        return None


def block_tridiagonal_band(diagonal: np.ndarray, upper: np.ndarray) -> np.ndarray:
    """The upper band ``(2K, n K)`` of the symmetric block-tridiagonal matrix with diagonal
    blocks ``diagonal (n, K, K)`` (symmetric) and blocks ``upper (n - 1, K, K)`` above them
    (block ``(t, t + 1)`` is ``upper[t]``), in :func:`to_upper_band`'s storage with ``u = 2K - 1``."""
    diagonal, upper = _checked_blocks(diagonal, upper, "block_tridiagonal_band")
    n, k = diagonal.shape[:2]
    u = 2 * k - 1
    ab = np.zeros((u + 1, n * k))
    rows, cols = np.triu_indices(k)  # entry (t K + i, t K + j), i <= j: ab[u + i - j, t K + j]
    view = ab.reshape(u + 1, n, k)
    view[u + rows - cols, :, cols] = diagonal[:, rows, cols].T
    if n > 1:  # entry ((t - 1) K + i, t K + j): ab[u - K + i - j, t K + j]
        i, j = np.meshgrid(np.arange(k), np.arange(k), indexing="ij")
        view[u - k + i - j, 1:, j] = upper.transpose(1, 2, 0)
    return ab


def _checked_blocks(
    diagonal: np.ndarray, upper: np.ndarray, who: str
) -> tuple[np.ndarray, np.ndarray]:
    """``diagonal (n, K, K)`` and ``upper (n - 1, K, K)`` as C-ordered float64 arrays, or a
    ShapeError naming ``who``."""
    diagonal = np.ascontiguousarray(diagonal, dtype=np.float64)
    upper = np.ascontiguousarray(upper, dtype=np.float64)
    n, k = (diagonal.shape + (0, 0))[:2]
    if diagonal.shape != (n, k, k) or upper.shape != (max(n - 1, 0), k, k):
        raise ShapeError(
            f"{who}: blocks (n, K, K) and (n - 1, K, K), got {diagonal.shape} and {upper.shape}"
        )
    return diagonal, upper


def nonneg_qp_banded(
    hessian: sp.spmatrix, rhs: np.ndarray, start: np.ndarray | None = None
) -> tuple[np.ndarray, dict]:
    """``argmin 1/2 x^T H x - rhs . x`` subject to ``x >= 0``.

    Parameters
    ----------
    hessian : (n, n) sparse, symmetric positive semidefinite, banded
    rhs : (n,) float
    start : (n,) float, optional
        A guess, shifted into the interior (default: the unconstrained minimiser); interior
        point methods gain little from a good one.

    Returns
    -------
    x : (n,) float64, ``x >= 0``
    info : dict
        ``steps`` (interior point steps), ``exact`` (True if the polished free-set solve
        passed the optimality conditions; else ``x`` is the last iterate, clipped at 0),
        ``kkt`` (the largest violation of the optimality conditions, relative: row by row
        if exact, :func:`_free_set_solve`; else to ``max |r|``).
    """
    hessian = sp.csc_matrix(hessian, dtype=np.float64)
    return nonneg_qp_band(to_upper_band(hessian)[0], rhs, start)


@blas_single_threaded  # a band of 2K: LAPACK's threads cost more than they save (faceretarget._threads)
def nonneg_qp_band(
    ab: np.ndarray, rhs: np.ndarray, start: np.ndarray | None = None
) -> tuple[np.ndarray, dict]:
    """:func:`nonneg_qp_banded` for ``H`` given as its upper band ``ab : (u + 1, n)``
    (:func:`to_upper_band`'s storage)."""
    ab = np.asfortranarray(ab, dtype=np.float64)  # LAPACK's and BLAS' order: no copy per call
    r = np.asarray(rhs, dtype=np.float64).ravel()
    n = r.size
    if ab.ndim != 2 or ab.shape[1] != n:
        raise ShapeError(f"nonneg_qp_band: the band must be (u + 1, {n}), got {ab.shape}")
    if start is not None and np.size(start) != n:
        raise ShapeError(f"nonneg_qp_band: start must have {n} entries, got {np.size(start)}")
    if n == 0:
        return np.zeros(0), {"steps": 0, "exact": True, "kkt": 0.0}
    return _interior_point(_Band(ab), r, start, lambda: ab)


@blas_single_threaded  # the polish's banded Cholesky, as above
def nonneg_qp_block_tridiagonal(
    diagonal: np.ndarray, upper: np.ndarray, rhs: np.ndarray, start: np.ndarray | None = None
) -> tuple[np.ndarray, dict]:
    """:func:`nonneg_qp_banded` for a block-tridiagonal ``H`` given by its blocks:
    ``diagonal (n, K, K)`` (symmetric) and ``upper (n - 1, K, K)`` (block ``(t, t + 1)``),
    as for :func:`block_tridiagonal_band`; ``rhs, start : (n K,)``. The same interior
    point and polish as :func:`nonneg_qp_band` (the same matrix: the upper triangles of
    the diagonal blocks; the same answer to rounding); from
    ``config.BLOCK_QP_MIN_VARIABLES`` variables each step's factorization is by blocks
    (:mod:`._banded_qp_kernels`) instead of LAPACK's banded Cholesky, which fills the
    whole band of ``2K - 1`` in."""
    diagonal, upper = _checked_blocks(diagonal, upper, "nonneg_qp_block_tridiagonal")
    n, k = diagonal.shape[:2]
    r = np.asarray(rhs, dtype=np.float64).ravel()
    for name, value in (("rhs", r), ("start", start)):
        if value is not None and np.size(value) != n * k:
            raise ShapeError(
                f"nonneg_qp_block_tridiagonal: {name} must have n K = {n * k} entries, got {np.size(value)}"
            )
    if r.size == 0:
        return np.zeros(0), {"steps": 0, "exact": True, "kkt": 0.0}

    def band() -> np.ndarray:
        return np.asfortranarray(block_tridiagonal_band(diagonal, upper))

    if r.size < config.BLOCK_QP_MIN_VARIABLES:  # as fast by the band, and nothing to compile
        ab = band()
        return _interior_point(_Band(ab), r, start, lambda: ab)
    return _interior_point(_Blocks(diagonal, upper), r, start, band)  # the band for the polish


class _Operator(Protocol):
    """What the interior point needs of ``H``: its diagonal, ``H x``, a factor of
    ``H + diag(d)`` (None if not positive definite) and solves with it. A new factor may
    reuse the memory of the last one (``_Blocks``): one factor is used at a time."""

    diagonal: np.ndarray

    def matvec(self, x: np.ndarray) -> np.ndarray: ...

    def factor(self, d: np.ndarray) -> Any: ...

    def solve(self, factor: Any, b: np.ndarray) -> np.ndarray: ...


class _Band:
    """``H`` as its upper band: LAPACK's banded Cholesky and BLAS' ``dsbmv``."""

    def __init__(self, ab: np.ndarray) -> None:
        self.ab = ab
        self.diagonal = ab[-1]

    def matvec(self, x: np.ndarray) -> np.ndarray:
        return _matvec(self.ab, x)

    def factor(self, d: np.ndarray) -> np.ndarray | None:
        return _factor(self.ab, d)

    def solve(self, factor: np.ndarray, b: np.ndarray) -> np.ndarray:
        return sla.cho_solve_banded((factor, False), b, check_finite=False)


class _Blocks:
    """``H`` as its blocks: the block Cholesky, solve and product of :mod:`._banded_qp_kernels`."""

    def __init__(self, diagonal: np.ndarray, upper: np.ndarray) -> None:
        from . import _banded_qp_kernels

        self.kernels = _banded_qp_kernels
        self.blocks = (diagonal, upper)
        self.diagonal = np.diagonal(diagonal, axis1=1, axis2=2).ravel()
        self.low = np.empty_like(diagonal)
        self.offt = np.empty_like(upper)

    def matvec(self, x: np.ndarray) -> np.ndarray:
        out = np.empty_like(x)
        self.kernels.block_matvec(*self.blocks, np.ascontiguousarray(x), out)
        return out

    def factor(self, d: np.ndarray) -> tuple[np.ndarray, np.ndarray] | None:
        ok = self.kernels.block_cholesky(
            *self.blocks, np.ascontiguousarray(d, dtype=np.float64), self.low, self.offt
        )
        return (self.low, self.offt) if ok else None  # one factor at a time: reused in place

    def solve(self, factor: tuple[np.ndarray, np.ndarray], b: np.ndarray) -> np.ndarray:
        out = np.empty_like(b)
        self.kernels.block_solve(*factor, np.ascontiguousarray(b, dtype=np.float64), out)
        return out


def _interior_point(
    ops: _Operator, r: np.ndarray, start: np.ndarray | None, band: Callable[[], np.ndarray]
) -> tuple[np.ndarray, dict]:
    """Mehrotra's predictor-corrector on ``ops`` (``H``'s product, factor of ``H + diag(d)``
    and solve), then the polish on the upper band ``band()`` of ``H``."""
    n = r.size
    h_scale = max(float(np.abs(ops.diagonal).max()), np.finfo(float).tiny)
    r_scale = max(float(np.abs(r).max()), np.finfo(float).tiny)
    x, z = _start(ops, r, start, h_scale, r_scale)
    steps = 0
    for steps in range(1, MAX_STEPS + 1):  # noqa: B007 (reported)
        grad = ops.matvec(x) - r
        dual = grad - z  # stationarity residual: H x - r - z = 0
        mu = float(x @ z) / n
        x_max = max(float(x.max()), r_scale / h_scale)  # not 0 when every bound binds
        # stop at the rounding floor of H x - r, and a duality measure TOL of the objective's scale
        if np.abs(dual).max() <= TOL * (r_scale + h_scale * x_max) and mu <= TOL * r_scale * x_max:
            break
        factor = ops.factor(z / x)
        if factor is None:
            break
        dx_a, dz_a = _newton(ops, factor, dual, x, z, -x * z)
        a_p, a_d = _to_boundary(x, dx_a), _to_boundary(z, dz_a)
        mu_aff = float((x + a_p * dx_a) @ (z + a_d * dz_a)) / n
        sigma = (mu_aff / mu) ** 3 if mu > 0 else 0.0
        dx, dz = _newton(ops, factor, dual, x, z, -x * z - dx_a * dz_a + sigma * mu)
        alpha = STEP_FRACTION * min(_to_boundary(x, dx), _to_boundary(z, dz))
        x = x + alpha * dx
        z = z + alpha * dz
    out, exact, kkt = _polish(band(), r, x, z, r_scale)
    return out, {"steps": steps, "exact": exact, "kkt": kkt}


def _matvec(ab: np.ndarray, x: np.ndarray) -> np.ndarray:
    """``H x`` for symmetric ``H`` stored as its upper band ``ab`` (BLAS ``dsbmv``)."""
    return sbmv(ab.shape[0] - 1, 1.0, ab, x)


def _newton(
    ops: _Operator, factor: Any, dual: np.ndarray, x: np.ndarray, z: np.ndarray, comp: np.ndarray
) -> tuple[np.ndarray, np.ndarray]:
    """Newton step towards ``H x - r - z = 0`` and ``x z + (z dx + x dz) = x z + comp``:
    ``(H + Z/X) dx = -dual + comp / x``, ``dz = (comp - z dx) / x``; ``factor`` is
    ``ops``' factor of ``H + Z/X``."""
    dx = ops.solve(factor, -dual + comp / x)
    return dx, (comp - z * dx) / x


def _start(
    ops: _Operator,
    r: np.ndarray,
    start: np.ndarray | None,
    h_scale: float,
    r_scale: float,
) -> tuple[np.ndarray, np.ndarray]:
    """Mehrotra's starting point (Nocedal & Wright 2006, sec. 14.2, for bounds): the
    unconstrained minimiser (of a slightly regularised problem), or ``start``, shifted into
    the interior, with multipliers from its gradient, both balanced so that ``x . z`` is
    not dominated by a few pairs."""
    if start is None:
        factor = ops.factor(np.full(r.size, 1e-8 * h_scale))
        x = np.full(r.size, r_scale / h_scale) if factor is None else ops.solve(factor, r)
    else:
        x = np.asarray(start, dtype=np.float64).ravel().copy()
    z = ops.matvec(x) - r
    x += max(-1.5 * float(x.min()), 0.0)
    z += max(-1.5 * float(z.min()), 0.0)
    x = np.maximum(x, 1e-8 * max(float(x.max()), r_scale / h_scale))
    z = np.maximum(z, 1e-8 * r_scale)
    pair = float(x @ z)
    return x + 0.5 * pair / float(z.sum()), z + 0.5 * pair / float(x.sum())


def _to_boundary(v: np.ndarray, dv: np.ndarray) -> float:
    """Largest ``a`` in (0, 1] with ``v + a dv >= 0``."""
    neg = dv < 0
    if not neg.any():
        return 1.0
    return float(min(1.0, np.min(-v[neg] / dv[neg])))


def _free_set_solve(
    ab: np.ndarray, r: np.ndarray, free: np.ndarray
) -> tuple[np.ndarray | None, float]:
    """``(x, violation)``: ``x`` solves ``H x = r`` on the ``free`` variables (bool) and is 0
    on the others (None if that block is singular); ``violation`` the larger of ``-x``
    relative to ``max |x|`` and of ``-(H x - r)`` on the other variables relative, row by
    row, to the terms it sums (``|H| |x| + |r|``, at least ``ROW_FLOOR`` of ``max |r|``): a
    scale of ``r`` for all rows let a 36,400-variable problem whose few constraint rows are
    1e7 times the others stop 1.2 above the optimum of an objective of 1; without the
    floor, a row whose terms are all below the interior point's accuracy (1e-15 against
    1e7) rejected an exact answer."""
    keep = np.flatnonzero(free)
    x = np.zeros(r.size)
    if keep.size:
        factor = _factor(sub_band(ab, keep))
        if factor is None:
            return None, np.inf
        x[keep] = sla.cho_solve_banded((factor, False), r[keep], check_finite=False)
    grad = _matvec(ab, x) - r
    grad[keep] = 0.0
    tiny = np.finfo(float).tiny
    floor = ROW_FLOOR * max(float(np.abs(r).max(initial=0.0)), tiny)
    magnitude = _matvec(np.abs(ab), np.abs(x)) + np.abs(r) + floor
    violation = max(
        float(-x.min(initial=0.0)) / max(float(np.abs(x).max(initial=0.0)), tiny),
        float(np.max(-grad / magnitude, initial=0.0)),
    )
    return x, violation


def _polish(
    ab: np.ndarray, r: np.ndarray, x: np.ndarray, z: np.ndarray, r_scale: float
) -> tuple[np.ndarray, bool, float]:
    """The exact solve on the free set ``x > z`` (banded Cholesky of its sub-band) if it
    meets the optimality conditions, else the iterate clipped at 0; and the violation
    (relative: :func:`_free_set_solve`; for the iterate, of ``H x - r`` to ``r``'s scale)."""
    exact, violation = _free_set_solve(ab, r, x > z)  # the larger of the pair is nonzero
    if exact is not None and violation <= POLISH_TOL:
        return np.maximum(exact, 0.0), True, violation
    grad = _matvec(ab, x) - r
    kkt = float(np.abs(np.where(x > z, grad, np.minimum(grad, 0.0))).max()) / r_scale
    return np.maximum(x, 0.0), False, kkt
