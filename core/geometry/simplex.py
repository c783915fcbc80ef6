"""The probability simplex: exact Euclidean projection and QPs over products of simplices.

- :func:`project_simplex`: ``argmin_x |x - v|`` over ``{x >= 0, sum x = r}``, batched
  over leading axes, by the sort-based method (O(n log n) a row, exact: no iteration).
- :func:`simplex_qp`: ``argmin 1/2 x^T G x - c^T x`` with ``x`` split into groups, each
  on its own simplex (barycentric coordinates of several simplicial bases at once),
  by the primal active-set method of :mod:`faceretarget.geometry._nnls_kernels`.

Both return points on the simplex to rounding: non-negative exactly, and each group
rescaled at the end so it sums to ``r`` within a few ulps.
"""

from __future__ import annotations

from collections.abc import Sequence

import numpy as np
import numpy.typing as npt

from ..errors import InputError, NonFiniteError, NumericalError, ShapeError

__all__ = ["project_simplex", "simplex_qp", "group_index"]


def project_simplex(values: npt.ArrayLike, radius: float = 1.0) -> np.ndarray:
    """Euclidean projection of each row of ``values : (..., n)`` onto the simplex.

    Parameters
    ----------
    values : (..., n) float
    radius : float > 0
        The simplex ``{x >= 0, sum x = radius}``.

    Returns
    -------
    (..., n) float64
    """
    from ._simplex_kernels import project_rows

    arr = np.asarray(values, dtype=np.float64)
    if arr.ndim == 0 or arr.shape[-1] == 0:
        raise ShapeError(
            f"project_simplex: values must be (..., n) with n >= 1, got shape {arr.shape}"
        )
    if not np.all(np.isfinite(arr)):
        raise NonFiniteError("project_simplex: values hold NaN or infinite entries")
    radius = float(radius)
    if not (np.isfinite(radius) and radius > 0):
        raise InputError(f"project_simplex: radius must be a positive number, got {radius}")
    rows = np.ascontiguousarray(arr.reshape(-1, arr.shape[-1]))
    out = np.empty_like(rows)
    project_rows(rows, radius, out)
    return out.reshape(arr.shape)


def group_index(sizes: Sequence[int] | np.ndarray) -> np.ndarray:
    """``(n,)`` group id of each variable for consecutive groups of the given ``sizes``."""
    sizes = np.asarray(sizes, dtype=np.int64)
    if sizes.ndim != 1 or sizes.size == 0 or np.any(sizes < 1):
        raise ShapeError(
            f"group sizes must be a non-empty list of positive counts, got {sizes.tolist()}"
        )
    return np.repeat(np.arange(sizes.size, dtype=np.int64), sizes)


def simplex_qp(
    G: npt.ArrayLike,
    c: npt.ArrayLike,
    groups: npt.ArrayLike | None = None,
    *,
    x0: npt.ArrayLike | None = None,
    tol: float = 1e-12,
) -> np.ndarray:
    """``argmin_x 1/2 x^T G x - c^T x``, every group of ``x`` on the unit simplex.

    Parameters
    ----------
    G : (n, n) float, symmetric positive semi-definite
    c : (n,) or (k, n) float
        One linear term, or k problems sharing ``G`` (rows).
    groups : (n,) int, optional
        Group id (0..g-1) of each variable; default: one simplex over all n.
    x0 : like ``c``, optional
        Warm start (projected onto the simplices first).

    Returns
    -------
    x : (n,) or (k, n) float64, each group >= 0 and summing to 1.
    """
    from ._nnls_kernels import active_set_qp_many

    gram = np.ascontiguousarray(np.asarray(G, dtype=np.float64))
    n = gram.shape[-1] if gram.ndim == 2 else 0
    if gram.ndim != 2 or gram.shape != (n, n) or n == 0:
        raise ShapeError(
            f"simplex_qp: G must be a non-empty square (n, n) matrix, got {gram.shape}"
        )
    lin = np.asarray(c, dtype=np.float64)
    single = lin.ndim == 1
    lin2 = np.ascontiguousarray(lin.reshape(1, -1) if single else lin)
    if lin2.ndim != 2 or lin2.shape[1] != n:
        raise ShapeError(f"simplex_qp: c must be (n,) or (k, n) with n = {n}, got {lin.shape}")
    if not (np.all(np.isfinite(gram)) and np.all(np.isfinite(lin2))):
        raise NonFiniteError("simplex_qp: G and c must be finite")
    grp = np.zeros(n, dtype=np.int64) if groups is None else np.asarray(groups)
    if grp.shape != (n,) or grp.dtype.kind not in "iu":
        raise ShapeError(f"simplex_qp: groups must be ({n},) integers")
    grp = grp.astype(np.int64)
    n_groups = int(grp.max()) + 1
    if grp.min() < 0 or np.any(np.bincount(grp, minlength=n_groups) == 0):
        raise InputError("simplex_qp: groups must number 0..g-1 with every group non-empty")
    start = np.empty_like(lin2)
    for g in range(n_groups):
        cols = grp == g
        guess = (
            np.full((lin2.shape[0], int(cols.sum())), 1.0)
            if x0 is None
            else np.asarray(x0, dtype=np.float64).reshape(lin2.shape)[:, cols]
        )
        start[:, cols] = project_simplex(guess)
    iters = np.zeros(lin2.shape[0], dtype=np.int64)
    lo, hi = np.zeros(n), np.full(n, np.inf)
    active_set_qp_many(
        gram, lin2, lo, hi, grp, np.ones(n_groups), start, 10 * n + 50, float(tol), iters
    )
    if np.any(iters < 0):
        raise NumericalError(
            "simplex_qp: the active-set method did not converge; G is probably near singular"
        )
    return start[0] if single else start
