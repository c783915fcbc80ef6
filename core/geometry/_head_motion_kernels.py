"""numba kernel of :mod:`faceretarget.geometry.head_motion` (compiled lazily, cached).

The Gauss-Newton iteration of the head motion, one frame at a time until that frame
converges. Each step needs only the per-frame moments ``P (6, 9)`` of the gain matrix and
the markers (see ``head_motion._moments``), so a step is a few hundred flops.
"""

from __future__ import annotations

import math

import numba as nb
import numpy as np


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
) -> None:
    """Iterate every frame in place on ``rot (F, 3, 3)``, ``trans (F, 3)``.

    ``iterations[f]`` receives the steps frame ``f`` took, or -1 if it did not converge in
    ``max_iter`` steps. Where ``warm[f]`` is set, frame ``f`` starts from frame ``f - 1``'s
    result when that converged (head motion is continuous: a step or two instead of five);
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
            for i in range(3):
                trans[f, i] = trans[f - 1, i]
                for j in range(3):
                    rot[f, i, j] = rot[f - 1, i, j]
        for it in range(max_iter):
            r = rot[f]
            for i in range(3):
                local_t[i] = trans[f, 0] * r[0, i] + trans[f, 1] * r[1, i] + trans[f, 2] * r[2, i]
            for k in range(6):
                acc = 0.0
                for a in range(3):
                    for b in range(3):
                        acc += moments[f, k, 3 * a + b] * r[b, a]
                for a in range(3):
                    acc -= sums[p, k, a] * local_t[a]
                step[k] = acc - offsets[p, k]
            v0, v1, v2 = step[0] / size, step[1] / size, step[2] / size
            angle2 = v0 * v0 + v1 * v1 + v2 * v2
            angle = math.sqrt(angle2)
            if angle < 1e-8:
                s = 1.0 - angle2 / 6.0
                c = 0.5 - angle2 / 24.0
            else:
                s = math.sin(angle) / angle
                c = (1.0 - math.cos(angle)) / angle2
            # Rodrigues: I + s K + c K^2, K^2 = v v^T - |v|^2 I
            d_rot[0, 0] = 1.0 + c * (v0 * v0 - angle2)
            d_rot[1, 1] = 1.0 + c * (v1 * v1 - angle2)
            d_rot[2, 2] = 1.0 + c * (v2 * v2 - angle2)
            d_rot[0, 1] = -s * v2 + c * v0 * v1
            d_rot[1, 0] = s * v2 + c * v0 * v1
            d_rot[0, 2] = s * v1 + c * v0 * v2
            d_rot[2, 0] = -s * v1 + c * v0 * v2
            d_rot[1, 2] = -s * v0 + c * v1 * v2
            d_rot[2, 1] = s * v0 + c * v1 * v2
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
                break
