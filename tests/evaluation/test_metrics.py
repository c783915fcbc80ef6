"""Each built-in metric on a hand-computed example (values worked out in the comments)."""
from types import SimpleNamespace

import numpy as np
import pytest

from faceretarget import Animation, BlendshapeRig, Landmarks, LayeredRig, Mesh, TargetRig
from faceretarget.evaluation import metrics as M

# Six vertices: lower lip v0, upper lip v1, v2; lower lid v3, upper lid v4, forehead v5.
NEUTRAL = np.array([[0, 0, 0], [0, 0.2, 0], [1, 0, 0], [0, 2, 0], [0, 2.2, 0], [1, 2.5, 0]], dtype=float)
TRIANGLES = np.array([[0, 2, 1], [1, 2, 5], [3, 5, 4], [1, 5, 3]])
H = 2.5  # extent along y
LINES = {"mouth_upper": [1, 1], "mouth_lower": [0, 0], "eye_L_upper": [4, 4], "eye_L_lower": [3, 3]}


def make_case(truth_vertices, *, head_motion=None, landmarks=(0, 1), layers=False, truth_weights=None):
    layered = None
    if layers:
        masks = np.array([[1, 1, 1, 0, 0, 0], [0, 0, 0, 1, 1, 0.6]], dtype=float)
        layered = LayeredRig({"one": NEUTRAL[None]}, masks, region_names=["mouth", "eyes"])
    target = TargetRig(Mesh(NEUTRAL, TRIANGLES), landmarks=Landmarks(list(landmarks)), feature_lines={k: v[:2] for k, v in LINES.items()}, layers=layered)
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
    assert M.METRICS["acceleration_error"].why_not(Animation(vertices=truth[:2]), make_case(truth[:2])) == "needs at least 3 frames; the result has 2"


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
    neutral = np.array([[0, 0, 0], [1, 0.1, 0], [0, -0.1, 0], [-1, 0.1, 0], [0, 0.3, 0], [0, -0.3, 0], [0, 5, 0], [0.2, 5.1, 0], [0.2, 4.9, 0]], float)
    lines = {"mouth_inner": np.array([0, 1, 2, 3]), "mouth_outer": np.array([4, 5]), "eye_R": np.array([6, 7, 8])}
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
    assert M.upper_face_vertices(M.feature_groups(case.target.feature_lines, NEUTRAL), NEUTRAL).tolist() == [3, 4, 5]
    std_sq = np.sqrt(np.mean(np.square([0, 0.01, 0])) - np.mean([0, 0.01, 0]) ** 2)  # std of |d|^2 over time
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
    case = SimpleNamespace(target=TargetRig(Mesh(verts, tris)), truth=Animation(vertices=truth, triangles=tris), source=None)
    same = value("detail_correlation", Animation(vertices=verts + 2 * (truth - verts)), case)
    flipped = value("detail_correlation", Animation(vertices=np.stack([verts, verts - detail + smooth])), case)
    assert same == pytest.approx(1.0)
    assert flipped == pytest.approx(-1.0)
    # the high-pass of a constant field is zero
    S = M.smoothing_operator(len(verts), tris)
    assert np.abs(M.high_pass(np.ones((1, len(verts), 3)), S)).max() < 1e-12
    static_case = SimpleNamespace(target=case.target, truth=Animation(vertices=np.stack([verts, verts])), source=None)
    anim = Animation(vertices=np.stack([verts, verts]))
    assert value("detail_correlation", anim, static_case) is None
    assert M.METRICS["detail_correlation"].why_not(anim, static_case) == "the ground truth has no fine-scale motion to preserve"


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
    assert value("weight_outside_share", anim, case) == pytest.approx(0.5)  # 1.2 and -0.1 outside [0, 1]
    assert value("weight_sparsity", anim, case) == pytest.approx(0.25)  # only the 0.0
    assert value("weight_error_rms", anim, case) == pytest.approx(np.sqrt((0.2**2 + 0.2**2) / 4))
    bounded = BlendshapeRig(Mesh(NEUTRAL, TRIANGLES), deltas, ["a", "b"], bounds=[[-0.2, 1.5], [-0.2, 1.5]])
    assert value("weight_outside_share", Animation(weights=w, rig=bounded), case) == 0.0
    verts_only = Animation(vertices=static(2))
    assert value("weight_min", verts_only, case) is None
    assert M.METRICS["weight_min"].why_not(verts_only, case) == "the method outputs vertices, not blendshape weights"


def test_time_and_memory_come_from_the_context():
    anim, case = Animation(vertices=static(1)), make_case(static(1))
    ctx = {"fit_s": 1.5, "retarget_s": 0.25, "total_s": 1.75, "peak_memory_mib": 12.0}
    assert [value(n, anim, case, ctx) for n in ("time_fit", "time_retarget", "time_total", "peak_memory")] == [1.5, 0.25, 1.75, 12.0]
    empty: dict = {}
    assert value("time_total", anim, case, empty) is None
    assert "not measured" in empty["reasons"]["time_total"]


def test_reasons_when_not_applicable():
    anim = Animation(vertices=static(2))
    no_truth = SimpleNamespace(target=make_case(static(2)).target, truth=None, source=None)
    for name in ("vertex_error_mean", "velocity_error", "lve", "fdd", "detail_correlation"):
        assert value(name, anim, no_truth) is None
        assert M.METRICS[name].why_not(anim, no_truth) == "the case has no ground truth"
    bare = SimpleNamespace(target=TargetRig(Mesh(NEUTRAL, TRIANGLES)), truth=Animation(vertices=static(2)), source=None)
    assert M.METRICS["lip_closure_error"].why_not(anim, bare).startswith("the target has no mouth feature lines")
    assert M.METRICS["marker_error_mean"].why_not(anim, bare) == "the target has no landmarks"
    assert M.METRICS["fdd_abs"].why_not(anim, bare).startswith("cannot find the upper face")
    assert M.METRICS["vertex_error_region"].why_not(anim, bare).startswith("the target has neither")


def test_every_metric_has_a_pinned_definition():
    for metric in M.builtin_metrics():
        assert len(metric.description) > 40, metric.name
        assert metric.better in ("lower", "higher", "none")
        assert metric.why_not is not None
