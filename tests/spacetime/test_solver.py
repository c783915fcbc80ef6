"""The numba kernels and structured solves agree with the brute-force references (tests/naive/spacetime.py)."""

import numpy as np
import pytest
from naive import spacetime as naive

from faceretarget.plugins.spacetime import solver
from faceretarget.plugins.spacetime.prior import fit_prior


def random_problem(
    seed=0,
    n_frames=30,
    n_markers=7,
    n_shapes=5,
    alpha=0.3,
    beta=0.0,
    marker_weights=None,
    center="neutral",
    column_scale=None,
):
    """Random basis (columns times ``column_scale``), smooth deltas, a PCA prior from the shapes and a System."""
    rng = np.random.default_rng(seed)
    basis = rng.normal(size=(3 * n_markers, n_shapes))
    if column_scale is not None:
        basis = basis * np.asarray(column_scale, dtype=np.float64)
    t = np.arange(n_frames)[:, None]
    deltas = np.sin(t / 5.0 + rng.uniform(0, 6, 3 * n_markers)) + 0.1 * rng.normal(
        size=(n_frames, 3 * n_markers)
    )
    deltas = deltas.reshape(n_frames, n_markers, 3)
    neutral = rng.normal(size=3 * n_markers)
    samples = neutral[None] + np.vstack([basis.T, 0.5 * rng.normal(size=(3, n_shapes)) @ basis.T])
    prior = fit_prior(samples, basis, neutral, center)
    mw = np.ones(n_markers) if marker_weights is None else marker_weights
    system = solver.System(basis, alpha * prior.matrix, alpha * prior.vector, beta, mw)
    energy = dict(
        prior_factor=prior.factor,
        prior_offset=prior.offset,
        alpha=alpha,
        beta=beta,
        marker_weights=mw,
        ridge=system.ridge_matrix,
    )
    return system, deltas, energy


def known_frames(n_frames, frames, n_shapes, seed=1):
    known = np.zeros(n_frames, bool)
    known[frames] = True
    values = np.random.default_rng(seed).normal(size=(n_frames, n_shapes))
    return known, values


def rel(a, b):
    return np.linalg.norm(a - b) / np.linalg.norm(b)


@pytest.mark.parametrize("beta", [0.0, 0.7])
@pytest.mark.parametrize("frames", [[0, 29], [0, 11, 12, 29], [5], [0]])
def test_structured_solve_matches_assembled_rows(beta, frames):
    system, deltas, energy = random_problem(beta=beta)
    known, values = known_frames(30, frames, 5)
    got = solver.solve_movement(system, deltas, known, values)
    want = naive.solve_rows(system.basis, deltas, known, values, **energy)
    assert rel(got, want) < 1e-8
    assert np.array_equal(got[known], values[known])


@pytest.mark.parametrize("weights", ["uniform 2.5", "varied"])
def test_structured_solve_with_marker_weights_matches_assembled_rows(weights):
    """Per-marker Sobolev weights in the structured solve: uniform ones (folded into beta, one
    projection) and varied ones (a second projection) both give the assembled optimum."""
    mw = np.full(7, 2.5) if weights == "uniform 2.5" else np.linspace(0.2, 3.0, 7)
    system, deltas, energy = random_problem(beta=0.6, marker_weights=mw)
    known, values = known_frames(30, [0, 29], 5)
    got = solver.solve_movement(system, deltas, known, values)
    want = naive.solve_rows(system.basis, deltas, known, values, **energy)
    assert rel(got, want) < 1e-8
    assert system.uniform_marker_weights == (weights == "uniform 2.5")


def test_structured_solve_matches_paper_kronecker_system():
    system, deltas, energy = random_problem(beta=0.2, center="mean")
    known, values = known_frames(30, [0, 17, 29], 5)
    got = solver.solve_movement(system, deltas, known, values)
    want = naive.solve_kronecker(
        system.basis,
        deltas,
        known,
        values,
        prior_matrix=system.prior_matrix,
        prior_vector=system.prior_vector,
        beta=0.2,
        ridge=system.ridge_matrix,
    )
    assert rel(got, want) < 1e-8


def test_missing_samples_drop_rows_exactly():
    system, deltas, energy = random_problem(seed=3, beta=0.4)
    rng = np.random.default_rng(4)
    deltas = np.where(rng.random(deltas.shape[:2])[..., None] < 0.2, np.nan, deltas)
    known, values = known_frames(30, [0, 29], 5)
    got = solver.solve_movement(system, deltas, known, values)
    want = naive.solve_rows(system.basis, deltas, known, values, **energy)
    assert rel(got, want) < 1e-8
    # zero-filling the missing samples would be a different (wrong) answer
    zero_filled = solver.solve_movement(system, np.nan_to_num(deltas), known, values)
    assert rel(zero_filled, want) > 1e-3


def test_per_frame_marker_weights_use_the_general_solve():
    rng = np.random.default_rng(5)
    frame_weights = rng.uniform(0.0, 2.0, (30, 7))
    frame_weights[:, 2] = 0.0
    system, deltas, energy = random_problem(seed=5, beta=1.5)
    energy["marker_weights"] = frame_weights
    known, values = known_frames(30, [0, 29], 5)
    got = solver.solve_movement(system, deltas, known, values, frame_weights)
    want = naive.solve_rows(system.basis, deltas, known, values, **energy)
    assert rel(got, want) < 1e-8


def test_general_solve_equals_structured_on_complete_data():
    system, deltas, _ = random_problem(seed=6, beta=0.3)
    known, values = known_frames(30, [0, 9, 29], 5)
    flat = solver.flatten_deltas(deltas)
    structured = solver._solve_structured(system, flat, known, values)
    general = solver._solve_general(system, flat, np.zeros((30, 7), bool), known, values, None)
    assert rel(general, structured) < 1e-9


def test_no_boundary_with_sobolev_term():
    system, deltas, energy = random_problem(seed=7, beta=0.5)
    known = np.zeros(30, bool)
    got = solver.solve_movement(system, deltas, known, np.zeros((30, 5)))
    want = naive.solve_rows(system.basis, deltas, known, np.zeros((30, 5)), **energy)
    assert rel(got, want) < 1e-8


def test_large_problem_normal_equation_residual():
    """At larger sizes the system's conditioning grows with frames squared: compare residuals."""
    system, deltas, energy = random_problem(
        seed=8, n_frames=1200, n_markers=20, n_shapes=16, alpha=0.05
    )
    known, values = known_frames(1200, [0, 600, 1199], 16)
    got = solver.solve_movement(system, deltas, known, values)
    kw = dict(
        prior_matrix=system.prior_matrix,
        prior_vector=system.prior_vector,
        ridge=system.ridge_matrix,
    )
    want = naive.solve_kronecker(system.basis, deltas, known, values, **kw)
    res_got = naive.kronecker_residual(got, system.basis, deltas, known, values, **kw)
    res_want = naive.kronecker_residual(want, system.basis, deltas, known, values, **kw)
    assert res_got < 1e-8
    assert res_got < 100 * max(res_want, 1e-15)
    assert rel(got, want) < 1e-6


def test_duplicate_shapes_are_regularized():
    system, deltas, _ = random_problem(seed=9)
    basis = np.hstack([system.basis, system.basis[:, :1]])  # shape 5 duplicates shape 0
    dup = solver.System(basis, np.zeros((6, 6)), np.zeros(6), 0.0, None)
    known, values = known_frames(30, [0, 29], 6)
    values[:, 5] = values[:, 0]
    got = solver.solve_movement(dup, deltas, known, values)
    want = naive.solve_rows(basis, deltas, known, values, ridge=dup.ridge_matrix)
    assert rel(got, want) < 1e-6
    np.testing.assert_allclose(got[:, 5], got[:, 0], atol=1e-6 * np.abs(got).max())


@pytest.mark.parametrize("use_prior", [False, True])
def test_per_frame_solve_matches_lstsq(use_prior):
    system, deltas, energy = random_problem(seed=10, alpha=0.8)
    deltas = np.where(
        np.random.default_rng(11).random(deltas.shape[:2])[..., None] < 0.15, np.nan, deltas
    )
    got = solver.solve_per_frame(system, deltas, use_prior=use_prior)
    kw = (
        dict(prior_factor=energy["prior_factor"], prior_offset=energy["prior_offset"], alpha=0.8)
        if use_prior
        else {}
    )
    want = naive.per_frame(system.basis, deltas, ridge=system.ridge_matrix, **kw)
    assert rel(got, want) < 1e-8


def test_bounded_active_set_matches_bvls_and_kkt():
    rng = np.random.default_rng(12)
    n_markers, m = 10, 8
    # correlated shapes make unconstrained weights leave the box, so bounds become active
    base = rng.normal(size=(3 * n_markers, 3))
    basis = base @ rng.normal(size=(3, m)) + 0.05 * rng.normal(size=(3 * n_markers, m))
    deltas = (basis @ rng.uniform(-0.5, 1.5, (m, 25))).T + 0.3 * rng.normal(
        size=(25, 3 * n_markers)
    )
    deltas = deltas.reshape(25, n_markers, 3)
    deltas[3, 4] = np.nan
    system = solver.System(basis, np.zeros((m, m)), np.zeros(m), 0.0, None)
    got = solver.solve_bounded(system, deltas, -0.5, 1.5)
    want = naive.bounded_per_frame(basis, deltas, -0.5, 1.5, ridge=system.ridge_matrix)
    free = solver.solve_per_frame(system, deltas, use_prior=False)
    assert ((free < -0.5) | (free > 1.5)).mean() > 0.1  # the bounds do bind
    assert np.all(got >= -0.5) and np.all(got <= 1.5)
    assert np.abs(got - want).max() < 1e-7
    # KKT: gradient vanishes on free variables and points outward on active bounds
    flat = deltas.reshape(25, -1)
    for t in range(25):
        ok = ~np.isnan(flat[t])
        grad = basis[ok].T @ (basis[ok] @ got[t] - flat[t, ok]) + system.ridge_matrix @ got[t]
        scale = np.abs(basis[ok].T @ flat[t, ok]).max()
        inside = (got[t] > -0.5 + 1e-9) & (got[t] < 1.5 - 1e-9)
        assert np.all(np.abs(grad[inside]) < 1e-8 * scale)
        assert np.all(grad[got[t] <= -0.5 + 1e-9] >= -1e-8 * scale)
        assert np.all(grad[got[t] >= 1.5 - 1e-9] <= 1e-8 * scale)


@pytest.mark.parametrize("center", ["neutral", "mean"])
def test_prior_matches_covariance_eigendecomposition(center):
    rng = np.random.default_rng(13)
    basis = rng.normal(size=(18, 5))
    neutral = rng.normal(size=18)
    samples = neutral[None] + rng.normal(size=(4, 5)) @ basis.T  # fewer samples than shapes
    prior = fit_prior(samples, basis, neutral, center)
    q_mat, q_vec = naive.pca_prior(samples, basis, neutral, center)
    np.testing.assert_allclose(prior.matrix, q_mat, atol=1e-9 * np.abs(q_mat).max())
    np.testing.assert_allclose(prior.vector, q_vec, atol=1e-9 * max(np.abs(q_mat).max(), 1.0))
    w = rng.normal(size=(3, 5))
    direct = np.einsum("fi,ij,fj->f", w, q_mat, w) - 2 * w @ q_vec
    offset = prior.energy(np.zeros((1, 5)))[0]
    np.testing.assert_allclose(prior.energy(w), direct + offset, rtol=1e-9, atol=1e-9)


def test_mean_centred_prior_penalizes_neutral_of_dependent_shapes():
    rng = np.random.default_rng(14)
    half = rng.normal(size=(12, 2))
    basis = np.hstack([half, half.sum(axis=1, keepdims=True)])  # shape 2 = shape 0 + shape 1
    neutral = rng.normal(size=12)
    samples = neutral[None] + basis.T
    zero = np.zeros((1, 3))
    assert fit_prior(samples, basis, neutral, "mean").energy(zero)[0] > 0.1
    assert fit_prior(samples, basis, neutral, "neutral").energy(zero)[0] == pytest.approx(
        0.0, abs=1e-12
    )


def test_single_and_two_frame_sequences():
    system, deltas, energy = random_problem(seed=15, n_frames=2)
    one = solver.solve_movement(system, deltas[:1], np.ones(1, bool), np.full((1, 5), 0.25))
    assert np.array_equal(one, np.full((1, 5), 0.25))
    known = np.array([True, False])
    values = np.zeros((2, 5))
    got = solver.solve_movement(system, deltas, known, values)
    want = naive.solve_rows(system.basis, deltas, known, values, **energy)
    assert rel(got, want) < 1e-8


@pytest.mark.parametrize("missing", [False, True])
def test_energy_terms_match_a_frame_by_frame_loop(missing):
    """Per-frame position and velocity residuals (fig. 11's measure), across the kernel's
    blocks of ``ENERGY_BLOCK`` frames, with missing markers dropped from both."""
    from faceretarget.plugins.spacetime._kernels import ENERGY_BLOCK

    n = 2 * ENERGY_BLOCK + 9
    system, deltas, _ = random_problem(n_frames=n)
    deltas = deltas.copy()
    if missing:
        deltas[6, 2] = deltas[7, 4] = deltas[20, 0] = np.nan
        deltas[ENERGY_BLOCK - 1, 1] = deltas[ENERGY_BLOCK, 3] = np.nan  # across a block edge
    weights = np.random.default_rng(5).normal(size=(n, system.n_shapes))
    got = solver.energy_terms(system, deltas, weights)
    s = deltas.reshape(n, -1)
    r = [np.where(np.isnan(s[t]), 0.0, weights[t] @ system.basis.T - s[t]) for t in range(n)]
    position = [float(np.nansum(x**2)) for x in r]
    velocity = [0.0] + [
        float(np.sum(np.where(np.isnan(s[t]) | np.isnan(s[t - 1]), 0.0, r[t] - r[t - 1]) ** 2))
        for t in range(1, n)
    ]
    np.testing.assert_allclose(got["position"], position, rtol=1e-12)
    np.testing.assert_allclose(got["velocity"], velocity, rtol=1e-12)


@pytest.mark.parametrize("beta, weighted", [(0.0, False), (0.7, False), (0.7, True)])
@pytest.mark.parametrize("frames", [[0, 39], [0, 11, 12, 39], []])
def test_structured_solve_energies_match_energy_terms(beta, weighted, frames):
    """The energies a structured solve returns (from its modal quantities, no ``B w``) are
    those of :func:`energy_terms` on its weights: known frames, Sobolev term, non-uniform
    marker weights (a second projection in the sweep)."""
    mw = np.linspace(0.5, 2.0, 7) if weighted else None
    system, deltas, _ = random_problem(n_frames=40, beta=beta, marker_weights=mw)
    known, values = known_frames(40, frames, system.n_shapes)
    terms = {}
    weights = solver.solve_movement(system, deltas, known, values, terms=terms)
    want = solver.energy_terms(system, deltas, weights)
    assert set(terms) == {"velocity", "position"}
    np.testing.assert_allclose(terms["position"], want["position"], rtol=1e-9, atol=1e-12)
    np.testing.assert_allclose(terms["velocity"], want["velocity"], rtol=1e-9, atol=1e-12)
    assert terms["velocity"][0] == 0.0


def test_solve_energies_are_left_to_the_caller_on_the_general_path():
    """With a missing marker the block-tridiagonal solve runs: ``terms`` stays empty (the
    retargeter then computes them from the weights)."""
    system, deltas, _ = random_problem(n_frames=20)
    deltas = deltas.copy()
    deltas[4, 2] = np.nan
    known, values = known_frames(20, [0, 19], system.n_shapes)
    terms = {}
    solver.solve_movement(system, deltas, known, values, terms=terms)
    assert terms == {}


def test_structured_energies_are_never_negative_on_an_exact_fit():
    """An exact fit (no prior, data in the basis' span): ``||s||^2 - ...`` cancels to
    rounding, which must not come out negative."""
    system, _, _ = random_problem(n_frames=40, alpha=0.0)
    weights = np.random.default_rng(2).normal(size=(40, system.n_shapes))
    deltas = (weights @ system.basis.T).reshape(40, -1, 3)
    known, values = known_frames(40, [0, 39], system.n_shapes)
    values[[0, 39]] = weights[[0, 39]]
    terms = {}
    solver.solve_movement(system, deltas, known, values, terms=terms)
    assert terms["position"].min() >= 0.0 and terms["velocity"].min() >= 0.0
    assert terms["position"].max() < 1e-12 * np.sum(deltas**2) / 40
