"""Bad input gives typed errors that name the cause; documented handling of missing markers."""

import warnings

import numpy as np
import pytest
from naive.layers import make_problem

import faceretarget as fr
from faceretarget import errors
from faceretarget.plugins.layers.retargeter import LayersRetargeter


@pytest.fixture(scope="module")
def problem():
    return make_problem(11, n_frames=20)


def _source(problem, positions=None, **extra):
    s = problem["source"]
    pos = s.performance.positions if positions is None else positions
    perf = fr.MarkerSequence(pos, names=s.performance.names, reference=s.performance.reference)
    return fr.Source(perf, actor_layers=extra.pop("actor_layers", s.actor_layers), **extra)


def _layers(rig, layers=None, masks=None, pose_names=None):
    return fr.LayeredRig(
        layers if layers is not None else rig.layers,
        rig.masks if masks is None else masks,
        pose_names=pose_names,
        region_names=None,
    )


def test_mismatched_layer_names(problem):
    t = problem["target"]
    renamed = {("talk" if k == "speech" else k): v for k, v in t.layers.layers.items()}
    target = fr.TargetRig(t.neutral, layers=_layers(t.layers, renamed))
    with pytest.raises(errors.TopologyMismatchError, match="talk|speech"):
        LayersRetargeter().fit(problem["source"], target)


def test_mismatched_pose_counts(problem):
    t = problem["target"]
    fewer = dict(t.layers.layers)
    fewer["emotion"] = fewer["emotion"][:-1]
    with pytest.raises(errors.TopologyMismatchError, match="emotion"):
        LayersRetargeter().fit(
            problem["source"], fr.TargetRig(t.neutral, layers=_layers(t.layers, fewer))
        )


def test_region_count_mismatch(problem):
    t = problem["target"]
    target = fr.TargetRig(t.neutral, layers=_layers(t.layers, masks=t.layers.masks[:2]))
    with pytest.raises(errors.TopologyMismatchError, match="region"):
        LayersRetargeter().fit(problem["source"], target)


def test_poses_matched_by_name_when_reordered(problem):
    """Same pose names in another order on the character: matched by name, same result."""
    t = problem["target"]
    order = np.arange(6)[::-1]
    emotion = np.asarray(t.layers.layers["emotion"])[order]
    names = {k: list(v) for k, v in t.layers.pose_names.items()}
    names["emotion"] = [names["emotion"][i] for i in order]
    layers = dict(t.layers.layers, emotion=emotion)
    shuffled = fr.TargetRig(
        t.neutral, layers=fr.LayeredRig(layers, t.layers.masks, pose_names=names)
    )
    a = LayersRetargeter().fit(problem["source"], t).retarget(problem["source"]).vertices
    b = LayersRetargeter().fit(problem["source"], shuffled).retarget(problem["source"]).vertices
    np.testing.assert_allclose(a, b, atol=1e-12)


def test_source_with_other_marker_count(problem):
    r = LayersRetargeter().fit(problem["source"], problem["target"])
    other = make_problem(11, n_markers=50, n_frames=5)
    with pytest.raises(errors.TopologyMismatchError, match="markers"):
        r.retarget(
            fr.Source(other["source"].performance, actor_layers=other["source"].actor_layers)
        )


def test_stream_frame_shapes_and_values(problem):
    r = LayersRetargeter().fit(problem["source"], problem["target"])
    good = np.asarray(problem["source"].performance.positions[0])
    with pytest.raises(errors.ShapeError, match="frame 1"):
        list(r.stream([good, good[:-1]]))
    with pytest.raises(errors.ShapeError):
        list(r.stream([(good, good, good)]))
    bad = good.copy()
    bad[3, 0] = np.inf
    with pytest.raises(errors.NonFiniteError):
        list(r.stream([bad]))
    half = good.copy()
    half[3, 1] = np.nan
    with pytest.raises(errors.NonFiniteError, match="some coordinates NaN"):
        list(r.stream([half]))
    huge = good + 1e308  # finite, but their sum overflows: accepted, and no warning escapes
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        from faceretarget.plugins.layers.solver import _check_points

        assert _check_points(huge[None], huge.shape[0], 3, "markers") is not None


def test_missing_markers_for_many_frames_are_dropped_per_frame(problem):
    """A third of the markers missing on every other frame: those rows leave the data term."""
    pos = np.array(problem["source"].performance.positions)
    rng = np.random.default_rng(0)
    for f in range(0, pos.shape[0], 2):
        pos[f, rng.choice(np.arange(2, pos.shape[1]), pos.shape[1] // 3, replace=False)] = np.nan
    full = LayersRetargeter().fit(problem["source"], problem["target"]).retarget(problem["source"])
    gappy = (
        LayersRetargeter().fit(problem["source"], problem["target"]).retarget(_source(problem, pos))
    )
    height = np.ptp(problem["target"].neutral.vertices[:, 1])
    err = (
        np.sqrt(np.mean(np.sum((np.asarray(gappy.vertices) - problem["truth"]) ** 2, axis=-1)))
        / height
    )
    err_full = (
        np.sqrt(np.mean(np.sum((np.asarray(full.vertices) - problem["truth"]) ** 2, axis=-1)))
        / height
    )
    assert np.isfinite(gappy.vertices).all()
    assert err < 3 * err_full + 1e-3


def test_too_few_markers_for_the_rigid_fit(problem):
    pos = np.array(problem["source"].performance.positions)
    pos[7, 2:] = np.nan
    r = LayersRetargeter().fit(problem["source"], problem["target"])
    with pytest.raises(errors.DegenerateGeometryError, match="frame 7"):
        r.retarget(_source(problem, pos))
    # with the head motion known, the frame keeps its parameters from the neighbours
    known = _source(problem, pos, head_motion=problem["head_motion"])
    out = r.retarget(known)
    assert np.isfinite(out.vertices).all()


def test_one_frame_sequence(problem):
    r = LayersRetargeter().fit(problem["source"], problem["target"])
    anim = r.retarget(_source(problem, problem["source"].performance.positions[4:5]))
    assert anim.vertices.shape == (1, problem["target"].neutral.n_vertices, 3)


@pytest.mark.parametrize(
    "params, error",
    [
        ({"gamma_max": 1.0}, errors.ConfigError),
        ({"smoothing": -1.0}, errors.ConfigError),
        ({"lip_sigma": -0.1}, errors.ConfigError),
        ({"head_motion": "guess"}, errors.ConfigError),
        ({"composition": "multiplicative"}, errors.ConfigError),
        ({"head_motion_refinement": -1}, errors.ConfigError),
        ({"head_motion_refinement": 1.5}, errors.ConfigError),
        ({"head_motion_refinement": 10_000}, errors.ConfigError),
        ({"residual": "rbf"}, errors.ConfigError),
        ({"residual": "blendshapes"}, errors.CapabilityError),
        ({"rigid_points": "some"}, errors.ConfigError),
        ({"closed_viseme": "MM"}, errors.UnknownNameError),
        ({"closed_viseme": 17}, errors.IndexRangeError),
        ({"lip_markers": ("nose", "chin")}, errors.UnknownNameError),
        ({"mouth_region": "jaw"}, errors.UnknownNameError),
        ({"speech_layer": "talk", "closed_viseme": 0}, errors.UnknownNameError),
        ({"project_blendshapes": True}, errors.CapabilityError),
    ],
)
def test_bad_parameters(problem, params, error):
    with pytest.raises(error):
        LayersRetargeter(**params).fit(problem["source"], problem["target"]).retarget(
            problem["source"]
        )


def test_missing_parts_and_degenerate_bases(problem):
    t = problem["target"]
    with pytest.raises(errors.CapabilityError, match="layers"):
        LayersRetargeter().fit(problem["source"], fr.TargetRig(t.neutral))
    with pytest.raises(errors.CapabilityError, match="actor layers"):
        LayersRetargeter().fit(fr.Source(problem["source"].performance), t)
    still = fr.LayeredRig(
        {
            k: np.repeat(np.asarray(problem["source"].performance.reference)[None], v.shape[0], 0)
            for k, v in problem["source"].actor_layers.layers.items()
        },
        problem["source"].actor_layers.masks,
    )
    with pytest.raises(errors.DegenerateGeometryError, match="neutral"):
        LayersRetargeter().fit(_source(problem, actor_layers=still), t)


def test_model_with_tracks_needs_tracks():
    problem = make_problem(12, n_tracks=8, n_frames=6)
    r = LayersRetargeter().fit(problem["source"], problem["target"])
    no_tracks = fr.Source(
        problem["source"].performance, actor_layers=problem["source"].actor_layers
    )
    with pytest.raises(errors.CapabilityError, match="2D tracks"):
        r.retarget(no_tracks)
    with pytest.raises(errors.CapabilityError, match="2D tracks"):
        list(r.stream(problem["source"].performance.positions))
