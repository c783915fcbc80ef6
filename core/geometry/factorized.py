"""Sparse symmetric positive-definite factorizations reused for many right-hand sides.

:class:`SPDFactor` factorizes once as ``L D L^T`` (QDLDL, approximate minimum-degree
ordering; no pivoting is needed for a positive-definite matrix, and only one triangle is
computed: about half the work of an LU) and solves blocks of right-hand sides with numba
triangular solves that read each factor entry once per block (``L`` and ``U = D L^T``,
stored apart so that both sweeps read columns). Never use
``scipy.sparse.linalg.spsolve`` on big systems: it refactorizes every call and can exhaust
memory without raising.

A factor pickles as its matrix and is refactorized on first use after unpickling. Only
the factors' arrays are kept (not the factorization's solver object), in the
strict-triangle CSC form the solves read.
"""

from __future__ import annotations

from collections.abc import Iterable
from typing import Any

import numpy as np
import numpy.typing as npt
import scipy.sparse as sp

from .._threads import in_blocks, in_threads, worker_count
from ..errors import ConfigError, NumericalError, ShapeError

__all__ = ["SPDFactor", "factorize"]

#: Right-hand-side columns per thread of a solve, at least (fewer columns: fewer threads).
_MIN_BLOCK_COLUMNS = 4
#: Relative residual above which a factorization is reported as numerically singular.
_RESIDUAL_TOL = 1e-6


class SPDFactor:
    """Factorization of a sparse symmetric positive-definite matrix.

    Parameters
    ----------
    matrix : (n, n) scipy sparse, symmetric positive definite (else NumericalError on
        first use)
    what : str
        Name used in error messages ("the Poisson system of the target mesh").
    frames_dtype : float64 (default) or float32
        Precision of :meth:`solve_frames` (:meth:`solve` is always float64). float32 halves
        the factor's memory traffic (~1.3x faster at 80K unknowns) at a relative error of
        about ``cond(A) * 6e-8``: only for well-conditioned systems, such as a screened
        uniform Laplacian (condition number ~20). float64 is used anyway when a factor value
        does not fit float32.
    """

    def __init__(
        self,
        matrix: sp.spmatrix | npt.ArrayLike,
        *,
        what: str = "matrix",
        frames_dtype: npt.DTypeLike = np.float64,
    ) -> None:
        # a canonical copy (sorted, duplicates summed); the caller's matrix stays as given
        m = sp.csc_matrix(matrix, dtype=np.float64, copy=True)
        if m.shape[0] != m.shape[1]:
            raise ShapeError(f"{what}: expected a square matrix, got {m.shape}")
        m.sum_duplicates()
        m.sort_indices()
        self.matrix = m
        self.what = what
        self.frames_dtype = np.dtype(frames_dtype)
        if self.frames_dtype not in (np.float32, np.float64):
            raise ConfigError(
                f"{what}: frames_dtype must be float32 or float64, got {frames_dtype!r}"
            )
        self._ready = False

    @property
    def n(self) -> int:
        return int(self.matrix.shape[0])

    def _factor(self) -> None:
        """Factorize (once): ``A[p][:, p] = (I + L) diag(d) (I + L)^T`` by QDLDL with an AMD
        ordering. Only the factors' arrays are kept, in the unit-lower / upper strict-triangle
        CSC form the solves read (``U = diag(d) L^T``)."""
        if self._ready:
            return
        m = self.matrix
        if not np.isfinite(m.data).all():
            raise NumericalError(
                f"{self.what}: the matrix holds NaN or infinite entries; check the input geometry"
            )
        diagonal = m.diagonal()
        if not np.all(diagonal > 0):
            i = int(np.argmin(diagonal > 0))
            raise NumericalError(
                f"{self.what}: not positive definite (diagonal entry {i} is {diagonal[i]:.3g}); "
                "the system is singular or was assembled wrong"
            )
        try:
            low, d, order = _ldl(sp.triu(m, format="csc"))
        except RuntimeError as exc:
            raise NumericalError(
                f"{self.what}: factorization failed ({exc}); the system is singular (a mesh part without anchor?)"
            ) from None
        if not (np.all(np.isfinite(d)) and np.all(d > 0)):
            raise NumericalError(
                f"{self.what}: not positive definite (pivot {float(np.min(d)):.3g}); the system is "
                "indefinite or singular (a mesh part without anchor?)"
            )
        index = np.int32 if self.n < 2**31 else np.int64
        rows = low.tocsr()  # row j of L = column j of L^T
        self._l = (
            low.indptr.astype(np.int64),
            low.indices.astype(index, copy=False),
            low.data.astype(np.float64, copy=False),
        )
        self._u = (
            rows.indptr.astype(np.int64),
            rows.indices.astype(index, copy=False),
            rows.data * d[rows.indices],  # U[i, j] = d_i L[j, i]
        )
        self._u_diag = np.asarray(d, dtype=np.float64)
        # the values solve_frames reads, in its precision (the same arrays for float64); a
        # pivot that float32 cannot hold (overflow, underflow to 0) keeps float64
        values = tuple(
            a.astype(self.frames_dtype, copy=False) for a in (self._l[2], self._u[2], self._u_diag)
        )
        usable = all(np.isfinite(a).all() for a in values) and bool(np.all(values[2] != 0))
        self._frame_values = values if usable else (self._l[2], self._u[2], self._u_diag)
        self._order = np.asarray(order, dtype=np.int64)  # pivot i is original index order[i]
        self._ready = True
        probe = np.cos(np.arange(self.n, dtype=np.float64))
        res = m @ self.solve(probe) - probe
        if not np.isfinite(res).all() or np.linalg.norm(res) > _RESIDUAL_TOL * np.linalg.norm(
            probe
        ):
            self._ready = False
            raise NumericalError(
                f"{self.what}: the factorization is numerically singular (residual {np.linalg.norm(res):.2e})"
            )

    def solve(self, rhs: np.ndarray) -> np.ndarray:
        """Solve ``A x = rhs`` for ``rhs : (n,)`` or ``(n, k)`` (float64 result)."""
        self._factor()
        b = np.asarray(rhs, dtype=np.float64)
        if b.shape[0] != self.n or b.ndim not in (1, 2):
            raise ShapeError(
                f"{self.what}: right-hand side must be ({self.n},) or ({self.n}, k), got {b.shape}"
            )
        cols = b.reshape(self.n, -1)
        x = self._solve_at(cols, self._order, np.empty(cols.shape))
        return x[:, 0] if b.ndim == 1 else x

    def solve_rows(self, rhs: np.ndarray, rows: np.ndarray, out: np.ndarray) -> np.ndarray:
        """Solve ``A x = rhs[rows]`` and write ``x`` into ``out[rows]`` (the other rows of
        ``out`` are left as they are); returns ``out``. ``rhs``, ``out : (m, k)``, ``rows :
        (n,)`` distinct row indices: what ``out[rows] = solve(rhs[rows])`` does, with one
        gather and one scatter instead of three copies of the right-hand sides.

        ``out`` may be ``rhs`` itself (C-contiguous float64): the rows are then put in pivot
        order, solved and put back in place, and no copy of the right-hand sides is made
        (a fresh ``(m, k)`` array costs page faults, ~0.15 s at 80K x 84 here)."""
        self._factor()
        idx = np.asarray(rows)
        if idx.dtype.kind not in "iu" or idx.shape != (self.n,):
            raise ShapeError(
                f"{self.what}: solve_rows needs ({self.n},) integer row indices, got {idx.dtype} {idx.shape}"
            )
        b = np.asarray(rhs)
        if b.ndim != 2 or out.ndim != 2 or out.shape != b.shape or out.dtype != np.float64:
            raise ShapeError(
                f"{self.what}: solve_rows needs a float64 out shaped like the 2-D rhs, "
                f"got rhs {b.shape}, out {out.dtype} {out.shape}"
            )
        m = b.shape[0]
        idx = idx.astype(np.int64, copy=False)
        if idx.size and (idx.min() < -m or idx.max() >= m):
            raise ShapeError(f"{self.what}: solve_rows' row indices must be in [-{m}, {m})")
        idx = idx % m if idx.size else idx  # as numpy reads negative indices
        if np.unique(idx).size != idx.size:
            raise ShapeError(f"{self.what}: solve_rows needs distinct rows, some are repeated")
        pivoted = idx[self._order]  # pivot i is row rows[order[i]]
        if out is b:
            return self._solve_in_place(out, pivoted)
        return self._solve_at(b, pivoted, out)

    def _solve_in_place(self, x: np.ndarray, pivoted: np.ndarray) -> np.ndarray:
        """``x[pivoted] = solve(x[pivoted])`` without copies: the rows of ``x (m, k)`` are
        permuted so that pivot ``i`` is row ``i`` (the rows not solved for after them), solved
        as the first ``n`` rows, and permuted back. Returns ``x``."""
        from ._factor_kernels import permute_rows

        if not x.flags.c_contiguous:
            raise ShapeError(f"{self.what}: solve_rows in place needs a C-contiguous out")
        rest = np.ones(x.shape[0], dtype=bool)
        rest[pivoted] = False
        source = np.concatenate([pivoted, np.flatnonzero(rest)])
        permute_rows(x, source)
        self._solve_pivoted(x[: self.n])
        back = np.empty_like(source)
        back[source] = np.arange(source.size)
        permute_rows(x, back)
        return x

    def _solve_at(self, rhs: np.ndarray, pivoted: np.ndarray, out: np.ndarray) -> np.ndarray:
        """``out[pivoted] = x`` for ``A x = rhs[pivoted]`` in pivot order (``pivoted[i]``: the
        row of ``rhs`` and ``out`` of pivot i): one gather, the triangular solves in place on
        it, one scatter; returns ``out``."""
        y = np.ascontiguousarray(rhs[pivoted], dtype=np.float64)
        self._solve_pivoted(y)
        out[pivoted] = y
        return out

    def _solve_pivoted(self, y: np.ndarray) -> None:
        """The triangular solves, in place, on ``y : (n, k)`` (C-contiguous float64) whose row
        ``i`` is pivot ``i``; blocks of columns side by side on threads."""
        from ._factor_kernels import lu_solve

        k = y.shape[1]
        l, u = self._l, self._u
        in_blocks(
            lu_solve,
            k,
            lambda c0, c1: (l[0], l[1], l[2], u[0], u[1], u[2], self._u_diag, y, c0, c1),
            parts=max(1, min(worker_count(k), k // _MIN_BLOCK_COLUMNS)),
        )

    def solve_frames(
        self, rhs: np.ndarray, add: np.ndarray | None = None, *, out: np.ndarray | None = None
    ) -> np.ndarray:
        """Solve for per-frame right-hand sides ``rhs : (C, n, 3)``; returns ``add + x``
        (``(C, n, 3)``, ``add`` default zero) without transposed copies, written into ``out``
        when given (C-contiguous float64; it may be ``rhs`` or ``add`` themselves: each
        column is read before it is written)."""
        r = np.ascontiguousarray(rhs, dtype=np.float64)
        if r.ndim != 3 or r.shape[1] != self.n:
            raise ShapeError(
                f"{self.what}: right-hand sides must be (C, {self.n}, 3), got {r.shape}"
            )
        a = np.zeros_like(r) if add is None else np.ascontiguousarray(add, dtype=np.float64)
        if out is None:
            out = np.empty_like(r)
        elif out.shape != r.shape or out.dtype != np.float64 or not out.flags.c_contiguous:
            raise ShapeError(
                f"{self.what}: solve_frames' out must be C-contiguous float64 {r.shape}, "
                f"got {out.dtype} {out.shape}"
            )
        self._factor()
        from ._factor_kernels import lu_solve_frames

        l, u = self._l, self._u
        l_val, u_val, u_diag = self._frame_values
        order = self._order
        in_blocks(
            lu_solve_frames,
            3 * r.shape[0],
            lambda c0, c1: (order, l[0], l[1], l_val, u[0], u[1], u_val, u_diag, r, a, out, c0, c1),
        )
        return out

    def __getstate__(self) -> dict[str, Any]:
        return {"matrix": self.matrix, "what": self.what, "frames_dtype": self.frames_dtype.str}

    def __setstate__(self, state: dict[str, Any]) -> None:
        self.__init__(  # type: ignore[misc]
            state["matrix"], what=state["what"], frames_dtype=state.get("frames_dtype", "<f8")
        )


_kernels_loaded = False


def _load_kernels() -> None:
    """Compile or load the factorization's numba kernels on the calling thread, once, by
    factorizing a 2 x 2 matrix: numba loading kernels on one worker thread while another
    ran or loaded others crashed the process now and then (SIGSEGV in LLVM)."""
    global _kernels_loaded
    if not _kernels_loaded:
        SPDFactor(sp.identity(2, format="csc") * 2.0, what="warm-up")._factor()
        _kernels_loaded = True


def _ldl(upper: sp.csc_matrix) -> tuple[sp.csc_matrix, np.ndarray, np.ndarray]:
    """QDLDL of the matrix whose upper triangle (diagonal included) is ``upper``: strictly
    lower ``L`` (CSC), pivots ``d (n,)`` and the AMD ordering ``p (n,)`` with
    ``A[p][:, p] = (I + L) diag(d) (I + L)^T``. The solver object is not kept."""
    import qdldl

    low, d, order = qdldl.Solver(upper, upper=True).factors()
    return low, np.asarray(d), np.asarray(order)


def factorize(factors: Iterable[SPDFactor]) -> None:
    """Factorize several matrices now, side by side on ``_threads.worker_count`` threads
    (QDLDL's ordering and factorization, the bulk of the time, release the GIL; building
    the factors' arrays mostly does not). The first error is raised."""
    todo = list({id(f): f for f in factors if not f._ready}.values())  # each once
    if len(todo) > 1:
        _load_kernels()
    in_threads([f._factor for f in todo], worker_count(len(todo)))
