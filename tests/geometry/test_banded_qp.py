"""The banded non-negative QP (interior point + polish) against brute force and scipy, and
its block-tridiagonal form (numba block Cholesky) against dense numpy and the band."""

import numpy as np
import pytest
import scipy.sparse as sp
from naive.qp import (
    block_tridiagonal,
    block_tridiagonal_dense,
    blocks_of,
    nonneg_qp_enumerate,
    nonneg_qp_scipy,
)

from faceretarget import config
from faceretarget.errors import ShapeError
from faceretarget.geometry import banded_qp
from faceretarget.geometry.banded_qp import (
    POLISH_TOL,
    _free_set_solve,
    _to_boundary,
    block_tridiagonal_band,
    nonneg_qp_band,
    nonneg_qp_banded,
    nonneg_qp_block_tridiagonal,
    sub_band,
    to_upper_band,
)


def _objective(h, r, x):
    return 0.5 * x @ (h @ x) - r @ x


def test_upper_band_storage():
    h, _ = block_tridiagonal(0, 4, 3, 0)
    ab, u = to_upper_band(h)
    assert u == 5 and ab.shape == (6, 12)
    dense = h.toarray()
    for j in range(12):
        for i in range(max(0, j - u), j + 1):
            assert ab[u + i - j, j] == dense[i, j]


@pytest.mark.parametrize("seed", range(4))
def test_sub_band_is_the_band_of_the_kept_rows_and_columns(seed):
    rng = np.random.default_rng(seed)
    h, _ = block_tridiagonal(seed, 6, 3, 0)
    h = (h + sp.coo_matrix((np.ones(2), ([0, 0], [0, 0])), shape=h.shape)).tocsc()  # duplicates
    keep = np.flatnonzero(rng.random(18) < 0.6)
    ab, u = to_upper_band(h)
    want, _ = to_upper_band(sp.csc_matrix(h.toarray()[np.ix_(keep, keep)]))
    got = sub_band(ab, keep)
    np.testing.assert_array_equal(got[u + 1 - want.shape[0] :], want)
    assert not got[: u + 1 - want.shape[0]].any()


@pytest.mark.parametrize("seed", range(12))
def test_exact_on_small_problems_against_enumeration(seed):
    rng = np.random.default_rng(seed)
    n, k = int(rng.integers(1, 5)), int(rng.integers(1, 4))
    h, r = block_tridiagonal(seed, n, k, decades=int(rng.integers(0, 3)))
    want = nonneg_qp_enumerate(h.toarray(), r)
    got, info = nonneg_qp_banded(h, r)
    assert info["exact"] and (got >= 0).all()
    assert info["steps"] <= 25  # Mehrotra's start and step: 7-19 here (a poor start took 38)
    np.testing.assert_allclose(got, want, atol=1e-9 * max(np.abs(want).max(), 1e-300))


@pytest.mark.parametrize("seed", [1, 179, 7])
def test_exact_where_the_active_set_method_cycles(seed):
    """Seed 179 made the primal-dual active-set method of the coating edit cycle."""
    h, r = block_tridiagonal(seed, 10, 6, decades=2)
    want = nonneg_qp_scipy(h.toarray(), r)
    got, info = nonneg_qp_banded(h, r, np.zeros(r.size))
    assert info["exact"] and 0 < (want > 0).mean() < 1  # the bounds bind
    np.testing.assert_allclose(got, want, atol=1e-9 * np.abs(want).max())


@pytest.mark.parametrize("seed", range(3))
def test_ill_conditioned_block_tridiagonal_reaches_the_optimum(seed):
    """40 frames x 28 bases with a metric over six decades (the coating edit's conditioning):
    the objective matches scipy's NNLS on the Cholesky factor to 1e-10 relative, whatever the
    weights do along directions the metric barely sees."""
    h, r = block_tridiagonal(seed, 40, 28, decades=6, ridge=1e-6)
    want = nonneg_qp_scipy(h.toarray(), r)
    got, info = nonneg_qp_banded(h, r)
    assert (got >= 0).all() and info["steps"] <= 22  # 17-19; a shorter step fraction took 23-25
    best = _objective(h, r, want)
    assert _objective(h, r, got) <= best + 1e-10 * abs(best)


def test_unbound_problem_is_the_linear_solve_and_start_is_only_a_guess():
    h, _ = block_tridiagonal(3, 6, 4, decades=1, ridge=1e-3)
    x_true = np.random.default_rng(3).uniform(0.5, 2.0, size=24)
    r = h @ x_true  # its unconstrained minimiser is positive: no bound binds
    for start in (None, np.zeros(24), 1e3 * np.ones(24), -np.ones(24)):
        got, info = nonneg_qp_banded(h, r, start)
        assert info["exact"]
        np.testing.assert_allclose(got, x_true, rtol=1e-9)


def test_all_bound_and_empty():
    h, _ = block_tridiagonal(4, 5, 2, decades=0)
    got, info = nonneg_qp_banded(h, -np.ones(10))  # the gradient is positive at 0
    assert info["exact"] and not got.any()
    assert info["steps"] < 40  # the stopping rule's scale does not vanish with x (it ran all 80)
    got, info = nonneg_qp_banded(sp.csc_matrix((0, 0)), np.zeros(0))
    assert got.shape == (0,) and info["exact"]


def test_duplicate_entries_are_summed():
    """A non-canonical matrix: entry (0, 0) stored twice (1 + 1)."""
    h = sp.csc_matrix(
        (np.array([1.0, 1.0, 1.0, 1.0, 2.0]), np.array([0, 0, 1, 0, 1]), np.array([0, 3, 5])),
        shape=(2, 2),
    )
    assert not h.has_canonical_format
    arrays = [a.copy() for a in (h.data, h.indices, h.indptr)]
    ab, u = to_upper_band(h)
    np.testing.assert_array_equal(ab, [[0.0, 1.0], [2.0, 2.0]])
    got, info = nonneg_qp_banded(h, np.array([3.0, 3.0]))
    assert info["exact"]
    np.testing.assert_allclose(got, [1.0, 1.0], rtol=1e-12)
    for before, after in zip(arrays, (h.data, h.indices, h.indptr)):  # the input is not modified
        np.testing.assert_array_equal(after, before)


def test_step_to_the_boundary_is_capped_at_a_full_step():
    assert _to_boundary(np.ones(2), np.array([-0.1, 1.0])) == 1.0
    assert _to_boundary(np.ones(2), np.array([-2.0, 1.0])) == 0.5
    assert _to_boundary(np.ones(2), np.array([0.5, 1.0])) == 1.0


@pytest.mark.parametrize(("n", "k"), [(1, 3), (2, 1), (5, 4)])
def test_block_tridiagonal_band_is_the_band_of_the_blocks(n, k):
    """Distinct blocks, those above the diagonal not symmetric: a transposed or shifted
    block would show."""
    rng = np.random.default_rng(n + k)
    diagonal = rng.normal(size=(n, k, k))
    diagonal = diagonal + diagonal.transpose(0, 2, 1)
    upper = rng.normal(size=(n - 1, k, k))
    dense = block_tridiagonal_dense(diagonal, upper)
    got = block_tridiagonal_band(diagonal, upper)
    u = 2 * k - 1
    assert got.shape == (u + 1, n * k)
    for j in range(n * k):
        for i in range(n * k):
            if i <= j <= i + u:
                assert got[u + i - j, j] == dense[i, j]
            else:
                assert dense[i, j] == 0.0 or i > j
    want, _ = to_upper_band(sp.csc_matrix(dense))
    np.testing.assert_array_equal(got[got.shape[0] - want.shape[0] :], want)
    with pytest.raises(ShapeError):
        block_tridiagonal_band(np.zeros((n, k)), np.zeros((n - 1, k, k)))
    with pytest.raises(ShapeError):
        block_tridiagonal_band(np.zeros((n, k, k)), np.zeros((n, k, k)))


def test_the_polish_measures_each_row_against_its_own_terms():
    """A row 1e7 times the others (a constraint row of the coating edit) must not set the
    tolerance of the others: leaving out variable 1, whose gradient is then -1e-3 (1e-10 of
    the big row), is not optimal; the measure of r's scale took it (a 36,400-variable edit
    stopped 1.2 above the optimum of an objective of 1)."""
    ab = np.array([[1e7, 1.0, 1.0]])  # H = diag(1e7, 1, 1): u = 0
    r = np.array([1e7, 1e-3, 1.0])
    x, violation = _free_set_solve(np.asfortranarray(ab), r, np.array([True, False, True]))
    np.testing.assert_allclose(x, [1.0, 0.0, 1.0])
    assert violation > 1e6 * POLISH_TOL
    x, violation = _free_set_solve(np.asfortranarray(ab), r, np.ones(3, bool))
    assert violation == 0.0
    got, info = nonneg_qp_band(ab, r)
    assert info["exact"]
    np.testing.assert_allclose(got, [1.0, 1e-3, 1.0], rtol=1e-12)
    # a row whose terms are all below the interior point's accuracy is measured at the floor
    # (ROW_FLOOR of max |r|): its exact answer is taken, not the iterate (1.5e-4 and 4.9e-4)
    got, info = nonneg_qp_band(ab, np.array([1e7, -1e-3, 1e-15]))
    assert info["exact"]
    np.testing.assert_allclose(got, [1.0, 0.0, 1e-15], rtol=1e-12, atol=1e-15)


def test_the_band_must_match_the_right_hand_side():
    with pytest.raises(ShapeError):
        nonneg_qp_band(np.ones((2, 4)), np.ones(3))
    with pytest.raises(ShapeError):
        nonneg_qp_band(np.ones(3), np.ones(3))


# ---------------------------------------------------------------------------------------
# the block-tridiagonal form
# ---------------------------------------------------------------------------------------
@pytest.fixture
def by_blocks(monkeypatch):
    """Factor by blocks whatever the size (small problems use the band by default)."""
    monkeypatch.setattr(config, "BLOCK_QP_MIN_VARIABLES", 0)


def _random_blocks(seed, n, k):
    """Distinct blocks making an SPD matrix, those above the diagonal not symmetric (a
    transposed or shifted block would show), and a positive shift."""
    rng = np.random.default_rng(seed)
    a = rng.normal(size=(n, k, k))
    upper = rng.normal(size=(max(n - 1, 0), k, k))
    diagonal = a @ a.transpose(0, 2, 1) + 4.0 * k * np.eye(k)  # diagonally dominant by blocks
    return diagonal, upper, rng.uniform(0.1, 2.0, n * k)


@pytest.mark.parametrize(("n", "k"), [(1, 1), (1, 4), (2, 3), (7, 5), (30, 2)])
def test_block_kernels_against_dense_numpy(n, k):
    from faceretarget.geometry._banded_qp_kernels import block_cholesky, block_matvec, block_solve

    diagonal, upper, shift = _random_blocks(n * 10 + k, n, k)
    dense = block_tridiagonal_dense(diagonal, upper) + np.diag(shift)
    low, offt = np.empty_like(diagonal), np.empty_like(upper)
    assert block_cholesky(diagonal, upper, shift, low, offt)
    factor = np.zeros_like(dense)
    for t in range(n):
        factor[t * k : (t + 1) * k, t * k : (t + 1) * k] = low[t]
    for t in range(n - 1):
        factor[(t + 1) * k : (t + 2) * k, t * k : (t + 1) * k] = offt[t].T
    np.testing.assert_allclose(factor, np.linalg.cholesky(dense), rtol=1e-12, atol=1e-12)
    b = np.random.default_rng(n).normal(size=n * k)
    out = np.empty(n * k)
    block_solve(low, offt, b, out)
    np.testing.assert_allclose(out, np.linalg.solve(dense, b), rtol=1e-10, atol=1e-12)
    in_place = b.copy()
    block_solve(low, offt, in_place, in_place)
    np.testing.assert_array_equal(in_place, out)
    block_matvec(diagonal, upper, b, out)
    np.testing.assert_allclose(out, (dense - np.diag(shift)) @ b, rtol=1e-12, atol=1e-12)


@pytest.mark.parametrize("where", ["coupling", "last pivot", "zero pivot", "NaN"])
def test_block_cholesky_refuses_a_matrix_that_is_not_positive_definite(where):
    from faceretarget.geometry._banded_qp_kernels import block_cholesky

    diagonal, upper, shift = _random_blocks(5, 4, 3)
    low, offt = np.empty_like(diagonal), np.empty_like(upper)
    if where == "coupling":
        upper[2] *= 100.0  # block 3's Schur complement turns indefinite
    elif where == "last pivot":
        diagonal[-1, -1, -1] = -100.0  # the very last pivot: no later step would see a NaN
    elif where == "zero pivot":  # exactly singular: no division by the zero pivot
        diagonal[0] = 0.0
        upper[0] = 0.0
        shift[:3] = 0.0
    else:
        diagonal[1, 0, 2] = np.nan
    if where != "NaN":
        dense = block_tridiagonal_dense(diagonal, upper) + np.diag(shift)
        assert np.linalg.eigvalsh(dense).min() <= 0
    assert not block_cholesky(diagonal, upper, shift, low, offt)


@pytest.mark.parametrize("seed", range(16))
def test_block_form_takes_the_band_forms_steps_and_answer(seed, by_blocks):
    """The same interior point on the same matrix: the same number of steps, the same
    exactness, the same answer to rounding, on small to 40 x 28 problems over 0-6 decades."""
    rng = np.random.default_rng(seed)
    n, k = (40, 28) if seed < 2 else (int(rng.integers(1, 30)), int(rng.integers(1, 6)))
    h, r = block_tridiagonal(seed, n, k, decades=int(rng.integers(0, 7)), ridge=1e-6)
    start = None if seed % 2 else rng.uniform(0.0, 1.0, n * k)  # a start changes the steps
    want, want_info = nonneg_qp_banded(h, r, start)
    got, info = nonneg_qp_block_tridiagonal(*blocks_of(h, n, k), r, start)
    assert info["steps"] == want_info["steps"] and info["exact"] == want_info["exact"]
    np.testing.assert_allclose(got, want, atol=1e-10 * np.abs(want).max())


@pytest.mark.parametrize("seed", range(6))
def test_block_form_is_exact_on_small_problems_against_enumeration(seed, by_blocks):
    rng = np.random.default_rng(seed)
    n, k = int(rng.integers(1, 5)), int(rng.integers(1, 4))
    h, r = block_tridiagonal(seed, n, k, decades=int(rng.integers(0, 3)))
    want = nonneg_qp_enumerate(h.toarray(), r)
    start = None if seed % 2 else np.zeros(r.size)
    got, info = nonneg_qp_block_tridiagonal(*blocks_of(h, n, k), r, start)
    assert info["exact"] and (got >= 0).all()
    np.testing.assert_allclose(got, want, atol=1e-9 * max(np.abs(want).max(), 1e-300))


def test_block_form_checks_its_shapes(by_blocks):
    with pytest.raises(ShapeError):
        nonneg_qp_block_tridiagonal(np.zeros((3, 2, 2)), np.zeros((3, 2, 2)), np.ones(6))
    with pytest.raises(ShapeError):
        nonneg_qp_block_tridiagonal(np.zeros((3, 2, 2)), np.zeros((2, 2, 2)), np.ones(5))
    got, info = nonneg_qp_block_tridiagonal(np.zeros((0, 2, 2)), np.zeros((0, 2, 2)), np.zeros(0))
    assert got.shape == (0,) and info["exact"]


def test_block_form_factors_by_blocks_from_its_threshold_only(monkeypatch):
    """Below ``config.BLOCK_QP_MIN_VARIABLES`` the band (nothing to compile), from it the blocks."""
    used = []

    class Spy(banded_qp._Blocks):
        def factor(self, d):
            used.append(d.size)
            return super().factor(d)

    monkeypatch.setattr(banded_qp, "_Blocks", Spy)
    h, r = block_tridiagonal(0, 6, 3, decades=1)
    diagonal, upper = blocks_of(h, 6, 3)
    monkeypatch.setattr(config, "BLOCK_QP_MIN_VARIABLES", 19)
    small, _ = nonneg_qp_block_tridiagonal(diagonal, upper, r)
    assert not used
    monkeypatch.setattr(config, "BLOCK_QP_MIN_VARIABLES", 18)
    large, _ = nonneg_qp_block_tridiagonal(diagonal, upper, r)
    assert used and set(used) == {18}
    np.testing.assert_allclose(large, small, atol=1e-12 * np.abs(small).max())


def test_a_start_of_the_wrong_size_is_refused(by_blocks):
    h, r = block_tridiagonal(0, 5, 3, decades=1)
    with pytest.raises(ShapeError, match="start"):
        nonneg_qp_block_tridiagonal(*blocks_of(h, 5, 3), r, np.ones(4))
    with pytest.raises(ShapeError, match="start"):
        nonneg_qp_band(to_upper_band(h)[0], r, np.ones(16))


def test_both_forms_read_the_upper_triangle_of_the_diagonal_blocks(by_blocks):
    """Diagonal blocks whose lower triangles hold other numbers (even NaN): the band stores
    the upper triangles, and the blocks read the same, in the factor and in the product."""
    from faceretarget.geometry._banded_qp_kernels import block_matvec

    n, k = 6, 4
    h, r = block_tridiagonal(3, n, k, decades=2, ridge=1e-3)
    diagonal, upper = blocks_of(h, n, k)
    lower = np.tril_indices(k, -1)
    skewed = diagonal.copy()
    skewed[:, lower[0], lower[1]] += np.random.default_rng(3).normal(size=(n, lower[0].size))
    x = np.random.default_rng(4).normal(size=n * k)
    out = np.empty(n * k)
    block_matvec(skewed, upper, x, out)
    np.testing.assert_allclose(out, h @ x, rtol=1e-12, atol=1e-12)
    want, want_info = nonneg_qp_banded(h, r)
    skewed[0, 1, 0] = np.nan
    got, info = nonneg_qp_block_tridiagonal(skewed, upper, r)
    assert info["steps"] == want_info["steps"] and info["exact"] == want_info["exact"]
    np.testing.assert_allclose(got, want, atol=1e-10 * np.abs(want).max())


def test_an_indefinite_matrix_stops_both_forms_alike(by_blocks):
    """The factor fails at the first step: both forms stop there and return the same."""
    h, r = block_tridiagonal(1, 8, 3, decades=0)
    diagonal, upper = blocks_of(h, 8, 3)
    upper[4] *= 50.0
    dense = block_tridiagonal_dense(diagonal, upper)
    assert np.linalg.eigvalsh(dense).min() < 0
    want, want_info = nonneg_qp_band(block_tridiagonal_band(diagonal, upper), r)
    got, info = nonneg_qp_block_tridiagonal(diagonal, upper, r)
    assert info == want_info
    np.testing.assert_array_equal(got, want)
