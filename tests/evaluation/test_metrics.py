"""Each built-in metric on a hand-computed example (values worked out in the comments)."""

from types import SimpleNamespace

import numpy as np
import pytest

from faceretarget import Animation, BlendshapeRig, Landmarks, LayeredRig, Mesh, TargetRig
from faceretarget.evaluation import metrics as M

# Six vertices: lower lip v0, upper lip v1, v2; lower lid v3, upper lid v4, forehead v5.
NEUTRAL = np.array(
    [[0, 0, 0], [0, 0.2, 0], [1, 0, 0], [0, 2, 0], [0, 2.2, 0], [1, 2.5, 0]], dtype=float
)
TRIANGLES = np.array([[0, 2, 1], [1, 2, 5], [3, 5, 4], [1, 5, 3]])
H = 2.5  # extent along y
LINES = {"mouth_upper": [1, 1], "mouth_lower": [0, 0], "eye_L_upper": [4, 4], "eye_L_lower": [3, 3]}


def make_case(
    truth_vertices, *, head_motion=None, landmarks=(0, 1), layers=False, truth_weights=None
):
    layered = None
    if layers:
        masks = np.array([[1, 1, 1, 0, 0, 0], [0, 0, 0, 1, 1, 0.6]], dtype=float)
        layered = LayeredRig({"one": NEUTRAL[None]}, masks, region_names=["mouth", "eyes"])
    target = TargetRig(
        Mesh(NEUTRAL, TRIANGLES),
        landmarks=Landmarks(list(landmarks)),
        feature_lines={k: v[:2] for k, v in LINES.items()},
        layers=layered,
    )
    if truth_weights is not None:
        rig, names, w = truth_weights
        truth = Animation(weights=w, rig=rig, weight_names=names)
    else:
        truth = Animation(vertices=truth_vertices, triangles=TRIANGLES, head_motion=head_motion)
    return SimpleNamespace(name="hand", source=None, target=target, truth=truth)


def static(n_frames):
    return np.repeat(NEUTRAL[None], n_frames, axis=0)


def value(name, animation, case, context=None):
    return M.METRICS[name].compute(animation, case, context)


def test_position_errors():
    truth = static(2)
    result = truth.copy()
    result[0, 0, 0] += 0.025  # frame 0, v0: 0.025 = 1 % of H
    result[1, 1, 1] += 0.05  # frame 1, v1: 0.05 = 2 % of H
    anim, case = Animation(vertices=result), make_case(truth)
    # distances in %H: [[1, 0, 0, 0, 0, 0], [0, 2, 0, 0, 0, 0]]
    assert value("vertex_error_mean", anim, case) == pytest.approx(3 / 12)
    assert value("vertex_error_rms", anim, case) == pytest.approx(np.sqrt(5 / 12))
    assert value("vertex_error_max", anim, case) == pytest.approx(2.0)
    # landmarks v0, v1: [[1, 0], [0, 2]]
    assert value("marker_error_mean", anim, case) == pytest.approx(0.75)
    assert value("marker_error_max", anim, case) == pytest.approx(2.0)


def test_region_errors_from_layer_masks():
    truth = static(1)
    result = truth.copy()
    result[0, 5, 2] += 0.25  # v5 (eyes region: mask 0.6 >= 0.5) 10 % of H
    result[0, 0, 2] += 0.05  # v0 (mouth region) 2 % of H
    out = value("vertex_error_region", Animation(vertices=result), make_case(truth, layers=True))
    assert out == pytest.approx({"mouth": 2 / 3, "eyes": 10 / 3})


def test_velocity_error_as_seol_fig11():
    truth = static(2)
    result = truth.copy()
    result[0, 0, 0] += 0.02
    result[1, 1, 1] += 0.04
    # D(P - Q) = frame 1 - frame 0: v0 (-0.02, 0, 0), v1 (0, 0.04, 0): 0.0004 + 0.0016 = 0.002; / H^2
    got = value("velocity_error", Animation(vertices=result), make_case(truth))
    assert got == pytest.approx(0.002 / H**2)


def test_velocity_error_ignores_shared_head_motion_but_not_wrong_motion():
    truth = static(3)
    motion = np.tile(np.eye(4), (3, 1, 1))
    motion[:, 0, 3] = [0.0, 0.5, 1.0]  # head translates along x
    moved = truth + motion[:, None, :3, 3]
    case = make_case(moved, head_motion=motion)
    assert value("velocity_error", Animation(vertices=moved), case) == pytest.approx(0.0, abs=1e-20)
    # a result that forgot the head motion: landmark velocity error 0.5^2 per landmark per step
    got = value("velocity_error", Animation(vertices=truth), case)
    assert got == pytest.approx(2 * 2 * 0.25 / H**2)


def test_acceleration_and_jitter():
    truth = static(3)
    result = truth.copy()
    a = 0.05
    result[1, 0, 0] += a  # one spike: second difference at t=1 is -2a for v0
    anim, case = Animation(vertices=result), make_case(truth)
    # RMS over 1 frame x 6 vertices of ||A X - A Y|| = sqrt((2a)^2 / 6)
    assert value("acceleration_error", anim, case) == pytest.approx(100 * 2 * a / np.sqrt(6) / H)
    # mean ||A X|| = 2a / 6, truth static -> 0
    assert value("jitter_excess", anim, case) == pytest.approx(100 * (2 * a / 6) / H)
    assert (
        M.METRICS["acceleration_error"].why_not(Animation(vertices=truth[:2]), make_case(truth[:2]))
        == "needs at least 3 frames; the result has 2"
    )


def test_closure_errors_and_lve():
    truth = static(2)
    result = truth.copy()
    result[1, 1, 1] -= 0.1  # upper lip down at frame 1: lip opening 0.2 -> 0.1
    result[0, 3, 1] += 0.05  # lower lid up at frame 0: lid opening 0.2 -> 0.15
    anim, case = Animation(vertices=result), make_case(truth)
    # |d_X - d_Y| mean over frames: lips (0 + 0.1) / 2 = 0.05; lids (0.05 + 0) / 2 = 0.025
    assert value("lip_closure_error", anim, case) == pytest.approx(100 * 0.05 / H)
    assert value("eyelid_closure_error", anim, case) == pytest.approx(100 * 0.025 / H)
    # LVE: per frame max over lip vertices {v0, v1}: frame 0 -> 0, frame 1 -> 0.1; mean 0.05
    assert value("lve", anim, case) == pytest.approx(100 * 0.05 / H)


def test_feature_groups_split_loops_and_prefer_inner_lines():
    neutral = np.array(
        [
            [0, 0, 0],
            [1, 0.1, 0],
            [0, -0.1, 0],
            [-1, 0.1, 0],
            [0, 0.3, 0],
            [0, -0.3, 0],
            [0, 5, 0],
            [0.2, 5.1, 0],
            [0.2, 4.9, 0],
        ],
        float,
    )
    lines = {
        "mouth_inner": np.array([0, 1, 2, 3]),
        "mouth_outer": np.array([4, 5]),
        "eye_R": np.array([6, 7, 8]),
    }
    groups = M.feature_groups(lines, neutral)
    upper, lower = groups["mouth"]
    # inner loop only (outer ignored); split at its centroid y = 0.025
    assert upper.tolist() == [1, 3] and lower.tolist() == [0, 2]
    assert sorted(groups) == ["eye_right", "mouth"]
    u, l = M.closure_pairs(upper, lower, neutral)
    assert l.tolist() == [0, 0]  # both corners' nearest lower vertex is v0 (distance 1.005 < 1.04)


def test_fdd_both_variants():
    truth = static(3)
    truth[1, 5, 2] += 0.1  # forehead v5 moves out and back: |d| = [0, 0.1, 0]
    anim, case = Animation(vertices=static(3)), make_case(truth)
    # upper face: y above (mean eye y 2.1 + mean mouth y 0.1) / 2 = 1.1 -> v3, v4, v5
    assert M.upper_face_vertices(
        M.feature_groups(case.target.feature_lines, NEUTRAL), NEUTRAL
    ).tolist() == [3, 4, 5]
    std_sq = np.sqrt(
        np.mean(np.square([0, 0.01, 0])) - np.mean([0, 0.01, 0]) ** 2
    )  # std of |d|^2 over time
    assert value("fdd", anim, case) == pytest.approx(std_sq / 3 * (100 / H) ** 2)
    std_abs = np.sqrt(np.mean(np.square([0, 0.1, 0])) - np.mean([0, 0.1, 0]) ** 2)
    assert value("fdd_abs", anim, case) == pytest.approx(100 * std_abs / 3 / H)
    # a result that moves more than the truth gives a negative (signed) FDD
    assert value("fdd", Animation(vertices=truth * [1, 1, 2]), case) < 0


def test_detail_correlation():
    from fake_retargeters import grid

    verts, tris = grid(7)
    detail = np.zeros_like(verts)
    detail[:, 2] = 0.01 * ((np.arange(len(verts)) % 2) * 2 - 1)  # checkerboard: pure high frequency
    smooth = np.zeros_like(verts)
    smooth[:, 1] = 0.05  # a translation: the uniform smoothing keeps it, so it is no detail
    truth = np.stack([verts, verts + detail + smooth])
    case = SimpleNamespace(
        target=TargetRig(Mesh(verts, tris)),
        truth=Animation(vertices=truth, triangles=tris),
        source=None,
    )
    same = value("detail_correlation", Animation(vertices=verts + 2 * (truth - verts)), case)
    flipped = value(
        "detail_correlation", Animation(vertices=np.stack([verts, verts - detail + smooth])), case
    )
    assert same == pytest.approx(1.0)
    assert flipped == pytest.approx(-1.0)
    # the high-pass of a constant field is zero
    S = M.smoothing_operator(len(verts), tris)
    assert np.abs(M.high_pass(np.ones((1, len(verts), 3)), S)).max() < 1e-12
    static_case = SimpleNamespace(
        target=case.target, truth=Animation(vertices=np.stack([verts, verts])), source=None
    )
    anim = Animation(vertices=np.stack([verts, verts]))
    assert value("detail_correlation", anim, static_case) is None
    assert (
        M.METRICS["detail_correlation"].why_not(anim, static_case)
        == "the ground truth has no fine-scale motion to preserve"
    )


def test_the_truths_fine_scale_detail_is_computed_once_per_truth_and_mesh(monkeypatch):
    """Every run scored against one truth shares its hn(Y - N) (compare scores each method
    against it): one computation for two runs, the same values as a fresh one, another for
    another target mesh, and the entry goes with the truth."""
    import gc

    from fake_retargeters import grid

    verts, tris = grid(7)
    rng = np.random.default_rng(0)
    truth = Animation(vertices=verts + 0.01 * rng.normal(size=(3, *verts.shape)), triangles=tris)
    case = SimpleNamespace(target=TargetRig(Mesh(verts, tris)), truth=truth, source=None)
    moved = SimpleNamespace(target=TargetRig(Mesh(1.5 * verts, tris)), truth=truth, source=None)
    runs = [Animation(vertices=verts + 0.01 * rng.normal(size=(3, *verts.shape))) for _ in range(2)]
    fresh = [value("detail_error", a, case) for a in runs]
    monkeypatch.setattr(M, "_TRUTH", M._TruthCache())  # as a new process: nothing cached yet
    calls = []
    real = M.normal_detail
    monkeypatch.setattr(
        M, "normal_detail", lambda d, *a, **k: calls.append(d.shape) or real(d, *a, **k)
    )
    assert [value("detail_error", a, case) for a in runs] == fresh
    assert len(calls) == 3  # two runs and the truth once
    value("detail_error", runs[0], moved)
    assert len(calls) == 5  # another mesh: the truth's detail there too
    del case, moved, truth
    gc.collect()
    assert not M._TRUTH._items


# ---------------------------------------------------------------------------------------
# Fine-scale detail on the synthetic case, whose rigs carry wrinkle fields (60 frames: the
# wrinkle shapes are active), against the same performance built without wrinkles
# ---------------------------------------------------------------------------------------
@pytest.fixture(scope="module")
def wrinkled():
    import faceretarget

    spec = dict(resolution=1500, n_frames=60)
    return faceretarget.cases.synthetic(**spec), faceretarget.cases.synthetic(
        **spec, wrinkles=False
    )


def _detail(name, vertices, case):
    return value(name, Animation(vertices=np.asarray(vertices, dtype=np.float64)), case)


def fake_rotation(rotvec):
    from scipy.spatial.transform import Rotation

    return Rotation.from_rotvec(rotvec).as_matrix()


def _in_world(case, local):
    """``local : (F, V, 3)`` offsets in the truth's head frame, rotated into the world."""
    return np.einsum("fij,fvj->fvi", case.truth.head_motion[:, :3, :3], local)


def test_detail_error_is_zero_for_identical_sequences(wrinkled):
    case, _ = wrinkled
    truth = case.truth.vertices
    assert _detail("detail_error", truth, case) == 0.0
    assert _detail("detail_correlation", truth, case) == pytest.approx(1.0)
    assert (
        _detail("detail_error", truth.astype(np.float32), case) < 1e-5
    )  # float32 output: rounding only


def test_detail_error_is_invariant_to_the_targets_units(wrinkled):
    case, free = wrinkled
    result = np.asarray(free.truth.vertices) + 0.002 * np.random.default_rng(0).normal(
        size=free.truth.vertices.shape
    )
    target = case.target
    for scale in (100.0, 0.01):
        motion = case.truth.head_motion.copy()
        motion[:, :3, 3] *= scale
        scaled = SimpleNamespace(
            target=TargetRig(
                Mesh(scale * np.asarray(target.neutral.vertices), target.neutral.triangles)
            ),
            truth=Animation(vertices=scale * np.asarray(case.truth.vertices), head_motion=motion),
            source=None,
        )
        for name in ("detail_error", "detail_correlation"):
            assert _detail(name, scale * result, scaled) == pytest.approx(
                _detail(name, result, case), rel=1e-9
            ), (name, scale)


def test_detail_error_ignores_smooth_errors_and_sees_a_removed_wrinkle(wrinkled):
    """RMS ranks these the other way: a broad bump 20x the RMS error of the missing wrinkles
    barely registers, the missing wrinkles cost their whole fine-scale motion."""
    case, free = wrinkled
    neutral, height = np.asarray(case.target.neutral.vertices), case.target.neutral.height
    removed = free.truth.vertices  # the same performance without its wrinkles
    centre = neutral.mean(axis=0)
    bump = np.exp(-0.5 * (np.linalg.norm(neutral - centre, axis=1) / (0.2 * height)) ** 2)
    direction = np.array([0.3, -0.5, 0.8]) / np.linalg.norm([0.3, -0.5, 0.8])
    swing = np.sin(np.linspace(0.0, 3.0, case.truth.n_frames))[:, None, None]
    smooth = case.truth.vertices + _in_world(
        case, 0.01 * height * swing * bump[None, :, None] * direction
    )
    affine = case.truth.vertices + _in_world(
        case,
        swing
        * (
            (neutral - centre) @ np.array([[0.01, 0, 0.002], [0.004, -0.008, 0], [0, 0.003, 0.006]])
        )[None],
    )
    turn = fake_rotation([0.02, 0.01, -0.015]) - np.eye(3)  # a face turned by about 1.5 degrees
    rotated = case.truth.vertices + _in_world(case, swing * ((neutral - centre) @ turn.T)[None])
    errors = {"removed": removed, "smooth": smooth, "affine": affine, "rotated": rotated}
    rms = {k: _detail("vertex_error_rms", x, case) for k, x in errors.items()}
    detail = {k: _detail("detail_error", x, case) for k, x in errors.items()}
    assert min(rms["smooth"], rms["affine"], rms["rotated"]) > 10 * rms["removed"]
    assert detail["removed"] > 0.8 * rms["removed"]  # the wrinkles are (nearly) all fine scale
    assert detail["smooth"] < 0.05 * rms["smooth"]
    # linear fields: the eye, mouth and outer rims smoothed along themselves do not leak them
    # (smoothing the rims like the interior gives 0.0105 and 0.0161)
    assert detail["affine"] < 0.01 * rms["affine"] and detail["rotated"] < 0.01 * rms["rotated"], (
        detail,
        rms,
    )
    assert detail["removed"] > 2 * max(detail["smooth"], detail["affine"], detail["rotated"])
    assert (
        _detail("detail_correlation", smooth, case)
        > 0.98
        > _detail("detail_correlation", removed, case)
    )


def test_detail_error_sees_coating_without_its_detail_layer(wrinkled):
    """Mutant: coating with its transferred fine-scale motion scaled to ~0 (the parameter must be
    > 0) is worse on the detail error, and more so when the performance has wrinkles
    (measured at 1500 vertices, 60 frames: 0.0190 vs 0.0142 % face height more)."""
    import faceretarget

    rise = {}
    for label, case in zip(("wrinkles", "none"), wrinkled):
        runs = {
            scale: faceretarget.get("coating", detail_scale=scale)
            .fit(case.source, case.target)
            .retarget(case.source)
            for scale in (1.0, 1e-9)
        }
        full, dropped = (value("detail_error", runs[s], case) for s in (1.0, 1e-9))
        assert dropped > full, (label, full, dropped)
        rise[label] = dropped - full
        if label == "wrinkles":
            assert dropped > 2 * full
            assert value("detail_correlation", runs[1e-9], case) < value(
                "detail_correlation", runs[1.0], case
            )
    # the layer also carries coating's basis-fit residual (issue 14 item 5), so dropping it costs
    # something without wrinkles too; the wrinkles add to that
    assert rise["wrinkles"] > rise["none"], rise


@pytest.mark.xfail(
    strict=True,
    reason=(
        "issue 14 item 6: on the wrinkled synthetic cases coating and normalmesh should beat deformation_transfer "
        "on detail_error; measured here (1500 vertices, 60 frames; % face height): human coating 0.00347 / normalmesh "
        "0.00479 vs DT 0.00290, stylized 0.01436 / 0.01771 vs 0.01294. Mechanism (docs/methods/coating.md, "
        "normalmesh.md; benchmarks/bench_dense_fidelity.py parts detail and detail-bound): the metric is the fine-scale "
        "normal motion of the large-scale expression (the wrinkle-free twin gives 97-99% of it; coating carries the "
        "wrinkles themselves at correlation 0.9998-1.0000, gain 0.94/1.11), 52-61% of DT's and coating's error on the "
        "eye, mouth and outer rims and the ring next to them: the truth slides the skin through each face's smooth cage, so over features shaped "
        "differently (lips, snout, lids) tangential motion gains a normal component, which per-triangle deformation "
        "gradients reproduce and local-frame (coating, Eq. 16) or normal-offset (normalmesh, Eq. 8) transfers do not. "
        "Coating tends to DT from above as its detail layer empties (Taubin iterations 40 -> 1: human 0.00347 -> "
        "0.00291, stylized 0.01436 -> 0.01311); the size ratio (detail_scale='auto') gives human 0.00296 but stylized "
        "0.01448, the detail keeping its rest direction instead of Eq. 16's rotation 0.00335 / 0.01323. Even applied exactly vertex to vertex, no such per-vertex "
        "transfer of the source's fine motion reaches 0.7x: normal to normal 1.49x / 1.24x, x size ratio 1.02x / 1.26x, "
        "direction kept 1.21x / 0.79x; only a per-vertex gain fitted to the truth does (0.58x / 0.66x). normalmesh: "
        "76-97% of its error is on the normal mesh (the example-based fallback at the rims adds 1-2%); 5 levels give "
        "human 0.00410, 6 levels 0.00493. The papers' setting, cases.cross_topology(wrinkles=True) (90 frames): coating "
        "0.95x DT, normalmesh 1.78x, the same on the twin (the lips' contact line), so this test keeps the "
        "synthetic cases. Remove this mark when it passes."
    ),
)
def test_dense_methods_beat_deformation_transfer_on_detail(wrinkled):
    import faceretarget

    human = wrinkled[0]
    stylized = faceretarget.cases.synthetic(resolution=1500, n_frames=60, target="stylized")
    for case in (human, stylized):
        got = {
            m: value(
                "detail_error",
                faceretarget.get(m).fit(case.source, case.target).retarget(case.source),
                case,
            )
            for m in ("coating", "normalmesh", "deformation_transfer")
        }
        assert (
            got["coating"] < got["deformation_transfer"]
            and got["normalmesh"] < got["deformation_transfer"]
        ), got


def test_weight_statistics():
    deltas = np.zeros((2, 6, 3))
    deltas[0, 0, 1], deltas[1, 1, 1] = 0.1, 0.1
    rig = BlendshapeRig(Mesh(NEUTRAL, TRIANGLES), deltas, ["a", "b"])
    w = np.array([[0.0, 0.5], [1.2, -0.1]])
    anim = Animation(weights=w, rig=rig)
    truth_w = np.array([[0.0, 0.5], [1.0, 0.1]])
    case = make_case(None, truth_weights=(rig, ["a", "b"], truth_w))
    assert value("weight_min", anim, case) == -0.1
    assert value("weight_max", anim, case) == 1.2
    assert value("weight_outside_share", anim, case) == pytest.approx(
        0.5
    )  # 1.2 and -0.1 outside [0, 1]
    assert value("weight_sparsity", anim, case) == pytest.approx(0.25)  # only the 0.0
    assert value("weight_error_rms", anim, case) == pytest.approx(np.sqrt((0.2**2 + 0.2**2) / 4))
    bounded = BlendshapeRig(
        Mesh(NEUTRAL, TRIANGLES), deltas, ["a", "b"], bounds=[[-0.2, 1.5], [-0.2, 1.5]]
    )
    assert value("weight_outside_share", Animation(weights=w, rig=bounded), case) == 0.0
    verts_only = Animation(vertices=static(2))
    assert value("weight_min", verts_only, case) is None
    assert (
        M.METRICS["weight_min"].why_not(verts_only, case)
        == "the method outputs vertices, not blendshape weights"
    )


def test_time_and_memory_come_from_the_context():
    anim, case = Animation(vertices=static(1)), make_case(static(1))
    ctx = {"fit_s": 1.5, "retarget_s": 0.25, "total_s": 1.75, "peak_memory_mib": 12.0}
    assert [
        value(n, anim, case, ctx)
        for n in ("time_fit", "time_retarget", "time_total", "peak_memory")
    ] == [1.5, 0.25, 1.75, 12.0]
    empty: dict = {}
    assert value("time_total", anim, case, empty) is None
    assert "not measured" in empty["reasons"]["time_total"]


def test_reasons_when_not_applicable():
    anim = Animation(vertices=static(2))
    no_truth = SimpleNamespace(target=make_case(static(2)).target, truth=None, source=None)
    for name in (
        "vertex_error_mean",
        "velocity_error",
        "lve",
        "fdd",
        "detail_error",
        "detail_correlation",
    ):
        assert value(name, anim, no_truth) is None
        assert M.METRICS[name].why_not(anim, no_truth) == "the case has no ground truth"
    bare = SimpleNamespace(
        target=TargetRig(Mesh(NEUTRAL, TRIANGLES)), truth=Animation(vertices=static(2)), source=None
    )
    assert (
        M.METRICS["lip_closure_error"]
        .why_not(anim, bare)
        .startswith("the target has no mouth feature lines")
    )
    assert M.METRICS["marker_error_mean"].why_not(anim, bare) == "the target has no landmarks"
    assert M.METRICS["fdd_abs"].why_not(anim, bare).startswith("cannot find the upper face")
    assert M.METRICS["vertex_error_region"].why_not(anim, bare).startswith("the target has neither")


def test_every_metric_has_a_pinned_definition():
    for metric in M.builtin_metrics():
        assert len(metric.description) > 40, metric.name
        assert metric.better in ("lower", "higher", "none")
        assert metric.why_not is not None
