"""Building the bases: actor simplices from chosen frames, character layers from an ARKit rig."""

import warnings

import numpy as np
import pytest
from naive.layers import make_problem

import faceretarget as fr
from faceretarget import errors
from faceretarget.plugins.layers import (
    actor_layers_from_frames,
    default_masks,
    layered_rig_from_blendshapes,
)
from faceretarget.plugins.layers.retargeter import LayersRetargeter


def _tiny_arkit_rig():
    """A 6-vertex rig: vertices 0-1 brows, 2-3 eyelids, 4-5 lips; one ARKit shape per part."""
    neutral = fr.Mesh(
        np.array([[0, 3, 0], [1, 3, 0], [0, 2, 0], [1, 2, 0], [0, 0, 0], [1, 0, 0]], float),
        [[0, 1, 2], [1, 3, 2], [2, 3, 4], [3, 5, 4]],
    )
    deltas = np.zeros((4, 6, 3))
    deltas[0, [0, 1], 1] = 0.3  # browInnerUp
    deltas[1, [2, 3], 1] = -0.4  # eyeBlink_L (ICT spelling)
    deltas[2, 5, 1] = -1.0  # jawOpen
    deltas[3, [4, 5], 0] = [0.2, -0.2]  # mouthPucker
    return fr.BlendshapeRig(
        neutral, deltas, ["browInnerUp", "eyeBlink_L", "jawOpen", "mouthPucker"]
    )


def test_actor_layers_from_frames_removes_head_motion():
    problem = make_problem(13, n_frames=30)
    chosen = {"emotion": {"a": 0, "b": 5, "c": 9}, "speech": [3, 12], "blink": [20]}
    perf = problem["source"].performance
    rig = actor_layers_from_frames(
        perf, chosen, problem["masks_actor"], head_motion=problem["head_motion"]
    )
    np.testing.assert_allclose(rig.layers["emotion"], problem["actor_local"][[0, 5, 9]], atol=1e-9)
    np.testing.assert_allclose(rig.layers["speech"], problem["actor_local"][[3, 12]], atol=1e-9)
    assert rig.pose_names["emotion"] == ("a", "b", "c")
    assert rig.n_regions == 3
    # without known motion: Procrustes onto the neutral, close to the true local pose, rigidly
    # related to the frame (distances between markers are kept)
    est = actor_layers_from_frames(perf, chosen, problem["masks_actor"]).layers["speech"][1]
    true = problem["actor_local"][12]
    size = np.ptp(true[:, 1])
    assert np.sqrt(np.mean(np.sum((est - true) ** 2, axis=1))) < 0.02 * size
    frame = np.asarray(perf.positions[12])
    np.testing.assert_allclose(
        np.linalg.norm(est[1:] - est[0], axis=1), np.linalg.norm(frame[1:] - frame[0], axis=1)
    )
    # a Source works too (one region when no masks are given)
    assert actor_layers_from_frames(problem["source"], {"x": [1, 2]}).n_regions == 1


def test_actor_layers_from_frames_errors():
    problem = make_problem(13, n_frames=10)
    pos = np.array(problem["source"].performance.positions)
    pos[4, 7] = np.nan
    with pytest.raises(errors.NonFiniteError, match="frame 4"):
        actor_layers_from_frames(pos, {"emotion": [0, 4]})
    with pytest.raises(errors.IndexRangeError):
        actor_layers_from_frames(pos, {"emotion": [0, 40]})
    with pytest.raises(errors.ShapeError):
        actor_layers_from_frames(pos[0], {"emotion": [0]})
    with pytest.raises(errors.InputError):
        actor_layers_from_frames(pos, {})


def test_layered_rig_from_blendshapes_with_own_recipes():
    rig = _tiny_arkit_rig()
    recipes = {
        "emotion": {"neutral": {}, "surprise": {"browInnerUp": 1.0, "jawOpen": 0.2}},
        "speech": {"MBP": {}, "AA": {"jawOpen": 0.8}, "U": {"mouthPucker": 1.0}},
        "blink": {"open": {}, "closed": {"eyeBlinkLeft": 1.0}},  # resolves to eyeBlink_L
    }
    layers = layered_rig_from_blendshapes(rig, recipes)
    assert layers.layer_names == ("emotion", "speech", "blink")
    np.testing.assert_allclose(layers.layers["speech"][1], rig.evaluate(np.array([0, 0, 0.8, 0])))
    np.testing.assert_allclose(layers.layers["blink"][1], rig.evaluate(np.array([0, 1.0, 0, 0])))
    masks = layers.masks
    assert layers.region_names == ("upper_face", "eyes", "mouth")
    np.testing.assert_allclose(masks.sum(axis=0), 1.0)
    assert masks[0, 0] == 1.0 and masks[1, 2] == 1.0 and masks[2, 5] == 1.0
    assert masks[2, 4] == 1.0  # moved only by mouthPucker
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        with pytest.raises(Exception, match="tongueOut"):
            layered_rig_from_blendshapes(rig, {"x": {"a": {"tongueOut": 1.0}}})


def test_default_masks_need_arkit_names():
    rig = _tiny_arkit_rig()
    anonymous = fr.BlendshapeRig(rig.neutral, rig.deltas, ["s0", "s1", "s2", "s3"])
    with pytest.raises(errors.CapabilityError):
        default_masks(anonymous)


def test_parallel_rigs_built_from_recipes_retarget_end_to_end():
    """Default recipes on the case's two ARKit rigs: the actor's layers sampled at its landmarks."""
    case = fr.cases.synthetic(resolution=400, n_frames=24)
    source_rig = case.source.rig
    actor_full = layered_rig_from_blendshapes(source_rig, on_unmapped="ignore")
    ids = case.source.landmarks.vertex_ids
    actor = fr.LayeredRig(
        {k: v[:, ids] for k, v in actor_full.layers.items()},
        actor_full.masks[:, ids],
        pose_names=actor_full.pose_names,
    )
    character = layered_rig_from_blendshapes(case.target.blendshapes, on_unmapped="ignore")
    assert character.pose_names["speech"][0] == "MBP"  # the default closed-lips viseme comes first
    s = case.source
    source = fr.Source(s.performance, landmarks=s.landmarks, actor_layers=actor)
    target = fr.TargetRig(case.target.neutral, layers=character)
    anim = LayersRetargeter().fit(source, target).retarget(source)
    height = case.target.neutral.height
    err = (
        np.sqrt(
            np.mean(
                np.sum((np.asarray(anim.vertices) - np.asarray(case.truth.vertices)) ** 2, axis=-1)
            )
        )
        / height
    )
    assert err < 0.05
