"""Brute-force references for ``faceretarget.geometry.head_motion``.

Written from the objective, one frame and one marker at a time; nothing is shared with the
vectorized estimator (no gains, no moments, no Schur complement). Small sizes only.
"""

from __future__ import annotations

import numpy as np
import scipy.optimize
from scipy.spatial.transform import Rotation


def face_size(reference):
    ref = np.asarray(reference, float)
    return float(np.sqrt(np.mean(np.sum((ref - ref.mean(axis=0)) ** 2, axis=1))))


def rigidity_weights(reference, basis, eps):
    """``1 / (eps^2 + m_i^2)`` marker by marker, ``m_i`` the RMS displacement over the shapes; mean 1."""
    ref = np.asarray(reference, float)
    b = np.asarray(basis, float)
    size = face_size(ref)
    w = np.empty(len(ref))
    for i in range(len(ref)):
        rows = b[3 * i : 3 * i + 3]  # (3, M)
        motion2 = np.mean([rows[:, j] @ rows[:, j] for j in range(b.shape[1])])
        w[i] = 1.0 / ((eps * size) ** 2 + motion2)
    return w / w.mean()


def _ridge(basis, w, ridge_eps):
    """Default ridge: ``ridge_eps`` times the mean diagonal of ``B^T W B`` (all markers)."""
    m = basis.shape[1]
    gram = sum(w[i] * basis[3 * i : 3 * i + 3].T @ basis[3 * i : 3 * i + 3] for i in range(len(w)))
    return ridge_eps * np.trace(gram) / m


def expression_residual(y, basis, w, visible, ridge):
    """``min_c sum_i w_i |y_i - B_i c|^2 + ridge |c|^2`` for one frame, by a stacked lstsq
    (the ridge as extra rows); returns the weighted residual without the ridge term."""
    rows, rhs = [], []
    for i in np.flatnonzero(visible):
        rows.append(np.sqrt(w[i]) * basis[3 * i : 3 * i + 3])
        rhs.append(np.sqrt(w[i]) * y[i])
    m = basis.shape[1]
    a = np.concatenate(rows + [np.sqrt(ridge) * np.eye(m)])
    b = np.concatenate(rhs + [np.zeros(m)])
    c = np.linalg.lstsq(a, b, rcond=None)[0]
    total = 0.0
    for i in np.flatnonzero(visible):
        r = y[i] - basis[3 * i : 3 * i + 3] @ c
        total += w[i] * (r @ r)
    return total


def fit_frame(reference, frame, basis, w, ridge, start=None):
    """``min over R, t, c of sum_i w_i |R^T (x_i - t) - n_i - B_i c|^2 + ridge |c|^2`` for one
    frame (NaN rows missing), by ``scipy.optimize.least_squares`` from ``start`` (4x4) or the
    weighted Kabsch fit. Returns the (4, 4) transform."""
    ref = np.asarray(reference, float)
    x = np.asarray(frame, float)
    visible = ~np.isnan(x).any(axis=1)
    m = basis.shape[1]
    if start is None:
        start = kabsch(ref[visible], x[visible], w[visible])
    size = face_size(ref)

    def residual(p):
        rot = Rotation.from_rotvec(p[:3]).as_matrix()
        t = p[3:6] * size
        c = p[6:]
        out = []
        for i in np.flatnonzero(visible):
            local = rot.T @ (x[i] - t)
            out.append(np.sqrt(w[i]) * (local - ref[i] - basis[3 * i : 3 * i + 3] @ c))
        out.append(np.sqrt(ridge) * c)
        return np.concatenate(out)

    p0 = np.concatenate(
        [Rotation.from_matrix(start[:3, :3]).as_rotvec(), start[:3, 3] / size, np.zeros(m)]
    )
    sol = scipy.optimize.least_squares(
        residual, p0, xtol=1e-15, ftol=1e-15, gtol=1e-15, max_nfev=2000, method="lm"
    )
    out = np.eye(4)
    out[:3, :3] = Rotation.from_rotvec(sol.x[:3]).as_matrix()
    out[:3, 3] = sol.x[3:6] * size
    return out


def balance_frame(reference, frame, basis, w, ridge, start=None):
    """The estimator's defining equations for one frame, solved by ``scipy.optimize.root``:
    with ``r_i`` the residual of the best (ridge) expression fit to the local markers
    ``R^T (x_i - t) - n_i``, zero weighted net force ``sum_i w_i r_i`` and zero weighted net
    torque ``sum_i w_i (n_i - c) x r_i`` about the weighted centre ``c``, lever arms at the
    neutral. (The least-squares optimum, :func:`fit_frame`, takes the lever arms at the
    local markers instead; the two agree where the expressions explain the markers.)"""
    ref = np.asarray(reference, float)
    x = np.asarray(frame, float)
    visible = ~np.isnan(x).any(axis=1)
    if start is None:
        start = kabsch(ref[visible], x[visible], w[visible])
    size = face_size(ref)
    centre = (w @ ref) / w.sum()

    def equations(p):
        rot = Rotation.from_rotvec(p[:3]).as_matrix()
        t = p[3:] * size
        ids = np.flatnonzero(visible)
        y = np.zeros_like(x)
        for i in ids:
            y[i] = rot.T @ (x[i] - t) - ref[i]
        rows = [np.sqrt(w[i]) * basis[3 * i : 3 * i + 3] for i in ids]
        rhs = [np.sqrt(w[i]) * y[i] for i in ids]
        m = basis.shape[1]
        c = np.linalg.lstsq(
            np.concatenate(rows + [np.sqrt(ridge) * np.eye(m)]),
            np.concatenate(rhs + [np.zeros(m)]),
            rcond=None,
        )[0]
        force, torque = np.zeros(3), np.zeros(3)
        for i in ids:
            r = y[i] - basis[3 * i : 3 * i + 3] @ c
            force += w[i] * r
            torque += w[i] * np.cross(ref[i] - centre, r)
        return np.concatenate([torque / size, force]) / w[visible].sum()

    p0 = np.concatenate([Rotation.from_matrix(start[:3, :3]).as_rotvec(), start[:3, 3] / size])
    sol = scipy.optimize.root(equations, p0, method="hybr", options={"xtol": 1e-14})
    out = np.eye(4)
    out[:3, :3] = Rotation.from_rotvec(sol.x[:3]).as_matrix()
    out[:3, 3] = sol.x[3:] * size
    return out


def kabsch(reference, frame, w):
    """Weighted Kabsch, one frame, no missing rows."""
    wn = w / w.sum()
    mu_r = wn @ reference
    mu_x = wn @ frame
    cov = sum(wn[i] * np.outer(frame[i] - mu_x, reference[i] - mu_r) for i in range(len(w)))
    u, _, vt = np.linalg.svd(cov)
    d = np.sign(np.linalg.det(u @ vt)) or 1.0
    rot = u @ np.diag([1.0, 1.0, d]) @ vt
    out = np.eye(4)
    out[:3, :3] = rot
    out[:3, 3] = mu_x - rot @ mu_r
    return out


def estimate(
    reference,
    markers,
    basis,
    *,
    eps,
    ridge_eps,
    floor_rel,
    window,
    starts=None,
    solve=balance_frame,
):
    """Per-frame fits (``solve``: :func:`balance_frame`, the estimator's equations, or
    :func:`fit_frame`, the least-squares optimum) and the exact gate statistic: the largest
    ``sum_f (c0_f - c1_f) / sum_f (c1_f + floor_f)`` over ``window`` consecutive frames
    (``c0``: expressions only at the identity, ``c1``: at the fitted motion). Returns
    ``(motion (F, 4, 4), evidence)``; ``starts`` (F, 4, 4) optional start transforms."""
    ref = np.asarray(reference, float)
    x = np.asarray(markers, float)
    b = np.asarray(basis, float)
    w = rigidity_weights(ref, b, eps)
    ridge = _ridge(b, w, ridge_eps)
    size = face_size(ref)
    motion = np.empty((len(x), 4, 4))
    gain, rest = np.zeros(len(x)), np.zeros(len(x))
    for f in range(len(x)):
        visible = ~np.isnan(x[f]).any(axis=1)
        motion[f] = solve(ref, x[f], b, w, ridge, None if starts is None else starts[f])
        rot, t = motion[f, :3, :3], motion[f, :3, 3]
        local = np.full_like(x[f], np.nan)
        for i in np.flatnonzero(visible):
            local[i] = rot.T @ (x[f, i] - t)
        c0 = expression_residual(x[f] - ref, b, w, visible, ridge)
        c1 = expression_residual(local - ref, b, w, visible, ridge)
        gain[f] = c0 - c1
        rest[f] = c1 + (floor_rel * size) ** 2 * 3 * w[visible].sum()
    span = min(window, len(x))
    best = max(
        gain[i : i + span].sum() / rest[i : i + span].sum() for i in range(len(x) - span + 1)
    )
    return motion, best
