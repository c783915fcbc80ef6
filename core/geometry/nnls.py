"""Non-negative and bounded least squares for many small dense problems.

``nnls(A, b)`` solves ``min |A x - b|^2 s.t. x >= 0`` (Lawson & Hanson 1974);
``bounded_lsq`` adds two-sided bounds ``lower <= x <= upper`` (Stark & Parker 1995's
BVLS problem). Both work on the Gram matrix ``A^T A`` so one factorisation-free
setup serves thousands of right-hand sides: the ``*_gram`` variants take
``AtA : (n, n)`` and ``Atb : (k, n)`` directly (e.g. projecting every frame of an
animation onto a blendshape basis); ``bounded_lsq_frames`` solves a sequence of frames,
each warm-started from the previous one, where some row blocks of ``A`` (markers) may be
missing at some frames. The solver is a primal active-set method in
numba (``_nnls_kernels.active_set_qp``); it is exact (finite termination) up to
rounding, with a tiny relative ridge only when a free block is singular.

Working on ``A^T A`` squares the condition number; for the sizes this is meant for
(n up to a few hundred columns, well-posed rigs) the objective agrees with
``scipy.optimize.nnls`` to ~1e-10 relative.
"""

from __future__ import annotations

import numpy as np
import numpy.typing as npt

from ..config import PIVOT_RTOL
from ..errors import InputError, NonFiniteError, NumericalError, ShapeError

__all__ = [
    "nnls",
    "nnls_gram",
    "bounded_lsq",
    "bounded_lsq_gram",
    "bounded_lsq_frames",
    "balanced_rho",
    "DEFAULT_TOL",
]

#: Relative optimality tolerance (times the largest |AtA_ii| or |Atb_i|).
DEFAULT_TOL = 1e-12


def nnls(A: npt.ArrayLike, b: npt.ArrayLike, *, tol: float = DEFAULT_TOL) -> np.ndarray:
    """``argmin_x |A x - b|^2`` subject to ``x >= 0``.

    Parameters
    ----------
    A : (m, n) float
    b : (m,) or (m, k) float
        One right-hand side, or k of them as columns.

    Returns
    -------
    x : (n,) or (n, k) float64
    """
    return bounded_lsq(A, b, 0.0, np.inf, tol=tol)


def nnls_gram(
    AtA: npt.ArrayLike,
    Atb: npt.ArrayLike,
    *,
    x0: npt.ArrayLike | None = None,
    tol: float = DEFAULT_TOL,
) -> np.ndarray:
    """NNLS from the normal equations: ``argmin 1/2 x^T AtA x - Atb.x``, ``x >= 0``.

    Parameters
    ----------
    AtA : (n, n) float, symmetric positive semi-definite
    Atb : (n,) or (k, n) float
        One problem, or k problems as rows (note: rows, unlike :func:`nnls`).
    x0 : like ``Atb``, optional
        Warm start (clipped to the bounds); good guesses cut iterations.

    Returns
    -------
    x : (n,) or (k, n) float64
    """
    return bounded_lsq_gram(AtA, Atb, 0.0, np.inf, x0=x0, tol=tol)


def bounded_lsq(
    A: npt.ArrayLike,
    b: npt.ArrayLike,
    lower: float | npt.ArrayLike,
    upper: float | npt.ArrayLike,
    *,
    tol: float = DEFAULT_TOL,
) -> np.ndarray:
    """``argmin_x |A x - b|^2`` subject to ``lower <= x <= upper``.

    ``A : (m, n)``, ``b : (m,)`` or ``(m, k)``; ``lower``, ``upper``: scalars or ``(n,)``
    (``-inf`` / ``inf`` for an open side). Returns ``(n,)`` or ``(n, k)`` float64.
    """
    a = _matrix(A, "A")
    rhs = _finite(b, "b")
    if rhs.ndim not in (1, 2) or rhs.shape[0] != a.shape[0]:
        raise ShapeError(
            f"nnls: b must be (m,) or (m, k) with m = {a.shape[0]} rows of A, got {rhs.shape}"
        )
    x = bounded_lsq_gram(a.T @ a, (a.T @ rhs).T, lower, upper, tol=tol)
    return x.T


def bounded_lsq_gram(
    AtA: npt.ArrayLike,
    Atb: npt.ArrayLike,
    lower: float | npt.ArrayLike,
    upper: float | npt.ArrayLike,
    *,
    x0: npt.ArrayLike | None = None,
    tol: float = DEFAULT_TOL,
) -> np.ndarray:
    """Bounded least squares from the normal equations (see :func:`nnls_gram`)."""
    from ._nnls_kernels import active_set_qp_many

    gram = _gram(AtA)
    n = gram.shape[1]
    rhs = _finite(Atb, "Atb")
    single = rhs.ndim == 1
    rhs2 = np.ascontiguousarray(rhs.reshape(1, -1) if single else rhs)
    if rhs2.ndim != 2 or rhs2.shape[1] != n:
        raise ShapeError(f"nnls_gram: Atb must be (n,) or (k, n) with n = {n}, got {rhs.shape}")
    lo, hi = _bounds(lower, upper, n)
    if x0 is None:
        start = np.zeros_like(rhs2)
    else:
        start = _finite(x0, "x0").reshape(rhs2.shape).copy()
    start = np.ascontiguousarray(np.clip(start, lo, hi))  # feasible (finite) start
    iters = np.zeros(rhs2.shape[0], dtype=np.int64)
    no_groups = np.full(n, -1, dtype=np.int64)
    active_set_qp_many(
        gram, rhs2, lo, hi, no_groups, np.zeros(0), start, _max_iter(n), float(tol), iters
    )
    if np.any(iters < 0):
        bad = int(np.flatnonzero(iters < 0)[0])
        raise NumericalError(
            f"nnls: the active-set method did not converge on problem {bad} (of {rhs2.shape[0]}); "
            "the Gram matrix is probably near singular: drop duplicate columns or scale them"
        )
    return start[0] if single else start


def bounded_lsq_frames(
    AtA: npt.ArrayLike,
    Atb: npt.ArrayLike,
    lower: float | npt.ArrayLike,
    upper: float | npt.ArrayLike,
    *,
    dropped: npt.ArrayLike | None = None,
    block_grams: npt.ArrayLike | None = None,
    ridge: float = 0.0,
    x0: npt.ArrayLike | None = None,
    tol: float = DEFAULT_TOL,
) -> np.ndarray:
    """Bounded least squares for each frame of a sequence, warm-started from the frame before.

    Frame t solves ``argmin 1/2 x^T AtA_t x - Atb[t].x`` subject to ``lower <= x <= upper``,
    where ``AtA_t`` is ``AtA`` minus the Grams of the row blocks missing at frame t (e.g. the
    3 rows of a marker that is not seen). Consecutive frames of an animation have close
    solutions, so each starts from the previous one's (few active-set iterations).

    Parameters
    ----------
    AtA : (n, n) float, symmetric positive semi-definite
        Gram matrix of all row blocks (plus any regularisation common to all frames).
    Atb : (F, n) float
        Right-hand sides, with the rows of missing blocks already left out.
    lower, upper : scalars or (n,)
    dropped : (F, B) bool, optional
        Row blocks missing at each frame; requires ``block_grams``.
    block_grams : (B, n, n) float, optional
        ``A_b^T A_b`` of each row block.
    ridge : float >= 0
        Added to the diagonal of a frame's ``AtA_t`` that is numerically singular once its
        missing blocks are removed (Cholesky pivot below ``config.PIVOT_RTOL`` times its largest
        diagonal entry): variables that no remaining row sees are then pulled to zero.
    x0 : (n,) float, optional
        Start of frame 0 (clipped to the bounds); default zeros.

    Returns
    -------
    x : (F, n) float64
    """
    from ._nnls_kernels import active_set_qp_frames

    gram = _gram(AtA)
    n = gram.shape[1]
    rhs = np.ascontiguousarray(_finite(Atb, "Atb"))
    if rhs.ndim != 2 or rhs.shape[1] != n:
        raise ShapeError(f"bounded_lsq_frames: Atb must be (F, n) with n = {n}, got {rhs.shape}")
    n_frames = rhs.shape[0]
    lo, hi = _bounds(lower, upper, n)
    if dropped is None:
        drop, grams = np.zeros((n_frames, 0), dtype=np.bool_), np.zeros((0, n, n))
    else:
        drop = np.ascontiguousarray(dropped, dtype=np.bool_)
        if block_grams is None:
            raise InputError(
                "bounded_lsq_frames: dropped needs block_grams (the Gram of each row block)"
            )
        grams = np.ascontiguousarray(_finite(block_grams, "block_grams"))
        if drop.ndim != 2 or drop.shape[0] != n_frames or grams.shape != (drop.shape[1], n, n):
            raise ShapeError(
                f"bounded_lsq_frames: dropped must be (F, B) = ({n_frames}, B) and block_grams (B, {n}, {n}), "
                f"got {drop.shape} and {grams.shape}"
            )
    if not (np.isfinite(ridge) and ridge >= 0.0):
        raise InputError(f"bounded_lsq_frames: ridge must be finite and >= 0, got {ridge!r}")
    start = np.zeros(n) if x0 is None else _finite(x0, "x0").reshape(n)
    start = np.ascontiguousarray(np.clip(start, lo, hi))
    out = np.empty((n_frames, n))
    iters = np.zeros(n_frames, dtype=np.int64)
    active_set_qp_frames(
        gram,
        grams,
        drop,
        rhs,
        lo,
        hi,
        start,
        float(ridge),
        PIVOT_RTOL,
        out,
        _max_iter(n),
        float(tol),
        iters,
    )
    if np.any(iters < 0):
        bad = int(np.flatnonzero(iters < 0)[0])
        raise NumericalError(
            f"nnls: the active-set method did not converge at frame {bad} (of {n_frames}) within {_max_iter(n)} "
            "iterations; the Gram matrix is probably near singular: drop duplicate columns or scale them"
        )
    return out


def balanced_rho(rho: float, ratio: float) -> float:
    """The next ADMM step size by residual balancing (Boyd et al. 2011, sec. 3.4.1; OSQP's
    rule), one rule for every ADMM solver of a bounded problem: ``ratio`` is
    ``sqrt(primal / dual)`` of the caller's scaled residuals; outside ``(0.2, 5)`` the step
    size is multiplied by it (clipped to ``[1e-3, 1e3]``), inside it is kept."""
    if 0.2 < ratio < 5.0:
        return rho
    return float(rho * np.clip(ratio, 1e-3, 1e3))


def _max_iter(n: int) -> int:
    """Iteration cap of the active-set method for ``n`` variables (it rarely needs ``n``)."""
    return 10 * n + 50


def _gram(value: npt.ArrayLike) -> np.ndarray:
    gram = _matrix(value, "AtA")
    n = gram.shape[1]
    if gram.shape != (n, n):
        raise ShapeError(f"nnls_gram: AtA must be square (n, n), got {gram.shape}")
    if not np.allclose(gram, gram.T, rtol=1e-8, atol=1e-12 * max(1.0, float(np.abs(gram).max()))):
        raise InputError(
            "nnls_gram: AtA must be symmetric (it is A^T A); symmetrise it with (M + M.T) / 2"
        )
    return gram


def _matrix(value: npt.ArrayLike, name: str) -> np.ndarray:
    arr = _finite(value, name)
    if arr.ndim != 2 or arr.shape[0] == 0 or arr.shape[1] == 0:
        raise ShapeError(f"nnls: {name} must be a non-empty 2D array, got shape {arr.shape}")
    return np.ascontiguousarray(arr)


def _finite(value: npt.ArrayLike, name: str) -> np.ndarray:
    try:
        arr = np.asarray(value, dtype=np.float64)
    except (TypeError, ValueError) as exc:
        raise ShapeError(f"nnls: {name} is not a numeric array ({exc})") from None
    if not np.all(np.isfinite(arr)):
        raise NonFiniteError(
            f"nnls: {name} holds NaN or infinite values; remove or fill them first"
        )
    return arr


def _bounds(
    lower: float | npt.ArrayLike, upper: float | npt.ArrayLike, n: int
) -> tuple[np.ndarray, np.ndarray]:
    try:
        lo = np.array(np.broadcast_to(np.asarray(lower, dtype=np.float64), (n,)))
        hi = np.array(np.broadcast_to(np.asarray(upper, dtype=np.float64), (n,)))
    except ValueError:
        raise ShapeError(f"nnls: lower and upper must be scalars or ({n},) arrays") from None
    if np.isnan(lo).any() or np.isnan(hi).any():
        raise NonFiniteError("nnls: bounds must not be NaN (use -inf / inf for an open side)")
    if np.any(lo > hi):
        raise InputError("nnls: every lower bound must be <= its upper bound")
    return lo, hi
