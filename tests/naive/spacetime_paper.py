"""Paper-exact settings of the spacetime plugin, and brute-force references for editing and the prior.

- :func:`paper` builds ``spacetime`` (or a baseline variant) with Seol et al. 2012's own choices,
  passing only the parameters the installed version accepts (``get_params()``), so the tests
  that check the paper's behaviour run before and after the plugin's defaults change.
- :func:`constrained_resolve`: the whole-sequence energy written out as dense least-squares rows
  (``kron(D, B)`` velocity rows, prior rows per frame, ridge rows), the known frames eliminated,
  solved by ``numpy.linalg.lstsq``. Written from the paper's Eq. 4-5, sharing nothing with the
  plugin's solver (nor with ``naive.spacetime``); small sizes only.
- :func:`linear_blend`: the edit offset spread linearly between fixed frames (the answer of
  pure Poisson editing, i.e. of ``alpha = 0``; wrong when the prior acts).
- :func:`mean_centred_prior`: ``(Q, q)`` of Eq. 3 as printed (PCA about the sample mean) from
  the covariance matrix, for the assembled reference.
"""

from __future__ import annotations

import numpy as np

import faceretarget as fr

#: Seol et al. 2012's choices where the plugin's defaults may differ: no weight bounds, no
#: Sobolev / L1 term, boundary values from per-frame solves, RBF scale-proportion matching,
#: the landmarks as the only correspondences.
PAPER = {
    "bounds": None,
    "beta": 0.0,
    "sparsity": 0.0,
    "boundary": "per_frame",
    "transfer": "rbf",
    "rbf_kernel": "linear",
    "samples": "landmarks",
}


def accepted(name: str, params: dict) -> dict:
    """The entries of ``params`` that retargeter ``name`` accepts."""
    known = fr.get(name).get_params()
    return {k: v for k, v in params.items() if k in known}


def paper(name: str = "spacetime", **overrides):
    """Retargeter ``name`` with the paper's settings (:data:`PAPER`) and ``overrides``."""
    return fr.get(name, **accepted(name, {**PAPER, **overrides}))


# ---------------------------------------------------------------------------------------
# Whole-sequence constrained solve (Eq. 4-5), dense rows
# ---------------------------------------------------------------------------------------
def _difference(n_frames: int) -> np.ndarray:
    """(F-1, F) forward difference ``D``: ``(D x)_t = x_{t+1} - x_t``."""
    d = np.zeros((n_frames - 1, n_frames))
    idx = np.arange(n_frames - 1)
    d[idx, idx] = -1.0
    d[idx, idx + 1] = 1.0
    return d


def _sqrt_psd(matrix: np.ndarray) -> np.ndarray:
    """Rows ``R`` with ``R^T R = matrix`` (PSD)."""
    lam, vec = np.linalg.eigh(np.asarray(matrix, float))
    keep = lam > 0
    return (np.sqrt(lam[keep]) * vec[:, keep]).T


def constrained_resolve(
    basis, deltas, known, values, *, prior_factor, prior_offset, alpha, ridge=None
):
    """Minimize ``||D (B W^T)^T - D S||^2 + alpha sum_t ||A w_t + a||^2 + sum_t w_t^T R w_t`` over
    the frames not ``known``, the ``known`` frames fixed at ``values``.

    basis (3N, M); deltas (F, N, 3) (NaN = missing: velocity rows touching it are dropped);
    known (F,) bool; values (F, M); prior_factor A (h, M), prior_offset a (h,); ridge R (M, M) PSD.
    Unknowns ``x = vec(W)`` frame-major; the velocity rows are ``kron(D, B)``.
    Returns (F, M) with the known frames equal to ``values``.
    """
    b = np.asarray(basis, float)
    s = np.asarray(deltas, float).reshape(len(deltas), -1)
    n_frames, m = s.shape[0], b.shape[1]
    blocks, rhs = [], []
    if n_frames > 1:
        d = _difference(n_frames)
        rows = np.kron(d, b)  # row (t, r): b_r . (w_{t+1} - w_t)
        target = (s[1:] - s[:-1]).ravel()  # = D S, NaN only where a sample is missing (no 0 * NaN)
        ok = np.isfinite(target)
        blocks.append(rows[ok])
        rhs.append(target[ok])
    if alpha:
        a = np.asarray(prior_factor, float)
        blocks.append(np.sqrt(alpha) * np.kron(np.eye(n_frames), a))
        rhs.append(np.tile(-np.sqrt(alpha) * np.asarray(prior_offset, float), n_frames))
    if ridge is not None and np.any(ridge):
        blocks.append(np.kron(np.eye(n_frames), _sqrt_psd(ridge)))
        rhs.append(np.zeros(n_frames * _sqrt_psd(ridge).shape[0]))
    rows, target = np.vstack(blocks), np.concatenate(rhs)
    fixed = np.repeat(np.asarray(known, bool), m)
    x = np.zeros(n_frames * m)
    x[fixed] = np.asarray(values, float)[np.asarray(known, bool)].ravel()
    free = ~fixed
    x[free] = np.linalg.lstsq(rows[:, free], target - rows[:, fixed] @ x[fixed], rcond=None)[0]
    return x.reshape(n_frames, m)


def linear_blend(current, frame: int, new, fixed) -> np.ndarray:
    """``current`` plus the edit offset ``new - current[frame]`` spread linearly from 0 at the
    nearest fixed frames on either side (``fixed``: sorted frame indices other than ``frame``)
    to the full offset at ``frame``: the exact answer of Poisson editing without a prior."""
    out = np.array(current, dtype=float)
    offset = np.asarray(new, float) - out[frame]
    before = max((f for f in fixed if f < frame), default=None)
    after = min((f for f in fixed if f > frame), default=None)
    for t in range(len(out)):
        if t == frame:
            share = 1.0
        elif t < frame:
            share = 1.0 if before is None else max(0.0, (t - before) / (frame - before))
        else:
            share = 1.0 if after is None else max(0.0, (after - t) / (after - frame))
        out[t] += share * offset
    return out


# ---------------------------------------------------------------------------------------
# The prior of Eq. 3 as printed
# ---------------------------------------------------------------------------------------
def mean_centred_prior(samples, basis, neutral, rtol=1e-10):
    """``(Q, q, c)`` of the PCA prior about the sample mean, from the covariance matrix:
    ``prior(w) = (B w + n - t_mean)^T C^+ (B w + n - t_mean)`` restricted to the samples' span,
    ``= w^T Q w - 2 q^T w + c``."""
    x = np.asarray(samples, float)
    mean = x.mean(axis=0)
    cov = (x - mean).T @ (x - mean) / len(x)
    lam, e = np.linalg.eigh(cov)
    keep = lam > rtol * lam.max()
    precision = e[:, keep] @ np.diag(1.0 / lam[keep]) @ e[:, keep].T
    b = np.asarray(basis, float)
    offset = np.asarray(neutral, float) - mean
    return b.T @ precision @ b, -b.T @ precision @ offset, float(offset @ precision @ offset)


def prior_rows(q_mat, q_vec, constant):
    """``(A, a)`` with ``||A w + a||^2 = w^T Q w - 2 q^T w + c`` (for :func:`constrained_resolve`)."""
    lam, vec = np.linalg.eigh(np.asarray(q_mat, float))
    keep = lam > 1e-12 * max(lam.max(), 1e-300)
    a_mat = (np.sqrt(lam[keep]) * vec[:, keep]).T
    # a = -A^{+T} q on the range of Q; the remainder of c is a constant (no effect on the minimizer)
    a_vec = -(vec[:, keep] / np.sqrt(lam[keep])).T @ np.asarray(q_vec, float)
    return a_mat, a_vec
