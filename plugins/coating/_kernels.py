"""numba kernels of the coating plugin (compiled lazily, cached)."""

from __future__ import annotations

import numba as nb


@nb.njit(parallel=True, cache=True)
def rigid(points, motion, out, inverse):
    """Apply (or undo, ``inverse``) rigid ``motion (C, 4, 4)`` to ``points (C, V, 3)`` into ``out``."""
    n_frames, n_points = points.shape[0], points.shape[1]
    for i in nb.prange(n_frames * n_points):
        f = i // n_points
        v = i - f * n_points
        x = points[f, v, 0]
        y = points[f, v, 1]
        z = points[f, v, 2]
        if inverse:
            x -= motion[f, 0, 3]
            y -= motion[f, 1, 3]
            z -= motion[f, 2, 3]
            out[f, v, 0] = motion[f, 0, 0] * x + motion[f, 1, 0] * y + motion[f, 2, 0] * z
            out[f, v, 1] = motion[f, 0, 1] * x + motion[f, 1, 1] * y + motion[f, 2, 1] * z
            out[f, v, 2] = motion[f, 0, 2] * x + motion[f, 1, 2] * y + motion[f, 2, 2] * z
        else:
            out[f, v, 0] = (
                motion[f, 0, 0] * x + motion[f, 0, 1] * y + motion[f, 0, 2] * z + motion[f, 0, 3]
            )
            out[f, v, 1] = (
                motion[f, 1, 0] * x + motion[f, 1, 1] * y + motion[f, 1, 2] * z + motion[f, 1, 3]
            )
            out[f, v, 2] = (
                motion[f, 2, 0] * x + motion[f, 2, 1] * y + motion[f, 2, 2] * z + motion[f, 2, 3]
            )
