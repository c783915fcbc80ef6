"""Radial basis function interpolation with a linear polynomial term.

``f(x) = sum_i w_i phi(|x - c_i|) + A x + b``, fitted so ``f(c_i) = y_i`` and the
weights are orthogonal to linear polynomials (the standard augmented system).

Kernels:
- ``"linear"``: phi(r) = r (biharmonic in 3D; Seol et al. 2012 sec. 3.2),
- ``"multiquadric"``: phi(r) = sqrt(r^2 + c^2) (Na & Jung 2004 Eq. 3),
- ``"gaussian"``: phi(r) = exp(-(r / c)^2),
- ``"thin_plate"``: phi(r) = r^2 log r.

Coincident centres: exact duplicates are merged (their values averaged), which is
the only consistent reading of an interpolation constraint given twice; a tiny
relative ridge (``config.RIDGE_EPS``) keeps near-coincident centres solvable.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import scipy.linalg

from .. import config
from ..errors import DegenerateGeometryError, ShapeError

KERNELS = ("linear", "multiquadric", "gaussian", "thin_plate")


def kernel_values(r: np.ndarray, kernel: str, c: float) -> np.ndarray:
    """phi(r) for distances ``r`` (any shape)."""
    if kernel == "linear":
        return r
    if kernel == "multiquadric":
        return np.sqrt(r * r + c * c)
    if kernel == "gaussian":
        return np.exp(-((r / c) ** 2))
    if kernel == "thin_plate":
        with np.errstate(divide="ignore", invalid="ignore"):
            out = r * r * np.log(r)
        return np.nan_to_num(out, nan=0.0)
    raise ShapeError(f"unknown RBF kernel {kernel!r}; choose one of {', '.join(KERNELS)}")


@dataclass(frozen=True)
class RBFInterpolant:
    """A fitted interpolant; call it on ``points (P, D)`` to get ``(P, K)`` values."""

    centers: np.ndarray  # (N, D)
    weights: np.ndarray  # (N, K)
    affine: np.ndarray  # (D + 1, K): rows for x_1..x_D, then the constant
    kernel: str
    c: float

    def __call__(self, points: np.ndarray) -> np.ndarray:
        p = np.asarray(points, dtype=np.float64)
        lead = p.shape[:-1]
        p = p.reshape(-1, p.shape[-1])
        r = _distances(p, self.centers)
        out = kernel_values(r, self.kernel, self.c) @ self.weights
        out += p @ self.affine[:-1] + self.affine[-1]
        return out.reshape(lead + (self.weights.shape[1],))


def _distances(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    d2 = np.einsum("ij,ij->i", a, a)[:, None] + np.einsum("ij,ij->i", b, b)[None] - 2.0 * a @ b.T
    return np.sqrt(np.maximum(d2, 0.0))


def fit_rbf(
    centers: np.ndarray,
    values: np.ndarray,
    *,
    kernel: str = "linear",
    c: float | None = None,
    polynomial: bool = True,
) -> RBFInterpolant:
    """Fit an RBF interpolant through ``values (N, K)`` at ``centers (N, D)``.

    ``c`` is the kernel shape parameter (default: the mean distance to the nearest
    other centre). ``polynomial`` adds the linear term (needs N >= D + 1 centres in
    general position; otherwise only the constant term is kept).
    """
    x = np.asarray(centers, dtype=np.float64)
    y = np.asarray(values, dtype=np.float64)
    if y.ndim == 1:
        y = y[:, None]
    if x.ndim != 2 or y.shape[0] != x.shape[0] or x.shape[0] == 0:
        raise ShapeError(
            f"fit_rbf: centers (N, D) and values (N, K) must agree, got {x.shape} and {y.shape}"
        )
    if not (np.isfinite(x).all() and np.isfinite(y).all()):
        raise DegenerateGeometryError("fit_rbf: centres and values must be finite")
    x, y = _merge_duplicates(x, y)
    n, dim = x.shape
    if c is None:
        if n > 1:
            d = _distances(x, x)
            np.fill_diagonal(d, np.inf)
            c = float(np.mean(d.min(axis=1)))
        else:
            c = 1.0
    if not (np.isfinite(c) and c > 0 and np.isfinite(1.0 / c)):
        raise DegenerateGeometryError(
            f"fit_rbf: the kernel width c={c!r} must be a positive, normal number"
        )
    phi = kernel_values(_distances(x, x), kernel, c)
    use_linear = polynomial and n > dim and np.linalg.matrix_rank(x - x.mean(axis=0)) == dim
    weights, affine = solve_system(
        x,
        y,
        phi,
        use_linear,
        "fit_rbf: the RBF system is singular ({}); check for coincident or collinear centres",
    )
    return RBFInterpolant(x, weights, affine, kernel, float(c))


def solve_system(
    x: np.ndarray, y: np.ndarray, phi: np.ndarray, use_linear: bool, message: str
) -> tuple[np.ndarray, np.ndarray]:
    """Weights (N, K) and affine part (D+1, K) of the RBF interpolant with kernel matrix
    ``phi`` (N, N) at centres ``x`` (N, D): the saddle-point system with the polynomial
    (linear + constant if ``use_linear``, else constant) and a ridge relative to the largest
    kernel value (so the fit does not depend on the length unit). ``message`` formats the
    error raised when the system is singular."""
    n, dim = x.shape
    poly = np.hstack([x, np.ones((n, 1))]) if use_linear else np.ones((n, 1))
    m = poly.shape[1]
    system = np.zeros((n + m, n + m))
    system[:n, :n] = phi
    system[:n, n:] = poly
    system[n:, :n] = poly.T
    rhs = np.zeros((n + m, y.shape[1]))
    rhs[:n] = y
    top = float(np.abs(phi).max()) if n > 1 else 0.0
    system[:n, :n] += config.RIDGE_EPS * (top if top > 0 else 1.0) * np.eye(n)
    try:
        sol = scipy.linalg.solve(system, rhs, assume_a="sym")
    except (np.linalg.LinAlgError, scipy.linalg.LinAlgError, ValueError) as exc:
        raise DegenerateGeometryError(message.format(exc)) from None
    affine = np.zeros((dim + 1, y.shape[1]))
    if use_linear:
        affine[:] = sol[n:]
    else:
        affine[-1] = sol[n]
    return sol[:n], affine


def _merge_duplicates(x: np.ndarray, y: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Merge centres closer than 1e-12 of the cloud's extent (their values averaged)."""
    extent = float(np.max(np.ptp(x, axis=0))) if len(x) > 1 else 0.0
    tol = extent * 1e-12 if extent > 0 and np.isfinite(extent) else 1.0
    keys = np.round((x - x.min(axis=0)) / tol)
    _, first, inverse, counts = np.unique(
        keys, axis=0, return_index=True, return_inverse=True, return_counts=True
    )
    if len(first) == len(x):
        return x, y
    inverse = inverse.ravel()
    merged = np.zeros((len(first), y.shape[1]))
    np.add.at(merged, inverse, y)
    return x[first], merged / counts[:, None]
