"""Streaming (the model is first-order Markov) equals batch retargeting."""

import numpy as np
import pytest
from naive.layers import make_problem

import faceretarget as fr
from faceretarget.plugins.layers.retargeter import LayersRetargeter


def _batch_and_stream(retargeter, source, frames):
    batch = np.asarray(retargeter.retarget(source).vertices)
    streamed = np.stack(list(retargeter.stream(frames)))
    return batch, streamed


def _close(a, b):
    """Equal up to the solver's tolerance: a lone frame and a batch round a few last bits
    differently (the batched Procrustes), and the per-frame solver, stopping at a relative
    decrease of 1e-8, passes that on; the conformance kit allows an RMS of 1e-6 of the size."""
    a, b = np.asarray(a), np.asarray(b)
    size = np.ptp(b[..., 1])
    assert np.sqrt(np.mean(np.sum((a - b) ** 2, axis=-1))) <= 1e-7 * size
    np.testing.assert_allclose(a, b, atol=1e-5 * size, rtol=0)


def test_markers_stream_equals_batch():
    problem = make_problem(7, noise=0.01)
    r = LayersRetargeter().fit(problem["source"], problem["target"])
    batch, streamed = _batch_and_stream(
        r, problem["source"], iter(problem["source"].performance.positions)
    )
    _close(streamed, batch)


def test_stream_with_2d_tracks_pairs_and_missing_markers():
    problem = make_problem(8, n_tracks=12)
    s = problem["source"]
    pos = np.array(s.performance.positions)
    pos[3, 4:9] = np.nan
    source = fr.Source(
        fr.MarkerSequence(pos, names=s.performance.names, reference=s.performance.reference),
        actor_layers=s.actor_layers,
        tracks2d=s.tracks2d,
        actor_layers_2d=s.actor_layers_2d,
    )
    r = LayersRetargeter().fit(source, problem["target"])
    frames = zip(pos, np.asarray(s.tracks2d.positions))
    batch, streamed = _batch_and_stream(r, source, frames)
    _close(streamed, batch)


def test_stream_with_known_head_motion_in_dicts():
    problem = make_problem(9)
    s = problem["source"]
    source = fr.Source(
        s.performance, head_motion=problem["head_motion"], actor_layers=s.actor_layers
    )
    r = LayersRetargeter().fit(source, problem["target"])
    frames = (
        {"markers": m, "head_motion": h}
        for m, h in zip(s.performance.positions, problem["head_motion"])
    )
    batch, streamed = _batch_and_stream(r, source, frames)
    _close(streamed, batch)


def test_stream_of_mesh_frames_and_blendshape_projection():
    case = fr.cases.synthetic(resolution=300, n_frames=8)
    r = LayersRetargeter(project_blendshapes=True).fit(case.source, case.target)
    anim = r.retarget(case.source)
    assert anim.weights is not None and anim.weights.shape == (8, case.target.blendshapes.n_shapes)
    assert (anim.weights >= 0).all()
    streamed = np.stack(list(r.stream(np.asarray(case.source.performance.vertices))))
    _close(streamed, np.asarray(anim.vertices))


def test_first_stream_frame_is_a_one_frame_retarget():
    problem = make_problem(10)
    s = problem["source"]
    r = LayersRetargeter().fit(s, problem["target"])
    one = fr.Source(
        fr.MarkerSequence(
            s.performance.positions[:1],
            names=s.performance.names,
            reference=s.performance.reference,
        ),
        actor_layers=s.actor_layers,
    )
    single = np.asarray(r.retarget(one).vertices)
    assert single.shape == (1, problem["target"].neutral.n_vertices, 3)
    first = next(iter(r.stream(s.performance.positions)))
    _close(first, single[0])


def test_stream_before_fit_raises():
    with pytest.raises(fr.NotFittedError):
        list(LayersRetargeter().stream([np.zeros((3, 3))]))
