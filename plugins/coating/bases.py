"""Blendshape bases from the source sequence (Xu et al. 2014, sec. 4.1, eq. 6-8).

Each smooth source frame is a non-negative combination of ``K`` bases,
``S~_t = sum_i w_ti b_i`` (eq. 6), with the bases chosen among the source frames
(following Huang et al. 2011): start from the reference ``b_1 = S~_0`` and add, greedily,
the frame that the current bases reconstruct worst, until the RMS reconstruction error
(eq. 7) is below ``epsilon`` times the face height (or ``max_bases`` is reached). The
weights come from NNLS on the Gram matrix (:func:`faceretarget.geometry.nnls.nnls_gram`;
the paper uses James & Twigg's NNLS).

Coordinates are taken relative to the reference's centroid, so the representation
does not depend on where the face sits in space. The selection criterion is evaluated
on an even subsample of at most ``SELECTION_VERTICES`` vertices: the smooth meshes are
low-frequency, so the subsample error tracks the full one, and memory for the
selection grows by only ``3 * SELECTION_VERTICES`` numbers a frame.
"""

from __future__ import annotations

import numpy as np

from faceretarget.errors import ShapeError
from faceretarget.geometry.mesh_ops import translated

__all__ = [
    "SELECTION_VERTICES",
    "selection_vertices",
    "nnls_rows",
    "select_bases",
    "BasisSpace",
    "blend",
    "blend_flat",
]

#: Vertices used to evaluate the greedy selection criterion.
SELECTION_VERTICES = 2000


def selection_vertices(n_vertices: int) -> np.ndarray:
    """Evenly spaced vertex ids (all of them for small meshes)."""
    if n_vertices <= SELECTION_VERTICES:
        return np.arange(n_vertices)
    return np.unique(np.linspace(0, n_vertices - 1, SELECTION_VERTICES).round().astype(np.int64))


def nnls_rows(gram: np.ndarray, rhs: np.ndarray) -> np.ndarray:
    """Non-negative ``x`` minimising ``1/2 x^T G x - rhs_k . x`` for each row of ``rhs (k, n)``."""
    from faceretarget.geometry.nnls import nnls_gram

    return nnls_gram(gram, rhs)


def _errors(gram, cross, sq, weights):
    """Squared residuals ``|B w_t - x_t|^2`` from Gram quantities."""
    return np.maximum(
        sq
        - 2.0 * np.einsum("fk,fk->f", weights, cross)
        + np.einsum("fk,kl,fl->f", weights, gram, weights),
        0.0,
    )


def select_bases(
    samples: np.ndarray, reference: np.ndarray, *, epsilon: float, max_bases: int, height: float
):
    """Greedy basis selection on subsampled, centred smooth frames.

    samples : (F, P) flattened smooth frames; reference : (P,) the smooth reference.
    Returns ``(frames, rms)``: chosen frame indices (the reference is basis 0 and is not
    a frame) and the RMS error per vertex relative to ``height`` after each step.
    """
    x = np.asarray(samples, dtype=np.float64)
    n_points = x.shape[1] // 3
    basis = [np.asarray(reference, dtype=np.float64)]
    chosen: list[int] = []
    history = []
    sq = np.einsum("fp,fp->f", x, x)
    while True:
        b = np.stack(basis, axis=1)
        gram = b.T @ b
        cross = x @ b
        w = nnls_rows(gram, cross)
        err = _errors(gram, cross, sq, w)
        err[chosen] = 0.0
        rms = float(np.sqrt(err.sum() / (x.shape[0] * n_points))) / height
        history.append(rms)
        if rms <= epsilon or len(basis) >= max_bases:
            break
        worst = int(np.argmax(err))
        if err[worst] <= 0.0:
            break
        chosen.append(worst)
        basis.append(x[worst])
    return chosen, history


class BasisSpace:
    """Non-negative weights of smooth meshes on fixed bases (full resolution).

    bases : (K, V, 3) absolute smooth meshes; center : (3,) origin of the coordinates.
    adjoint : callable, optional
        The transposed smoothing filter ``G^T`` (``(K, V, 3) -> (K, V, 3)``). With it,
        :meth:`weights_of_raw` gives the weights of the *smoothed* frames ``G S_t`` from
        the raw frames ``S_t`` exactly: ``B^T G (S - c) = (G^T B)^T (S - c)`` (the filter
        is linear and keeps constants), so frames need not be smoothed one by one.
    adjoint_bases : (K, V, 3), optional
        ``G^T (bases - center)`` when the caller has it (then ``adjoint`` is not called).
    centred : bool
        ``bases`` are already ``bases - center`` (float64, C order): kept without a copy.
    """

    def __init__(
        self,
        bases: np.ndarray,
        center: np.ndarray,
        adjoint=None,
        adjoint_bases=None,
        *,
        centred: bool = False,
    ):
        b = (
            np.ascontiguousarray(bases, dtype=np.float64)
            if centred
            else np.asarray(bases, dtype=np.float64) - center
        )
        self.center = np.asarray(center, dtype=np.float64)
        # (3V, K) Fortran-ordered views of the (K, 3V) rows: BLAS reads them as they are
        self.matrix = b.reshape(b.shape[0], -1).T
        self.gram = self.matrix.T @ self.matrix
        self.adjoint_matrix = None
        if adjoint_bases is None and adjoint is not None:
            adjoint_bases = adjoint(b)
        if adjoint_bases is not None:  # G^T B, (3V, K)
            lifted = np.ascontiguousarray(adjoint_bases, dtype=np.float64)
            if lifted.shape != b.shape:
                raise ShapeError(
                    f"BasisSpace: adjoint_bases must have the bases' shape {b.shape}, got {lifted.shape}"
                )
            self.adjoint_matrix = lifted.reshape(b.shape[0], -1).T

    def weights(self, smooth: np.ndarray) -> np.ndarray:
        """(C, K) weights of ``smooth : (C, V, 3)`` (eq. 6)."""
        return nnls_rows(self.gram, self._centred(smooth) @ self.matrix)

    def weights_of_raw(self, frames: np.ndarray) -> np.ndarray:
        """(C, K) weights of the smoothed ``G frames`` computed from the raw ``frames : (C, V, 3)``."""
        return nnls_rows(self.gram, self._centred(frames) @ self.adjoint_matrix)

    def _centred(self, meshes: np.ndarray) -> np.ndarray:
        """``(C, 3V)`` rows of ``meshes - center``."""
        return translated(meshes, -self.center).reshape(np.shape(meshes)[0], -1)


def blend(bases: np.ndarray, center: np.ndarray, weights: np.ndarray) -> np.ndarray:
    """``center + sum_i w_ti (b_i - center)`` -> ``(C, V, 3)`` (eq. 8), formed as
    ``sum_i w_ti b_i + (1 - sum_i w_ti) center``: no ``(K, V, 3)`` copy of the centred bases
    (54 MB and 0.1 s at 80K vertices and 28 bases, for each frame or chunk of an edited
    result). The bases' ``(K, 3V)`` rows are read in place when they are a matrix (C order,
    or deformation transfer's ``(V, 3, K)`` layout: Fortran order)."""
    b = np.asarray(bases, dtype=np.float64)
    w = np.asarray(weights, dtype=np.float64)
    k, n = b.shape[0], b.shape[1]
    if w.ndim != 2 or w.shape[1] != k:
        raise ShapeError(f"blend: weights must be (C, {k}) for {k} bases, got {w.shape}")
    out = w @ b.reshape(k, -1)
    tiled = np.tile(np.asarray(center, dtype=np.float64), n)
    for row, rest in zip(out, 1.0 - w.sum(axis=1)):
        row += rest * tiled
    return out.reshape(w.shape[0], n, 3)


def blend_flat(weights: np.ndarray, flat: np.ndarray, center: np.ndarray) -> np.ndarray:
    """:func:`blend` of bases given as ``flat = (bases - center)`` rows ``(K, 3V)``: the centre
    added in place over rows of ``3V`` (numpy's broadcast of a (3,) vector is ~3x slower)."""
    out = np.asarray(weights, dtype=np.float64) @ flat
    out += np.tile(np.asarray(center, dtype=np.float64), flat.shape[1] // 3)
    return out.reshape(out.shape[0], flat.shape[1] // 3, 3)
