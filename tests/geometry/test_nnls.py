"""Active-set NNLS / bounded least squares against scipy (the naive reference)."""

import numpy as np
import pytest
import scipy.optimize

from faceretarget.errors import InputError, NonFiniteError, ShapeError
from faceretarget.geometry.nnls import (
    bounded_lsq,
    bounded_lsq_frames,
    bounded_lsq_gram,
    nnls,
    nnls_gram,
)


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
    np.testing.assert_allclose(
        nnls_gram(A.T @ A, (A.T @ B).T, x0=Xg + 0.1), Xg, atol=1e-9
    )  # warm start, same answer


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


def _blocks_problem(seed, n_frames=12, n_blocks=8, n=6):
    """Row blocks of 3 rows (markers), their Grams, and per-frame data with some blocks missing."""
    rng = np.random.default_rng(seed)
    A = rng.normal(size=(3 * n_blocks, n))
    X = np.cumsum(rng.normal(0.0, 0.3, (n_frames, n)), axis=0)  # smooth: warm starts matter
    Y = X @ A.T + 0.1 * rng.normal(size=(n_frames, 3 * n_blocks))
    dropped = rng.random((n_frames, n_blocks)) < 0.2
    dropped[0] = False
    grams = np.einsum("bki,bkj->bij", A.reshape(n_blocks, 3, n), A.reshape(n_blocks, 3, n))
    seen = np.repeat(~dropped, 3, axis=1)
    Atb = np.where(seen, Y, 0.0) @ A
    return A, Y, dropped, grams, seen, Atb


@pytest.mark.parametrize("seed", range(4))
def test_bounded_lsq_frames_matches_each_frame_solved_alone(seed):
    """Every frame is the bounded least squares of its own rows (missing blocks left out),
    whatever the warm start from the frame before: against scipy's BVLS frame by frame."""
    A, Y, dropped, grams, seen, Atb = _blocks_problem(seed)
    lo, hi = -0.4, 0.6
    got = bounded_lsq_frames(A.T @ A, Atb, lo, hi, dropped=dropped, block_grams=grams)
    assert dropped.any() and got.shape == Y.shape[:1] + A.shape[1:]
    for t in range(len(Y)):
        rows = A[seen[t]]
        ref = scipy.optimize.lsq_linear(
            rows, Y[t, seen[t]], bounds=(lo, hi), method="bvls", tol=1e-14
        ).x
        assert np.all(got[t] >= lo) and np.all(got[t] <= hi)
        assert (
            _cost(rows, got[t], Y[t, seen[t]])
            <= _cost(rows, ref, Y[t, seen[t]]) * (1 + 1e-9) + 1e-12
        )
        np.testing.assert_allclose(got[t], ref, atol=1e-7)
    # no missing blocks: the same as one batch of independent problems
    full = bounded_lsq_frames(A.T @ A, Y @ A, lo, hi)
    np.testing.assert_allclose(full, bounded_lsq_gram(A.T @ A, Y @ A, lo, hi), atol=1e-10)


def test_bounded_lsq_frames_ridges_a_frame_that_leaves_a_variable_unseen():
    """A variable seen by one block only: at frames without that block the ridge decides it
    (pulled to 0, or to the bound nearest 0), the other variables are the data's."""
    rng = np.random.default_rng(7)
    n_blocks, n = 5, 4
    A = rng.normal(size=(3 * n_blocks, n))
    A[3:, 3] = 0.0  # variable 3 moves block 0 only
    grams = np.einsum("bki,bkj->bij", A.reshape(n_blocks, 3, n), A.reshape(n_blocks, 3, n))
    Y = rng.normal(size=(3, 3 * n_blocks))
    dropped = np.zeros((3, n_blocks), bool)
    dropped[1:, 0] = True
    seen = np.repeat(~dropped, 3, axis=1)
    Atb = np.where(seen, Y, 0.0) @ A
    ridge = 1e-6
    for lower, unseen in (
        (-1.0, 0.0),
        ([-1.0, -1.0, -1.0, 0.2], 0.2),
    ):  # zero, or the bound nearest zero
        got = bounded_lsq_frames(
            A.T @ A,
            Atb,
            lower,
            1.0,
            dropped=dropped,
            block_grams=grams,
            ridge=ridge,
            x0=np.full(n, 0.9),
        )
        np.testing.assert_allclose(got[1:, 3], unseen, atol=1e-9)
        for t in (1, 2):
            H = A[seen[t]].T @ A[seen[t]] + ridge * np.eye(n)
            np.testing.assert_allclose(got[t], bounded_lsq_gram(H, Atb[t], lower, 1.0), atol=1e-9)


def test_bounded_lsq_frames_rejects_bad_input():
    A, Y, dropped, grams, seen, Atb = _blocks_problem(0)
    with pytest.raises(InputError):
        bounded_lsq_frames(A.T @ A, Atb, 0.0, 1.0, dropped=dropped)  # no block Grams
    with pytest.raises(ShapeError):
        bounded_lsq_frames(A.T @ A, Atb, 0.0, 1.0, dropped=dropped[:, 1:], block_grams=grams)
    with pytest.raises(ShapeError):
        bounded_lsq_frames(A.T @ A, Atb[0], 0.0, 1.0)
    with pytest.raises(InputError):
        bounded_lsq_frames(A.T @ A, Atb, 0.0, 1.0, ridge=-1.0)
    with pytest.raises(NonFiniteError):
        bounded_lsq_frames(A.T @ A, np.where(seen, Y, np.nan) @ A, 0.0, 1.0)
