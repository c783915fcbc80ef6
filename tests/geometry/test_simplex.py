"""Exact simplex projection and simplex-constrained QPs against brute-force references."""

import numpy as np
import pytest
from naive.simplex import project_simplex_bisection, simplex_qp_slsqp

from faceretarget.errors import InputError, NonFiniteError, ShapeError
from faceretarget.geometry.simplex import group_index, project_simplex, simplex_qp


@pytest.mark.parametrize("n", [1, 2, 5, 40])
@pytest.mark.parametrize("radius", [1.0, 0.3, 7.5])
def test_projection_matches_bisection_and_is_on_the_simplex(n, radius):
    rng = np.random.default_rng(n)
    v = rng.normal(scale=3.0, size=(50, n))
    x = project_simplex(v, radius)
    ref = np.array([project_simplex_bisection(row, radius) for row in v])
    np.testing.assert_allclose(x, ref, atol=1e-10)
    assert (x >= 0).all()
    np.testing.assert_allclose(x.sum(axis=1), radius, rtol=1e-14)


def test_projection_keeps_points_on_the_simplex_and_batches_leading_axes():
    rng = np.random.default_rng(0)
    p = rng.dirichlet(np.ones(6), size=(3, 4))
    np.testing.assert_allclose(project_simplex(p), p, atol=1e-15)
    v = rng.normal(size=(3, 4, 6))
    assert project_simplex(v).shape == (3, 4, 6)
    np.testing.assert_allclose(project_simplex(v)[1, 2], project_simplex(v[1, 2]))


def test_projection_is_the_closest_point():
    """No random point of the simplex is closer to v than the projection."""
    rng = np.random.default_rng(1)
    v = rng.normal(size=5)
    x = project_simplex(v)
    others = rng.dirichlet(np.ones(5), size=2000)
    assert np.linalg.norm(x - v) <= np.linalg.norm(others - v, axis=1).min() + 1e-12


def test_projection_rejects_bad_input():
    with pytest.raises(NonFiniteError):
        project_simplex([0.1, np.nan])
    with pytest.raises(ShapeError):
        project_simplex(np.zeros((3, 0)))
    with pytest.raises(InputError):
        project_simplex([0.2, 0.3], radius=0.0)


@pytest.mark.parametrize("seed", range(6))
def test_simplex_qp_objective_at_or_below_slsqp(seed):
    rng = np.random.default_rng(seed)
    sizes = rng.integers(1, 6, size=rng.integers(1, 4))
    groups = group_index(sizes)
    n = int(sizes.sum())
    a = rng.normal(size=(n + 2, n))
    G, c = a.T @ a, rng.normal(size=n) * 3
    x = simplex_qp(G, c, groups)
    ref = simplex_qp_slsqp(G, c, groups)
    f = lambda y: 0.5 * y @ G @ y - c @ y  # noqa: E731
    assert f(x) <= f(ref) + 1e-9 * max(1.0, abs(f(ref)))
    assert (x >= 0).all()
    np.testing.assert_allclose(np.bincount(groups, x), 1.0, atol=1e-14)


def test_simplex_qp_singular_gram_and_many_right_hand_sides():
    """Duplicate columns (a singular G) and a batch of k problems sharing G."""
    rng = np.random.default_rng(3)
    a = rng.normal(size=(8, 4))
    a = np.hstack([a, a[:, :1]])  # column 4 == column 0
    G = a.T @ a
    cs = rng.normal(size=(7, 5))
    xs = simplex_qp(G, cs)
    for c, x in zip(cs, xs):
        ref = simplex_qp_slsqp(G, c, np.zeros(5, int))
        f = lambda y, c=c: 0.5 * y @ G @ y - c @ y  # noqa: E731
        assert f(x) <= f(ref) + 1e-9
    assert xs.shape == (7, 5) and (xs >= 0).all()
    np.testing.assert_allclose(xs.sum(axis=1), 1.0, atol=1e-14)


def test_simplex_qp_rejects_bad_input():
    with pytest.raises(ShapeError):
        simplex_qp(np.eye(3), np.zeros(4))
    with pytest.raises(NonFiniteError):
        simplex_qp(np.eye(2), [np.nan, 0.0])
    with pytest.raises(InputError):
        simplex_qp(np.eye(3), np.zeros(3), groups=np.array([0, 2, 2]))
