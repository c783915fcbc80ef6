"""Bad input gives a typed error naming the cause, or a documented regularized result."""

import numpy as np
import pytest

import faceretarget as fr
from faceretarget.errors import (
    CapabilityError,
    ConfigError,
    DegenerateGeometryError,
    IndexRangeError,
    InputError,
    NonFiniteError,
    NotFittedError,
    ShapeError,
    TopologyMismatchError,
    UnknownNameError,
)
from faceretarget.plugins.spacetime.retargeter import PAPER
from faceretarget.plugins.spacetime.retargeter import SpacetimeRetargeter as DefaultSpacetime


def SpacetimeRetargeter(**params):
    """The paper's method as published (these tests check its equations); the defaults'
    departures from the paper are tested in test_bounded.py and test_fidelity.py."""
    return DefaultSpacetime(**{**PAPER, **params})


def fitted(toy, **params):
    return SpacetimeRetargeter(**params).fit(toy.source, toy.target)


@pytest.mark.parametrize(
    "params, error, words",
    [
        (dict(mode="framewise"), ConfigError, "mode"),
        (dict(alpha=-1.0), ConfigError, "alpha"),
        (dict(beta=float("nan")), ConfigError, "beta"),
        (dict(lower=1.0, upper=0.0), ConfigError, "lower"),
        (dict(rbf_kernel="cubic"), ConfigError, "rbf_kernel"),
        (dict(head_motion_refinement=-1), ConfigError, "head_motion_refinement"),
        (dict(boundary="start"), ConfigError, "boundary"),
        (dict(boundary="none"), ConfigError, "beta > 0"),
        (dict(constraints=[1, 2]), ConfigError, "constraints"),
        (dict(prior_center="median"), ConfigError, "center"),
        (dict(marker_weights=np.ones(3)), ShapeError, "marker_weights"),
        (dict(marker_weights={"nope": 1.0}), TopologyMismatchError, "nope"),
        (dict(marker_weights=-np.ones(24)), ConfigError, "marker_weights"),
        (dict(prior_shapes=["nope"]), UnknownNameError, "nope"),
        (dict(prior_shapes=[99]), IndexRangeError, "99"),
        (dict(prior_animations=np.ones((3, 2))), ShapeError, "prior_animations"),
        (dict(prior_animations=np.full((3, 6), np.nan)), NonFiniteError, "prior_animations"),
    ],
)
def test_bad_parameters_raise_at_fit(make_toy, params, error, words):
    toy = make_toy(n_frames=10)
    with pytest.raises(error, match=words):
        fitted(toy, **params)


@pytest.mark.parametrize(
    "params, error, words",
    [
        (dict(boundary=np.zeros((3, 6))), ShapeError, "boundary"),
        (dict(constraints={4: np.ones(5)}), ShapeError, "constraint"),
        (dict(constraints={4: np.full(6, np.nan)}), NonFiniteError, "constraint"),
        (dict(constraints={40: np.ones(6)}), IndexRangeError, "40"),
        (dict(constraints={4: {"nope": 1.0}}), UnknownNameError, "nope"),
        (dict(marker_weights=np.ones((3, 24)), beta=1.0), ShapeError, "frames"),
    ],
)
def test_bad_sequence_parameters_raise_at_retarget(make_toy, params, error, words):
    toy = make_toy(n_frames=10)
    r = fitted(toy, **params)
    with pytest.raises(error, match=words):
        r.retarget(toy.source)


def test_missing_correspondences(make_toy):
    toy = make_toy(n_frames=5)
    perf = toy.source.performance
    renamed = fr.Source(
        fr.MarkerSequence(
            perf.positions, names=[f"x{i}" for i in range(24)], reference=perf.reference
        )
    )
    # no names in common but equal counts: paired by order (documented), works
    SpacetimeRetargeter().fit(renamed, toy.target)
    partly = [f"x{i}" for i in range(12)] + list(perf.names[12:])
    with pytest.raises(TopologyMismatchError, match="missing correspondences"):
        SpacetimeRetargeter().fit(
            fr.Source(fr.MarkerSequence(perf.positions, names=partly, reference=perf.reference)),
            toy.target,
        )
    fewer = fr.Source(
        fr.MarkerSequence(
            perf.positions[:, :20],
            names=[f"x{i}" for i in range(20)],
            reference=perf.reference[:20],
        )
    )
    with pytest.raises(TopologyMismatchError, match="24 landmarks"):
        SpacetimeRetargeter().fit(fewer, toy.target)
    # a source with extra markers is fine when names pair every landmark
    extra = np.concatenate([perf.positions, perf.positions[:, :2] + 1.0], axis=1)
    more = fr.Source(
        fr.MarkerSequence(
            extra,
            names=list(perf.names) + ["e0", "e1"],
            reference=np.concatenate([perf.reference, perf.reference[:2] + 1.0]),
        )
    )
    anim = SpacetimeRetargeter().fit(more, toy.target).retarget(more)
    assert anim.weights.shape == (5, 6)


def test_retarget_with_another_marker_set(make_toy):
    toy = make_toy(n_frames=5)
    r = fitted(toy)
    perf = toy.source.performance
    small = fr.Source(fr.MarkerSequence(perf.positions[:, :10], reference=perf.reference[:10]))
    with pytest.raises(TopologyMismatchError, match="markers"):
        r.retarget(small)


def test_marker_dimension_and_landmarks_at_retarget(make_toy, synthetic_case):
    toy = make_toy(n_frames=5)
    flat = fr.Source(
        fr.MarkerSequence(
            toy.source.performance.positions[..., :2], names=toy.source.performance.names
        )
    )
    with pytest.raises(ShapeError, match="3D"):
        SpacetimeRetargeter().fit(flat, toy.target)
    r = SpacetimeRetargeter().fit(synthetic_case.source, synthetic_case.target)
    bare = fr.Source(synthetic_case.source.performance)
    with pytest.raises(CapabilityError, match="landmarks"):
        r.retarget(bare)


def test_degenerate_geometry(make_toy):
    toy = make_toy(n_frames=5)
    perf = toy.source.performance
    line = np.zeros((24, 3))
    line[:, 0] = np.arange(24.0)
    flat = fr.Source(
        fr.MarkerSequence(np.repeat(line[None], 5, axis=0), names=perf.names, reference=line)
    )
    with pytest.raises(DegenerateGeometryError, match="collinear"):
        SpacetimeRetargeter().fit(flat, toy.target)
    still = fr.BlendshapeRig(toy.rig.neutral, np.zeros_like(toy.rig.deltas), toy.rig.names)
    target = fr.TargetRig(toy.rig.neutral, blendshapes=still, landmarks=toy.target.landmarks)
    with pytest.raises(DegenerateGeometryError, match="moves any landmark"):
        SpacetimeRetargeter().fit(toy.source, target)


def test_too_few_markers_for_head_motion(make_toy):
    toy = make_toy(n_frames=6)
    x = np.array(toy.source.performance.positions)
    x[3, 2:] = np.nan  # only 2 markers left at frame 3
    source = fr.Source(
        fr.MarkerSequence(
            x, names=toy.source.performance.names, reference=toy.source.performance.reference
        )
    )
    r = fitted(toy)
    with pytest.raises(DegenerateGeometryError, match="frame 3"):
        r.retarget(source)
    # without head-motion estimation the frame is solved from its neighbours (prior + ridge)
    anim = SpacetimeRetargeter(remove_head_motion=False).fit(source, toy.target).retarget(source)
    assert np.isfinite(anim.weights).all()


def test_nan_and_wrong_types(make_toy):
    toy = make_toy(n_frames=5)
    with pytest.raises(NonFiniteError):
        fr.MarkerSequence(np.full((5, 24, 3), np.nan))  # no complete neutral
    with pytest.raises(NotFittedError):
        SpacetimeRetargeter().retarget(toy.source)
    weights_source = fr.Source(fr.WeightSequence(np.zeros((5, 6)), toy.rig.names), rig=toy.rig)
    with pytest.raises(CapabilityError):
        SpacetimeRetargeter().fit(weights_source, toy.target)
    no_landmarks = fr.TargetRig(toy.rig.neutral, blendshapes=toy.rig)
    with pytest.raises(CapabilityError, match="landmarks"):
        SpacetimeRetargeter().fit(toy.source, no_landmarks)


def test_duplicate_blendshapes_share_weight(make_toy):
    """Documented regularization: duplicate shapes get equal weights, the result is unchanged."""
    toy = make_toy(n_frames=20, head_motion=True)
    rig = toy.rig
    dup = fr.BlendshapeRig(
        rig.neutral, np.concatenate([rig.deltas, rig.deltas[:1]]), list(rig.names) + ["shape0_copy"]
    )
    target = fr.TargetRig(rig.neutral, blendshapes=dup, landmarks=toy.target.landmarks)
    anim = SpacetimeRetargeter(alpha=0.0).fit(toy.source, target).retarget(toy.source)
    np.testing.assert_allclose(anim.weights[:, 0], anim.weights[:, -1], atol=1e-7)
    np.testing.assert_allclose(
        anim.weights[:, 0] + anim.weights[:, -1], toy.weights[:, 0], atol=1e-6
    )
    np.testing.assert_allclose(anim.weights[:, 1:-1], toy.weights[:, 1:], atol=1e-6)
    # Range PF and the prior handle the rank-deficient rig too
    for mode in ("rangepf", "priorpf", "movement"):
        assert np.isfinite(
            SpacetimeRetargeter(mode=mode).fit(toy.source, target).retarget(toy.source).weights
        ).all()


def test_shape_invisible_when_its_markers_are_missing(make_toy):
    """A frame where the markers seeing a shape are all missing gets the fallback ridge."""
    mesh_x = make_toy().rig.neutral.vertices[:, 0]
    support = np.array([mesh_x < -2.0] + [np.ones_like(mesh_x)] * 5, dtype=float)
    toy = make_toy(support=support, n_frames=12)
    x = np.array(toy.source.performance.positions)
    left = (
        toy.source.performance.reference[:, 0] < toy.source.performance.reference[:, 0].mean() - 1.5
    )
    x[5, left] = np.nan
    source = fr.Source(
        fr.MarkerSequence(
            x, names=toy.source.performance.names, reference=toy.source.performance.reference
        )
    )
    for mode in ("movement", "noconst", "rangepf"):
        anim = (
            SpacetimeRetargeter(mode=mode, alpha=0.0, remove_head_motion=False)
            .fit(source, toy.target)
            .retarget(source)
        )
        assert np.isfinite(anim.weights).all()


def test_one_frame_and_single_shape(make_toy):
    toy = make_toy(n_frames=1, head_motion=True)
    anim = SpacetimeRetargeter().fit(toy.source, toy.target).retarget(toy.source)
    per_frame = (
        fr.get("spacetime_priorpf", alpha=0.01).fit(toy.source, toy.target).retarget(toy.source)
    )
    np.testing.assert_allclose(anim.weights, per_frame.weights, atol=1e-12)
    single = make_toy(n_shapes=1, n_frames=15)
    for center in ("neutral", "mean"):  # mean-centred PCA of one sample is empty: no prior
        got = (
            SpacetimeRetargeter(alpha=0.0, prior_center=center)
            .fit(single.source, single.target)
            .retarget(single.source)
        )
        assert np.abs(got.weights - single.weights).max() < 1e-6


def test_edit_errors(make_toy):
    toy = make_toy(n_frames=20)
    r = fitted(toy)
    anim = r.retarget(toy.source)
    m = toy.rig.n_shapes
    with pytest.raises(InputError, match="frame="):
        r.edit(anim)
    with pytest.raises(IndexRangeError, match="outside the window"):
        r.edit(anim, frame=15, weights=np.zeros(m), window=(2, 10))
    with pytest.raises(IndexRangeError):
        r.edit(anim, frame=25, weights=np.zeros(m))
    with pytest.raises(ShapeError):
        r.edit(anim, frame=5, weights=np.zeros(m + 1))
    with pytest.raises(NonFiniteError):
        r.edit(anim, frame=5, weights=np.full(m, np.nan))
    with pytest.raises(UnknownNameError):
        r.edit(anim, frame=5, weights={"nope": 1.0})
    with pytest.raises(InputError, match="window start"):
        r.edit(anim, frame=5, weights=np.zeros(m), window=(8, 3))
    foreign = fr.Animation(weights=anim.weights, rig=toy.rig)
    with pytest.raises(InputError, match="retarget"):
        r.edit(foreign, frame=5, weights=np.zeros(m))
    other = SpacetimeRetargeter(alpha=0.5).fit(toy.source, toy.target)
    with pytest.raises(InputError, match="another"):
        other.edit(anim, frame=5, weights=np.zeros(m))
    baseline = fr.get("spacetime_rangepf").fit(toy.source, toy.target)
    with pytest.raises(CapabilityError):
        baseline.edit(baseline.retarget(toy.source), frame=5, weights=np.zeros(m))
