"""Evaluation cases: ground truth, determinism, rig parts, topology and semantics."""

import numpy as np
import pytest

import faceretarget as fr
from faceretarget import cases, recipes
from faceretarget.errors import InputError, UnknownNameError


@pytest.fixture(scope="module", params=["human", "stylized"])
def synth(request):
    return cases.synthetic(target=request.param, resolution=1500, n_frames=60)


@pytest.fixture(scope="module")
def ict_case():
    return cases.ict(n_frames=40)


def _rigid_apply(motion, points):
    """Head motion applied frame by frame (independent of model.apply_head_motion)."""
    return np.stack(
        [points[f] @ motion[f, :3, :3].T + motion[f, :3, 3] for f in range(len(motion))]
    )


def _check_truth(case):
    w, motion = case.meta["weights"], case.meta["head_motion"]
    rig = case.target.blendshapes
    local = np.stack([rig.neutral.vertices + np.tensordot(wf, rig.deltas, axes=1) for wf in w])
    np.testing.assert_allclose(case.truth.vertices, _rigid_apply(motion, local), atol=1e-9)
    np.testing.assert_allclose(case.truth.local_vertices, local, atol=1e-9)
    src = case.source.rig
    src_local = np.stack([src.neutral.vertices + np.tensordot(wf, src.deltas, axes=1) for wf in w])
    np.testing.assert_allclose(
        case.source.performance.vertices, _rigid_apply(motion, src_local), atol=1e-9
    )
    assert case.truth.weight_names == rig.names
    assert case.meta["weight_names"] == src.names == rig.names


def _check_layers_exact(case):
    w = case.meta["weights"]
    coeffs, layer_w = case.meta["layer_coefficients"], case.meta["layer_recipes"]
    rebuilt = sum(coeffs[k] @ layer_w[k] for k in coeffs)
    np.testing.assert_allclose(rebuilt, w, atol=1e-12)
    for k, c in coeffs.items():
        assert (c >= -1e-12).all(), k
        np.testing.assert_allclose(c.sum(axis=1), 1.0, atol=1e-12)
    # every layer pose is neutral + its recipe on the target rig; actor layers sample the source rig
    tl, al = case.target.layers, case.source.actor_layers
    ids = case.source.landmarks.vertex_ids
    for layer, poses in tl.layers.items():
        np.testing.assert_allclose(
            poses, case.target.blendshapes.evaluate(layer_w[layer]), atol=1e-9
        )
        np.testing.assert_allclose(
            al.layers[layer], case.source.rig.evaluate(layer_w[layer])[:, ids], atol=1e-9
        )
    for masks in (tl.masks, al.masks):
        assert (masks >= 0).all()
        np.testing.assert_allclose(masks.sum(axis=0), 1.0, atol=1e-9)


def test_synthetic_truth_is_the_target_rig_driven_by_the_source_weights(synth):
    _check_truth(synth)


def test_ict_truth_is_the_target_rig_driven_by_the_source_weights(ict_case):
    _check_truth(ict_case)
    assert ict_case.target.blendshapes.n_shapes == 45
    assert ict_case.meta["unmapped_recipe_names"] == []
    assert not np.allclose(ict_case.source.rig.neutral.vertices, ict_case.target.neutral.vertices)


def test_layered_description_is_exact(synth, ict_case):
    _check_layers_exact(synth)
    _check_layers_exact(ict_case)


def test_weights_are_speech_like_and_bounded(synth):
    w = synth.meta["weights"]
    assert w.min() >= 0.0 and w.max() <= 1.0 + 1e-9
    coeffs = synth.meta["layer_coefficients"]
    # visemes other than the closed-lips rest are spoken, blinks happen, emotions change
    assert (coeffs["speech"][:, 1:].max(axis=0) > 0.5).sum() >= 5
    assert coeffs["blink"][:, 1].max() > 0.8
    assert coeffs["emotion"][:, 1:].max() > 0.5
    # smooth: no frame-to-frame jump larger than a blink closing step
    assert np.abs(np.diff(w, axis=0)).max() < 0.6


def test_determinism_by_seed():
    a = cases.synthetic(seed=3, resolution=400, n_frames=30)
    b = cases.synthetic(seed=3, resolution=400, n_frames=30)
    c = cases.synthetic(seed=4, resolution=400, n_frames=30)
    np.testing.assert_array_equal(a.source.performance.vertices, b.source.performance.vertices)
    np.testing.assert_array_equal(a.truth.vertices, b.truth.vertices)
    np.testing.assert_array_equal(a.target.landmarks.vertex_ids, b.target.landmarks.vertex_ids)
    assert not np.allclose(a.meta["weights"], c.meta["weights"])
    np.testing.assert_array_equal(a.target.neutral.vertices, c.target.neutral.vertices)


def test_every_part_is_present_and_paired(synth):
    src, tgt = synth.source, synth.target
    assert set(tgt.parts()) == set(fr.TargetRig.PARTS)
    assert src.kind == "mesh" and src.head_motion is None
    assert len(src.landmarks) == len(tgt.landmarks) == 54
    assert src.landmarks.names == tgt.landmarks.names
    assert src.marker_positions().shape == (synth.source.n_frames, 54, 3)
    assert (
        set(src.feature_lines)
        == set(tgt.feature_lines)
        == {"eye_L", "eye_R", "mouth_inner", "mouth_outer"}
    )
    assert src.example_names == tgt.example_names and len(src.example_names) == 7
    assert src.examples.shape == (7, src.performance.n_vertices, 3)
    assert tgt.examples.shape == (7, tgt.neutral.n_vertices, 3)
    np.testing.assert_allclose(src.examples[0], src.performance.reference.vertices)
    assert src.actor_layers.layer_names == tgt.layers.layer_names == ("emotion", "speech", "blink")
    assert src.actor_layers.n_points == 54
    assert tgt.layers.pose_names["speech"][0] == "MBP"
    assert tgt.layers.masks.shape == (3, tgt.neutral.n_vertices)
    assert len(tgt.blendshapes.names) == len(recipes.RECIPE_SHAPES) >= 20
    assert all(recipes.normalize_shape_name(n) == n for n in tgt.blendshapes.names)
    assert synth.meta["unmapped_recipe_names"] == []


def _loop_is_closed_chain(mesh, loop):
    adj = mesh.adjacency
    nxt = np.roll(loop, -1)
    return all(adj[a, b] for a, b in zip(loop, nxt))


def test_holes_at_eyes_and_mouth(synth, ict_case):
    for case in (synth, ict_case):
        for mesh, lines in (
            (case.source.performance.reference, case.source.feature_lines),
            (case.target.neutral, case.target.feature_lines),
        ):
            boundary = set(mesh.boundary_vertices.tolist())
            for k in ("eye_L", "eye_R", "mouth_inner"):
                loop = lines[k]
                assert set(loop.tolist()) <= boundary, k
                assert _loop_is_closed_chain(mesh, loop), k
            # character's left eye is on +x, the mouth below the eyes
            v = mesh.vertices
            assert v[lines["eye_L"], 0].mean() > 0 > v[lines["eye_R"], 0].mean()
            assert v[lines["mouth_inner"], 1].mean() < v[lines["eye_L"], 1].mean()
            mesh.check_nondegenerate("the case meshes")


def test_shapes_mean_the_same_on_both_rigs(synth):
    ids = dict(zip(synth.target.landmarks.names, range(54)))
    for rig, lm in (
        (synth.source.rig, synth.source.landmarks),
        (synth.target.blendshapes, synth.target.landmarks),
    ):

        def moved(shape, marker, lm=lm, rig=rig):
            d = rig.deltas[rig.index(shape)]
            return d[lm.vertex_ids[ids[marker]]]

        height = rig.neutral.height
        assert moved("jawOpen", "chin")[1] < -0.05 * height
        assert abs(moved("jawOpen", "forehead_C")).max() < 1e-3 * height
        # a blink brings the upper lid down onto the lower lid
        ref = rig.neutral.vertices[lm.vertex_ids]
        gap0 = ref[ids["eye_L_upper"], 1] - ref[ids["eye_L_lower"], 1]
        closed = ref + rig.deltas[rig.index("eyeBlinkLeft")][lm.vertex_ids]
        assert closed[ids["eye_L_upper"], 1] - closed[ids["eye_L_lower"], 1] < 0.1 * gap0
        assert abs(moved("eyeBlinkLeft", "eye_R_upper")).max() < 1e-6 * height
        assert moved("mouthSmileLeft", "mouth_corner_L")[1] > 0.01 * height
        assert moved("browInnerUp", "brow_L_1")[1] > 0.01 * height


def test_stylized_target_has_larger_eyes_and_a_snout():
    human = cases.synthetic(target="human", resolution=1500, n_frames=2)
    styl = cases.synthetic(target="stylized", resolution=1500, n_frames=2)

    def eye_width(case):
        v = case.target.neutral.vertices
        return np.ptp(v[case.target.feature_lines["eye_L"], 0]) / np.ptp(v[:, 0])

    def mouth_width(case):
        v = case.target.neutral.vertices
        return np.ptp(v[case.target.feature_lines["mouth_inner"], 0]) / np.ptp(v[:, 0])

    assert eye_width(styl) > 1.2 * eye_width(human)
    assert mouth_width(styl) > 1.15 * mouth_width(human)
    tip = list(styl.target.landmarks.names).index("nose_base")
    for case, factor in ((human, 1.0), (styl, 1.0)):
        v = case.target.neutral.vertices
        assert v[case.target.landmarks.vertex_ids[tip], 2] > factor * np.median(v[:, 2])
    zs = styl.target.neutral.vertices[styl.target.landmarks.vertex_ids[tip], 2]
    zh = human.target.neutral.vertices[human.target.landmarks.vertex_ids[tip], 2]
    assert zs - np.median(styl.target.neutral.vertices[:, 2]) > zh - np.median(
        human.target.neutral.vertices[:, 2]
    )


def test_head_motion_is_rigid_smooth_and_starts_at_identity(synth):
    h = synth.meta["head_motion"]
    np.testing.assert_allclose(h[0], np.eye(4), atol=1e-12)
    rot = h[:, :3, :3]
    np.testing.assert_allclose(
        rot @ rot.transpose(0, 2, 1), np.broadcast_to(np.eye(3), rot.shape), atol=1e-12
    )
    angle = np.degrees(np.arccos(np.clip((np.trace(rot, axis1=1, axis2=2) - 1) / 2, -1, 1)))
    assert 2.0 < angle.max() < 20.0
    assert (
        np.degrees(
            np.arccos(
                np.clip(
                    (np.trace(rot[1:] @ rot[:-1].transpose(0, 2, 1), axis1=1, axis2=2) - 1) / 2,
                    -1,
                    1,
                )
            )
        ).max()
        < 2.0
    )
    still = cases.synthetic(resolution=400, n_frames=10, head_motion=False)
    np.testing.assert_array_equal(still.meta["head_motion"], np.tile(np.eye(4), (10, 1, 1)))


def test_wrinkles_are_high_frequency_normal_offsets():
    smooth = cases.synthetic(resolution=6000, n_frames=2, wrinkles=False)
    wrinkled = cases.synthetic(resolution=6000, n_frames=2, wrinkles=True)
    for a, b in (
        (smooth.source.rig, wrinkled.source.rig),
        (smooth.target.blendshapes, wrinkled.target.blendshapes),
    ):
        k = a.index("browInnerUp")
        diff = b.deltas[k] - a.deltas[k]
        normals = a.neutral.vertex_normals
        along = np.einsum("vi,vi->v", diff, normals)
        assert np.abs(along).max() > 0.002 * a.neutral.height
        # offsets lie along the (analytic) surface normal
        assert (
            np.linalg.norm(diff - along[:, None] * normals, axis=1).max()
            < 0.1 * np.abs(along).max()
        )
        # high frequency: the field changes sign many times along the forehead
        fore = np.abs(along) > 0.3 * np.abs(along).max()
        assert fore.sum() > 20
        assert np.any(along[fore] > 0) and np.any(along[fore] < 0)
        np.testing.assert_array_equal(b.deltas[a.index("jawOpen")], a.deltas[a.index("jawOpen")])


def test_resolution_scales_and_target_topology_can_differ():
    big = cases.synthetic(resolution=100_000, n_frames=2, head_motion=False)
    n = big.source.performance.n_vertices
    assert 90_000 < n < 110_000
    assert big.truth.vertices.shape == (2, n, 3)
    other = cases.synthetic(resolution=800, target_resolution=2500, n_frames=5)
    assert other.target.neutral.n_vertices > 2 * other.source.performance.n_vertices
    _check_truth(other)
    # landmarks of both sit at (nearly) the same parameter points
    uv_s = other.meta["source_uv"][other.source.landmarks.vertex_ids]
    uv_t = other.meta["target_uv"][other.target.landmarks.vertex_ids]
    assert np.abs(uv_s - uv_t).max() < 0.1


def test_bad_arguments_raise_typed_errors():
    with pytest.raises(UnknownNameError):
        cases.synthetic(target="alien")
    with pytest.raises(InputError):
        cases.synthetic(resolution=10)
    with pytest.raises(InputError):
        cases.synthetic(n_frames=0)
    with pytest.raises(InputError):
        cases.ict(source_identity=np.ones(30))
    with pytest.raises(UnknownNameError):
        cases.get_case("nope")
    assert cases.get_case("synthetic", resolution=300, n_frames=3).source.n_frames == 3
