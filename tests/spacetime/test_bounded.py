"""Bounded movement matching (ADMM over the structured solve) and the defaults that depart
from the paper: weight bounds, the position term that keeps held expressions, the global
similarity scale, dense samples for mesh sources."""

import numpy as np
import pytest
from naive import spacetime as naive
from spacetime.test_solver import known_frames, random_problem

import faceretarget as fr
from faceretarget.plugins.spacetime import solver
from faceretarget.plugins.spacetime.retargeter import SpacetimeRetargeter


def energy(system, deltas, weights, l1=0.0):
    """Half the movement-matching energy (the ADMM objective) with ``l1 * sum |w|``."""
    terms = solver.energy_terms(system, deltas, weights)
    prior = np.einsum("fi,ij,fj->", weights, system.prior_matrix, weights) - 2 * np.sum(
        weights @ system.prior_vector
    )
    return (
        0.5 * (terms["velocity"].sum() + system.beta * terms["position"].sum() + prior)
        + l1 * np.abs(weights).sum()
    )


@pytest.fixture
def tight(monkeypatch):
    monkeypatch.setattr(solver, "ADMM_EPS_ABS", 1e-10)
    monkeypatch.setattr(solver, "ADMM_EPS_REL", 1e-9)
    monkeypatch.setattr(solver, "ADMM_MAX_ITER", 20000)
    monkeypatch.setattr(solver, "ADMM_SINGLE", False)  # float32 stops near 1e-6 relative


@pytest.mark.parametrize("beta, l1", [(0.0, 0.0), (0.7, 0.0), (0.7, 0.3)])
@pytest.mark.parametrize("missing", [False, True])
def test_bounded_solve_matches_bvls_on_the_assembled_rows(tight, beta, l1, missing):
    system, deltas, energy_kw = random_problem(beta=beta, n_frames=40)
    if missing:
        deltas = deltas.copy()
        deltas[5, 1] = deltas[17, 3] = np.nan
    known, values = known_frames(40, [0, 20, 39], 5)
    values = np.clip(values, 0, 1)
    lo, hi = np.zeros(5), np.ones(5)
    stats = solver.BoundedStats()
    got = solver.solve_movement_bounded(system, deltas, known, values, lo, hi, l1=l1, stats=stats)
    want = naive.solve_rows_bounded(system.basis, deltas, known, values, lo, hi, l1=l1, **energy_kw)
    assert stats.converged and stats.iterations > 0
    assert np.abs(got - want).max() < 1e-6
    # the bounds bind on this problem: the unconstrained solution leaves them
    free = solver.solve_movement(system, deltas, known, values)
    assert ((free < -1e-3) | (free > 1 + 1e-3)).mean() > 0.1


@pytest.mark.parametrize("l1", [0.0, "per-shape"])
def test_bounded_solve_with_shapes_of_very_different_sizes(tight, l1):
    """A jaw and an eyelid differ ~3,000x in the Gram: the scaled ADMM penalty and per-shape
    L1 weights still give the exact bounded optimum."""
    system, deltas, energy_kw = random_problem(
        beta=0.7, n_frames=40, column_scale=[1.0, 30.0, 0.02, 1.0, 5.0]
    )
    known, values = known_frames(40, [0, 39], 5)
    values = np.clip(values, 0, 1)
    lo, hi = np.zeros(5), np.ones(5)
    weight = 0.05 * np.diag(system.gram) if l1 else 0.0
    got = solver.solve_movement_bounded(system, deltas, known, values, lo, hi, l1=weight)
    want = naive.solve_rows_bounded(
        system.basis, deltas, known, values, lo, hi, l1=weight, **energy_kw
    )
    assert np.abs(got - want).max() < 1e-6


def test_admm_scaling_halves_the_iterations_on_unequal_shapes(monkeypatch):
    system, deltas, _ = random_problem(
        beta=0.7, n_frames=200, column_scale=[1.0, 30.0, 0.02, 1.0, 5.0]
    )
    known, values = known_frames(200, [], 5)
    lo, hi = np.zeros(5), np.ones(5)
    scaled = solver.BoundedStats()
    solver.solve_movement_bounded(system, deltas, known, values, lo, hi, stats=scaled)
    monkeypatch.setattr(solver.System, "admm_scale", property(lambda self: np.ones(self.n_shapes)))
    plain = solver.BoundedStats()
    solver.solve_movement_bounded(system, deltas, known, values, lo, hi, stats=plain)
    assert scaled.converged and plain.converged
    assert scaled.iterations <= 0.5 * plain.iterations


def test_default_tolerance_is_near_optimal_and_exactly_feasible():
    system, deltas, _ = random_problem(beta=0.7, n_frames=60)
    known, values = known_frames(60, [], 5)
    lo, hi = np.zeros(5), np.ones(5)
    got = solver.solve_movement_bounded(system, deltas, known, values, lo, hi)
    assert got.min() >= 0.0 and got.max() <= 1.0
    want = naive.solve_rows_bounded(
        system.basis, deltas, known, values, lo, hi, **random_problem(beta=0.7, n_frames=60)[2]
    )
    assert energy(system, deltas, got) - energy(system, deltas, want) < 1e-3 * energy(
        system, deltas, want
    )


def test_single_precision_w_step_matches_double(monkeypatch):
    """The float32 changes of basis (the default) give the float64 kernel's answer at the
    default tolerance, with known frames inside the sequence and bounds that bind."""
    system, deltas, energy_kw = random_problem(beta=0.7, n_frames=60, n_markers=9, n_shapes=6)
    known, values = known_frames(60, [0, 30, 59], 6)
    values = np.clip(values, 0, 1)
    lo, hi = np.zeros(6), np.ones(6)
    runs = {}
    for single in (True, False):
        monkeypatch.setattr(solver, "ADMM_SINGLE", single)
        stats = solver.BoundedStats()
        got = solver.solve_movement_bounded(system, deltas, known, values, lo, hi, stats=stats)
        assert stats.converged and stats.iterations > 1
        runs[single] = got
    np.testing.assert_array_equal(runs[True][known], values[known])
    assert np.abs(runs[True] - runs[False]).max() < 1e-3
    want = naive.solve_rows_bounded(system.basis, deltas, known, values, lo, hi, **energy_kw)
    assert energy(system, deltas, runs[True]) - energy(system, deltas, want) < 1e-3 * energy(
        system, deltas, want
    )


def test_kept_factors_give_the_answer_of_a_fresh_system():
    """The w-step's Thomas factor is kept per system for the next solve, by step size, dtype
    and known frames: solves with other known frames, or after another length, give exactly
    what a fresh system gives (the factor of one pattern is never used for another)."""
    import copy

    system, deltas, _ = random_problem(beta=0.7, n_frames=40)
    lo, hi = np.zeros(5), np.ones(5)
    patterns = [known_frames(40, frames, 5) for frames in ([0, 39], [0, 20, 39], [0, 39])]
    fresh = copy.deepcopy(system)
    for known, values in patterns:
        values = np.clip(values, 0, 1)
        got = solver.solve_movement_bounded(system, deltas, known, values, lo, hi)
        want = solver.solve_movement_bounded(copy.deepcopy(fresh), deltas, known, values, lo, hi)
        np.testing.assert_array_equal(got, want)
    assert 1 <= len(system._factors) <= solver.ADMM_FACTORS_KEPT
    for kept in system._factors.values():
        assert not any(a.flags.writeable for a in kept)


def test_unconstrained_solution_inside_the_bounds_is_returned_unchanged():
    system, deltas, _ = random_problem(beta=0.7, n_frames=30)
    known, values = known_frames(30, [0], 5)
    free = solver.solve_movement(system, deltas, known, values)
    stats = solver.BoundedStats()
    got = solver.solve_movement_bounded(
        system, deltas, known, values, free.min(0) - 1, free.max(0) + 1, stats=stats
    )
    assert stats.iterations == 0 and np.allclose(got, free, rtol=0, atol=1e-12 * np.abs(free).max())


def test_l1_shrinks_small_weights_to_exactly_zero():
    system, deltas, _ = random_problem(beta=1.0, n_frames=30)
    known, values = known_frames(30, [], 5)
    lo, hi = np.zeros(5), np.ones(5)
    plain = solver.solve_movement_bounded(system, deltas, known, values, lo, hi)
    sparse = solver.solve_movement_bounded(system, deltas, known, values, lo, hi, l1=5.0)
    assert (sparse == 0).sum() > (plain == 0).sum()
    assert np.abs(sparse).sum() < np.abs(plain).sum()


def test_per_shape_l1_shrinks_every_held_shape_by_the_same_amount():
    """``sparsity`` weighs each shape's L1 term by its own position term: a held large shape
    and a held shape 1,000x smaller both lose ``sparsity`` of their weight (a single weight
    from the mean size would zero the small one)."""
    basis = np.zeros((9, 2))
    basis[0, 0], basis[4, 1] = 10.0, 0.01  # orthogonal columns, 1,000x apart
    system = solver.System(basis, np.zeros((2, 2)), np.zeros(2), 1.0, np.ones(3))
    held = np.full((50, 2), 0.5)
    deltas = (held @ basis.T).reshape(50, 3, 3)
    known = np.zeros(50, bool)
    sparsity = 0.05
    got = solver.solve_movement_bounded(
        system, deltas, known, held, np.zeros(2), np.ones(2), l1=sparsity * np.diag(system.gram)
    )
    assert np.abs(got - (0.5 - sparsity)).max() < 1e-3
    source, target, _ = held_smile(30)
    fitted = fr.get("spacetime", sparsity=sparsity).fit(source, target)
    l1 = fitted.system_.l1 / np.diag(fitted.system_.gram)
    assert np.ptp(l1) < 1e-12 * l1.max() and l1.max() > 0


# ---------------------------------------------------------------------------------------
# Through the retargeter
# ---------------------------------------------------------------------------------------
def held_smile(n_hold: int = 300):
    """The synthetic source with a smile ramped in over 15 frames, held, ramped out."""
    case = fr.cases.synthetic(n_frames=30, head_motion=False)
    src = case.source
    names = list(src.rig.names)
    n = 15 + n_hold + 15
    w = np.zeros((n, len(names)))
    ramp = np.linspace(0, 1, 15)
    for shape in ("mouthSmileLeft", "mouthSmileRight"):
        j = names.index(shape)
        w[:15, j], w[15:-15, j], w[-15:, j] = ramp, 1.0, ramp[::-1]
    perf = fr.MeshSequence(src.rig.evaluate(w), src.performance.triangles, fps=30.0)
    return (
        src.replace(performance=perf, head_motion=None),
        case.target,
        case.target.blendshapes.evaluate(w),
    )


@pytest.mark.parametrize("name, keeps", [("spacetime", True), ("spacetime_paper", False)])
def test_held_expression_keeps_its_amplitude_by_default(name, keeps):
    """A smile held 10 s at 30 fps: the default keeps >= 95% of it mid-hold; the paper's pure
    movement matching under the prior lets it fade (a high-pass filter in time)."""
    source, target, truth = held_smile()
    out = np.asarray(fr.get(name).fit(source, target).retarget(source).vertices)
    mid = len(truth) // 2
    kept = np.linalg.norm(out[mid] - truth[0]) / np.linalg.norm(truth[mid] - truth[0])
    assert (kept >= 0.95) == keeps, kept


def test_error_does_not_grow_with_shot_length():
    """The same performance at 120 and at 1,200 frames: error within 20%."""
    errors = []
    for n in (120, 1200):
        case = fr.cases.synthetic(n_frames=n, head_motion=False, resolution=1500)
        anim = fr.get("spacetime").fit(case.source, case.target).retarget(case.source)
        truth = np.asarray(case.truth.vertices)
        errors.append(np.sqrt(np.mean(np.sum((np.asarray(anim.vertices) - truth) ** 2, axis=-1))))
    assert abs(errors[1] / errors[0] - 1) < 0.2, errors


def test_default_weights_stay_in_the_rig_bounds_and_paper_leaves_them(synthetic_case):
    case = synthetic_case
    anim = fr.get("spacetime").fit(case.source, case.target).retarget(case.source)
    paper = fr.get("spacetime_paper").fit(case.source, case.target).retarget(case.source)
    assert anim.weights.min() >= 0.0 and anim.weights.max() <= 1.0
    assert anim.provenance["diagnostics"]["fraction_outside_bounds"] == 0.0
    assert ((paper.weights < 0) | (paper.weights > 1)).mean() > 0.01
    declared = case.target.replace(
        blendshapes=fr.BlendshapeRig(
            case.target.blendshapes.neutral,
            case.target.blendshapes.deltas,
            case.target.blendshapes.names,
            bounds=np.tile([0.0, 0.5], (case.target.blendshapes.n_shapes, 1)),
        )
    )
    capped = fr.get("spacetime").fit(case.source, declared).retarget(case.source)
    assert capped.weights.max() <= 0.5 and capped.weights.max() > 0.45  # the rig's own bounds win


def test_mesh_source_is_fitted_densely_and_markers_on_landmarks(synthetic_case):
    case = synthetic_case
    dense = fr.get("spacetime").fit(case.source, case.target).retarget(case.source)
    diag = dense.provenance["diagnostics"]
    assert diag["samples"] == "dense" and diag["n_points"] > 10 * len(case.target.landmarks)
    markers = fr.Source(
        fr.MarkerSequence(
            case.source.marker_positions(),
            names=case.source.landmarks.names,
            reference=case.source.marker_reference(),
            fps=case.source.fps,
        )
    )
    sparse = fr.get("spacetime").fit(markers, case.target).retarget(markers)
    assert sparse.provenance["diagnostics"]["samples"] == "landmarks"
    with pytest.raises(fr.errors.CapabilityError, match="mesh-sequence source"):
        fr.get("spacetime", samples="dense").fit(markers, case.target)


def test_units_of_the_source_do_not_change_the_weights(synthetic_case):
    """Source in metres instead of centimetres: the global scale absorbs the unit."""
    case = synthetic_case
    perf = case.source.performance
    metres = case.source.replace(
        performance=fr.MeshSequence(
            np.asarray(perf.vertices) * 0.01,
            perf.triangles,
            fps=perf.fps,
            reference=np.asarray(perf.reference.vertices) * 0.01,
        ),
        examples=None,
        rig=None,
        actor_layers=None,
        head_motion=None,
    )
    plain = case.source.replace(examples=None, rig=None, actor_layers=None, head_motion=None)
    a = fr.get("spacetime").fit(plain, case.target).retarget(plain)
    b = fr.get("spacetime").fit(metres, case.target).retarget(metres)
    assert np.abs(a.weights - b.weights).max() < 1e-4
    assert (
        abs(
            b.provenance["diagnostics"]["transfer_scale"]
            / a.provenance["diagnostics"]["transfer_scale"]
            - 0.01
        )
        < 1e-9
    )


def test_admm_sweep_with_steady_pivots_matches_the_thomas_solve():
    """The ADMM sweep reads the converged interior pivot in place of most rows of the factor:
    same solution as the plain Thomas solve (float64), with known frames cutting the chain."""
    from faceretarget.plugins.spacetime import _kernels as k

    rng = np.random.default_rng(3)
    n_frames, m = 400, 6
    lam = np.array([0.01, 0.03, 0.1, 0.5, 0.9, 1.0])
    known = np.zeros(n_frames, bool)
    known[[0, 150, 151, 399]] = True
    yk = rng.normal(size=(n_frames, m))
    r = rng.normal(size=(n_frames, m))
    inv, limit, steady = np.empty((n_frames, m)), np.empty(m), np.empty(n_frames, bool)
    k.thomas_factor(lam, known, inv)
    k.steady_pivots(lam, known, inv, limit, steady)
    assert 0.3 < steady.mean() < 0.95  # the fast path runs, and not on every row
    assert not steady[known].any() and not steady[[1, 152]].any()
    g = 1 - lam
    np.testing.assert_allclose(limit, 1 / (2 * g + lam - g * g * limit), rtol=1e-13)
    want = np.empty_like(r)
    k.thomas_apply(r, lam, known, yk, inv, want)
    got, sweep, carry = r.copy(), np.empty_like(r), np.empty(m)
    k._thomas_steady(got, lam, known, yk, inv, limit, steady, sweep, carry)
    np.testing.assert_allclose(got, want, rtol=1e-9, atol=1e-9 * np.abs(want).max())
    # a mode whose pivots converge too slowly keeps every row on the factor
    slow = np.array([1e-4, 0.1, 0.1, 0.1, 0.1, 0.1])
    k.thomas_factor(slow, known, inv)
    k.steady_pivots(slow, known, inv, np.empty(m), flags := np.empty(n_frames, bool))
    assert not flags.any()
    k.thomas_factor(lam, known, inv)
    # a wrong limit on the steady rows is seen
    k._thomas_steady(got := r.copy(), lam, known, yk, inv, limit * 1.001, steady, sweep, carry)
    assert np.abs(got - want).max() > 1e-6 * np.abs(want).max()


def test_fraction_outside_bounds_counts_a_constraint_outside_them(make_toy):
    """A user constraint outside the bounds is kept (the user's explicit choice) and counted
    by the diagnostic; without bounds the diagnostic is 0."""
    toy = make_toy()
    r = SpacetimeRetargeter(bounds=(0.0, 1.0), constraints={5: {"shape0": 1.8}})
    anim = r.fit(toy.source, toy.target).retarget(toy.source)
    assert anim.weights[5, 0] == 1.8
    assert anim.provenance["diagnostics"]["fraction_outside_bounds"] == pytest.approx(
        1 / anim.weights.size
    )
    free = SpacetimeRetargeter(bounds=None).fit(toy.source, toy.target).retarget(toy.source)
    assert free.provenance["diagnostics"]["fraction_outside_bounds"] == 0.0
