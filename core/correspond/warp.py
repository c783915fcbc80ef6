"""Landmark-driven space warps."""
from __future__ import annotations

import numpy as np

from ..errors import DegenerateGeometryError, ShapeError
from ..geometry.rbf import RBFInterpolant, fit_rbf

__all__ = ["rbf_warp"]


def rbf_warp(source_positions, target_positions, *, kernel: str = "linear") -> RBFInterpolant:
    """A smooth map of 3D space taking ``source_positions (N, 3)`` onto ``target_positions (N, 3)``.

    ``f(x) = sum_i w_i phi(|x - s_i|) + A x + b`` with phi(r) = r (the biharmonic kernel
    in 3D) and a linear polynomial, as in Seol et al. 2012 sec. 3.2; the result is
    callable on ``(P, 3)`` points. N >= 4 landmarks not all in one plane give the full
    affine part (otherwise only a translation is kept).
    """
    src = np.asarray(source_positions, dtype=np.float64)
    tgt = np.asarray(target_positions, dtype=np.float64)
    if src.ndim != 2 or src.shape[1] != 3 or src.shape != tgt.shape:
        raise ShapeError(f"rbf_warp: source and target positions must both be (N, 3), got {src.shape} and {tgt.shape}")
    if len(src) == 0:
        raise DegenerateGeometryError("rbf_warp: at least one landmark pair is needed")
    return fit_rbf(src, tgt, kernel=kernel, polynomial=True)
