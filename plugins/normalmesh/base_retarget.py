"""Example-based base mesh retargeting (Na & Jung 2004 sec. 4.1, Eq. 3-4).

Each base point ``i`` has its own map from source displacement ``x = S[i] - S_neut[i]`` to
target displacement ``T[i] - T_neut[i]``: a multiquadric RBF ``h(r) = sqrt(r^2 + c^2)`` over
the example displacements (Eq. 3, centres ``x_j``), its weights solved from the M example
pairs (Eq. 4). Additions, each documented in ``docs/methods/normalmesh.md``:

- the neutral is always an example (displacement 0 -> 0), and the map is anchored,
  ``f(x) = g(x) - g(0)``, so a resting source gives exactly the resting target;
- the RBF interpolates the *residual* of a default linear map ``F0 = s R`` (the similarity
  aligning the source's neutral feature points with the target's): directions the examples
  do not span are mapped by the neutral-to-neutral similarity instead of the multiquadric's
  linear growth; with the neutral as the only example the map is F0 (the identity when
  source = target);
- the weights solve ``(H - lambda I) w = y`` with ``lambda = rbf_smoothing * c`` (a smoothing
  RBF; the sign because -H is conditionally positive definite) instead of exact interpolation: example displacements that nearly coincide at a
  point (a cheek point that barely moves in three examples) but ask for different target
  displacements (feature points a few millimetres apart on two meshes) otherwise need
  weights of 1e6 and throw the point far off in other frames. ``rbf_smoothing = 0`` is the
  paper's exact interpolation.

``c`` is per point ``rbf_c`` x the mean distance between each example displacement and its
nearest other one. Exactly coincident example displacements are merged (targets averaged).
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from faceretarget import config
from faceretarget.geometry.procrustes import fit_rigid
from faceretarget.geometry.rbf import kernel_values


@dataclass(frozen=True)
class BaseMap:
    """Per-point multiquadric maps, stacked for evaluation over frames.

    linear : (3, 3) F0; centers : (N, M, 3) padded; weights : (N, M, 3) (0 for padding);
    constant : (N, 3) (includes the anchor -g(0)); c : (N,)
    """

    linear: np.ndarray
    centers: np.ndarray
    weights: np.ndarray
    constant: np.ndarray
    c: np.ndarray

    def __call__(self, displacement: np.ndarray) -> np.ndarray:
        """Target displacements ``(F, N, 3)`` for source displacements ``(F, N, 3)`` (Eq. 3)."""
        x = np.asarray(displacement, dtype=np.float64)
        return self._rbf(x) + self.constant + x @ self.linear.T

    def _rbf(self, x: np.ndarray) -> np.ndarray:
        r = np.sqrt(np.sum((x[:, :, None, :] - self.centers[None]) ** 2, axis=-1))  # (F, N, M)
        return np.einsum("fnm,nmd->fnd", kernel_values(r, "multiquadric", self.c[None, :, None]), self.weights)


def _unique_rows(x: np.ndarray, y: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    uniq, inverse = np.unique(x, axis=0, return_inverse=True)
    inverse = inverse.ravel()
    merged = np.zeros((len(uniq), y.shape[1]))
    np.add.at(merged, inverse, y)
    return uniq, merged / np.bincount(inverse)[:, None]


def _solve(x: np.ndarray, y: np.ndarray, c: float, smoothing: float) -> tuple[np.ndarray, np.ndarray]:
    """Weights (M, 3) and constant (3,) of ``sum_j w_j h(|x - x_j|) + b`` with sum_j w_j = 0."""
    m = len(x)
    h = kernel_values(np.linalg.norm(x[:, None] - x[None], axis=-1), "multiquadric", c)
    system = np.zeros((m + 1, m + 1))
    # -h is conditionally positive definite (order 1) on sum_j w_j = 0, so the smoothing term
    # is subtracted: (h - lambda I); adding it would push the eigenvalues towards 0 instead
    system[:m, :m] = h - (smoothing * c + config.RIDGE_EPS * max(float(h.max()), 1.0)) * np.eye(m)
    system[:m, m] = system[m, :m] = 1.0
    rhs = np.zeros((m + 1, 3))
    rhs[:m] = y
    sol = np.linalg.solve(system, rhs)
    return sol[:m], sol[m]


def fit_base_map(src_neutral, tgt_neutral, src_examples, tgt_examples, *, rbf_c: float, rbf_smoothing: float) -> BaseMap:
    """Fit the maps from ``src_neutral (N, 3)``, ``tgt_neutral (N, 3)`` and paired examples ``(M, N, 3)``."""
    sn = np.asarray(src_neutral, dtype=np.float64)
    tn = np.asarray(tgt_neutral, dtype=np.float64)
    rot, _, scale = fit_rigid(sn, tn, scale=True)
    linear = float(scale) * rot
    xs = np.asarray(src_examples, dtype=np.float64) - sn  # (M, N, 3)
    ys = np.asarray(tgt_examples, dtype=np.float64) - tn
    n_points = sn.shape[0]
    fits = []
    for i in range(n_points):
        x = np.concatenate([np.zeros((1, 3)), xs[:, i]])
        y = np.concatenate([np.zeros((1, 3)), ys[:, i]])
        x, y = _unique_rows(x, y - x @ linear.T)
        if len(x) > 1:
            d = np.linalg.norm(x[:, None] - x[None], axis=-1)
            np.fill_diagonal(d, np.inf)
            c = float(rbf_c) * float(d.min(axis=1).mean())
        else:
            c = 1.0
        w, b = _solve(x, y, c, float(rbf_smoothing))
        fits.append((x, w, b, c))
    m = max(len(f[0]) for f in fits)
    centers = np.zeros((n_points, m, 3))
    weights = np.zeros((n_points, m, 3))
    for i, (x, w, _, _) in enumerate(fits):
        centers[i, : len(x)] = x
        weights[i, : len(x)] = w
    c = np.array([f[3] for f in fits])
    unanchored = BaseMap(linear, centers, weights, np.stack([f[2] for f in fits]), c)
    anchor = unanchored(np.zeros((1, n_points, 3)))[0]
    return BaseMap(linear, centers, weights, unanchored.constant - anchor, c)
