"""Active-set NNLS / bounded least squares against scipy (the naive reference)."""
import numpy as np
import pytest
import scipy.optimize

from faceretarget.errors import InputError, NonFiniteError, ShapeError
from faceretarget.geometry.nnls import bounded_lsq, bounded_lsq_gram, nnls, nnls_gram


def _cost(A, x, b):
    r = A @ x - b
    return float(r @ r)


@pytest.mark.parametrize("seed", range(8))
def test_nnls_matches_scipy(seed):
    rng = np.random.default_rng(seed)
    m, n = int(rng.integers(3, 40)), int(rng.integers(1, 25))
    A, b = rng.normal(size=(m, n)), rng.normal(size=m) * rng.uniform(0.1, 10)
    x = nnls(A, b)
    ref, _ = scipy.optimize.nnls(A, b)
    assert (x >= 0).all()
    assert _cost(A, x, b) <= _cost(A, ref, b) * (1 + 1e-9) + 1e-12
    if m >= n:  # full column rank: the minimiser is unique
        np.testing.assert_allclose(x, ref, atol=1e-7)


def test_nnls_many_columns_and_gram_batch_agree():
    rng = np.random.default_rng(11)
    A = rng.normal(size=(30, 12))
    B = rng.normal(size=(30, 9))
    X = nnls(A, B)
    assert X.shape == (12, 9)
    for k in range(9):
        ref, _ = scipy.optimize.nnls(A, B[:, k])
        np.testing.assert_allclose(X[:, k], ref, atol=1e-8)
    Xg = nnls_gram(A.T @ A, (A.T @ B).T)
    np.testing.assert_allclose(Xg, X.T, atol=1e-12)
    np.testing.assert_allclose(nnls_gram(A.T @ A, (A.T @ B).T, x0=Xg + 0.1), Xg, atol=1e-9)  # warm start, same answer


@pytest.mark.parametrize("seed", range(6))
def test_bounded_lsq_matches_scipy_bvls(seed):
    rng = np.random.default_rng(100 + seed)
    m, n = int(rng.integers(5, 30)), int(rng.integers(2, 15))
    A, b = rng.normal(size=(m, n)), rng.normal(size=m)
    lo = rng.uniform(-1, 0, n)
    hi = lo + rng.uniform(0.05, 1.0, n)
    hi[0] = np.inf  # one open side
    x = bounded_lsq(A, b, lo, hi)
    ref = scipy.optimize.lsq_linear(A, b, bounds=(lo, hi), method="bvls", tol=1e-14).x
    assert np.all(x >= lo) and np.all(x <= hi)
    assert _cost(A, x, b) <= _cost(A, ref, b) * (1 + 1e-8) + 1e-12


def test_rank_deficient_problem_still_optimal():
    rng = np.random.default_rng(5)
    A = rng.normal(size=(20, 4))
    A = np.hstack([A, A])  # every column twice
    b = rng.normal(size=20)
    x = nnls(A, b)
    ref, _ = scipy.optimize.nnls(A, b)
    assert _cost(A, x, b) <= _cost(A, ref, b) + 1e-9


def test_nnls_rejects_bad_input():
    with pytest.raises(NonFiniteError):
        nnls(np.eye(2), [np.nan, 1.0])
    with pytest.raises(ShapeError):
        nnls(np.eye(3), np.ones(4))
    with pytest.raises(ShapeError):
        nnls_gram(np.ones((2, 3)), np.ones(2))
    with pytest.raises(InputError):
        nnls_gram(np.array([[1.0, 2.0], [0.0, 1.0]]), np.ones(2))
    with pytest.raises(InputError):
        bounded_lsq_gram(np.eye(2), np.ones(2), [1.0, 0.0], [0.0, 1.0])
