"""Cotangent and uniform Laplacians against dense per-triangle loops."""

import numpy as np
import pytest
from naive.coating import cotangent_laplacian as naive_cot
from naive.coating import grid_mesh
from naive.coating import uniform_laplacian as naive_uniform

from faceretarget.errors import DegenerateGeometryError, ShapeError
from faceretarget.geometry.laplacian import (
    cotangent_laplacian,
    cotangent_weights,
    laplacian_pattern,
    umbrella_operator,
    uniform_laplacian,
)


def test_cotangent_matches_naive_angles():
    v, t = grid_mesh(7, seed=1)
    got = cotangent_laplacian(v, t).toarray()
    np.testing.assert_allclose(got, naive_cot(v, t), atol=1e-12)


def test_cotangent_properties():
    v, t = grid_mesh(9, seed=2)
    lap = cotangent_laplacian(v, t)
    dense = lap.toarray()
    np.testing.assert_allclose(dense, dense.T, atol=1e-14)
    np.testing.assert_allclose(dense.sum(axis=1), 0.0, atol=1e-12)
    assert np.linalg.eigvalsh(dense).min() > -1e-10  # positive semi-definite


def test_cotangent_linear_precision_on_a_plane():
    v, t = grid_mesh(9, seed=3)
    v[:, 2] = 0.3 * v[:, 0] - 0.2 * v[:, 1]  # planar surface
    lap = cotangent_laplacian(v, t)
    interior = np.ones(len(v), bool)
    n = 9
    grid = np.arange(n * n).reshape(n, n)
    interior[np.r_[grid[0], grid[-1], grid[:, 0], grid[:, -1]]] = False
    np.testing.assert_allclose((lap @ v)[interior], 0.0, atol=1e-12)


def test_pattern_refill_equals_fresh_build_for_other_geometry():
    v, t = grid_mesh(8, seed=4)
    pattern = laplacian_pattern(t, len(v))
    moved = v + 0.05 * np.random.default_rng(0).normal(size=v.shape)
    a = cotangent_laplacian(moved, t, pattern).toarray()
    b = cotangent_laplacian(moved, t).toarray()
    np.testing.assert_array_equal(a, b)
    np.testing.assert_allclose(a, naive_cot(moved, t), atol=1e-10)


def test_cotangent_weights_per_corner():
    v, t = grid_mesh(5, seed=5)
    w = cotangent_weights(v, t)
    for j, tri in enumerate(t[:6]):
        for k in range(3):
            c, i, l = tri[k], tri[(k + 1) % 3], tri[(k + 2) % 3]
            u, s = v[i] - v[c], v[l] - v[c]
            angle = np.arccos(u @ s / np.linalg.norm(u) / np.linalg.norm(s))
            assert w[j, k] == pytest.approx(0.5 / np.tan(angle), rel=1e-12)


def test_uniform_and_umbrella():
    v, t = grid_mesh(6, seed=6)
    np.testing.assert_array_equal(uniform_laplacian(t, len(v)).toarray(), naive_uniform(t, len(v)))
    w = umbrella_operator(t, len(v))
    np.testing.assert_allclose(np.asarray(w.sum(axis=1)).ravel(), 1.0)
    assert w.diagonal().max() == 0.0


def test_zero_area_triangle_is_named():
    v, t = grid_mesh(5, seed=7)
    a, b, c = t[3]
    v[c] = 0.5 * (v[a] + v[b])  # collinear corners: zero area
    bad = [
        j
        for j, tri in enumerate(t)
        if np.linalg.norm(np.cross(v[tri[1]] - v[tri[0]], v[tri[2]] - v[tri[0]])) < 1e-12
    ]
    with pytest.raises(DegenerateGeometryError, match=str(bad[0])):
        cotangent_laplacian(v, t)


def test_shape_errors():
    v, t = grid_mesh(4)
    with pytest.raises(ShapeError):
        cotangent_laplacian(v[:, :2], t)
    with pytest.raises(ShapeError):
        cotangent_laplacian(v, t, laplacian_pattern(t[:-1], len(v)))
