"""The model-specific PCA prior (Seol et al. 2012, sec. 5, Eq. 3-5).

PCA of target face samples (by default the blendshapes themselves, "an animation whose
j-th frame is the j-th blendshape"; optionally a subset of them, fig. 13, and/or supplied
target animations) at the (scale-matched) marker positions gives eigenvectors ``E`` and
eigenvalues ``lambda`` (variances about ``t_mean``: the sample mean as in Eq. 3, or by
default the neutral, see :func:`fit_prior`). With ``v = E^T (B w + n - t_mean)`` the prior energy per frame is
``v^T Lambda^{-1} v = ||A w + a||^2`` with ``A = Lambda^{-1/2} E^T B`` and
``a = Lambda^{-1/2} E^T (n - t_mean)``; its normal-equation contribution is
``Q w - q`` with ``Q = A^T A`` and ``q = -A^T a``.

Scale: ``Q`` and ``q`` are unit-free (eigenvalues scale with the square of the face size,
like ``(E^T B w)^2``), whereas the matching term grows with the square of the face size;
the retargeter therefore scales ``alpha`` with the face size (see ``retargeter``).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from faceretarget import config
from faceretarget.errors import ConfigError, ShapeError


@dataclass(frozen=True)
class Prior:
    """A fitted PCA prior in weight space.

    matrix : (M, M) float64      Q = A^T A
    vector : (M,) float64        q = -A^T a (right-hand side term)
    factor : (h, M) float64      A
    offset : (h,) float64        a
    eigenvalues : (h,) float64   PCA variances kept (non-zero ones)
    n_samples : int              number of face samples the PCA saw
    """

    matrix: np.ndarray
    vector: np.ndarray
    factor: np.ndarray
    offset: np.ndarray
    eigenvalues: np.ndarray
    n_samples: int

    def energy(self, weights: np.ndarray) -> np.ndarray:
        """Per-frame prior energy ``v^T Lambda^-1 v`` for ``weights (F, M)`` -> ``(F,)``."""
        v = np.asarray(weights, dtype=np.float64) @ self.factor.T + self.offset
        return np.einsum("fk,fk->f", v, v)


def fit_prior(
    samples: np.ndarray, basis: np.ndarray, neutral: np.ndarray, center: str = "neutral"
) -> Prior:
    """PCA prior from face samples.

    Parameters
    ----------
    samples : (K, 3N) float
        Absolute marker positions of the K training faces (x-y-z interleaved per marker).
    basis : (3N, M) float
        Blendshape delta matrix ``B`` at the markers.
    neutral : (3N,) float
        Neutral marker positions ``n`` (the model is ``n + B w``).
    center : "neutral" | "mean"
        Centre of the PCA: the sample mean ``t_mean`` (Eq. 3 as printed), or the neutral
        (second moments of the deltas; the default of the retargeter). With shapes that are
        linearly dependent at the markers (e.g. a symmetric shape equal to the sum of its
        left and right halves) the mean-centred prior gives the neutral itself a non-zero
        energy, so a source at rest would be pulled toward the mean expression; centred at the
        neutral, ``w = 0`` always has zero prior energy. With linearly independent shapes the
        mean-centred prior also gives the neutral a non-zero energy in general (the part of
        the mean's offset that lies in the samples' span), so a source at rest is pulled
        toward the mean there too (tests/spacetime/test_prior_center.py).

    Eigen-directions with (numerically) zero variance are left out (Eq. 3 keeps the ``h``
    eigenvectors with non-zero eigenvalues), so the prior does not constrain motion outside
    the span of the samples; with fewer than two distinct samples the prior is empty
    (all zeros) and only the matching term acts.
    """
    x = np.asarray(samples, dtype=np.float64)
    b = np.asarray(basis, dtype=np.float64)
    n = np.asarray(neutral, dtype=np.float64)
    if x.ndim != 2 or x.shape[1] != b.shape[0] or n.shape != (b.shape[0],):
        raise ShapeError(
            f"fit_prior: samples (K, 3N), basis (3N, M) and neutral (3N,) must agree, got {x.shape}, {b.shape}, {n.shape}"
        )
    if center not in ("neutral", "mean"):
        raise ConfigError(f"fit_prior: center must be 'neutral' or 'mean', got {center!r}")
    n_samples = x.shape[0]
    mean = x.mean(axis=0) if center == "mean" else n
    centred = x - mean
    # eigenvectors of the (3N, 3N) covariance from the small (K, K) Gram of the samples:
    # centred^T = U S V^T, so centred centred^T = V S^2 V^T and U = centred^T V / S
    sig2, v = np.linalg.eigh(centred @ centred.T)
    sig2, v = sig2[::-1], v[:, ::-1]
    lam = np.maximum(sig2, 0.0) / max(n_samples, 1)
    keep = lam > config.RANK_RTOL * (lam.max() if lam.size else 0.0)
    if not keep.any():
        m = b.shape[1]
        return Prior(
            np.zeros((m, m)), np.zeros(m), np.zeros((0, m)), np.zeros(0), np.zeros(0), n_samples
        )
    e = (centred.T @ v[:, keep]) / np.sqrt(sig2[keep])
    inv_sqrt = 1.0 / np.sqrt(lam[keep])
    factor = inv_sqrt[:, None] * (e.T @ b)
    offset = inv_sqrt * (e.T @ (n - mean))
    return Prior(factor.T @ factor, -factor.T @ offset, factor, offset, lam[keep], n_samples)
