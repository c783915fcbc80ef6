"""Taubin smoothing: numba kernel against a per-vertex loop; batching and precision."""

import numpy as np
import pytest
from naive.coating import grid_mesh
from naive.coating import taubin as naive_taubin

from faceretarget.errors import ShapeError
from faceretarget.geometry.smoothing import TaubinSmoother, taubin_smooth


def test_matches_naive_loop():
    v, t = grid_mesh(7, seed=0)
    np.testing.assert_allclose(
        taubin_smooth(v, t, iterations=6), naive_taubin(v, t, iterations=6), atol=1e-13
    )


def test_batch_of_frames_equals_one_by_one_exactly():
    v, t = grid_mesh(8, seed=1)
    rng = np.random.default_rng(0)
    frames = v + 0.02 * rng.normal(size=(5,) + v.shape)
    for dtype in (np.float64, np.float32):
        smoother = TaubinSmoother(t, len(v), iterations=40, dtype=dtype)
        batch = smoother(frames)
        single = np.stack([smoother(f) for f in frames])
        np.testing.assert_array_equal(batch, single)


def test_float32_close_to_float64():
    v, t = grid_mesh(8, seed=2)
    a = taubin_smooth(v, t, dtype=np.float64)
    b = taubin_smooth(v, t, dtype=np.float32)
    assert np.abs(a - b).max() < 1e-5 * np.abs(v).max()


def test_removes_high_frequencies_and_commutes_with_translation():
    v, t = grid_mesh(21, seed=3, jitter=0.0)
    noise = (
        0.01 * np.where(np.arange(len(v)) % 2 == 0, 1.0, -1.0)[:, None] * np.array([0.0, 0.0, 1.0])
    )
    # the filter is linear: what is left of the checkerboard noise is smooth(v + noise) - smooth(v)
    left = taubin_smooth(v + noise, t) - taubin_smooth(v, t)
    assert np.linalg.norm(left) < 0.05 * np.linalg.norm(noise)
    translated = taubin_smooth(v + np.array([1.0, 2.0, 3.0]), t)
    np.testing.assert_allclose(
        translated - taubin_smooth(v, t), np.broadcast_to([1.0, 2.0, 3.0], v.shape), atol=1e-12
    )


def test_shape_error():
    v, t = grid_mesh(4)
    with pytest.raises(ShapeError):
        TaubinSmoother(t, len(v))(v[:-1])
    with pytest.raises(ShapeError):
        taubin_smooth(v[:, :2], t)


def test_adjoint_filter_is_the_transpose():
    v, t = grid_mesh(9, seed=4)
    rng = np.random.default_rng(1)
    x, b = rng.normal(size=v.shape), rng.normal(size=v.shape)
    forward = TaubinSmoother(t, len(v), iterations=7)
    adjoint = TaubinSmoother(t, len(v), iterations=7, adjoint=True)
    assert np.sum(b * forward(x)) == pytest.approx(np.sum(adjoint(b) * x), rel=1e-12)
