"""Example-based adaptation of the transferred blendshapes (beyond Seol et al. 2012).

Two rig families name the same motion differently (one family's ``mouthClose`` is the
other's ``mouthClose`` plus ``mouthFrown``); geometry alone cannot see that, example pose
pairs can. With E example pairs (a source pose and the target pose that means the same),
the target weights of each example ``w_e`` come from a least-squares fit of the target
example onto the target rig, and the transferred basis ``B`` (source space, rows = point
coordinates) is corrected by the smallest change that reproduces the source examples,
weighted to where each shape moves (the spirit of example-based facial rigging, Li, Weise &
Pauly 2010, reduced to a linear least-squares problem per row)::

    min_B'  sum_e ||B' w_e - s_e||^2 + mu sum_{r,j} c_rj (B'_rj - B_rj)^2,
    c_rj = 1 / (|b_ij|^2 / mean_i |b_ij|^2 + FLOOR)     (point i of row r, shape j)

so a shape is cheap to change where it moves and expensive where it does not. Each row is
an independent (M, M) system; all are solved in one batched call.
"""

from __future__ import annotations

import numpy as np

#: Relative motion below which a shape counts as not moving a point (see ``c_rj``).
FLOOR = 0.01


def example_weights(
    target_deltas: np.ndarray, target_displacements: np.ndarray, lower=None, upper=None
) -> np.ndarray:
    """Target weights (E, M) of example displacements (E, V, 3) on deltas (M, V, 3): least
    squares, clipped to the bounds when given (the examples are poses of the rig itself)."""
    d = np.asarray(target_deltas, dtype=np.float64).reshape(len(target_deltas), -1)
    x = np.asarray(target_displacements, dtype=np.float64).reshape(len(target_displacements), -1)
    gram = d @ d.T
    ridge = 1e-9 * np.trace(gram) / len(gram)
    w = np.linalg.solve(gram + ridge * np.eye(len(gram)), d @ x.T).T
    if lower is not None:
        w = np.clip(w, lower, upper)
    return w


def adapt_basis(
    basis: np.ndarray, weights: np.ndarray, displacements: np.ndarray, mu: float
) -> np.ndarray:
    """The corrected basis ``B'`` (3P, M).

    basis : (3P, M) transferred blendshapes at the points (x-y-z interleaved per point)
    weights : (E, M) the examples' target weights
    displacements : (E, 3P) the source examples' displacements at the same points
    mu : weight of the change penalty (unit-free; larger = trust the geometry more)
    """
    b = np.asarray(basis, dtype=np.float64)
    w = np.asarray(weights, dtype=np.float64)
    s = np.asarray(displacements, dtype=np.float64)
    n_rows, m = b.shape
    motion = np.repeat(
        (b.reshape(-1, 3, m) ** 2).sum(axis=1), 3, axis=0
    )  # (3P, M) |b_ij|^2 per row
    typical = motion.mean(axis=0)
    c = 1.0 / (motion / np.where(typical > 0, typical, 1.0) + FLOOR)  # (3P, M)
    gram = w.T @ w  # (M, M), shared by all rows
    systems = gram[None] + mu * c[:, :, None] * np.eye(m)[None]
    rhs = s.T @ w + mu * c * b  # (3P, M)
    return np.linalg.solve(systems, rhs[..., None])[..., 0]
