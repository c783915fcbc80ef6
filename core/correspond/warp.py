"""Landmark-driven space warps."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import numpy.typing as npt

from ..errors import DegenerateGeometryError, ShapeError
from ..geometry.rbf import RBFInterpolant, _merge_duplicates, kernel_values, solve_system

__all__ = ["rbf_warp"]

#: Points evaluated per block (bounds the (block, N, 3) difference array).
_BLOCK = 4096


def _exact_distances(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """(P, N) distances from the differences (not |a|^2 + |b|^2 - 2 a.b, whose rounding
    error near zero, about sqrt(eps) times the coordinates' size, makes the warp of a point
    on or near a landmark depend on the units and placement of the faces)."""
    out = np.empty((len(a), len(b)))
    for start in range(0, len(a), _BLOCK):
        d = a[start : start + _BLOCK, None, :] - b[None, :, :]
        out[start : start + _BLOCK] = np.sqrt(np.einsum("pnk,pnk->pn", d, d))
    return out


@dataclass(frozen=True)
class _Warp(RBFInterpolant):
    """An :class:`~faceretarget.geometry.rbf.RBFInterpolant` evaluated with exact distances."""

    def __call__(self, points: np.ndarray) -> np.ndarray:
        p = np.asarray(points, dtype=np.float64)
        lead = p.shape[:-1]
        p = p.reshape(-1, p.shape[-1])
        out = kernel_values(_exact_distances(p, self.centers), self.kernel, self.c) @ self.weights
        out += p @ self.affine[:-1] + self.affine[-1]
        return out.reshape(lead + (self.weights.shape[1],))


def rbf_warp(
    source_positions: npt.ArrayLike, target_positions: npt.ArrayLike, *, kernel: str = "linear"
) -> RBFInterpolant:
    """A smooth map of 3D space taking ``source_positions (N, 3)`` onto ``target_positions (N, 3)``.

    ``f(x) = sum_i w_i phi(|x - s_i|) + A x + b`` with phi(r) = r (the biharmonic kernel
    in 3D) and a linear polynomial, as in Seol et al. 2012 sec. 3.2; the result is
    callable on ``(P, 3)`` points. N >= 4 landmarks not all in one plane give the full
    affine part (otherwise only a translation is kept).

    The warp commutes with similarities: scaling, rotating or moving the source positions
    (and the points warped) or the target positions changes the result by the same
    similarity, up to rounding. Distances are taken from coordinate differences, and the
    ridge that keeps near-coincident landmarks solvable (``config.RIDGE_EPS``) is relative
    to the largest kernel value, whatever the units.
    """
    src = np.asarray(source_positions, dtype=np.float64)
    tgt = np.asarray(target_positions, dtype=np.float64)
    if src.ndim != 2 or src.shape[1] != 3 or src.shape != tgt.shape:
        raise ShapeError(
            f"rbf_warp: source and target positions must both be (N, 3), got {src.shape} and {tgt.shape}"
        )
    if len(src) == 0:
        raise DegenerateGeometryError("rbf_warp: at least one landmark pair is needed")
    if not (np.isfinite(src).all() and np.isfinite(tgt).all()):
        raise DegenerateGeometryError("rbf_warp: landmark positions must be finite")
    x, y = _merge_duplicates(src, tgt)
    n, dim = x.shape
    r = _exact_distances(x, x)
    if n > 1:
        nearest = np.where(np.eye(n, dtype=bool), np.inf, r).min(axis=1)
        c = float(np.mean(nearest))
    else:
        c = 1.0
    if kernel != "linear" and not (np.isfinite(c) and c > 0 and np.isfinite(1.0 / c)):
        raise DegenerateGeometryError(
            f"rbf_warp: the kernel width c={c!r} must be a positive, normal number"
        )
    phi = kernel_values(r, kernel, c)
    use_linear = n > dim and np.linalg.matrix_rank(x - x.mean(axis=0)) == dim
    weights, affine = solve_system(
        x,
        y,
        phi,
        use_linear,
        "rbf_warp: the RBF system is singular ({}); check for coincident or collinear landmarks",
    )
    return _Warp(x, weights, affine, kernel, float(c))
