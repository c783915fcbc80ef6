"""numba kernel of :mod:`faceretarget.geometry.head_motion` (compiled lazily, cached).

The Gauss-Newton iteration of the head motion, one frame at a time until that frame
converges. Each step needs only the per-frame moments ``P (3, 18)`` of the gain matrix and
the markers (see ``head_motion._moments``), so a step is a few hundred flops. A converged
frame also gets its rigid coordinates (the significance gate's ``z``, ``_log_map``).
"""

from __future__ import annotations

import math

import numba as nb
import numpy as np


@nb.njit(cache=True, inline="always")
def _rodrigues(v0: float, v1: float, v2: float, out: np.ndarray) -> None:
    """The rotation ``(3, 3)`` of rotation vector ``v`` into ``out``: ``I + s K + c K^2``
    with ``K^2 = v v^T - |v|^2 I`` (Rodrigues)."""
    angle2 = v0 * v0 + v1 * v1 + v2 * v2
    if angle2 < 1e-4:  # |v| < 0.01: Taylor series, truncation below 3e-22 (most steps)
        s = 1.0 - angle2 / 6.0 * (1.0 - angle2 / 20.0 * (1.0 - angle2 / 42.0))
        c = 0.5 - angle2 / 24.0 * (1.0 - angle2 / 30.0 * (1.0 - angle2 / 56.0))
    else:
        angle = math.sqrt(angle2)
        s = math.sin(angle) / angle
        c = (1.0 - math.cos(angle)) / angle2
    out[0, 0] = 1.0 + c * (v0 * v0 - angle2)
    out[1, 1] = 1.0 + c * (v1 * v1 - angle2)
    out[2, 2] = 1.0 + c * (v2 * v2 - angle2)
    out[0, 1] = -s * v2 + c * v0 * v1
    out[1, 0] = s * v2 + c * v0 * v1
    out[0, 2] = s * v1 + c * v0 * v2
    out[2, 0] = -s * v1 + c * v0 * v2
    out[1, 2] = -s * v0 + c * v1 * v2
    out[2, 1] = s * v0 + c * v1 * v2


@nb.njit(cache=True, inline="always")
def _log_map(r: np.ndarray, out: np.ndarray) -> None:
    """The rotation vector of the rotation ``r (3, 3)`` into ``out[:3]`` (angle from atan2 of
    the skew part's length and the trace; near 180 degrees the axis from ``R + I``)."""
    v0 = 0.5 * (r[2, 1] - r[1, 2])
    v1 = 0.5 * (r[0, 2] - r[2, 0])
    v2 = 0.5 * (r[1, 0] - r[0, 1])
    sin = math.sqrt(v0 * v0 + v1 * v1 + v2 * v2)
    cos = 0.5 * (r[0, 0] + r[1, 1] + r[2, 2] - 1.0)
    if cos < 0.0 and sin < 1e-6:  # the skew part vanishes: the axis is R + I's largest column
        best, col = -1.0, 0
        for j in range(3):
            norm2 = 0.0
            for i in range(3):
                e = r[i, j] + (1.0 if i == j else 0.0)
                norm2 += e * e
            if norm2 > best:
                best, col = norm2, j
        scale = math.pi / math.sqrt(best)
        for i in range(3):
            out[i] = (r[i, col] + (1.0 if i == col else 0.0)) * scale
        return
    scale = math.atan2(sin, cos) / sin if sin > 1e-12 else 1.0
    out[0], out[1], out[2] = v0 * scale, v1 * scale, v2 * scale


#: Largest frame-to-frame rotation (radians) through which a warm start is extrapolated;
#: beyond it (a cut between shots) the previous frame is the start.
EXTRAPOLATE_STEP = 0.2


@nb.njit(cache=True)
def gauss_newton(
    moments: np.ndarray,
    sums: np.ndarray,
    offsets: np.ndarray,
    which: np.ndarray,
    centre: np.ndarray,
    size: float,
    rot: np.ndarray,
    trans: np.ndarray,
    max_iter: int,
    tol: float,
    iterations: np.ndarray,
    warm: np.ndarray,
    coords: np.ndarray,
) -> None:
    """Iterate every frame in place on ``rot (F, 3, 3)``, ``trans (F, 3)``.

    ``iterations[f]`` receives the steps frame ``f`` took, or -1 if it did not converge in
    ``max_iter`` steps; a converged frame's ``coords[f] (6,)`` receives the rigid
    coordinates of its motion about the centre ``c``: ``size * log(R)`` and ``R c + t - c``.
    Where ``warm[f]`` is set, frame ``f`` starts from frame ``f - 1``'s result when that
    converged (head motion is continuous), its rotation extrapolated at constant angular
    velocity from frames ``f - 2, f - 1`` when both converged and turned less than
    :data:`EXTRAPOLATE_STEP` apart (about one step a frame fewer on smooth motion);
    elsewhere it starts from the given ``rot``/``trans``.
    """
    n_frames = rot.shape[0]
    step = np.empty(6)
    local_t = np.empty(3)
    d_rot = np.empty((3, 3))
    new_rot = np.empty((3, 3))
    shift = np.empty(3)
    for f in range(n_frames):
        p = which[f]
        iterations[f] = -1
        if warm[f] and f > 0 and iterations[f - 1] >= 0:
            a = rot[f - 1]
            for i in range(3):
                trans[f, i] = trans[f - 1, i]
                for j in range(3):
                    rot[f, i, j] = a[i, j]
            if f > 1 and iterations[f - 2] >= 0:
                # D = R_{f-1} R_{f-2}^T; start from D R_{f-1}, with D rebuilt from its rotation
                # vector (a product of rounded rotations drifts off orthogonality, and
                # D R_{f-1} would amplify that from frame to frame). The translation starts
                # at t_{f-1}: extrapolating it saved no step.
                b = rot[f - 2]
                for i in range(3):
                    for j in range(3):
                        new_rot[i, j] = a[i, 0] * b[j, 0] + a[i, 1] * b[j, 1] + a[i, 2] * b[j, 2]
                if new_rot[0, 0] + new_rot[1, 1] + new_rot[2, 2] >= 1.0 + 2.0 * math.cos(
                    EXTRAPOLATE_STEP
                ):  # trace = 1 + 2 cos(angle): a small turn, not a cut
                    v0 = 0.5 * (new_rot[2, 1] - new_rot[1, 2])
                    v1 = 0.5 * (new_rot[0, 2] - new_rot[2, 0])
                    v2 = 0.5 * (new_rot[1, 0] - new_rot[0, 1])
                    sin2 = v0 * v0 + v1 * v1 + v2 * v2
                    if sin2 > 0.0:  # the skew part has length sin(angle): back to the angle
                        scale = math.asin(min(math.sqrt(sin2), 1.0)) / math.sqrt(sin2)
                        v0, v1, v2 = v0 * scale, v1 * scale, v2 * scale
                    _rodrigues(v0, v1, v2, d_rot)
                    for i in range(3):
                        for j in range(3):
                            rot[f, i, j] = (
                                d_rot[i, 0] * a[0, j]
                                + d_rot[i, 1] * a[1, j]
                                + d_rot[i, 2] * a[2, j]
                            )
        for it in range(max_iter):
            r = rot[f]
            for i in range(3):
                local_t[i] = trans[f, 0] * r[0, i] + trans[f, 1] * r[1, i] + trans[f, 2] * r[2, i]
            for k in range(6):
                acc = 0.0
                for a in range(3):
                    for b in range(3):
                        acc += moments[f, b, 3 * k + a] * r[b, a]
                for a in range(3):
                    acc -= sums[p, k, a] * local_t[a]
                step[k] = acc - offsets[p, k]
            v0, v1, v2 = step[0] / size, step[1] / size, step[2] / size
            _rodrigues(v0, v1, v2, d_rot)
            # local ~ dR (p - c) + c + dt  =>  world = R dR (p - c) + R (c + dt) + t
            for i in range(3):
                shift[i] = (
                    centre[i]
                    - (d_rot[i, 0] * centre[0] + d_rot[i, 1] * centre[1] + d_rot[i, 2] * centre[2])
                    + step[3 + i]
                )
            for i in range(3):
                trans[f, i] += r[i, 0] * shift[0] + r[i, 1] * shift[1] + r[i, 2] * shift[2]
            for i in range(3):
                for j in range(3):
                    new_rot[i, j] = (
                        r[i, 0] * d_rot[0, j] + r[i, 1] * d_rot[1, j] + r[i, 2] * d_rot[2, j]
                    )
            for i in range(3):
                for j in range(3):
                    rot[f, i, j] = new_rot[i, j]
            big = max(abs(v0), abs(v1), abs(v2))
            move = max(abs(step[3]), abs(step[4]), abs(step[5]))
            if big <= tol and move <= tol * size:
                iterations[f] = it + 1
                r = rot[f]
                _log_map(r, coords[f])
                for i in range(3):
                    coords[f, i] *= size
                    coords[f, 3 + i] = (
                        (r[i, 0] * centre[0] + r[i, 1] * centre[1] + r[i, 2] * centre[2])
                        + trans[f, i]
                        - centre[i]
                    )
                break
