"""The cross-rig case: different topology, units and shape meanings; animation-like weights."""

import numpy as np
import pytest

import faceretarget as fr
from faceretarget import cases
from faceretarget.errors import InputError, UnknownNameError
from faceretarget.evaluation.harness import CASE_NAMES, DEFAULT_CASES, resolve_case


@pytest.fixture(scope="module")
def case():
    return cases.cross_rig(n_frames=600)


@pytest.fixture(scope="module")
def markers():
    return cases.cross_rig(n_frames=600, source_kind="markers")


def _index(case, name):
    return list(case.meta["weight_names"]).index(name)


def test_topology_and_vertex_counts_differ(case):
    src, tgt = case.source.performance.reference, case.target.neutral
    assert 1500 <= src.n_vertices <= 3000 and tgt.n_vertices == 9409
    assert src.n_triangles != tgt.n_triangles
    assert case.source.rig.neutral.n_vertices == src.n_vertices
    # every source vertex is a barycentric point of a target triangle, not a target vertex
    corr = case.meta["source_correspondence"]
    assert corr["triangles"].shape == (src.n_vertices,) and corr["barycentric"].shape == (
        src.n_vertices,
        3,
    )
    assert (corr["barycentric"].max(axis=1) < 1 - 1e-6).mean() > 0.5
    src.check_nondegenerate("cross-rig source")
    # the same holes (outline, 2 eyes, mouth) and feature lines on both sides
    assert (
        set(case.source.feature_lines)
        == set(case.target.feature_lines)
        == {"eye_L", "eye_R", "mouth_inner", "mouth_outer"}
    )


def test_units_differ_by_a_hundred(case):
    ratio = case.target.neutral.height / case.source.performance.reference.height
    assert 80 < ratio < 125
    assert case.meta["unit_scale"] == 100.0
    assert case.meta["face_height"] == pytest.approx(case.target.neutral.height)
    assert case.meta["source_face_height"] == pytest.approx(case.source.rig.neutral.height)
    assert (
        case.source.rig.neutral.height < 1.0 < case.target.neutral.height
    )  # metres vs centimetres


def test_identities_differ(case):
    src = case.source.rig.neutral.vertices * 100.0
    hits = case.meta["source_correspondence"]
    corners = case.target.neutral.triangles[hits["triangles"]]
    tgt_at_src = np.einsum("skd,sk->sd", case.target.neutral.vertices[corners], hits["barycentric"])
    assert np.sqrt(((src - tgt_at_src) ** 2).sum(axis=1).mean()) > 0.3  # cm


def test_target_deltas_are_not_a_perfect_transfer(case):
    pert = case.meta["perturbation"]
    transferred, deltas = pert["transferred"], case.target.blendshapes.deltas
    assert transferred.shape == deltas.shape
    corr = np.einsum("mvd,mvd->m", deltas, transferred) / (
        np.linalg.norm(deltas.reshape(len(deltas), -1), axis=1)
        * np.linalg.norm(transferred.reshape(len(deltas), -1), axis=1)
    )
    assert (corr < 0.99).sum() >= 15, np.round(corr, 3)
    assert corr.max() < 0.9995
    # gains, rotations and mixes rebuild the target
    rebuilt = pert["gain"][:, :, None] * np.einsum(
        "mij,mvj->mvi", pert["rotation"], np.tensordot(pert["mix"], transferred, axes=1)
    )
    np.testing.assert_allclose(deltas, rebuilt, atol=1e-10)
    assert 0.69 < pert["gain"].min() < 0.85 and 1.15 < pert["gain"].max() < 1.31


def test_mouth_shapes_mix_across_families(case):
    """The source's mouthClose projects onto the target's mouthClose + mouthFrown; mouthFunnel onto mouthPucker."""
    transferred = case.meta["perturbation"]["transferred"]
    basis = case.target.blendshapes.deltas.reshape(45, -1).T
    names = list(case.meta["weight_names"])

    def project(name):
        return dict(
            zip(
                names, np.linalg.lstsq(basis, transferred[names.index(name)].ravel(), rcond=None)[0]
            )
        )

    close = project("mouthClose")
    assert 0.5 < close["mouthClose"] < 0.85
    assert close["mouthFrown_L"] > 0.25 and close["mouthFrown_R"] > 0.25
    funnel = project("mouthFunnel")
    assert funnel["mouthPucker"] > funnel["mouthFunnel"] > 0.1


def test_weights_are_sparse_bounded_and_held(case):
    w = case.meta["weights"]
    fps = case.source.fps
    assert w.shape == (600, 45) and w.min() >= 0.0 and w.max() <= 1.0
    active = (w > 0.02).sum(axis=1)
    assert 2 <= np.median(active) <= 14 and (w < 1e-9).mean() > 0.6
    assert np.allclose(w[0], 0.0)  # starts at rest
    # an expression held for at least a second: some shape constant and non-zero for >= fps frames
    longest = 0
    for i in range(w.shape[1]):
        flat = np.r_[False, (np.abs(np.diff(w[:, i])) < 1e-12) & (w[1:, i] > 0.05), False]
        edges = np.flatnonzero(np.diff(flat.astype(int)))
        if len(edges):
            longest = max(longest, (edges[1::2] - edges[::2]).max())
    assert longest >= fps


def test_blinks_and_speech(case):
    w, fps = case.meta["weights"], case.source.fps
    left, right = w[:, _index(case, "eyeBlink_L")], w[:, _index(case, "eyeBlink_R")]
    closed = left > 0.5
    starts = np.flatnonzero(np.diff(closed.astype(int)) == 1)
    assert len(starts) >= 3  # 20 s: a blink every 2-6 s
    gaps = np.diff(starts)
    assert ((gaps >= 1.5 * fps) | (gaps < 0.5 * fps)).all() and (
        gaps >= 1.5 * fps
    ).sum() >= 2  # 2-6 s apart, or a double blink
    assert closed.sum() / len(starts) <= 0.2 * fps  # each shut briefly (~150 ms)
    np.testing.assert_array_equal(closed, right > 0.5)  # both eyes
    jaw = w[:, _index(case, "jawOpen")]
    # speech: the jaw changes direction several times per second while talking
    turns = np.flatnonzero(np.diff(np.sign(np.diff(jaw))) != 0)
    assert len(turns) / (len(jaw) / fps) > 3
    assert (np.abs(np.diff(jaw)) < 1e-9).mean() > 0.2  # and is still between bursts


def test_weights_are_smooth():
    w = cases.cross_rig(n_frames=1200, fps=240.0, source_kind="markers").meta["weights"]
    assert np.abs(np.diff(w, axis=0)).max() < 0.2  # no steps (a 50 ms blink closing is the fastest)
    assert np.abs(np.diff(w, n=2, axis=0)).max() < 0.05


def test_no_head_motion_by_default_and_rigid_when_asked(case):
    np.testing.assert_array_equal(
        case.meta["head_motion"], np.tile(np.eye(4), (case.source.n_frames, 1, 1))
    )
    assert case.source.head_motion is None
    moving = cases.cross_rig(n_frames=60, head_motion=True)
    src_m, tgt_m = moving.meta["head_motion"], moving.truth.head_motion
    angle = np.degrees(
        np.arccos(np.clip((np.trace(src_m[:, :3, :3], axis1=1, axis2=2) - 1) / 2, -1, 1))
    )
    assert angle.max() > 1.0
    np.testing.assert_array_equal(tgt_m[:, :3, :3], src_m[:, :3, :3])
    np.testing.assert_allclose(
        tgt_m[:, :3, 3], 100.0 * src_m[:, :3, 3]
    )  # same motion in centimetres


def test_truth_is_the_target_rig_at_the_weights(case):
    w, rig = case.meta["weights"], case.target.blendshapes
    frames = [0, 150, 451, 599]
    expected = rig.neutral.vertices + np.einsum("fm,mvd->fvd", w[frames], rig.deltas)
    np.testing.assert_allclose(case.truth.vertices[frames], expected, atol=1e-9)
    src = case.source.rig
    np.testing.assert_allclose(
        case.source.performance.vertices[frames],
        src.neutral.vertices + np.einsum("fm,mvd->fvd", w[frames], src.deltas),
        atol=1e-12,
    )
    assert case.truth.weight_names == rig.names == case.source.rig.names
    assert rig.bounds is None and case.source.rig.bounds is None
    assert case.source.fps == case.truth.fps == 30.0


def test_rig_parts_for_other_methods(case):
    src, tgt = case.source, case.target
    assert tgt.parts() == ("blendshapes", "layers", "landmarks", "feature_lines", "examples")
    assert src.landmarks.triangle_ids is not None and len(src.landmarks) == 68
    assert src.landmarks.names == tgt.landmarks.names == cases.ICT_LANDMARK_NAMES
    assert (
        src.examples.shape[0] == tgt.examples.shape[0] == 7
        and src.example_names == tgt.example_names
    )
    assert (
        src.actor_layers.n_points == 68 and src.actor_layers.layer_names == tgt.layers.layer_names
    )
    # source landmarks sit where the target's do (up to identity), in metres
    src_lm = src.marker_reference() * 100.0
    tgt_lm = tgt.landmarks.positions(tgt.neutral.vertices)
    assert np.median(np.linalg.norm(src_lm - tgt_lm, axis=1)) < 1.5
    assert case.meta["layer_coefficients"] is None


def test_marker_source(markers, case):
    perf = markers.source.performance
    assert isinstance(perf, fr.MarkerSequence) and perf.positions.shape == (600, 68, 3)
    assert perf.names == markers.target.landmarks.names == cases.ICT_LANDMARK_NAMES
    np.testing.assert_allclose(perf.positions, case.source.marker_positions(), atol=1e-12)
    np.testing.assert_allclose(perf.reference, case.source.marker_reference(), atol=1e-12)
    assert (
        markers.source.examples.shape == (7, 68, 3) and markers.source.actor_layers.n_points == 68
    )
    np.testing.assert_array_equal(markers.meta["weights"], case.meta["weights"])


def test_long_and_short_sequences():
    long = cases.cross_rig(n_frames=2000, source_kind="markers", seed=4)
    w = long.meta["weights"]
    assert w.shape == (2000, 45) and w.min() >= 0.0 and w.max() <= 1.0
    assert (w[-300:] > 0.02).any(axis=0).sum() >= 4  # still animated at the end
    short = cases.cross_rig(n_frames=2)
    assert short.source.n_frames == short.truth.n_frames == 2


def test_determinism_by_seed():
    a = cases.cross_rig(n_frames=90, seed=3, source_kind="markers")
    b = cases.cross_rig(n_frames=90, seed=3, source_kind="markers")
    c = cases.cross_rig(n_frames=90, seed=4, source_kind="markers")
    np.testing.assert_array_equal(a.meta["weights"], b.meta["weights"])
    np.testing.assert_array_equal(a.target.blendshapes.deltas, b.target.blendshapes.deltas)
    np.testing.assert_array_equal(a.source.performance.positions, b.source.performance.positions)
    assert not np.array_equal(a.meta["weights"], c.meta["weights"])
    assert not np.array_equal(a.target.blendshapes.deltas, c.target.blendshapes.deltas)
    # the prefix of a longer take is not required to match, but the rigs are
    np.testing.assert_array_equal(
        cases.cross_rig(n_frames=30, seed=3).target.blendshapes.deltas, a.target.blendshapes.deltas
    )


def test_registered_by_name_but_not_default():
    assert cases.CASES["cross_rig"] is cases.cross_rig
    assert "cross_rig" in CASE_NAMES and "cross_rig" not in DEFAULT_CASES
    assert resolve_case("cross_rig?n_frames=12&source_kind=markers").source.kind == "markers"


def test_bad_arguments_raise_typed_errors():
    with pytest.raises(UnknownNameError):
        cases.cross_rig(source_kind="weights")
    with pytest.raises(InputError):
        cases.cross_rig(n_frames=0)
    with pytest.raises(InputError):
        cases.cross_rig(source_identity=np.ones(30))
