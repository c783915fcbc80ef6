"""The residual: what the actor's layers do not span, carried to the character through its blendshapes."""

import numpy as np
import pytest
from naive.layers import make_problem

import faceretarget as fr
from faceretarget import errors
from faceretarget.plugins.layers import compose
from faceretarget.plugins.layers.residual import pair_markers, solve_residual
from faceretarget.plugins.layers.retargeter import LayersRetargeter


def _error(vertices, case):
    got, want = np.asarray(vertices), np.asarray(case.truth.vertices)
    return np.sqrt(np.mean(np.sum((got - want) ** 2, axis=-1))) / np.ptp(want[0][:, 1])


@pytest.fixture(scope="module")
def case():
    return fr.cases.cross_rig(n_frames=120, source_kind="markers")


def test_residual_adds_exactly_its_blendshape_displacements(case):
    r = LayersRetargeter().fit(case.source, case.target)
    anim = r.retarget(case.source)
    assert (
        r.residual_ is not None
        and "45 shapes through 68 landmarks" in anim.provenance["diagnostics"]["residual"]
    )
    w = anim.extras["residual_weights"]
    assert (
        w.shape == (120, case.target.blendshapes.n_shapes)
        and anim.extras["residual_names"] == case.target.blendshapes.names
    )
    beta = compose.region_coefficients(
        anim.extras["layer_weights"],
        np.concatenate(list(anim.extras["coefficients"].values()), axis=1),
        r.actor_.layer_of,
    )
    layers_only = compose.world_vertices(r.character_, beta, anim.head_motion)
    deltas = np.asarray(case.target.blendshapes.deltas)
    np.testing.assert_allclose(
        anim.local_vertices, layers_only + np.einsum("fm,mvd->fvd", w, deltas), atol=1e-9
    )


def test_residual_off_is_the_layers_alone(case):
    """residual='none' (the paper) = the same parameters without the residual block."""
    on = LayersRetargeter().fit(case.source, case.target).retarget(case.source)
    off = LayersRetargeter(residual="none").fit(case.source, case.target).retarget(case.source)
    for key in ("layer_weights", "lip_gamma"):
        np.testing.assert_allclose(on.extras[key], off.extras[key], atol=1e-12)
    assert (
        "residual_weights" not in off.extras
        and off.provenance["diagnostics"]["residual"] == "off (residual='none')"
    )
    # what the layers do not span (accents, jaw slides...) is what the residual carries: half the error
    assert _error(on.vertices, case) < 0.6 * _error(off.vertices, case)


def test_residual_of_an_exactly_layered_actor_is_nothing():
    """Frames the actor's layers explain exactly leave nothing to carry (synthetic case)."""
    case = fr.cases.synthetic(resolution=600, n_frames=30, head_motion=False)
    anim = (
        LayersRetargeter(smoothing=0.0, lip_sigma=0.0)
        .fit(case.source, case.target)
        .retarget(case.source)
    )
    assert np.abs(anim.extras["residual_weights"]).max() < 1e-6


def test_residual_is_unit_free(case):
    """The cross-rig source is in metres, the character in centimetres: the same source in
    millimetres gives the same character (the layers' data term and the residual's transfer
    are both unit-free)."""
    s = case.source
    mm = fr.Source(
        fr.MarkerSequence(
            1000 * s.marker_positions(),
            names=s.performance.names,
            reference=1000 * s.marker_reference(),
            fps=s.fps,
        ),
        actor_layers=fr.LayeredRig(
            {k: 1000 * np.asarray(v) for k, v in s.actor_layers.layers.items()},
            s.actor_layers.masks,
            pose_names=s.actor_layers.pose_names,
            region_names=s.actor_layers.region_names,
        ),
    )
    a = LayersRetargeter().fit(s, case.target).retarget(s)
    b = LayersRetargeter().fit(mm, case.target).retarget(mm)
    assert (
        np.abs(np.asarray(a.vertices) - np.asarray(b.vertices)).max()
        < 1e-6 * case.target.neutral.height
    )


def test_residual_needs_blendshapes_and_paired_landmarks():
    problem = make_problem(11, n_frames=8)
    anim = LayersRetargeter().fit(problem["source"], problem["target"]).retarget(problem["source"])
    assert "residual_weights" not in anim.extras
    assert anim.provenance["diagnostics"]["residual"] == "off: the target has no blendshapes"
    with pytest.raises(errors.CapabilityError, match="blendshapes"):
        LayersRetargeter(residual="blendshapes").fit(problem["source"], problem["target"])
    assert pair_markers(["a", "b", "c"], ["c", "a"]).tolist() == [2, 0]
    assert pair_markers(["m0", "m1"], ["l0", "l1"]).tolist() == [0, 1]
    assert pair_markers(["a", "b"], ["a", "x"]) is None


def test_residual_smoothing_is_first_order_and_streams():
    """w(t) = argmin |D w - r(t)|^2 + rho |w|^2 + lambda |w - w(t-1)|^2, in one block or frame by frame."""
    case = fr.cases.cross_rig(n_frames=20, source_kind="markers")
    r = LayersRetargeter().fit(case.source, case.target)
    model = r.residual_
    rng = np.random.default_rng(0)
    res = rng.normal(scale=1e-3, size=(20, 68, 3))
    res[5, 7] = np.nan  # a missing marker: that frame's own least squares
    block, _ = solve_residual(model, res, 0.1)
    state, frames = None, []
    for t in range(20):
        out, state = solve_residual(model, res[t : t + 1], 0.1, state)
        frames.append(out[0])
    np.testing.assert_allclose(np.array(frames), block, rtol=1e-10, atol=1e-14)
    # frame 5 by brute force
    keep = ~np.isnan(res[5, model.marker_ids, 0])
    d = model.deltas_at[:, keep].reshape(model.n_shapes, -1).T
    rc = (res[5, model.marker_ids] @ model.transfer.T)[keep].ravel()
    norm = 1.0 / (len(model.marker_ids) * model.unit**2)
    lhs = d.T @ d * norm + (model.ridge + 0.1) * np.eye(model.n_shapes)
    want = np.linalg.solve(lhs, d.T @ rc * norm + 0.1 * block[4])
    np.testing.assert_allclose(block[5], want, rtol=1e-8, atol=1e-12)
