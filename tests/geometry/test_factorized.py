"""SPDFactor: LDL^T factorization (QDLDL) with numba multi-column triangular solves."""

import os
import pickle
import subprocess
import sys
import threading
from pathlib import Path

import numpy as np
import pytest
import scipy.sparse as sp
import scipy.sparse.linalg
from naive.coating import grid_mesh

from faceretarget.errors import ConfigError, NumericalError, ShapeError
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


@pytest.mark.parametrize("dtype, tol", [(np.float64, 1e-12), (np.float32, 2e-6)])
def test_solve_frames_adds_the_solution_in_the_chosen_precision(dtype, tol):
    m = _system()
    fac = SPDFactor(m, frames_dtype=dtype)
    rng = np.random.default_rng(4)
    rhs, add = rng.normal(size=(5, fac.n, 3)), rng.normal(size=(5, fac.n, 3))
    dense = np.linalg.solve(m.toarray(), rhs.transpose(1, 0, 2).reshape(fac.n, -1))
    want = add + dense.reshape(fac.n, 5, 3).transpose(1, 0, 2)
    got = fac.solve_frames(rhs, add)
    assert got.dtype == np.float64
    assert all(a.dtype == dtype for a in fac._frame_values)  # the solves really run in it
    assert np.abs(got - want).max() <= tol * np.abs(dense).max()
    np.testing.assert_allclose(fac.solve(rhs[0]), dense[:, :3], atol=1e-12)  # solve: float64
    again = pickle.loads(pickle.dumps(fac))
    assert again.frames_dtype == dtype
    np.testing.assert_array_equal(again.solve_frames(rhs, add), got)
    assert all(a.dtype == dtype for a in again._frame_values)
    for into in (0, 1):  # into the caller's rhs or add: each column read before written
        arrays = [rhs.copy(), add.copy()]
        assert fac.solve_frames(*arrays, out=arrays[into]) is arrays[into]
        np.testing.assert_array_equal(arrays[into], got)
    with pytest.raises(ShapeError, match="out must be"):
        fac.solve_frames(rhs, add, out=np.empty((5, fac.n, 3), dtype=np.float32))
    with pytest.raises(ConfigError, match="frames_dtype"):
        SPDFactor(m, frames_dtype=np.int32)


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
    assert all(f._ready for f in factors)
    for f, m, b in zip(factors, systems, rhs, strict=True):
        np.testing.assert_array_equal(f.solve(b), SPDFactor(m).solve(b))
    v, t = grid_mesh(6)
    singular = SPDFactor(uniform_laplacian(t, len(v)), what="the singular one")
    with pytest.raises(NumericalError, match="the singular one"):
        factorize([SPDFactor(_system(9)), singular])


def test_factorize_runs_side_by_side_and_once_per_factor(monkeypatch):
    monkeypatch.setattr(factorized, "worker_count", lambda n: min(n, 2))
    both = threading.Barrier(2, timeout=20)  # one after the other would break the barrier
    calls = []

    ldl = factorized._ldl

    def waiting(upper):
        calls.append(upper.shape[0])
        both.wait()
        return ldl(upper)

    monkeypatch.setattr(factorized, "_ldl", waiting)
    one, two = SPDFactor(_system(10)), SPDFactor(_system(12))
    factorize([one, two, one])  # listed twice: factorized once
    assert sorted(calls) == [100, 144]
    assert one._ready and two._ready


LEAK_SCRIPT = """
import ctypes, ctypes.util, gc, sys
from pathlib import Path
import numpy as np, scipy.sparse as sp
from faceretarget.geometry import factorized
factorized.worker_count = lambda n: min(n, int(sys.argv[1]))
n = 200_000
a = sp.diags([-np.ones(n - 1), 4 * np.ones(n), -np.ones(n - 1)], [-1, 0, 1], format="csc")
trim = getattr(ctypes.CDLL(ctypes.util.find_library("c")), "malloc_trim", lambda pad: 0)
def rss():
    return int(Path("/proc/self/statm").read_text().split()[1]) * 4096 / 2**20
def once():
    factors = [factorized.SPDFactor(a), factorized.SPDFactor(a)]
    factorized.factorize(factors)
    del factors
    gc.collect()
    trim(0)
once()
before = rss()
for _ in range(24):
    once()
print(rss() - before)
"""


@pytest.mark.skipif(not Path("/proc/self/statm").exists(), reason="reads the RSS from /proc")
def test_factorize_on_threads_frees_its_factors():
    """Factors made on factorize's threads are freed like those made serially (scipy frees
    a SuperLU object only on the thread that made it, issue 15921: keeping one lost ~170 MB
    per coating fit at 80K vertices). A fresh process each, 24 rounds of two factorizations
    of 200K unknowns: a leak of the factors is ~22 MB a round (500 MB), of SuperLU's objects
    ~25 MB a round; the worker threads' malloc arenas keep 20-40 MB however many rounds
    (measured: 23-24 MB after 8 rounds, 28-40 MB after 32), hence the bound of 60 MB."""

    def growth(workers):
        done = subprocess.run(
            [sys.executable, "-c", LEAK_SCRIPT, str(workers)],
            capture_output=True,
            text=True,
            timeout=300,
        )
        assert done.returncode == 0, done.stderr
        return float(done.stdout.split()[-1])

    serial, threaded = growth(1), growth(2)
    assert serial < 60, f"{serial:.0f} MiB kept serially: the factors leak"
    assert threaded < serial + 60, f"{threaded:.0f} MiB kept on threads, {serial:.0f} MiB serially"


def test_only_arrays_are_kept():
    """The factors' arrays, not the factorization's solver object (nor SuperLU's: those
    leak when freed on another thread than the one that made them, scipy issue 15921)."""
    import qdldl

    fac = SPDFactor(_system())
    fac.solve(np.ones(fac.n))
    kept = [
        k
        for k, v in vars(fac).items()
        if isinstance(v, (qdldl.Solver, scipy.sparse.linalg.SuperLU))
    ]
    assert not kept, f"solver objects kept in {kept}"


def test_the_callers_matrix_is_left_as_given():
    m = _system(9)
    dup = sp.csc_matrix(
        (np.r_[1.0, m.data], np.r_[0, m.indices], np.r_[0, m.indptr[1:] + 1]), shape=m.shape
    )  # (0, 0) listed twice, unsorted
    data, indices = dup.data.copy(), dup.indices.copy()
    fac = SPDFactor(dup)
    x = fac.solve(np.ones(m.shape[0]))
    np.testing.assert_allclose(dup @ x, np.ones(m.shape[0]), atol=1e-10)
    np.testing.assert_array_equal(dup.data, data)
    np.testing.assert_array_equal(dup.indices, indices)


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


KERNELS_SCRIPT = """
import threading
import scipy.sparse as sp
from faceretarget.geometry import _factor_kernels, factorized
seen = []
start = threading.Thread.start
def counted(self):
    seen.append(len(_factor_kernels.lu_solve.signatures))
    return start(self)
threading.Thread.start = counted
def system(n):
    return (sp.diags([-1.0] * (n - 1), -1) + sp.diags([4.0] * n) + sp.diags([-1.0] * (n - 1), 1)).tocsc()
factorized.factorize([factorized.SPDFactor(system(50)), factorized.SPDFactor(system(60))])
print(seen)
"""


def test_factorize_loads_its_kernels_on_the_callers_thread(tmp_path):
    """numba loading kernels on one worker thread while another ran or loaded others
    crashed the process now and then (SIGSEGV in LLVM: ~1 run in 3 of the compare example
    in docs/evaluation.md when the coating fit factorized on background threads, a design
    since dropped): ``factorize`` compiles or loads them first, so the workers only run
    them. A fresh process with its own empty numba cache."""
    env = dict(os.environ, NUMBA_CACHE_DIR=str(tmp_path / "numba"))
    out = subprocess.run(
        [sys.executable, "-c", KERNELS_SCRIPT], capture_output=True, text=True, env=env, check=True
    )
    seen = eval(out.stdout.strip())  # one entry per worker thread started (one or two)
    assert seen and all(entry == 1 for entry in seen), out.stdout + out.stderr


def test_matrices_that_are_not_positive_definite_are_refused():
    """An LDL^T without pivoting is exact for positive-definite matrices only: an
    indefinite or a zero diagonal is a NumericalError naming the matrix, never a solve."""
    indefinite = sp.csc_matrix(np.array([[1.0, 2.0, 0.0], [2.0, 1.0, 0.0], [0.0, 0.0, 3.0]]))
    with pytest.raises(NumericalError, match="the indefinite one.*not positive definite"):
        SPDFactor(indefinite, what="the indefinite one").solve(np.ones(3))
    zero_pivot = sp.csc_matrix(np.ones((2, 2)))  # positive diagonal, second pivot exactly 0
    with pytest.raises(NumericalError, match="the flat one: factorization failed"):
        SPDFactor(zero_pivot, what="the flat one").solve(np.ones(2))
    d = np.diag(np.arange(1.0, 13.0))
    d[0, 0] = d[1, 1] = 0.0
    d[0, 1] = d[1, 0] = 1.0
    with pytest.raises(NumericalError, match="diagonal entry 0 is 0"):
        SPDFactor(sp.csc_matrix(d)).solve(np.ones(12))


def test_the_ordering_is_applied_on_both_sides():
    """The fill-reducing ordering permutes rows and columns: a grid Laplacian's AMD order is
    far from the identity, and ``solve`` / ``solve_frames`` must undo it on the way out."""
    m = _system(14)
    fac = SPDFactor(m)
    rhs = np.random.default_rng(7).normal(size=(m.shape[0], 3))
    np.testing.assert_allclose(fac.solve(rhs), np.linalg.solve(m.toarray(), rhs), atol=1e-12)
    assert np.count_nonzero(fac._order != np.arange(fac.n)) > fac.n // 2
    frames = np.stack([rhs, 2 * rhs])
    want = np.stack([np.linalg.solve(m.toarray(), f) for f in frames])
    np.testing.assert_allclose(fac.solve_frames(frames), want, atol=1e-12)


def test_solve_rows_into_its_own_right_hand_sides():
    """``solve_rows(x, rows, x)`` (no copies) gives ``solve_rows(x, rows, out)`` bit for bit
    and leaves the rows not solved for as they were; a strided ``x`` is refused."""
    m = _system(11)
    fac = SPDFactor(m)
    rng = np.random.default_rng(6)
    rows = rng.choice(fac.n + 9, fac.n, replace=False)  # unsorted, 9 rows not solved for
    rhs = rng.normal(size=(fac.n + 9, 12))  # two blocks of columns on two threads
    want = fac.solve_rows(rhs, rows, np.zeros_like(rhs))
    x = rhs.copy()
    assert fac.solve_rows(x, rows, x) is x
    np.testing.assert_array_equal(x[rows], want[rows])
    others = np.setdiff1d(np.arange(fac.n + 9), rows)
    np.testing.assert_array_equal(x[others], rhs[others])
    strided = np.zeros((fac.n + 9, 10))[:, ::2]
    with pytest.raises(ShapeError, match="C-contiguous"):
        fac.solve_rows(strided, rows, strided)
    wrapped = np.where(rows > 4, rows - (fac.n + 9), rows)  # negative rows, as numpy reads them
    for where in (lambda x: np.zeros_like(x), lambda x: x):  # a copy, in place
        x = rhs.copy()
        np.testing.assert_array_equal(fac.solve_rows(x, wrapped, where(x))[rows], want[rows])
    for bad in (np.r_[rows[:-1], -(fac.n + 10)], np.r_[rows[:-1], fac.n + 9]):
        with pytest.raises(ShapeError, match=r"must be in \[-"):
            fac.solve_rows(rhs.copy(), bad, rhs.copy())
    clash = rows.copy()
    clash[-1] = clash[0] - (fac.n + 9)  # -1 and m - 1: one row twice
    with pytest.raises(ShapeError, match="distinct rows"):
        fac.solve_rows(rhs, clash, np.zeros_like(rhs))


@pytest.mark.parametrize("n", [1, 2, 7, 40])
def test_permute_rows_is_fancy_indexing(n):
    """The in-place kernel moves rows as ``x[source]`` does, for permutations with cycles of
    every length (fixed points included)."""
    from faceretarget.geometry._factor_kernels import permute_rows

    rng = np.random.default_rng(n)
    for source in (rng.permutation(n), np.arange(n), np.roll(np.arange(n), 1)):
        x = rng.normal(size=(n, 3))
        want = x[source]
        permute_rows(x, source)
        np.testing.assert_array_equal(x, want)


def test_solve_rows_is_solve_on_the_rows_in_place():
    """``solve_rows(rhs, rows, out)`` is ``out[rows] = solve(rhs[rows])`` bit for bit, and
    leaves the other rows of ``out`` alone (the deformation transfer's free vertices)."""
    m = _system(11)
    fac = SPDFactor(m)
    rng = np.random.default_rng(5)
    rows = np.sort(rng.choice(fac.n + 9, fac.n, replace=False))  # 9 rows are not solved for
    rhs = rng.normal(size=(fac.n + 9, 6))
    out = np.full((fac.n + 9, 6), 7.0)
    got = fac.solve_rows(rhs, rows, out)
    assert got is out
    want = np.full_like(out, 7.0)
    want[rows] = fac.solve(rhs[rows])
    np.testing.assert_array_equal(out, want)
    np.testing.assert_allclose(m @ out[rows], rhs[rows], atol=1e-10)
    with pytest.raises(ShapeError, match="solve_rows"):
        fac.solve_rows(rhs, rows[:-1], out)
    with pytest.raises(ShapeError, match="solve_rows"):
        fac.solve_rows(rhs, rows, out.astype(np.float32))
    single = np.zeros_like(out)  # other dtypes are solved in float64, as by solve
    fac.solve_rows(rhs.astype(np.float32), rows, single)
    np.testing.assert_array_equal(single[rows], fac.solve(rhs.astype(np.float32)[rows]))
    mask = np.zeros(fac.n + 9, dtype=bool)
    mask[rows] = True
    with pytest.raises(ShapeError, match="integer row indices"):
        fac.solve_rows(rhs, mask[: fac.n], out)  # a boolean mask is not row indices
    with pytest.raises(ShapeError, match="distinct rows"):
        fac.solve_rows(rhs, np.r_[rows[:-1], rows[0]], out)
