"""The data model validates its inputs, never mutates them, and accepts float32 / read-only arrays."""

import numpy as np
import pytest

import faceretarget as fr
from faceretarget import errors


def quad():
    v = np.array([[0, 0, 0], [1, 0, 0], [1, 1, 0], [0, 1, 0]], dtype=np.float64)
    t = np.array([[0, 1, 2], [0, 2, 3]])
    return v, t


def test_mesh_basics_and_cached_readonly_operators():
    v, t = quad()
    m = fr.Mesh(v, t)
    assert m.n_vertices == 4 and m.n_triangles == 2
    np.testing.assert_allclose(m.face_areas, [0.5, 0.5])
    np.testing.assert_allclose(m.vertex_normals, np.tile([0, 0, 1.0], (4, 1)))
    assert sorted(m.boundary_vertices.tolist()) == [0, 1, 2, 3]
    assert len(m.edges) == 5
    with pytest.raises(ValueError):
        m.vertex_normals[0, 0] = 1.0  # cached operators are read-only
    with pytest.raises(ValueError):
        m.vertices[0, 0] = 1.0


def test_mesh_does_not_touch_caller_arrays_and_accepts_float32_readonly():
    v, t = quad()
    v32 = v.astype(np.float32)
    v32.flags.writeable = False
    m = fr.Mesh(v32, t)
    assert m.vertices.dtype == np.float64
    v2 = v.copy()
    fr.Mesh(v2, t)
    assert v2.flags.writeable, "the caller's array must keep its flags"


@pytest.mark.parametrize(
    "vertices, triangles, error",
    [
        (np.zeros((4, 2)), [[0, 1, 2]], errors.ShapeError),
        (np.full((4, 3), np.nan), [[0, 1, 2]], errors.NonFiniteError),
        (np.eye(4, 3), [[0, 1, 4]], errors.IndexRangeError),
        (np.eye(4, 3), [[0, -1, 2]], errors.IndexRangeError),
        (np.eye(4, 3), [[0, 1, 1]], errors.DegenerateGeometryError),
        (np.eye(4, 3), [[0, 1, 2], [2, 0, 1]], errors.DegenerateGeometryError),
        (np.eye(4, 3), np.zeros((0, 3), int), errors.ShapeError),
        (np.eye(4, 3), [[0.5, 1, 2]], errors.ShapeError),
        (np.eye(2, 3), [[0, 1, 1]], errors.ShapeError),
    ],
)
def test_mesh_rejects_bad_input_with_typed_errors(vertices, triangles, error):
    with pytest.raises(error) as info:
        fr.Mesh(vertices, triangles)
    assert isinstance(info.value, errors.FaceRetargetError)
    assert "Mesh" in str(info.value)


def test_zero_area_triangles_found_and_rejected_on_request():
    v = np.array([[0, 0, 0], [1, 0, 0], [2, 0, 0], [0, 1, 0]], dtype=float)
    m = fr.Mesh(v, [[0, 1, 2], [0, 1, 3]])
    assert m.degenerate_triangles().tolist() == [0]
    with pytest.raises(errors.DegenerateGeometryError, match="zero-area"):
        m.check_nondegenerate("coating")


def test_marker_sequence_missing_samples_are_nan_and_partial_nan_rejected():
    pos = np.random.default_rng(0).normal(size=(5, 4, 3))
    pos[2, 1] = np.nan
    seq = fr.MarkerSequence(pos, names=list("abcd"))
    assert seq.missing.sum() == 1 and seq.missing[2, 1]
    bad = pos.copy()
    bad[3, 0, 0] = np.nan
    with pytest.raises(errors.NonFiniteError, match="every coordinate"):
        fr.MarkerSequence(bad)
    inf = pos.copy()
    inf[0, 0, 0] = np.inf
    with pytest.raises(errors.NonFiniteError, match="inf"):
        fr.MarkerSequence(inf)
    first_missing = pos.copy()
    first_missing[0, 0] = np.nan
    with pytest.raises(errors.NonFiniteError, match="reference"):
        fr.MarkerSequence(first_missing)
    with pytest.raises(errors.InputError, match="duplicate"):
        fr.MarkerSequence(pos, names=["a", "a", "b", "c"])
    assert fr.MarkerSequence(pos[..., :2]).dim == 2


def test_mesh_sequence_keeps_float32_and_checks_topology():
    v, t = quad()
    frames = np.repeat(v[None], 3, axis=0).astype(np.float32)
    seq = fr.MeshSequence(frames, t, fps=24)
    assert seq.vertices.dtype == np.float32 and seq.n_frames == 3
    assert seq.frame(1).n_vertices == 4
    with pytest.raises(errors.TopologyMismatchError):
        fr.MeshSequence(frames, t, reference=np.zeros((5, 3)))
    frames[1, 2, 0] = np.nan
    with pytest.raises(errors.NonFiniteError, match="frame 1, vertex 2"):
        fr.MeshSequence(frames, t)
    with pytest.raises(errors.InputError, match="fps"):
        fr.MeshSequence(np.repeat(v[None], 2, axis=0), t, fps=0)


def test_blendshape_rig_evaluate_and_errors():
    v, t = quad()
    neutral = fr.Mesh(v, t)
    deltas = np.zeros((2, 4, 3))
    deltas[0, :, 2] = 1.0
    deltas[1, 0, 0] = 2.0
    rig = fr.BlendshapeRig(neutral, deltas, ["up", "stretch"])
    out = rig.evaluate([[0.5, 1.0]])
    np.testing.assert_allclose(out[0, :, 2], 0.5)
    np.testing.assert_allclose(out[0, 0, 0], 2.0)
    assert rig.index("up") == 0
    with pytest.raises(errors.UnknownNameError, match="stretch"):
        rig.index("nope")
    with pytest.raises(errors.TopologyMismatchError):
        fr.BlendshapeRig(neutral, np.zeros((2, 5, 3)), ["a", "b"])
    with pytest.raises(errors.ShapeError):
        fr.BlendshapeRig(neutral, deltas, ["a"])
    with pytest.raises(errors.ShapeError):
        rig.evaluate(np.zeros(3))


def test_blendshape_rig_evaluate_matches_a_loop_over_frames_and_shapes():
    """The one-product evaluation (neutral added inside the BLAS call) against the definition
    v_t = neutral + sum_j w_tj d_j, for several frames, one frame, no frame and strided weights."""
    rng = np.random.default_rng(3)
    v, t = quad()
    neutral = fr.Mesh(v + rng.normal(size=v.shape), t)
    deltas = rng.normal(size=(5, 4, 3))
    rig = fr.BlendshapeRig(neutral, deltas, [f"s{j}" for j in range(5)])
    w = rng.normal(size=(7, 10))[:, ::2]  # (7, 5), not contiguous
    want = np.array([neutral.vertices + np.einsum("j,jvc->vc", row, deltas) for row in w])
    np.testing.assert_allclose(rig.evaluate(w), want, rtol=0, atol=1e-12)
    np.testing.assert_allclose(rig.evaluate(w[2]), want[2], rtol=0, atol=1e-12)
    assert rig.evaluate(np.zeros((0, 5))).shape == (0, 4, 3)


def test_blendshape_rig_over_the_affine_cap_adds_the_neutral_inside_the_product(monkeypatch):
    """A rig whose ``[deltas; neutral]`` matrix would pass ``config.RIG_AFFINE_MAX_BYTES`` does not
    build it and evaluates the same vertices (to rounding); pickles carry neither that matrix
    nor the other matrices derived from the deltas."""
    import pickle

    from faceretarget import config

    rng = np.random.default_rng(4)
    v, t = quad()
    neutral = fr.Mesh(v + rng.normal(size=v.shape), t)
    deltas = rng.normal(size=(5, 4, 3))
    w = rng.normal(size=(6, 5))
    kept = fr.BlendshapeRig(neutral, deltas, [f"s{j}" for j in range(5)])
    assert kept._affine is not None and kept._affine.shape == (6, 12)
    monkeypatch.setattr(config, "RIG_AFFINE_MAX_BYTES", 6 * 12 * 8 - 1)
    capped = fr.BlendshapeRig(neutral, deltas, [f"s{j}" for j in range(5)])
    assert capped._affine is None
    np.testing.assert_allclose(capped.evaluate(w), kept.evaluate(w), rtol=0, atol=1e-12)
    kept.delta_matrix, kept.delta_extent  # noqa: B018 - derived, then pickled
    state = pickle.loads(pickle.dumps(kept)).__dict__
    assert not {"_affine", "delta_matrix", "delta_extent"} & set(state)


def test_layered_rig_validation():
    poses = {"emotion": np.zeros((3, 4, 3)), "speech": np.zeros((2, 4, 3))}
    masks = np.array([[1, 1, 0, 0], [0, 0, 1, 1.0]])
    rig = fr.LayeredRig(poses, masks)
    assert rig.layer_names == ("emotion", "speech") and rig.n_regions == 2
    with pytest.raises(errors.TopologyMismatchError):
        fr.LayeredRig({"a": np.zeros((2, 4, 3)), "b": np.zeros((2, 5, 3))}, masks)
    with pytest.raises(errors.InputError, match=">= 0"):
        fr.LayeredRig(poses, -masks)
    with pytest.raises(errors.ShapeError):
        fr.LayeredRig(poses, np.ones((2, 3)))


def test_landmarks_vertex_and_barycentric():
    v, t = quad()
    lm = fr.Landmarks([0, 2], names=["a", "b"])
    np.testing.assert_allclose(lm.positions(v), v[[0, 2]])
    bary = fr.Landmarks(triangle_ids=[0], barycentric=[[1 / 3, 1 / 3, 1 / 3]])
    np.testing.assert_allclose(bary.positions(v, t)[0], v[[0, 1, 2]].mean(axis=0))
    np.testing.assert_allclose(
        bary.positions(np.stack([v, v + 1]), t)[1, 0], v[[0, 1, 2]].mean(axis=0) + 1
    )
    with pytest.raises(errors.IndexRangeError):
        fr.Landmarks([0, 9]).validate_for(fr.Mesh(v, t))
    with pytest.raises(errors.InputError):
        fr.Landmarks([0], triangle_ids=[0], barycentric=[[1, 0, 0]])


def test_source_and_target_validation():
    v, t = quad()
    neutral = fr.Mesh(v, t)
    seq = fr.MeshSequence(np.repeat(v[None], 3, axis=0), t)
    src = fr.Source(seq, landmarks=fr.Landmarks([0, 1, 2]))
    assert src.kind == "mesh" and src.marker_positions().shape == (3, 3, 3)
    with pytest.raises(errors.IndexRangeError):
        fr.Source(seq, landmarks=fr.Landmarks([0, 7]))
    with pytest.raises(errors.ShapeError):
        fr.Source(seq, head_motion=np.tile(np.eye(4), (2, 1, 1)))
    with pytest.raises(errors.InputError):
        fr.Source(np.zeros((3, 4, 3)))
    target = fr.TargetRig(
        neutral, landmarks=fr.Landmarks([0, 1, 2]), feature_lines={"mouth": [0, 1, 2]}
    )
    assert target.parts() == ("landmarks", "feature_lines")
    other = fr.Mesh(np.vstack([v, [[2, 2, 0]]]), [[0, 1, 2], [2, 3, 4]])
    rig = fr.BlendshapeRig(other, np.zeros((1, 5, 3)), ["a"])
    with pytest.raises(errors.TopologyMismatchError):
        fr.TargetRig(neutral, blendshapes=rig)
    with pytest.raises(errors.IndexRangeError):
        fr.TargetRig(neutral, feature_lines={"eye": [0, 8]})


def test_animation_lazy_vertices_with_head_motion_and_provenance():
    v, t = quad()
    rig = fr.BlendshapeRig(fr.Mesh(v, t), np.ones((1, 4, 3)), ["lift"])
    motion = np.tile(np.eye(4), (2, 1, 1))
    motion[:, :3, 3] = [10.0, 0, 0]
    anim = fr.Animation(
        weights=[[0.0], [1.0]], rig=rig, head_motion=motion, provenance={"method": "x"}
    )
    assert anim.is_blendshape_based and not anim.is_computed
    assert anim.compute() is anim and anim.is_computed
    np.testing.assert_allclose(anim.vertices[1], v + 1 + [10, 0, 0])
    np.testing.assert_allclose(anim.local_vertices[1], v + 1)
    assert anim.weight_names == ("lift",) and anim.provenance["method"] == "x"
    with pytest.raises(errors.InputError):
        fr.Animation(weights=[[1.0]])
    with pytest.raises(errors.NonFiniteError):
        fr.Animation(vertices=np.full((1, 4, 3), np.nan))
    with pytest.raises(errors.ShapeError):
        fr.Animation(weights=[[1.0, 2.0]], rig=rig)


def test_frames_of_a_lazy_blendshape_result_compute_only_those():
    v, t = quad()
    rig = fr.BlendshapeRig(fr.Mesh(v, t), np.ones((1, 4, 3)), ["lift"])
    motion = np.tile(np.eye(4), (3, 1, 1))
    motion[:, :3, 3] = [[0.0, 0, 0], [10.0, 0, 0], [0, 5.0, 0]]
    anim = fr.Animation(weights=[[0.0], [1.0], [2.0]], rig=rig, head_motion=motion)
    np.testing.assert_allclose(anim.frames(1), v + 1 + [10, 0, 0])
    np.testing.assert_allclose(anim.frames([2, 0]), [v + 2 + [0, 5, 0], v])
    np.testing.assert_allclose(anim.frames(slice(1, None))[0], v + 1 + [10, 0, 0])
    assert not anim.is_computed  # frames() kept it lazy
    np.testing.assert_array_equal(anim.frames([2, 0]), anim.vertices[[2, 0]])


def _counting_source(n_frames=7, n_vertices=4, chunk=3, poison=None):
    calls = []

    def frames(ids):
        calls.append(ids.tolist())
        out = np.repeat(0.1 * ids[:, None, None], n_vertices, axis=1).repeat(3, axis=2)
        if poison is not None:
            out[ids == poison] = np.nan
        return out

    return fr.model.FrameSource(frames, n_frames, n_vertices, chunk=chunk), calls


def test_frame_source_computes_the_frames_read_and_all_of_them_by_chunks():
    v, t = quad()
    source, calls = _counting_source()
    anim = fr.Animation(vertices=source, triangles=t, provenance={"method": "x"})
    assert (anim.n_frames, anim.n_vertices) == (7, 4) and not anim.is_computed
    assert "4 vertices" in repr(anim)
    np.testing.assert_array_equal(anim.frames(5), np.full((4, 3), 0.5))
    assert anim.frames(np.int64(5)).shape == (4, 3)  # a numpy integer is one frame too
    np.testing.assert_array_equal(anim.mesh(2).vertices, np.full((4, 3), 0.2))
    assert calls == [[5], [5], [2]]
    again = anim.replace(provenance={"method": "y"})  # stays lazy, same source
    assert not again.is_computed and again.frames(1)[0, 0] == 0.1
    calls.clear()
    assert anim.compute().is_computed
    assert calls == [[0, 1, 2], [3, 4, 5], [6]]  # a chunk at a time
    assert anim.vertices.dtype == np.float64
    np.testing.assert_array_equal(anim.vertices[:, 0, 0], 0.1 * np.arange(7))
    assert not anim.vertices.flags.writeable
    anim.frames([1, 2])
    assert len(calls) == 3  # computed once


def test_frame_source_chunks_and_release():
    import gc
    import weakref

    short, _ = _counting_source(n_frames=2, chunk=3)  # fewer frames than a chunk
    assert fr.Animation(vertices=short).vertices.shape == (2, 4, 3)
    zero, calls = _counting_source(n_frames=3, chunk=0)
    assert zero.chunk == 1 and fr.Animation(vertices=zero).vertices.shape == (3, 4, 3)
    assert calls == [[0], [1], [2]]

    class Frames:
        def __call__(self, ids):
            return np.zeros((ids.size, 4, 3))

    frames = Frames()
    ref = weakref.ref(frames)
    anim = fr.Animation(vertices=fr.model.FrameSource(frames, 3, 4)).compute()
    del frames
    gc.collect()
    assert ref() is None and anim.is_computed  # a computed result lets its source go


def test_frame_source_output_is_checked():
    bad, _ = _counting_source(poison=4)
    anim = fr.Animation(vertices=bad)
    anim.frames([0, 1])
    with pytest.raises(errors.NonFiniteError, match="frame 4"):
        anim.frames([3, 4])
    with pytest.raises(errors.NonFiniteError):
        _ = anim.vertices
    wrong = fr.model.FrameSource(lambda ids: np.zeros((ids.size, 5, 3)), 3, 4)
    with pytest.raises(errors.ShapeError, match="5"):
        fr.Animation(vertices=wrong).frames([0])
    with pytest.raises(errors.InputError):
        fr.model.FrameSource(np.zeros(3), 3, 4)
    with pytest.raises(errors.ShapeError):
        fr.model.FrameSource(lambda ids: None, 0, 4)
    with pytest.raises(errors.ShapeError):
        fr.model.FrameSource(lambda ids: None, 3, 0)
    v, t = quad()
    rig = fr.BlendshapeRig(fr.Mesh(v, t), np.ones((1, 4, 3)), ["lift"])
    with pytest.raises(errors.TopologyMismatchError):
        fr.Animation(vertices=fr.model.FrameSource(lambda ids: None, 3, 5), rig=rig)
    with pytest.raises(errors.ShapeError, match="weight frames"):
        fr.Animation(
            vertices=fr.model.FrameSource(lambda ids: None, 7, 4), weights=np.zeros((3, 1)), rig=rig
        )


@pytest.mark.parametrize(
    "values, finite",
    [
        (np.array([1e308, 1e308, -5.0]), True),  # the sum overflows: the exact test decides
        (np.array([3e38, 3e38], dtype=np.float32), True),
        (np.array([1.0, np.nan]), False),
        (np.array([np.inf, -np.inf]), False),  # the sum is NaN
        (np.array([1.0, -np.inf]), False),
        (np.zeros((0, 3)), True),
    ],
)
def test_all_finite_is_exact_whatever_the_sum_does(values, finite):
    """The summing check (no boolean temporary) against np.isfinite, quietly (no overflow
    warning); the validators built on it still say where a bad value is."""
    import warnings

    from faceretarget._validate import all_finite, check_finite

    with warnings.catch_warnings():
        warnings.simplefilter("error")
        assert all_finite(values) is finite
    if not finite:
        with pytest.raises(errors.NonFiniteError, match="first at index"):
            check_finite(values, "x")
        frames = np.zeros((3, 2, 3))
        frames[2, 1, 0] = values[-1]
        with pytest.raises(errors.NonFiniteError, match="frame 2, vertex 1"):
            fr.Animation(vertices=frames)


def test_check_output_reads_vertices_written_after_the_animation_was_made():
    """The constructor's finiteness check is no proof at output time: the stored vertices are
    a read-only view of the caller's array, which a plugin may still write into before it
    returns (or a memory-mapped file may change); the output check reads them again."""
    from faceretarget.retargeter import _finite_vertices

    v, _ = quad()
    frames = np.repeat(v[None], 3, axis=0)
    anim = fr.Animation(vertices=frames)
    assert _finite_vertices(anim)
    frames[1, 2, 0] = np.nan
    assert not _finite_vertices(anim)


def test_check_output_finds_nan_in_a_frame_source():
    from faceretarget.retargeter import _finite_vertices

    bad, _ = _counting_source(poison=6)
    good, _ = _counting_source()
    assert not _finite_vertices(fr.Animation(vertices=bad), chunk=2)
    assert _finite_vertices(fr.Animation(vertices=good), chunk=2)


def test_delta_extent_bounds_negative_deltas_too():
    """The finiteness check of a rig result bounds the vertices by ``delta_extent`` (the
    largest |delta| of each shape): negative deltas that overflow are caught as well."""
    from faceretarget.retargeter import _finite_vertices

    mesh = fr.Mesh(np.random.default_rng(0).normal(size=(10, 3)), np.array([[0, 1, 2]]))
    deltas = np.full((2, 10, 3), -10.0)
    deltas[1, 3, 2] = 4.0
    rig = fr.BlendshapeRig(mesh, deltas, ["a", "b"])
    np.testing.assert_array_equal(rig.delta_extent, [10.0, 10.0])
    assert not _finite_vertices(fr.Animation(weights=np.full((4, 2), 1e308), rig=rig))
    assert _finite_vertices(fr.Animation(weights=np.full((4, 2), 1e300), rig=rig))


def test_head_motion_rotates_each_frame_like_a_point_by_point_loop():
    from scipy.spatial.transform import Rotation

    from faceretarget.model import apply_head_motion

    rng = np.random.default_rng(3)
    motion = np.tile(np.eye(4), (4, 1, 1))
    motion[:, :3, :3] = Rotation.random(4, random_state=1).as_matrix()
    motion[:, :3, 3] = rng.normal(size=(4, 3))
    points = rng.normal(size=(4, 6, 3))
    want = np.array([[m[:3, :3] @ p + m[:3, 3] for p in frame] for m, frame in zip(motion, points)])
    np.testing.assert_allclose(apply_head_motion(motion, points), want, atol=1e-12)
    identity = np.tile(np.eye(4), (4, 1, 1))
    np.testing.assert_array_equal(apply_head_motion(identity, points), points)


def test_inputs_never_mutated():
    v, t = quad()
    v_before, t_before = v.copy(), t.copy()
    m = fr.Mesh(v, t)
    _ = m.vertex_normals, m.adjacency, m.boundary_vertices
    rig = fr.BlendshapeRig(m, np.ones((1, 4, 3)), ["a"])
    rig.evaluate([1.0])
    assert np.array_equal(v, v_before) and np.array_equal(t, t_before)


def test_mesh_sequence_keeps_big_endian_memory_maps_on_disk(tmp_path):
    v, t = quad()
    path = tmp_path / "frames.bin"
    np.repeat(v[None], 4, axis=0).astype(">f4").tofile(path)
    mapped = np.memmap(path, dtype=">f4", mode="r", shape=(4, 4, 3))
    seq = fr.MeshSequence(mapped, t)
    assert seq.vertices.dtype == np.dtype(">f4")
    assert np.shares_memory(seq.vertices, mapped), (
        "a memory-mapped cache must not be copied into memory"
    )


def test_source_and_target_replace_revalidate_and_drop_example_names():
    v, t = quad()
    neutral = fr.Mesh(v, t)
    target = fr.TargetRig(
        neutral,
        landmarks=fr.Landmarks([0, 1, 2]),
        examples=np.zeros((1, 4, 3)),
        example_names=["rest"],
    )
    bare = target.replace(examples=None, landmarks=None)
    assert bare.parts() == () and bare.example_names == ()
    assert target.parts() == ("landmarks", "examples"), "replace must not change the original"
    with pytest.raises(errors.IndexRangeError):
        target.replace(feature_lines={"eye": [0, 9]})
    seq = fr.MeshSequence(np.repeat(v[None], 3, axis=0), t)
    src = fr.Source(seq, landmarks=fr.Landmarks([0, 1, 2]), name="shot")
    moved = src.replace(head_motion=np.tile(np.eye(4), (3, 1, 1)))
    assert moved.head_motion.shape == (3, 4, 4) and moved.name == "shot" and src.head_motion is None
    with pytest.raises(errors.ShapeError):
        src.replace(head_motion=np.tile(np.eye(4), (2, 1, 1)))
