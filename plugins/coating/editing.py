"""Large-scale editing of a coating result (Xu et al. 2014, sec. 4.3, eq. 12-15).

The target smooth frames are ``T~_t = c + sum_i w_ti (b'_i - c)``. An edit solves

    min  lambda_b E_b(b') + lambda_w E_w(w') + lambda_c E_c(b', w')        (eq. 12)

E_b  = sum_i |A (b'_i - b0_i)|^2, the deformation-transfer error of the bases. For the
       transferred bases ``b0`` (the minimisers of eq. 9) this equals eq. 9 up to a
       constant; measuring it from the *current* bases makes successive edits add up
       instead of undoing each other.
E_w  = sum_t |d(w'_t) - d(w_t)|^2 over the window (eq. 13): the weight velocities
       keep the source's; frames outside the window keep their weights.
E_c  = point (eq. 14), distance (eq. 15) and fixed-point residuals at the edited
       frames, divided by the squared mean edge length so ``lambda_c`` does not depend
       on the mesh resolution or units.

by alternating (as in the paper) (i) the bases with the weights fixed: a linear solve,
done exactly with the factorized deformation-transfer normal matrix ``N`` and the
Woodbury identity (one solve per constrained vertex, whatever the number of frames or
bases), and (ii) the weights with the bases fixed: with velocity matching the optimal
change is piecewise linear in time between the edited frames and the window ends, so
only the weights of the edited frames are unknown; they are found by NNLS. Between
edited frames the interpolated weights are clipped at zero (the exact problem would
bend the interpolant where it meets the bound). The loop stops when the objective
changes by less than 5% (the paper's rule).

``mode`` "bases" fixes the weights (edit spreads to similar expressions everywhere),
"weights" fixes the bases (only frames inside the window change).

Translation: ``N`` does not see translations, so the basis change is kept with zero
(stable-vertex weighted) mean per connected component: constraints are met by
deforming the bases, never by sliding them.
"""
from __future__ import annotations

import time
from dataclasses import dataclass

import numpy as np

from faceretarget.errors import ConfigError, IndexRangeError, InputError, NonFiniteError, ShapeError

from .alignment import to_local
from .bases import nnls_rows

__all__ = ["Constraint", "parse_constraints", "apply_large_scale", "solve_bases", "solve_weights"]

_MODES = ("both", "bases", "weights")
_MAX_ITER = 10
_REL_STOP = 0.05


@dataclass(frozen=True)
class Constraint:
    """One linear constraint on the smooth target, per coordinate.

    ``sum_v coeffs[v] * T~_t[vertices[v]] = value`` (value a 3-vector, local coordinates).
    """

    frame: int
    vertices: np.ndarray
    coeffs: np.ndarray
    value: np.ndarray


def _index(value, upper, what, noun):
    """An integer ``frame`` / ``vertex`` id in ``0..upper-1``, or a typed error naming it."""
    if isinstance(value, bool) or not isinstance(value, (int, np.integer)):
        raise ShapeError(f"coating.edit: {what} {noun} must be an integer, got {value!r}")
    if not 0 <= int(value) < upper:
        raise IndexRangeError(f"coating.edit: {what} {noun} {value} is outside 0..{upper - 1}")
    return int(value)


def _frame(f, n_frames, what):
    return _index(f, n_frames, what, "frame")


def _vertex(v, n_vertices, what):
    return _index(v, n_vertices, what, "vertex")


def _point(p, what):
    arr = np.asarray(p, dtype=np.float64)
    if arr.shape != (3,):
        raise ShapeError(f"coating.edit: {what} position must be 3 numbers (x, y, z), got shape {arr.shape}")
    if not np.isfinite(arr).all():
        raise NonFiniteError(f"coating.edit: {what} position {arr.tolist()} is not finite")
    return arr


def parse_constraints(track, animation, smooth_at, *, points, distances, fixed) -> list[Constraint]:
    """Turn user constraints on output vertices (world) into constraints on ``T~`` (local).

    ``smooth_at(frame) -> (V, 3)`` gives the current smooth target frame. The detail offset
    of each vertex (final minus smooth) is held fixed, so a final position ``p`` asks the
    smooth mesh for ``p - offset``.
    """
    n_frames = track.n_frames
    world = animation.vertices
    n_target = world.shape[1]
    cache: dict[int, tuple[np.ndarray, np.ndarray]] = {}

    def frame_data(t):
        if t not in cache:
            local = to_local(track.motion[t : t + 1], np.asarray(world[t : t + 1], dtype=np.float64))[0]
            cache[t] = (local, smooth_at(t))
        return cache[t]

    out: list[Constraint] = []
    for item in points or ():
        try:
            t, v, p = item
        except (TypeError, ValueError):
            raise ShapeError(f"coating.edit: each point constraint is (frame, vertex, (x, y, z)), got {item!r}") from None
        t = _frame(t, n_frames, "point constraint")
        v = _vertex(v, n_target, "point constraint")
        p = _point(p, "point constraint")
        local, smooth = frame_data(t)
        c = int(track.target_vertex[v])
        p_local = to_local(track.motion[t : t + 1], p[None, None])[0, 0]
        offset = local[v] - smooth[c]
        out.append(Constraint(t, np.array([c]), np.array([1.0]), p_local - offset))
    for item in distances or ():
        try:
            t, a, b, dist = item
        except (TypeError, ValueError):
            raise ShapeError(f"coating.edit: each distance constraint is (frame, vertex_a, vertex_b, distance), got {item!r}") from None
        t = _frame(t, n_frames, "distance constraint")
        a = _vertex(a, n_target, "distance constraint")
        b = _vertex(b, n_target, "distance constraint")
        if a == b:
            raise InputError(f"coating.edit: a distance constraint needs two different vertices, got {a} twice")
        dist = float(dist)
        if not np.isfinite(dist) or dist < 0:
            raise NonFiniteError(f"coating.edit: distance must be a finite number >= 0, got {dist!r}")
        local, smooth = frame_data(t)
        direction = local[a] - local[b]
        norm = np.linalg.norm(direction)
        if norm <= 0:
            raise InputError(f"coating.edit: vertices {a} and {b} coincide at frame {t}; a distance constraint needs a direction")
        ca, cb = int(track.target_vertex[a]), int(track.target_vertex[b])
        offset = (local[a] - smooth[ca]) - (local[b] - smooth[cb])
        out.append(Constraint(t, np.array([ca, cb]), np.array([1.0, -1.0]), dist * direction / norm - offset))
    for item in fixed or ():
        try:
            t, ids = item
        except (TypeError, ValueError):
            raise ShapeError(f"coating.edit: each fixed constraint is (frame, vertex_ids), got {item!r}") from None
        t = _frame(t, n_frames, "fixed constraint")
        ids = np.atleast_1d(np.asarray(ids))
        _, smooth = frame_data(t)
        for v in ids.tolist():
            c = int(track.target_vertex[_vertex(v, n_target, "fixed constraint")])
            out.append(Constraint(t, np.array([c]), np.array([1.0]), smooth[c].copy()))
    return out


def _functional(con: Constraint, n_vertices: int) -> np.ndarray:
    f = np.zeros(n_vertices)
    np.add.at(f, con.vertices, con.coeffs)
    return f


def _value(con: Constraint, bases: np.ndarray, center: np.ndarray, weights: np.ndarray) -> np.ndarray:
    """Current value of the constraint's left side on the smooth frame of ``weights``."""
    pts = center + np.einsum("k,kvd->vd", weights, bases[:, con.vertices] - center)
    return con.coeffs @ pts


def _basis_coefficients(bases0, center, weights, constraints, mu, lambda_b, gram):
    """Woodbury coefficients of step (i): the basis change is ``sum_r z_r coef[r]`` with
    ``coef : (R, K, 3)``; ``bases0`` only needs the constraints' vertices. Returns
    ``(coef, E_b)``."""
    w = np.stack([weights[c.frame] for c in constraints])  # (R, K)
    resid = np.stack([c.value - _value(c, bases0, center, weights[c.frame]) for c in constraints])  # (R, 3)
    s = (w @ w.T) * gram  # (R, R)
    y = np.linalg.solve(lambda_b * np.eye(len(constraints)) + mu * s, mu * resid)  # (R, 3)
    return w[:, :, None] * y[:, None, :], float(np.einsum("rd,rs,sd->", y, s, y))


def _apply_change(bases0, z, coef):
    """``bases0 + sum_r z_r coef[r]`` -> ``(K, n, 3)`` for ``z : (n, R)``."""
    k = coef.shape[1]
    delta = (z @ coef.reshape(coef.shape[0], -1)).reshape(z.shape[0], k, 3)
    return bases0 + np.transpose(delta, (1, 0, 2))


def solve_bases(bases0, center, weights, constraints, mu, lambda_b, influence):
    """Step (i): bases minimising ``lambda_b sum |A (b - b0)|^2 + mu E_c`` with weights fixed.

    influence : :class:`Influence` of the constraints (the Woodbury columns).
    Returns ``(bases, E_b)``.
    """
    coef, energy = _basis_coefficients(bases0, center, weights, constraints, mu, lambda_b, influence.gram)
    return _apply_change(bases0, influence.z, coef), energy


class Influence:
    """``z_r = P N_ff^-1 P^T l_r`` for constraint functionals ``l_r`` (the Woodbury columns)."""

    def __init__(self, dt, constraints):
        n = dt.n_vertices
        g = dt.gauge_weights
        labels = dt.labels
        cols = []
        for con in constraints:
            f = _functional(con, n)
            # P^T l: subtract, per component, the functional's total times the gauge weights
            totals = np.bincount(labels, weights=f, minlength=dt.n_components)
            cols.append(f - g * totals[labels])
        self.functionals = np.stack(cols)  # (R, V)
        z = np.zeros((n, len(cols)))
        z[dt.free] = dt.factor.solve(self.functionals[:, dt.free].T)
        means = np.stack([np.bincount(labels, weights=g * z[:, r], minlength=dt.n_components) for r in range(z.shape[1])], axis=1)
        self.z = z - means[labels]  # apply P: zero gauge-weighted mean per component
        self.gram = self.functionals @ self.z  # (R, R) l_r^T P N^-1 P^T l_s


def solve_weights(bases, center, weights, constraints, window, mu, lambda_w):
    """Step (ii): weights minimising ``lambda_w E_w + mu E_c`` with bases fixed (NNLS at knots).

    Returns ``(new weights (F, K), E_w)``.
    """
    n_frames, k = weights.shape
    w0, w1 = window
    knots = sorted({c.frame for c in constraints if w0 <= c.frame <= w1})
    if not knots:
        return weights.copy(), 0.0
    n = len(knots)
    lap = np.zeros((n, n))
    for j in range(n - 1):
        g = 1.0 / (knots[j + 1] - knots[j])
        lap[j, j] += g
        lap[j + 1, j + 1] += g
        lap[j, j + 1] -= g
        lap[j + 1, j] -= g
    if w0 > 0:
        lap[0, 0] += 1.0 / (knots[0] - (w0 - 1))
    if w1 < n_frames - 1:
        lap[-1, -1] += 1.0 / ((w1 + 1) - knots[-1])
    gram = lambda_w * np.kron(lap, np.eye(k))
    rhs = gram @ weights[knots].ravel()
    index = {t: j for j, t in enumerate(knots)}
    for c in constraints:
        if c.frame not in index:
            continue
        j = index[c.frame]
        a = np.einsum("v,kvd->kd", c.coeffs, bases[:, c.vertices] - center)  # (K, 3)
        const = center * c.coeffs.sum()
        blk = slice(j * k, (j + 1) * k)
        gram[blk, blk] += mu * a @ a.T
        rhs[blk] += mu * a @ (c.value - const)
    y = nnls_rows(gram, rhs[None])[0].reshape(n, k)
    delta_knots = y - weights[knots]
    frames = np.arange(w0, w1 + 1)
    xs = list(knots)
    ys = list(delta_knots)
    if w0 > 0:
        xs.insert(0, w0 - 1)
        ys.insert(0, np.zeros(k))
    if w1 < n_frames - 1:
        xs.append(w1 + 1)
        ys.append(np.zeros(k))
    xs_a = np.asarray(xs, dtype=np.float64)
    ys_a = np.asarray(ys)
    delta = np.stack([np.interp(frames, xs_a, ys_a[:, i]) for i in range(k)], axis=1)
    out = weights.copy()
    out[w0 : w1 + 1] = np.maximum(weights[w0 : w1 + 1] + delta, 0.0)
    padded = [np.zeros((1, k))] * (w0 > 0) + [delta] + [np.zeros((1, k))] * (w1 < n_frames - 1)
    return out, float(lambda_w * np.sum(np.diff(np.concatenate(padded), axis=0) ** 2))


def _constraint_energy(bases, center, weights, constraints, mu):
    return float(mu * sum(np.sum((c.value - _value(c, bases, center, weights[c.frame])) ** 2) for c in constraints))


def apply_large_scale(retargeter, track, animation, *, points, distances, fixed, window, mode, lambdas):
    """Solve a large-scale edit; returns ``(new track, changed frame ids, diagnostics)``."""
    if mode not in _MODES:
        raise ConfigError(f"coating.edit: mode must be one of {_MODES}, got {mode!r}")
    lambda_b, lambda_w, lambda_c = (float(x) for x in lambdas)
    for name, val in (("lambda_b", lambda_b), ("lambda_w", lambda_w), ("lambda_c", lambda_c)):
        if not np.isfinite(val) or val <= 0:
            raise ConfigError(f"coating.edit: {name} must be a positive number, got {val!r}")
    n_frames = track.n_frames
    if window is None:
        window = (0, n_frames - 1)
    try:
        w0, w1 = (int(x) for x in window)
    except (TypeError, ValueError):
        raise ShapeError(f"coating.edit: window must be (first, last) frames, got {window!r}") from None
    if not 0 <= w0 <= w1 < n_frames:
        raise IndexRangeError(f"coating.edit: window {window} must satisfy 0 <= first <= last < {n_frames}")
    model = track.model
    center = model.target_center

    def smooth_at(t):
        return model.smooth_target(track.weights[t : t + 1], track.bases)[0]

    start = time.perf_counter()
    constraints = parse_constraints(track, animation, smooth_at, points=points, distances=distances, fixed=fixed)
    if not constraints:
        raise InputError("coating.edit: the constraints are empty")
    if mode == "weights" and not any(w0 <= c.frame <= w1 for c in constraints):
        raise InputError(f"coating.edit: mode 'weights' changes only frames in the window {w0}..{w1}, but no constraint lies there")
    dt = model.transfer
    edges = model.triangles
    ref = model.target.smooth_reference
    edge_len = np.mean(np.linalg.norm(ref[edges[:, [1, 2, 0]]] - ref[edges], axis=-1))
    mu = lambda_c / edge_len**2
    bases0 = np.asarray(track.bases, dtype=np.float64)
    weights = np.asarray(track.weights, dtype=np.float64).copy()
    # iterate on the constrained vertices only; the full bases are formed once at the end
    used = np.unique(np.concatenate([c.vertices for c in constraints]))
    local = [Constraint(c.frame, np.searchsorted(used, c.vertices), c.coeffs, c.value) for c in constraints]
    sub0 = bases0[:, used]
    sub = sub0
    influence = Influence(dt, constraints) if mode != "weights" else None
    coef = None
    energy_b = energy_w = 0.0
    history = []
    iterations = 0
    for iterations in range(1, _MAX_ITER + 1):
        if mode != "weights":
            coef, energy_b = _basis_coefficients(sub0, center, weights, local, mu, lambda_b, influence.gram)
            sub = _apply_change(sub0, influence.z[used], coef)
        if mode != "bases":
            weights, energy_w = solve_weights(sub, center, track.weights, local, (w0, w1), mu, lambda_w)
        total = lambda_b * energy_b + energy_w + _constraint_energy(sub, center, weights, local, mu)
        history.append(total)
        if mode != "both" or (len(history) > 1 and abs(history[-2] - total) <= _REL_STOP * max(abs(history[-2]), 1e-300)):
            break
    bases = bases0 if coef is None else _apply_change(bases0, influence.z, coef)
    solve_s = time.perf_counter() - start
    changed_w = np.flatnonzero(np.any(weights != track.weights, axis=1))
    moved = np.zeros(0, dtype=np.int64) if coef is None else np.flatnonzero(np.abs(coef).max(axis=(0, 2)) > 0)
    uses = np.flatnonzero(np.any(weights[:, moved] > 0, axis=1)) if moved.size else np.zeros(0, dtype=np.int64)
    changed = np.union1d(changed_w, uses).astype(np.int64)
    residual = max(float(np.linalg.norm(c.value - _value(c, sub, center, weights[c.frame]))) for c in local)
    diagnostics = {
        "kind": "large_scale",
        "mode": mode,
        "window": [w0, w1],
        "iterations": iterations,
        "objective": history,
        "constraints": len(constraints),
        "max_constraint_residual": residual,
        "solve_s": solve_s,
    }
    return track.replace(bases=bases, weights=weights), changed, diagnostics
