"""Sec. 6 spacetime editing against an independent constrained re-solve (paper-exact settings).

An edit makes the edited frame (and, with a window, the window's ends) extra boundary
conditions of the whole-sequence problem (Eq. 4). The reference assembles that problem's
least-squares rows densely with the edited and boundary frames fixed and solves it with
``lstsq`` (``naive.spacetime_paper.constrained_resolve``). With the prior (``alpha > 0``) the
true edit is a screened-Poisson response that decays faster than the linear blend of the
edit offset that pure Poisson editing gives, so a shortcut that blends the offset is caught.
"""

import numpy as np
import pytest
from naive.spacetime_paper import constrained_resolve, linear_blend, paper

#: Prior weight of these tests: the prior's decay length is 3-7 frames on the toy rig, so the
#: edit differs clearly from a linear blend over windows of 10-20 frames.
ALPHA = 1.0


def rel(a, b):
    return float(np.abs(np.asarray(a) - np.asarray(b)).max() / np.abs(np.asarray(b)).max())


def setup(make_toy, alpha=ALPHA, **toy):
    toy = make_toy(**{"n_frames": 40, "noise": 0.02, "extra_source_shapes": 2, **toy})
    # the paper's prior (Eq. 3, about the sample mean): its linear term q is non-zero, so a sign
    # error there shows (the neutral-centred prior of independent shapes has q = 0)
    r = paper(alpha=alpha, prior_center="mean", remove_head_motion=False).fit(
        toy.source, toy.target
    )
    assert alpha == 0 or np.abs(r.prior_.vector).max() > 0.1
    anim = r.retarget(toy.source)
    deltas = toy.world - toy.src_neutral  # no head motion: the local deltas, computed here
    np.testing.assert_allclose(anim.extras["spacetime"]["deltas"], deltas, atol=1e-12)
    prior = dict(
        prior_factor=r.prior_.factor,
        prior_offset=r.prior_.offset,
        alpha=r.alpha_effective_,
        ridge=r.system_.ridge_matrix,
    )
    return toy, r, anim, deltas, prior


def resolve(r, deltas, current, fixed, edits, prior):
    """Whole-sequence re-solve with ``fixed`` frames at ``current`` and ``edits {frame: weights}``."""
    known = np.zeros(len(current), bool)
    known[list(fixed) + list(edits)] = True
    values = np.array(current, dtype=float)
    for f, w in edits.items():
        values[f] = w
    return constrained_resolve(r.basis_, deltas, known, values, **prior)


def test_retarget_is_the_constrained_solve_with_its_boundary_frames(make_toy):
    _, r, anim, deltas, prior = setup(make_toy)
    want = resolve(r, deltas, anim.weights, [0, 39], {}, prior)
    assert rel(anim.weights, want) < 1e-8


def test_whole_sequence_edit_matches_the_resolve_not_a_linear_blend(make_toy):
    toy, r, anim, deltas, prior = setup(make_toy)
    k = 22
    new = anim.weights[k] + np.linspace(-0.6, 0.8, toy.rig.n_shapes)
    edited = r.edit(anim, frame=k, weights=new)
    want = resolve(r, deltas, anim.weights, [0, 39], {k: new}, prior)
    assert rel(edited.weights, want) < 1e-8
    blend = linear_blend(anim.weights, k, new, [0, 39])
    offset = np.abs(new - anim.weights[k]).max()
    # with the prior the response decays within a few frames: the linear blend is far off
    assert np.abs(blend - want).max() > 0.2 * offset
    assert np.abs(edited.weights - blend).max() > 0.2 * offset


def test_windowed_edit_matches_the_resolve_with_the_window_ends_fixed(make_toy):
    toy, r, anim, deltas, prior = setup(make_toy)
    a, k, b = 8, 15, 27
    new = anim.weights[k] - np.linspace(0.9, -0.4, toy.rig.n_shapes)
    edited = r.edit(anim, frame=k, weights=new, window=(a, b))
    want = resolve(r, deltas, anim.weights, [0, a, b, 39], {k: new}, prior)
    assert rel(edited.weights, want) < 1e-8
    assert np.array_equal(edited.weights[: a + 1], anim.weights[: a + 1]) and np.array_equal(
        edited.weights[b:], anim.weights[b:]
    )
    blend = linear_blend(anim.weights, k, new, [0, a, b, 39])
    assert np.abs(blend - want).max() > 0.1 * np.abs(new - anim.weights[k]).max()


def test_accumulated_edits_keep_earlier_edits_as_constraints(make_toy):
    toy, r, anim, deltas, prior = setup(make_toy)
    m = toy.rig.n_shapes
    first_w, second_w = np.full(m, 0.9), np.linspace(0.0, 0.5, m)
    first = r.edit(anim, frame=12, weights=first_w, window=(5, 20))
    second = r.edit(first, frame=30, weights=second_w)  # whole sequence: 0, 12, 30, 39 fixed
    want = resolve(r, deltas, first.weights, [0, 39], {12: first_w, 30: second_w}, prior)
    assert rel(second.weights, want) < 1e-8
    # the window ends of the first edit are not constraints of the second
    assert (
        abs(second.weights[5] - first.weights[5]).max() > 1e-6
        or abs(second.weights[20] - first.weights[20]).max() > 1e-6
    )


def test_edit_with_missing_markers_matches_the_resolve(make_toy):
    """Frames with missing samples (the exact block-tridiagonal path): velocity rows that touch
    a missing sample are dropped in both."""
    toy, r, anim, deltas, prior = setup(make_toy, missing=0.15)
    assert np.isnan(deltas).any()
    assert rel(anim.weights, resolve(r, deltas, anim.weights, [0, 39], {}, prior)) < 1e-8
    k = 17
    new = anim.weights[k] + 0.5
    edited = r.edit(anim, frame=k, weights=new, window=(6, 33))
    want = resolve(r, deltas, anim.weights, [0, 6, 33, 39], {k: new}, prior)
    assert rel(edited.weights, want) < 1e-8


@pytest.mark.parametrize("window", [None, (8, 30)])
def test_without_prior_the_edit_is_the_linear_blend(make_toy, window):
    """alpha = 0 (pure Poisson): the change is the edit offset spread linearly, which validates
    :func:`linear_blend` as the baseline the tests above tell apart from the true edit."""
    toy, r, anim, deltas, prior = setup(make_toy, alpha=0.0)
    k = 19
    new = anim.weights[k] + np.linspace(-0.5, 0.5, toy.rig.n_shapes)
    edited = r.edit(anim, frame=k, weights=new, window=window)
    fixed = [0, 39] if window is None else [0, *window, 39]
    blend = linear_blend(anim.weights, k, new, fixed)
    assert rel(edited.weights, blend) < 1e-8
    assert rel(resolve(r, deltas, anim.weights, fixed, {k: new}, prior), blend) < 1e-8
