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
The points are solved together (one batched ``(M + 2)``-square solve each), so the same map
serves the base points and, as the dense fallback, thousands of target vertices.
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

    def one(self, displacement: np.ndarray) -> np.ndarray:
        """Target displacements ``(N, 3)`` of one frame's ``(N, 3)`` (numba; same as ``self(d[None])[0]``)."""
        from . import _kernels as k

        out = np.empty((len(displacement), 3))
        k.multiquadric_maps(
            np.ascontiguousarray(displacement, dtype=np.float64),
            self.centers,
            self.weights,
            self.constant,
            self.c,
            self.linear,
            out,
        )
        return out

    def _rbf(self, x: np.ndarray) -> np.ndarray:
        r = np.sqrt(np.sum((x[:, :, None, :] - self.centers[None]) ** 2, axis=-1))  # (F, N, M)
        return np.einsum(
            "fnm,nmd->fnd", kernel_values(r, "multiquadric", self.c[None, :, None]), self.weights
        )


def _solve_points(x: np.ndarray, y: np.ndarray, rbf_c: float, smoothing: float):
    """Per point ``i`` the weights ``w (m, 3)`` and constant ``b (3,)`` of
    ``sum_j w_j h(|x - x_ij|) + b`` through ``y (N, m, 3)`` at ``x (N, m, 3)``, with
    ``sum_j w_j = 0``, ``h`` the multiquadric of width ``c_i`` and the ridge ``-lambda I``.

    Rows repeating an earlier row of the same point exactly are merged (their targets
    averaged; weight 0). Returns weights (N, m, 3), constant (N, 3), c (N,).
    """
    n, m, _ = x.shape
    d = np.linalg.norm(x[:, :, None] - x[:, None], axis=-1)  # (N, m, m)
    same = d == 0.0
    first = np.argmax(same, axis=2)  # the first row equal to each row
    unique = first == np.arange(m)[None]
    merged = np.zeros_like(y)
    rows = np.arange(n)[:, None]
    np.add.at(merged, (np.broadcast_to(rows, first.shape), first), y)
    counts = np.zeros((n, m))
    np.add.at(counts, (np.broadcast_to(rows, first.shape), first), 1.0)
    merged = np.where(unique[..., None], merged / np.maximum(counts, 1.0)[..., None], 0.0)
    # c: rbf_c x the mean distance from each distinct displacement to its nearest other one
    both = unique[:, :, None] & unique[:, None, :] & ~np.eye(m, dtype=bool)[None]
    nearest = np.where(both, d, np.inf).min(axis=2)
    n_unique = unique.sum(axis=1)
    mean_nearest = np.where(unique, np.where(np.isfinite(nearest), nearest, 0.0), 0.0).sum(
        axis=1
    ) / np.maximum(n_unique, 1)
    c = np.where(n_unique > 1, float(rbf_c) * mean_nearest, 1.0)
    h = kernel_values(d, "multiquadric", c[:, None, None])
    pair = unique[:, :, None] & unique[:, None, :]
    h = np.where(pair, h, 0.0)
    # -h is conditionally positive definite (order 1) on sum_j w_j = 0, so the smoothing term
    # is subtracted: (h - lambda I); adding it would push the eigenvalues towards 0 instead
    ridge = float(smoothing) * c + config.RIDGE_EPS * h.max(axis=(1, 2))
    system = np.zeros((n, m + 1, m + 1))
    system[:, :m, :m] = h - ridge[:, None, None] * np.eye(m)[None] * unique[:, :, None]
    system[:, :m, :m] += np.eye(m)[None] * ~unique[:, :, None]  # merged rows: w_j = 0
    system[:, :m, m] = system[:, m, :m] = unique
    rhs = np.zeros((n, m + 1, 3))
    rhs[:, :m] = merged
    sol = np.linalg.solve(system, rhs)
    return sol[:, :m], sol[:, m], c


def fit_base_map(
    src_neutral,
    tgt_neutral,
    src_examples,
    tgt_examples,
    *,
    rbf_c: float,
    rbf_smoothing: float,
    linear=None,
) -> BaseMap:
    """Fit the maps from ``src_neutral (N, 3)``, ``tgt_neutral (N, 3)`` and paired examples ``(M, N, 3)``.

    ``linear (3, 3)``: the default linear map F0 (default: the similarity aligning the two
    neutrals' points).
    """
    sn = np.asarray(src_neutral, dtype=np.float64)
    tn = np.asarray(tgt_neutral, dtype=np.float64)
    if linear is None:
        rot, _, scale = fit_rigid(sn, tn, scale=True)
        linear = float(scale) * rot
    linear = np.asarray(linear, dtype=np.float64)
    xs = np.asarray(src_examples, dtype=np.float64) - sn  # (M, N, 3)
    ys = np.asarray(tgt_examples, dtype=np.float64) - tn
    n_points = sn.shape[0]
    x = np.concatenate([np.zeros((n_points, 1, 3)), xs.transpose(1, 0, 2)], axis=1)  # (N, M + 1, 3)
    y = np.concatenate([np.zeros((n_points, 1, 3)), ys.transpose(1, 0, 2)], axis=1)
    weights, constant, c = _solve_points(x, y - x @ linear.T, rbf_c, rbf_smoothing)
    unanchored = BaseMap(linear, x, weights, constant, c)
    anchor = unanchored(np.zeros((1, n_points, 3)))[0]
    return BaseMap(linear, x, weights, unanchored.constant - anchor, c)
