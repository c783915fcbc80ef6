"""Large-scale editing of a coating result (Xu et al. 2014, sec. 4.3, eq. 12-15).

The target smooth frames are ``T~_t = c + sum_i w_ti (b'_i - c)``. An edit solves

    min  lambda_b E_b(b') + lambda_w E_w(w') + lambda_c E_c(b', w')        (eq. 12)

E_b  = sum_i |A (b'_i - b0_i)|^2, the deformation-transfer error of the bases. For the
       transferred bases ``b0`` (the minimisers of eq. 9) this equals eq. 9 up to a
       constant; measuring it from the *current* bases makes successive edits add up
       instead of undoing each other.
E_w  = sum_t |d(w'_t) - d(w_t)|_G^2 over the window and its two edges (eq. 13): the
       weight velocities keep the source's; the change is zero just outside the window
       (anchors; a virtual frame past a sequence end), so frames outside keep their
       weights and the change dies out within the window. The velocities are measured in
       the metric ``G = B^T B / (V h^2)`` of the bases ``B`` (``h`` the mean edge length,
       plus a 1e-6 ridge): ``|d w|_G`` is the RMS velocity of the smooth target mesh, in
       edge lengths. In the paper's plain weight metric a point edit is met by the
       smallest *weight* change, which, when the bases hardly move the edited vertex in
       the asked direction, is a large change of the whole face (measured on ICT: 17 cm at
       frames far from a 0.3 cm edit); in ``G`` it is the smallest change of the face.
E_c  = point (eq. 14), distance (eq. 15) and fixed-point residuals at the edited
       frames, divided by the squared mean edge length so ``lambda_c`` does not depend
       on the mesh resolution or units.

by alternating (as in the paper) (ii) the weights with the bases fixed: with velocity
matching the optimal change is piecewise linear in time between the edited frames and
the window's anchors, so only the weights of the edited frames are unknown (NNLS); where
the interpolated weights would cross zero, the frame of the deepest crossing becomes a
knot too, until every frame's weights are non-negative (:func:`solve_weights`; the knots'
bounded problem by an interior point method over its band); and (i)
the bases with the weights fixed: a linear solve, done exactly with the factorized
deformation-transfer normal matrix ``N`` and the Woodbury identity (one solve per
constrained vertex, whatever the number of frames or bases). The loop stops when the
objective changes by less than 5% (the paper's rule). The paper starts with the bases;
we start with the weights: with the constraints weighted high, the first block alone
meets them and the alternation stops there, so starting with the bases gives "bases"
mode, whose change reaches every frame using the changed bases (a 0.3 cm point edit
moved frames seconds away by as much as the edit); starting with the weights, which
change only inside the window, leaves the bases only what the weights cannot do.

``mode`` "bases" fixes the weights (edit spreads to similar expressions everywhere),
"weights" fixes the bases (only frames inside the window change). The default window is
``edit_window`` seconds either side of the edited frames (the retargeter's parameter).

Translation: ``N`` does not see translations, so the basis change is kept with zero
(stable-vertex weighted) mean per connected component: constraints are met by
deforming the bases, never by sliding them.
"""

from __future__ import annotations

import time
from dataclasses import dataclass

import numpy as np

from faceretarget.errors import ConfigError, IndexRangeError, InputError, NonFiniteError, ShapeError
from faceretarget.geometry.banded_qp import nonneg_qp_block_tridiagonal

from .alignment import to_local
from .bases import nnls_rows

__all__ = [
    "Constraint",
    "parse_constraints",
    "apply_large_scale",
    "solve_bases",
    "solve_weights",
    "velocity_metric",
]

_MODES = ("both", "bases", "weights")
#: Sweeps (weights, then bases) of the alternation at most, and the relative change of the
#: objective by one step of it at which it stops (the paper's 5%; a step is a half sweep: the
#: second sweep of a whole-shot edit moved the objective by 9e-5 of it and cost 0.6 s).
_MAX_ITER = 10
_REL_STOP = 0.05
#: Rounds of correcting the smooth targets for the change of the detail offsets, and the
#: miss (relative to the requested move) at which they stop.
_MAX_OUTER = 3
_OUTER_TOL = 0.01
#: Rounds of adding knots where the interpolated weights would cross zero (:func:`solve_weights`).
MAX_KNOT_ROUNDS = 64
#: Beyond this fraction of the window's frames as knots, or after this many rounds, the next
#: round takes every frame (the full problem, solved once) instead of growing the knots round
#: by round: a whole-shot edit of 1,300 frames went through 64 rounds of 200-9,000 variables a
#: weight step (knots grow by about three per offending segment a round).
KNOTS_FULL_FRACTION = 0.25
KNOT_ROUNDS_BEFORE_FULL = 4


@dataclass(frozen=True)
class Constraint:
    """One linear constraint on the smooth target, per coordinate.

    ``sum_v coeffs[v] * T~_t[vertices[v]] = value`` (value a 3-vector, local coordinates).
    ``goal``: what the same combination of the *output* vertices ``target_vertices``
    (target topology, local coordinates) should be; the value is corrected towards it
    when the edit changes the detail offsets (:func:`apply_large_scale`).
    """

    frame: int
    vertices: np.ndarray
    coeffs: np.ndarray
    value: np.ndarray
    target_vertices: np.ndarray | None = None
    goal: np.ndarray | None = None


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
        raise ShapeError(
            f"coating.edit: {what} position must be 3 numbers (x, y, z), got shape {arr.shape}"
        )
    if not np.isfinite(arr).all():
        raise NonFiniteError(f"coating.edit: {what} position {arr.tolist()} is not finite")
    return arr


def parse_constraints(track, animation, smooth_at, *, points, distances, fixed) -> list[Constraint]:
    """Turn user constraints on output vertices (world) into constraints on ``T~`` (the
    transfer's coordinates: head motion removed, centred on the target, :class:`~.alignment.Placement`).

    ``smooth_at(frame) -> (V, 3)`` gives the current smooth target frame. The detail offset
    of each vertex (final minus smooth) is held fixed, so a final position ``p`` asks the
    smooth mesh for ``p - offset``.
    """
    n_frames = track.n_frames
    n_target = animation.n_vertices
    cache: dict[int, tuple[np.ndarray, np.ndarray]] = {}

    def frame_data(t):
        if t not in cache:  # only the edited frames are read (a lazy result stays lazy)
            world = np.asarray(animation.frames([t]), dtype=np.float64)
            local = track.placement.to_model(to_local(track.motion[t : t + 1], world)[0])
            cache[t] = (local, smooth_at(t))
        return cache[t]

    out: list[Constraint] = []
    for item in points or ():
        try:
            t, v, p = item
        except (TypeError, ValueError):
            raise ShapeError(
                f"coating.edit: each point constraint is (frame, vertex, (x, y, z)), got {item!r}"
            ) from None
        t = _frame(t, n_frames, "point constraint")
        v = _vertex(v, n_target, "point constraint")
        p = _point(p, "point constraint")
        local, smooth = frame_data(t)
        c = int(track.target_vertex[v])
        p_local = track.placement.to_model(to_local(track.motion[t : t + 1], p[None, None])[0, 0])
        offset = local[v] - smooth[c]
        out.append(
            Constraint(t, np.array([c]), np.array([1.0]), p_local - offset, np.array([v]), p_local)
        )
    for item in distances or ():
        try:
            t, a, b, dist = item
        except (TypeError, ValueError):
            raise ShapeError(
                f"coating.edit: each distance constraint is (frame, vertex_a, vertex_b, distance), got {item!r}"
            ) from None
        t = _frame(t, n_frames, "distance constraint")
        a = _vertex(a, n_target, "distance constraint")
        b = _vertex(b, n_target, "distance constraint")
        if a == b:
            raise InputError(
                f"coating.edit: a distance constraint needs two different vertices, got {a} twice"
            )
        dist = float(dist)
        if not np.isfinite(dist) or dist < 0:
            raise NonFiniteError(
                f"coating.edit: distance must be a finite number >= 0, got {dist!r}"
            )
        local, smooth = frame_data(t)
        direction = local[a] - local[b]
        norm = np.linalg.norm(direction)
        if norm <= 0:
            raise InputError(
                f"coating.edit: vertices {a} and {b} coincide at frame {t}; a distance constraint needs a direction"
            )
        ca, cb = int(track.target_vertex[a]), int(track.target_vertex[b])
        offset = (local[a] - smooth[ca]) - (local[b] - smooth[cb])
        out.append(
            Constraint(
                t,
                np.array([ca, cb]),
                np.array([1.0, -1.0]),
                dist * direction / norm - offset,
                np.array([a, b]),
                dist * direction / norm,
            )
        )
    for item in fixed or ():
        try:
            t, ids = item
        except (TypeError, ValueError):
            raise ShapeError(
                f"coating.edit: each fixed constraint is (frame, vertex_ids), got {item!r}"
            ) from None
        t = _frame(t, n_frames, "fixed constraint")
        ids = np.atleast_1d(np.asarray(ids))
        local, smooth = frame_data(t)
        for v in ids.tolist():
            v = _vertex(v, n_target, "fixed constraint")
            c = int(track.target_vertex[v])
            out.append(
                Constraint(
                    t,
                    np.array([c]),
                    np.array([1.0]),
                    smooth[c].copy(),
                    np.array([v]),
                    local[v].copy(),
                )
            )
    return out


def _achieved(track, constraints) -> np.ndarray:
    """(R, 3) the output-vertex combinations of the constraints on ``track`` (local coordinates)."""
    frames = sorted({c.frame for c in constraints})
    world = track.world_frames(frames)
    local = {
        t: track.placement.to_model(to_local(track.motion[t : t + 1], world[i : i + 1])[0])
        for i, t in enumerate(frames)
    }
    return np.stack([c.coeffs @ local[c.frame][c.target_vertices] for c in constraints])


def _functional(con: Constraint, n_vertices: int) -> np.ndarray:
    f = np.zeros(n_vertices)
    np.add.at(f, con.vertices, con.coeffs)
    return f


def _value(
    con: Constraint, bases: np.ndarray, center: np.ndarray, weights: np.ndarray
) -> np.ndarray:
    """Current value of the constraint's left side on the smooth frame of ``weights``."""
    pts = center + np.einsum("k,kvd->vd", weights, bases[:, con.vertices] - center)
    return con.coeffs @ pts


def _basis_coefficients(bases0, center, weights, constraints, mu, lambda_b, gram):
    """Woodbury coefficients of step (i): the basis change is ``sum_r z_r coef[r]`` with
    ``coef : (R, K, 3)``; ``bases0`` only needs the constraints' vertices. Returns
    ``(coef, E_b)``."""
    w = np.stack([weights[c.frame] for c in constraints])  # (R, K)
    resid = np.stack(
        [c.value - _value(c, bases0, center, weights[c.frame]) for c in constraints]
    )  # (R, 3)
    s = (w @ w.T) * gram  # (R, R)
    y = np.linalg.solve(lambda_b * np.eye(len(constraints)) + mu * s, mu * resid)  # (R, 3)
    return w[:, :, None] * y[:, None, :], float(np.einsum("rd,rs,sd->", y, s, y))


def _apply_change(bases0, z, coef):
    """``bases0 + sum_r z_r coef[r]`` -> ``(K, n, 3)`` for ``z : (n, R)``."""
    k = coef.shape[1]
    delta = (z @ coef.reshape(coef.shape[0], -1)).reshape(z.shape[0], k, 3)
    out = np.empty_like(bases0)  # in the layout of bases0: its (K, 3n) rows stay a view
    return np.add(bases0, np.transpose(delta, (1, 0, 2)), out=out)


def solve_bases(bases0, center, weights, constraints, mu, lambda_b, influence):
    """Step (i): bases minimising ``lambda_b sum |A (b - b0)|^2 + mu E_c`` with weights fixed.

    influence : :class:`Influence` of the constraints (the Woodbury columns).
    Returns ``(bases, E_b)``.
    """
    coef, energy = _basis_coefficients(
        bases0, center, weights, constraints, mu, lambda_b, influence.gram
    )
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
        dt.factor.solve_rows(self.functionals.T, dt.free, z)
        means = np.stack(
            [
                np.bincount(labels, weights=g * z[:, r], minlength=dt.n_components)
                for r in range(z.shape[1])
            ],
            axis=1,
        )
        self.z = z - means[labels]  # apply P: zero gauge-weighted mean per component
        self.gram = self.functionals @ self.z  # (R, R) l_r^T P N^-1 P^T l_s


def velocity_metric(bases, center, edge_len: float) -> np.ndarray:
    """(K, K) metric ``G = B^T B / (V h^2)`` (+ a 1e-6 relative ridge) of the bases ``(K, V, 3)``."""
    b = np.asarray(bases, dtype=np.float64)
    k, n = b.shape[0], b.shape[1]
    flat = (b - center).reshape(k, -1)  # in the bases' layout: a view for the retarget's
    gram = (flat @ flat.T) / (n * float(edge_len) ** 2)
    return gram + 1e-6 * max(float(np.trace(gram)) / gram.shape[0], np.finfo(float).tiny) * np.eye(
        gram.shape[0]
    )


def solve_weights(bases, center, weights, constraints, window, mu, lambda_w, metric=None):
    """Step (ii): weights minimising ``lambda_w E_w + mu E_c`` with bases fixed, ``w >= 0``.

    ``E_w`` sums the squared velocity change, in ``metric (K, K)`` (default: the identity),
    over the window and its two edges: the change is zero at the frames just outside
    ``window = (w0, w1)`` (virtual frames ``-1`` or ``F`` at the sequence ends), so it is
    unique and dies out within the window.

    Without bounds the optimal change is linear in time between the edited frames (knots)
    and the anchors, so only the knots' weights are unknown (NNLS on them). Where the
    interpolated weights would cross zero, the exact bounded solution bends: on each
    offending segment, the first crossing seen from either end and the deepest one become
    knots (their weights NNLS-bound too) and the knots are solved again, until every frame's weights are
    non-negative (at worst every frame is a knot: the full problem; in practice a basis
    that must fade out does so at its first zero, a few knots). After ``MAX_KNOT_ROUNDS``
    rounds the remaining crossings are removed by shrinking the change at those frames
    (never by clipping single weights). Clipping the interpolant at zero
    instead breaks the balance of the weights: a knot that trades some bases for others (a
    small change of the face there) becomes, where the traded-away bases are already zero,
    the addition of the others alone (measured on ICT: far frames scaled by 1.7, 13 cm).

    Returns ``(new weights (F, K), E_w)``.
    """
    n_frames, k = weights.shape
    w0, w1 = window
    edited = sorted({c.frame for c in constraints if w0 <= c.frame <= w1})
    if not edited:
        return weights.copy(), 0.0
    g = np.eye(k) if metric is None else np.asarray(metric, dtype=np.float64)
    w = np.asarray(weights, dtype=np.float64)
    frames = np.arange(w0, w1 + 1)
    knots = list(edited)
    scale = max(float(np.abs(w[w0 : w1 + 1]).max()), 1.0)
    for round_ in range(MAX_KNOT_ROUNDS):
        delta_knots = _knot_change(bases, center, w, constraints, knots, (w0, w1), mu, lambda_w, g)
        xs_a = np.asarray([w0 - 1] + knots + [w1 + 1], dtype=np.float64)
        ys_a = np.concatenate([np.zeros((1, k)), delta_knots, np.zeros((1, k))])
        delta = np.stack([np.interp(frames, xs_a, ys_a[:, i]) for i in range(k)], axis=1)
        low = (w[w0 : w1 + 1] + delta).min(axis=1)
        bad = low < -1e-12 * scale
        if not bad.any():
            break
        segment = np.searchsorted(xs_a, frames)  # frames between xs[s-1] and xs[s]
        extra = set()
        for seg in np.unique(segment[bad]):
            inside = np.flatnonzero(bad & (segment == seg))
            extra.update(
                int(frames[i]) for i in (inside[0], inside[-1], inside[np.argmin(low[inside])])
            )
        knots = sorted(set(knots) | extra)
        if (
            len(knots) > KNOTS_FULL_FRACTION * len(frames) or round_ + 1 >= KNOT_ROUNDS_BEFORE_FULL
        ):  # many crossings: the full problem
            knots = [int(f) for f in frames]
    new = w[w0 : w1 + 1] + delta
    if (
        new < -1e-12 * scale
    ).any():  # still crossing: shrink the change where it would (the face change only shrinks)
        neg = delta < 0
        room = np.where(neg, w[w0 : w1 + 1] / np.where(neg, -delta, 1.0), np.inf).min(axis=1)
        delta = delta * np.clip(room, 0.0, 1.0)[:, None]
        new = w[w0 : w1 + 1] + delta
    out = w.copy()
    out[w0 : w1 + 1] = np.maximum(new, 0.0)
    padded = np.concatenate([np.zeros((1, k)), delta, np.zeros((1, k))])
    velocity = np.diff(padded, axis=0)
    return out, float(lambda_w * np.einsum("tk,kl,tl->", velocity, g, velocity))


def _knot_change(
    bases, center, weights, constraints, knots, window, mu, lambda_w, metric
) -> np.ndarray:
    """(n, K) weight changes at ``knots`` minimising ``lambda_w E_w + mu E_c`` for a change
    linear in time between knots and the anchors, with the knots' new weights non-negative."""
    w0, w1 = window
    k = weights.shape[1]
    n = len(knots)
    x = np.asarray(knots, dtype=np.float64)
    gap = 1.0 / np.diff(
        np.concatenate([[w0 - 1.0], x, [w1 + 1.0]])
    )  # anchors: zero change past both ends
    # lambda_w (L kron G) with L the knots' weighted path Laplacian: blocks on and above the diagonal
    diagonal = lambda_w * (gap[:-1] + gap[1:])[:, None, None] * metric
    upper = -lambda_w * gap[1:-1, None, None] * metric
    target = weights[knots]
    lap_target = (gap[:-1] + gap[1:])[:, None] * target
    lap_target[:-1] -= gap[1:-1, None] * target[1:]
    lap_target[1:] -= gap[1:-1, None] * target[:-1]
    rhs = lambda_w * lap_target @ metric  # (L kron G) vec(target); G symmetric
    index = {t: j for j, t in enumerate(knots)}
    for c in constraints:
        if c.frame not in index:
            continue
        j = index[c.frame]
        a = np.einsum("v,kvd->kd", c.coeffs, bases[:, c.vertices] - center)  # (K, 3)
        const = center * c.coeffs.sum()
        diagonal[j] += mu * a @ a.T
        rhs[j] += mu * a @ (c.value - const)
    if n == 1:
        y = nnls_rows(diagonal[0], rhs)[0][None]
    else:
        y = _nnls_band(diagonal, upper, rhs.ravel(), np.maximum(target, 0.0).ravel())
        y = y.reshape(n, k)
    return y - weights[knots]


def _nnls_band(diagonal, upper, rhs, start) -> np.ndarray:
    """``argmin 1/2 x^T H x - rhs . x`` s.t. ``x >= 0`` for the knots' block-tridiagonal ``H``
    (``diagonal (n, K, K)``, ``upper (n - 1, K, K)``): a primal-dual interior point method
    (:func:`faceretarget.geometry.banded_qp.nonneg_qp_block_tridiagonal`), 15-25 Cholesky
    steps whatever the conditioning (by blocks for large problems, by the band below). An
    active-set method cycles here (the metric couples the bases: ``H`` is not an M-matrix)
    and ADMM stalls (condition number ~1e13): the 3,640-variable full problem of a
    whole-shot edit (130 frames x 28 bases) took 3.1-3.7 s by ADMM, 5,000 iterations
    without reaching the optimum, and takes 60 ms this way, with a lower objective."""
    return nonneg_qp_block_tridiagonal(diagonal, upper, rhs, start)[0]


def _settled(history) -> bool:
    """The alternation stops when a step (weights or bases) changes the objective by less
    than ``_REL_STOP`` of it."""
    return len(history) > 1 and abs(history[-2] - history[-1]) <= _REL_STOP * max(
        abs(history[-2]), 1e-300
    )


def _constraint_energy(bases, center, weights, constraints, mu):
    return float(
        mu
        * sum(
            np.sum((c.value - _value(c, bases, center, weights[c.frame])) ** 2) for c in constraints
        )
    )


def apply_large_scale(
    retargeter, track, animation, *, points, distances, fixed, window, mode, lambdas
):
    """Solve a large-scale edit; returns ``(new track, changed frame ids, diagnostics)``."""
    if mode not in _MODES:
        raise ConfigError(f"coating.edit: mode must be one of {_MODES}, got {mode!r}")
    lambda_b, lambda_w, lambda_c = (float(x) for x in lambdas)
    for name, val in (("lambda_b", lambda_b), ("lambda_w", lambda_w), ("lambda_c", lambda_c)):
        if not np.isfinite(val) or val <= 0:
            raise ConfigError(f"coating.edit: {name} must be a positive number, got {val!r}")
    n_frames = track.n_frames
    if window is not None:
        try:
            w0, w1 = (int(x) for x in window)
        except (TypeError, ValueError):
            raise ShapeError(
                f"coating.edit: window must be (first, last) frames, got {window!r}"
            ) from None
        if not 0 <= w0 <= w1 < n_frames:
            raise IndexRangeError(
                f"coating.edit: window {window} must satisfy 0 <= first <= last < {n_frames}"
            )
    model = track.model
    center = model.target_center

    def smooth_at(t):
        return model.smooth_target(track.weights[t : t + 1], track.bases)[0]

    start = time.perf_counter()
    constraints = parse_constraints(
        track, animation, smooth_at, points=points, distances=distances, fixed=fixed
    )
    if not constraints:
        raise InputError("coating.edit: the constraints are empty")
    if window is None:  # edit_window seconds either side of the edited frames
        half = int(round(float(retargeter.edit_window) * float(animation.fps or 30.0)))
        frames = [c.frame for c in constraints]
        w0, w1 = max(0, min(frames) - half), min(n_frames - 1, max(frames) + half)
    if mode == "weights" and not any(w0 <= c.frame <= w1 for c in constraints):
        raise InputError(
            f"coating.edit: mode 'weights' changes only frames in the window {w0}..{w1}, but no constraint lies there"
        )
    dt = model.transfer
    edges = model.triangles
    ref = model.target.smooth_reference
    edge_len = np.mean(np.linalg.norm(ref[edges[:, [1, 2, 0]]] - ref[edges], axis=-1))
    mu = lambda_c / edge_len**2
    bases0 = np.asarray(track.bases, dtype=np.float64)
    metric = velocity_metric(bases0, center, edge_len) if mode != "bases" else None
    # iterate on the constrained vertices only; the full bases are formed once at the end
    used = np.unique(np.concatenate([c.vertices for c in constraints]))
    sub0 = bases0[:, used]
    influence = Influence(dt, constraints) if mode != "weights" else None
    goals = np.stack([c.goal for c in constraints])
    # the move asked of the output vertices: each constraint's value is its goal less the
    # detail offset (parse_constraints), so this is the smooth mesh's residual (no synthesis)
    requested = max(
        float(np.abs(c.value - _value(c, bases0, center, track.weights[c.frame])).max())
        for c in constraints
    )
    best = None
    for _ in range(_MAX_OUTER):
        local = [
            Constraint(c.frame, np.searchsorted(used, c.vertices), c.coeffs, c.value)
            for c in constraints
        ]
        weights = np.asarray(track.weights, dtype=np.float64).copy()
        sub = sub0
        coef = None
        energy_b = energy_w = 0.0
        history = []  # the objective after each step of the alternation
        iterations = 0
        for iterations in range(1, _MAX_ITER + 1):  # noqa: B007 (the count is read after the loop)
            if mode != "bases":
                weights, energy_w = solve_weights(
                    sub, center, track.weights, local, (w0, w1), mu, lambda_w, metric
                )
                if mode == "both":
                    history.append(
                        lambda_b * energy_b
                        + energy_w
                        + _constraint_energy(sub, center, weights, local, mu)
                    )
                    if _settled(history):
                        break
            if mode != "weights":
                coef, energy_b = _basis_coefficients(
                    sub0, center, weights, local, mu, lambda_b, influence.gram
                )
                sub = _apply_change(sub0, influence.z[used], coef)
            history.append(
                lambda_b * energy_b + energy_w + _constraint_energy(sub, center, weights, local, mu)
            )
            if mode != "both" or _settled(history):
                break
        bases = bases0 if coef is None else _apply_change(bases0, influence.z, coef)
        # the output vertices are the smooth mesh plus a detail offset that turns with the
        # smooth mesh's frames: measure where they landed and correct the smooth targets
        miss = goals - _achieved(track.replace(bases=bases, weights=weights), constraints)
        size = float(np.abs(miss).max())
        if (
            best is not None and size >= best[0]
        ):  # no better (e.g. out of the weights' reach): keep the best
            size, bases, weights, coef, local, history, iterations = best
            break
        best = (size, bases, weights, coef, local, history, iterations)
        if size <= _OUTER_TOL * requested:
            break
        constraints = [
            Constraint(c.frame, c.vertices, c.coeffs, c.value + m, c.target_vertices, c.goal)
            for c, m in zip(constraints, miss)
        ]
    sub = bases[:, used]
    solve_s = time.perf_counter() - start
    changed_w = np.flatnonzero(np.any(weights != track.weights, axis=1))
    if coef is None:
        uses = np.zeros(0, dtype=np.int64)
    else:  # frame t's smooth mesh changes by sum_r z_r (w_t . coef_r): skip the frames it misses
        reach = np.abs(np.einsum("tk,rkd->trd", weights, coef)).max(axis=(1, 2))
        uses = np.flatnonzero(reach > 1e-12 * max(float(reach.max()), np.finfo(float).tiny))
    changed = np.union1d(changed_w, uses).astype(np.int64)
    residual = max(
        float(np.linalg.norm(c.value - _value(c, sub, center, weights[c.frame]))) for c in local
    )
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
