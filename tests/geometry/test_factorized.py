"""SPDFactor: SuperLU factorization with numba multi-column triangular solves."""

import pickle

import numpy as np
import pytest
import scipy.sparse as sp
from naive.coating import grid_mesh

from faceretarget.errors import NumericalError, ShapeError
from faceretarget.geometry import factorized
from faceretarget.geometry.factorized import SPDFactor, factorize
from faceretarget.geometry.laplacian import uniform_laplacian


def _system(n=12):
    v, t = grid_mesh(n, seed=0)
    lap = uniform_laplacian(t, len(v))
    return (lap + 0.1 * sp.identity(len(v))).tocsc()


def test_multi_column_solve_matches_dense():
    m = _system()
    fac = SPDFactor(m)
    rhs = np.random.default_rng(0).normal(size=(m.shape[0], 37))
    np.testing.assert_allclose(fac.solve(rhs), np.linalg.solve(m.toarray(), rhs), atol=1e-10)
    np.testing.assert_allclose(
        fac.solve(rhs[:, 0]), np.linalg.solve(m.toarray(), rhs[:, 0]), atol=1e-10
    )


def test_columns_do_not_depend_on_the_block():
    fac = SPDFactor(_system())
    rhs = np.random.default_rng(1).normal(size=(fac.n, 40))
    np.testing.assert_array_equal(fac.solve(rhs)[:, :20], fac.solve(rhs[:, :20]))


def test_pickle_refactorizes():
    fac = SPDFactor(_system())
    rhs = np.random.default_rng(2).normal(size=(fac.n, 9))
    again = pickle.loads(pickle.dumps(fac))
    np.testing.assert_array_equal(again.solve(rhs), fac.solve(rhs))


@pytest.mark.parametrize("workers", [1, 2])
def test_factorize_several_at_once(workers, monkeypatch):
    """Side by side on threads: the same factors as one by one; an error is raised, not lost."""
    monkeypatch.setattr(factorized, "worker_count", lambda n: min(n, workers))
    systems = [_system(10), _system(13), _system(7)]
    rhs = [np.random.default_rng(3).normal(size=(m.shape[0], 9)) for m in systems]
    factors = [SPDFactor(m) for m in systems]
    factorize(factors)
    assert all(f._lu is not None for f in factors)
    for f, m, b in zip(factors, systems, rhs, strict=True):
        np.testing.assert_array_equal(f.solve(b), SPDFactor(m).solve(b))
    v, t = grid_mesh(6)
    singular = SPDFactor(uniform_laplacian(t, len(v)), what="the singular one")
    with pytest.raises(NumericalError, match="the singular one"):
        factorize([SPDFactor(_system(9)), singular])


def test_singular_and_bad_inputs():
    v, t = grid_mesh(6)
    with pytest.raises(NumericalError):
        SPDFactor(uniform_laplacian(t, len(v))).solve(np.ones(len(v)))
    with pytest.raises(ShapeError):
        SPDFactor(_system()).solve(np.ones(3))
    bad = _system().tolil()
    bad[0, 0] = np.nan
    with pytest.raises(NumericalError):
        SPDFactor(bad).solve(np.ones(bad.shape[0]))


@pytest.mark.parametrize("lower", [True, False])
def test_strict_triangles_match_a_dense_mask(lower):
    """The factors the solves read: every entry strictly below (above) the diagonal, in
    stored order, with its value; none of the diagonal or the other side. A random
    pattern (unsorted rows, explicit zeros, empty columns) in both index dtypes."""
    from faceretarget.geometry.factorized import _strict

    rng = np.random.default_rng(3)
    dense = rng.normal(size=(40, 40)) * (rng.random((40, 40)) < 0.2)
    dense[:, 7] = 0.0
    m = sp.csc_matrix(dense)
    m.data[::5] = 0.0  # explicit zeros are kept
    order = rng.permutation(m.indptr[1] - m.indptr[0])
    m.indices[: len(order)] = m.indices[: len(order)][order]  # unsorted first column
    m.data[: len(order)] = m.data[: len(order)][order]
    for index in (np.int32, np.int64):
        m.indices = m.indices.astype(index)
        ptr, rows, values = _strict(m, lower=lower)
        cols = np.repeat(np.arange(40), np.diff(m.indptr))
        keep = m.indices > cols if lower else m.indices < cols
        assert rows.dtype == np.int32 and values.dtype == np.float64
        np.testing.assert_array_equal(rows, m.indices[keep])
        np.testing.assert_array_equal(values, m.data[keep])
        np.testing.assert_array_equal(
            ptr, np.r_[0, np.cumsum(np.bincount(cols[keep], minlength=40))]
        )
