"""Taubin lambda|mu smoothing (Taubin 1995), batched over frames.

Each iteration is a shrinking step ``x += lam (W x - x)`` followed by an inflating step
``x += mu (W x - x)`` with the umbrella operator ``W`` (neighbour average), so the
filter removes high frequencies without the shrinkage of plain Laplacian smoothing.
The filter is linear in the vertex positions, with fixed (topology-only) weights.

Sparse mat-vecs are memory-bound; smoothing many frames at once, as columns of one
``(V, 3F)`` block, reuses every matrix entry and neighbour row for all frames, and
float32 blocks halve the traffic (``dtype=np.float32``; about 8 ms a frame at 80K
vertices on 2 cores).
"""

from __future__ import annotations

import numpy as np
import numpy.typing as npt

from .. import config
from ..errors import NumericalError, ShapeError
from .laplacian import umbrella_operator

__all__ = [
    "TaubinSmoother",
    "SmoothedDisplacements",
    "taubin_smooth",
    "TAUBIN_LAMBDA",
    "TAUBIN_MU",
]

#: Taubin's classic pass-band parameters (k_PB = 1/lam + 1/mu ~ 0.1).
TAUBIN_LAMBDA = 0.5
TAUBIN_MU = -0.53


class TaubinSmoother:
    """Taubin smoothing on one topology, reusable for any number of meshes.

    Parameters
    ----------
    triangles : (T, 3) int
    n_vertices : int
    iterations : int
        Number of lambda|mu pairs (the paper uses about 40).
    lam, mu : float
        Shrink (> 0) and inflate (< -lam) factors.
    dtype : float32 or float64
        Arithmetic precision of the batched kernel.
    adjoint : bool
        Apply the transposed filter ``G^T`` (the same steps with ``W^T``) instead of ``G``.
        The filter is linear, so ``<b, G x> = <G^T b, x>``: projecting smoothed frames on
        fixed vectors ``b`` needs ``G^T b`` once, not a smoothing of every frame.
    """

    def __init__(
        self,
        triangles: npt.ArrayLike,
        n_vertices: int,
        *,
        iterations: int = 40,
        lam: float = TAUBIN_LAMBDA,
        mu: float = TAUBIN_MU,
        dtype: npt.DTypeLike = np.float64,
        adjoint: bool = False,
    ) -> None:
        w = umbrella_operator(np.asarray(triangles, dtype=np.int64), int(n_vertices))
        if adjoint:
            w = w.T.tocsr()
            w.sort_indices()
        self.n_vertices = int(n_vertices)
        self.indptr = w.indptr.astype(np.int64)
        self.indices = w.indices.astype(np.int32 if n_vertices < 2**31 else np.int64)
        self.weights = w.data.astype(np.float64)
        self.iterations = int(iterations)
        self.lam = float(lam)
        self.mu = float(mu)
        self.dtype = np.dtype(dtype)

    def __call__(self, points: np.ndarray) -> np.ndarray:
        """Smooth ``points : (V, 3)`` or ``(F, V, 3)``; returns float64 of the same shape.

        Blocks of coordinate columns run side by side on threads; the kernel gathers its
        block itself, so frames are read in place (float32 or float64, C order) without
        transposed copies.
        """
        from .._threads import in_blocks, worker_count
        from ._laplacian_kernels import SIMD_COLUMNS, taubin_frames

        p = np.asarray(points)
        single = p.ndim == 2
        if single:
            p = p[None]
        if p.ndim != 3 or p.shape[1:] != (self.n_vertices, 3):
            raise ShapeError(
                f"TaubinSmoother: expected (V, 3) or (F, V, 3) with V={self.n_vertices}, got {np.shape(points)}"
            )
        if p.dtype not in (np.float32, np.float64):
            p = p.astype(np.float64)
        p = np.ascontiguousarray(p)
        out = np.empty(p.shape, dtype=np.float64)
        proto = np.empty(0, dtype=self.dtype)
        # fewer meshes than threads: a block per mesh (its 3 columns take the kernel's
        # unrolled path: 1 mesh 0.14 -> 0.06 s at 80K vertices against 2 + 1 columns)
        in_blocks(
            taubin_frames,
            3 * p.shape[0],
            lambda c0, c1: (
                self.indptr,
                self.indices,
                self.weights,
                p,
                out,
                self.iterations,
                self.lam,
                self.mu,
                c0,
                c1,
                proto,
            ),
            parts=worker_count(p.shape[0]),
            align=SIMD_COLUMNS,
        )
        return out[0] if single else out


class SmoothedDisplacements:
    """``G D`` for the displacements ``D`` of C meshes from one reference, read at chosen
    vertices (:meth:`at`) or as whole frames (:meth:`frames`); ``G`` is a
    :class:`TaubinSmoother`. The filter is linear, so ``G (R + D_c) = G R + G D_c``.

    Written as the ``(3C, V)`` matrix ``A`` (a row per frame and coordinate), the
    displacements of a face performance have a low numerical rank (tens of independent
    motions for hundreds of rows). With ``A A^T = Q diag(lam) Q^T`` and ``Q_r`` the
    eigenvectors of the ``r`` largest eigenvalues, ``A ~ Q_r (Q_r^T A)``, so the smoothed
    rows are ``Q_r G(Q_r^T A)``: ``r`` coordinate rows are smoothed instead of ``3C``. ``r``
    is the fewest whose discarded eigenvalues sum to at most ``tol^2`` of their total: the
    truncation error of ``A`` is at most ``tol ||A||_F`` over all frames together (one frame
    may carry more than its share: up to ~2x ``tol`` of its own norm was measured), and the
    filter changes it by its gain, ~1 (Taubin's pass band; ``||G||_2`` 1.06 on a 12 x 12
    grid). The criterion is relative, so the rank does not depend on the length unit.

    When ``r`` exceeds ``max_share`` of the rows, or the rows are more than ``max_rows`` or
    than ``V`` (the ``(3C)^2`` eigenproblem would outgrow the data), every frame is smoothed
    (in chunks of ``chunk`` frames) and :attr:`rank` is None.

    displacements : (C, 3, V) float32 or float64, C-contiguous, finite: each frame
        coordinate-major (the layout in which ``A A^T`` is a product of contiguous rows).
        The dense path overwrites it with the smoothed displacements (it is work space
        then). Memory besides it: ``(3C)^2`` float64 twice, ``r V`` float64 (at most
        ``max_share`` of the input's rows) and one chunk.
    """

    #: Vertices per block of the two passes over the displacements (float64 copies of
    #: ``(3C, block)``: 12 MB at 130 frames).
    BLOCK = 4096

    def __init__(
        self,
        smoother: TaubinSmoother,
        displacements: np.ndarray,
        *,
        tol: float = config.LOW_RANK_TOL,
        max_share: float = config.LOW_RANK_MAX_SHARE,
        max_rows: int = config.LOW_RANK_MAX_ROWS,
        chunk: int = 32,
    ) -> None:
        d = displacements
        n_vertices = smoother.n_vertices
        if (
            d.ndim != 3
            or d.shape[1:] != (3, n_vertices)
            or d.dtype not in (np.float32, np.float64)
            or not d.flags.c_contiguous
        ):
            raise ShapeError(
                f"SmoothedDisplacements: expected C-contiguous float32 or float64 (C, 3, {n_vertices}), "
                f"got {d.dtype} {d.shape}{'' if d.flags.c_contiguous else ' (not C-contiguous)'}"
            )
        n_frames = d.shape[0]
        self.n_frames, self.n_vertices, self._chunk = n_frames, n_vertices, max(1, int(chunk))
        rows = d.reshape(3 * n_frames, n_vertices)
        self.rank: int | None = None
        if rows.shape[0] > min(max_rows, n_vertices):
            self._smooth_all(smoother, d)
            return
        gram = np.zeros((rows.shape[0], rows.shape[0]))
        with np.errstate(over="ignore", invalid="ignore"):  # checked just below
            for v0 in range(0, n_vertices, self.BLOCK):
                blk = rows[:, v0 : v0 + self.BLOCK].astype(np.float64)
                gram += blk @ blk.T
        if not np.isfinite(gram).all():
            raise NumericalError(
                "SmoothedDisplacements: the displacements hold NaN, infinite or overflowing values; "
                "check the meshes (and their head-motion removal) for non-finite vertices"
            )
        lam, q = np.linalg.eigh(gram)
        lam, q = np.maximum(lam[::-1], 0.0), q[:, ::-1]
        tail = np.cumsum(lam[::-1])[::-1]  # tail[k] = sum of lam[k:]
        total = float(tail[0]) if tail.size else 0.0
        rank = int(np.count_nonzero(tail > tol * tol * total))
        if rank > max_share * rows.shape[0]:
            self._smooth_all(smoother, d)
            return
        self.rank = rank
        self._mix = np.ascontiguousarray(q[:, :rank])  # (3C, r): Q_r
        reduced = np.zeros((3 * -(-rank // 3), n_vertices))  # Q_r^T A, whole "frames" of 3 rows
        for v0 in range(0, n_vertices, self.BLOCK):
            blk = rows[:, v0 : v0 + self.BLOCK].astype(np.float64)
            reduced[:rank, v0 : v0 + blk.shape[1]] = self._mix.T @ blk
        self._smooth = self._apply(smoother, reduced)[:rank]  # (r, V): G (Q_r^T A)

    def _smooth_all(self, smoother: TaubinSmoother, d: np.ndarray) -> None:
        """The dense path: every frame smoothed, in place, a chunk at a time."""
        self._apply(smoother, d.reshape(-1, d.shape[2]))
        self._dense = d

    def _apply(self, smoother: TaubinSmoother, rows: np.ndarray) -> np.ndarray:
        """``smoother`` on coordinate rows ``(3n, V)``, in place, a chunk of frames at a time."""
        n_vertices = rows.shape[1]
        step = 3 * self._chunk
        for start in range(0, rows.shape[0], step):
            part = rows[start : start + step].reshape(-1, 3, n_vertices)
            out = smoother(np.ascontiguousarray(part.transpose(0, 2, 1)))
            part[:] = out.transpose(0, 2, 1)
        return rows

    def at(self, vertex_ids: npt.ArrayLike) -> np.ndarray:
        """(C, n, 3) float64: every frame's smoothed displacements at ``vertex_ids`` (n,)."""
        ids = np.asarray(vertex_ids, dtype=np.int64)
        if self.rank is None:
            part = self._dense[:, :, ids].astype(np.float64)
        else:
            part = (self._mix @ self._smooth[:, ids]).reshape(self.n_frames, 3, ids.size)
        return np.ascontiguousarray(part.transpose(0, 2, 1))

    def frames(self, frame_ids: npt.ArrayLike, out: np.ndarray | None = None) -> np.ndarray:
        """(k, V, 3) float64: the smoothed displacements of frames ``frame_ids`` (k,), written
        into ``out`` when given. Formed a few frames at a time: no ``(k, 3, V)`` temporary
        (at 80K vertices each fresh 50 MB array costs up to 0.15 s of page faults)."""
        ids = np.asarray(frame_ids, dtype=np.int64)
        shape = (ids.size, self.n_vertices, 3)
        if out is None:
            out = np.empty(shape)
        elif out.shape != shape or out.dtype != np.float64:
            raise ShapeError(
                f"SmoothedDisplacements.frames: out must be float64 {shape}, got {out.dtype} {out.shape}"
            )
        return self._frames_into(ids, out)

    def _frames_into(
        self, ids: np.ndarray, out: np.ndarray, basis: np.ndarray | None = None
    ) -> np.ndarray:
        """``out (k, V, 3)`` = :meth:`frames` ``ids``, a few frames at a time; of ``Q_r basis``
        when ``basis (r, V)`` (another filter of the smoothed rows ``G (Q_r^T A)``) is given."""
        step = config.scratch_items(24 * self.n_vertices)
        for start in range(0, ids.size, step):
            block = ids[start : start + step]
            out[start : start + block.size] = self._rows(block, basis).transpose(0, 2, 1)
        return out

    def _rows(self, frame_ids: npt.ArrayLike, basis: np.ndarray | None = None) -> np.ndarray:
        """(k, 3, V) float64: :meth:`frames` (of ``basis``, as for :meth:`_frames_into`),
        coordinate-major."""
        ids = np.asarray(frame_ids, dtype=np.int64)
        if self.rank is None:
            return self._dense[ids].astype(np.float64)
        cols = (3 * ids[:, None] + np.arange(3)).ravel()
        rows = self._smooth if basis is None else basis
        return (self._mix[cols] @ rows).reshape(ids.size, 3, self.n_vertices)

    def filtered(
        self, smoother: TaubinSmoother, frame_ids: npt.ArrayLike, also: np.ndarray
    ) -> np.ndarray:
        """Another linear filter ``H`` (``smoother``, e.g. the adjoint ``G^T``) applied to the
        meshes ``also : (n, V, 3)`` and to the smoothed displacements ``G D_c`` of
        ``frame_ids`` (k,), in one call: ``(n + k, V, 3)`` float64. Through the row basis
        (``Q_r H G (Q_r^T A)``) when that is fewer rows than the ``3k`` of the frames; exact
        either way (up to rounding), since :meth:`frames` is built from that basis."""
        ids = np.asarray(frame_ids, dtype=np.int64)
        extra = np.asarray(also, dtype=np.float64)
        if self.rank is None or self.rank >= 3 * ids.size:
            return smoother(np.concatenate([extra, self.frames(ids)]))
        n_vertices, n, r = self.n_vertices, extra.shape[0], self.rank
        rows = np.zeros((3 * n + 3 * -(-r // 3), n_vertices))
        rows[: 3 * n] = extra.transpose(0, 2, 1).reshape(3 * n, n_vertices)
        rows[3 * n : 3 * n + r] = self._smooth
        applied = self._apply(smoother, rows)
        out = np.empty((n + ids.size, n_vertices, 3))
        out[:n] = applied[: 3 * n].reshape(n, 3, n_vertices).transpose(0, 2, 1)
        self._frames_into(ids, out[n:], applied[3 * n : 3 * n + r])  # Q_r H G (Q_r^T A)
        return out


def taubin_smooth(
    points: np.ndarray,
    triangles: np.ndarray,
    *,
    iterations: int = 40,
    lam: float = TAUBIN_LAMBDA,
    mu: float = TAUBIN_MU,
    dtype: npt.DTypeLike = np.float64,
) -> np.ndarray:
    """Taubin-smooth ``points : (V, 3)`` or ``(F, V, 3)`` on the mesh ``triangles : (T, 3)``.

    Returns float64 positions of the same shape. For repeated calls on one topology,
    build a :class:`TaubinSmoother` once.
    """
    p = np.asarray(points)
    if p.ndim not in (2, 3) or p.shape[-1] != 3:
        raise ShapeError(f"taubin_smooth: points must be (V, 3) or (F, V, 3), got {p.shape}")
    return TaubinSmoother(
        triangles, p.shape[-2], iterations=iterations, lam=lam, mu=mu, dtype=dtype
    )(p)
