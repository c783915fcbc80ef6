"""Spacetime editing of coating results: large-scale (bases / weights) and fine-scale details."""
import numpy as np
import pytest
from naive.coating import bases_edit as naive_bases_edit
from naive.coating import grid_mesh
from naive.coating import propagate as naive_propagate
from scipy.optimize import nnls

import faceretarget as fr
from faceretarget.errors import ConfigError, IndexRangeError, InputError, NonFiniteError
from faceretarget.geometry.deformation_gradients import DeformationTransfer
from faceretarget.plugins.coating import DetailEdit
from faceretarget.plugins.coating.details import active_range, propagate, select_region
from faceretarget.plugins.coating.editing import Constraint, Influence, solve_bases, solve_weights
from faceretarget.plugins.coating.retargeter import CoatingRetargeter

HALF = 25
FRAMES = 2 * HALF


@pytest.fixture(scope="module")
def setup():
    """The performance played twice: frame t and t + HALF show the same expression."""
    case = fr.cases.synthetic(seed=2, resolution=900, n_frames=HALF)
    perf = case.source.performance
    twice = fr.MeshSequence(np.concatenate([perf.vertices, perf.vertices]), perf.triangles, reference=perf.reference)
    source = fr.Source(twice, feature_lines=case.source.feature_lines)
    r = CoatingRetargeter().fit(source, case.target)
    anim = r.retarget(source)
    names = list(case.target.landmarks.names)
    corner = int(case.target.landmarks.vertex_ids[names.index("mouth_corner_L")])
    return case, r, anim, corner


def _edit_frame(anim):
    w = anim.extras["weights"]
    return int(np.argmax(np.abs(w[5:20, 1:]).sum(axis=1))) + 5  # an expressive frame of the first half


def test_bases_mode_meets_the_constraint_and_reaches_similar_expressions(setup):
    case, r, anim, v = setup
    t = _edit_frame(anim)
    h = case.target.neutral.height
    goal = anim.vertices[t, v] + np.array([0.0, 0.02 * h, 0.0])
    window = (t - 3, t + 3)
    out = r.edit(anim, points=[(t, v, goal)], window=window, mode="bases")
    requested = np.linalg.norm(goal - anim.vertices[t, v])
    assert np.linalg.norm(out.vertices[t, v] - goal) < 0.05 * requested
    w = anim.extras["weights"]
    outside = np.r_[0 : window[0], window[1] + 1 : FRAMES]
    dissimilar = outside[np.argmax(np.linalg.norm(w[outside] - w[t], axis=1))]
    change = np.linalg.norm(out.vertices[:, v] - anim.vertices[:, v], axis=-1)
    # fig. 4(b): the same expression later in the sequence, far outside the window, is edited alike
    np.testing.assert_allclose(change[t + HALF], change[t], rtol=1e-6)
    assert change[t + HALF] > 10 * change[dissimilar]
    assert out.provenance["diagnostics"]["last_edit"]["mode"] == "bases"


def test_weights_mode_changes_nothing_outside_the_window(setup):
    case, r, anim, v = setup
    t = _edit_frame(anim)
    goal = anim.vertices[t, v] + np.array([0.0, 0.01 * case.target.neutral.height, 0.0])
    window = (t - 4, t + 6)
    out = r.edit(anim, points=[(t, v, goal)], window=window, mode="weights")
    outside = np.r_[0 : window[0], window[1] + 1 : FRAMES]
    np.testing.assert_array_equal(out.vertices[outside], anim.vertices[outside])
    np.testing.assert_array_equal(out.extras["weights"][outside], anim.extras["weights"][outside])
    assert t + HALF in outside  # fig. 4(d): the same expression outside the window is untouched
    assert np.linalg.norm(out.vertices[t, v] - goal) < np.linalg.norm(anim.vertices[t, v] - goal)
    assert (out.extras["weights"] >= 0).all()


def test_both_mode_and_distance_and_fixed(setup):
    case, r, anim, v = setup
    t = _edit_frame(anim)
    h = case.target.neutral.height
    goal = anim.vertices[t, v] + np.array([0.01 * h, 0.01 * h, 0.0])
    out = r.edit(anim, points=[(t, v, goal)], mode="both")
    assert np.linalg.norm(out.vertices[t, v] - goal) < 0.05 * np.linalg.norm(goal - anim.vertices[t, v])
    # distance constraint between the lip corners
    names = list(case.target.landmarks.names)
    other = int(case.target.landmarks.vertex_ids[names.index("mouth_corner_R")])
    d0 = np.linalg.norm(anim.vertices[t, v] - anim.vertices[t, other])
    out = r.edit(anim, distances=[(t, v, other, 1.1 * d0)])
    d1 = np.linalg.norm(out.vertices[t, v] - out.vertices[t, other])
    assert abs(d1 - 1.1 * d0) < 0.05 * 0.1 * d0
    # fixed points keep their place while a neighbour moves
    keep = np.argsort(np.linalg.norm(anim.vertices[t] - anim.vertices[t, v], axis=1))[5:25]
    free = r.edit(anim, points=[(t, v, goal)], mode="bases")
    fixed = r.edit(anim, points=[(t, v, goal)], fixed=[(t, keep)], mode="bases")
    moved_free = np.linalg.norm(free.vertices[t, keep] - anim.vertices[t, keep], axis=1).max()
    moved_fixed = np.linalg.norm(fixed.vertices[t, keep] - anim.vertices[t, keep], axis=1).max()
    assert moved_fixed < 0.5 * moved_free


def test_zero_edit_changes_nothing(setup):
    case, r, anim, v = setup
    t = _edit_frame(anim)
    out = r.edit(anim, points=[(t, v, anim.vertices[t, v])], mode="both")
    assert np.abs(out.vertices - anim.vertices).max() < 1e-8 * case.target.neutral.height


def test_edits_chain_and_keep_the_input(setup):
    case, r, anim, v = setup
    before = np.array(anim.vertices)
    t = _edit_frame(anim)
    goal = anim.vertices[t, v] + 0.01 * case.target.neutral.height
    once = r.edit(anim, points=[(t, v, goal)], mode="bases")
    twice = r.edit(once, points=[(t + 5, v, once.vertices[t + 5, v])], mode="bases")
    np.testing.assert_array_equal(anim.vertices, before)
    assert np.linalg.norm(twice.vertices[t, v] - goal) < 0.1 * 0.01 * case.target.neutral.height * np.sqrt(3)
    assert twice.provenance["edits"] == ["large_scale", "large_scale"]


def test_bases_step_matches_the_assembled_solve():
    v, t = grid_mesh(5, seed=0)
    rng = np.random.default_rng(0)
    gauge = np.zeros(len(v))
    gauge[:5] = 1.0
    dt = DeformationTransfer(v, t, gauge_weights=gauge)
    bases = v + 0.05 * rng.normal(size=(3,) + v.shape)
    center = v.mean(axis=0)
    weights = rng.uniform(0.1, 1.0, size=(4, 3))
    cons = [
        Constraint(1, np.array([12]), np.array([1.0]), v[12] + [0.1, 0.0, 0.05]),
        Constraint(3, np.array([18, 6]), np.array([1.0, -1.0]), v[18] - v[6] + [0.0, 0.1, 0.0]),
    ]
    got, _ = solve_bases(bases, center, weights, cons, 30.0, 2.0, Influence(dt, cons))
    want = naive_bases_edit(dt.normal_matrix.toarray(), dt.gauge_weights, bases, center, weights, cons, 30.0, 2.0, dt.free)
    np.testing.assert_allclose(got, want, atol=1e-9)


def test_weights_step_matches_the_full_temporal_problem():
    rng = np.random.default_rng(1)
    n_frames, k = 12, 3
    bases = rng.normal(size=(k, 6, 3))
    center = np.zeros(3)
    weights = rng.uniform(0.5, 1.0, size=(n_frames, k))
    cons = [Constraint(5, np.array([2]), np.array([1.0]), np.array([0.3, -0.2, 0.1])), Constraint(8, np.array([4]), np.array([1.0]), np.array([0.0, 0.2, 0.1]))]
    window, mu, lam = (2, 10), 0.5, 1.0
    got, _ = solve_weights(bases, center, weights, cons, window, mu, lam)
    # dense: unknowns are every window frame's weights; velocity terms include the fixed neighbours
    frames = np.arange(window[0], window[1] + 1)
    n = frames.size * k
    rows, rhs = [], []
    for t in range(window[0] - 1, window[1] + 1):
        for i in range(k):
            row = np.zeros(n)
            target = weights[t + 1, i] - weights[t, i]
            for s, sign in ((t + 1, 1.0), (t, -1.0)):
                if window[0] <= s <= window[1]:
                    row[(s - window[0]) * k + i] += sign
                else:
                    target -= sign * weights[s, i]
            rows.append(np.sqrt(lam) * row)
            rhs.append(np.sqrt(lam) * target)
    for c in cons:
        a = bases[:, c.vertices[0]] - center  # (k, 3)
        for d in range(3):
            row = np.zeros(n)
            row[(c.frame - window[0]) * k : (c.frame - window[0] + 1) * k] = a[:, d]
            rows.append(np.sqrt(mu) * row)
            rhs.append(np.sqrt(mu) * (c.value[d] - center[d]))
    dense = nnls(np.array(rows), np.array(rhs))[0].reshape(frames.size, k)
    np.testing.assert_allclose(got[window[0] : window[1] + 1], dense, atol=1e-8)
    np.testing.assert_array_equal(got[: window[0]], weights[: window[0]])


def test_propagation_matches_the_assembled_system():
    rng = np.random.default_rng(2)
    change = rng.normal(size=(5, 3))
    edges = np.array([[0, 1], [1, 2], [2, 3], [3, 4], [0, 2]])
    for key in (0, 3, 6):
        got = propagate(change, edges, key, 7, lambda_key=1.0, lambda_gradient=0.1, lambda_boundary=1.0, fix_start=True, fix_end=True)
        want = naive_propagate(change, edges, key, 7, 1.0, 0.1, 1.0)
        np.testing.assert_allclose(got, want, atol=1e-12)


def test_large_regions_use_lanczos_close_to_the_dense_solve(monkeypatch):
    from faceretarget.geometry.mesh_ops import unique_edges
    from faceretarget.plugins.coating import details

    v, t = grid_mesh(16, seed=3)
    edges = unique_edges(t)
    g = np.sin(25 * v[:, 1])[:, None] * np.exp(-((v[:, 0] - 0.5) ** 2) / 0.05)[:, None] * [0.1, 0.2, 1.0]
    kw = dict(lambda_key=1.0, lambda_gradient=0.1, lambda_boundary=1.0, fix_start=True, fix_end=True)
    dense = propagate(g, edges, 20, 60, **kw)
    monkeypatch.setattr(details, "DENSE_REGION", 50)
    monkeypatch.setattr(details, "LANCZOS_STEPS", 60)
    approx = propagate(g, edges, 20, 60, **kw)
    assert np.abs(approx - dense).max() < 1e-4 * np.abs(dense).max()


def test_active_range_and_region_selection():
    m = np.array([0.0, 0.1, 0.3, 0.9, 1.0, 0.5, 0.2, 0.8])
    assert active_range(m, 4, 0.23) == (2, 5)
    assert active_range(np.zeros(5), 2, 0.23) == (2, 2)
    pts = np.stack([np.linspace(0, 1, 11), np.zeros(11), np.zeros(11)], axis=1)
    ids = select_region(pts, curve=np.array([[0.0, 0.0, 0.05], [0.3, 0.0, 0.05]]), radius=0.08)
    np.testing.assert_array_equal(ids, [0, 1, 2, 3])


def _furrow_setup(setup):
    case, r, anim, _ = setup
    uv = case.meta["target_uv"]
    region = np.flatnonzero((np.abs(uv[:, 0]) < 0.35) & (uv[:, 1] > 0.65) & (uv[:, 1] < 0.95))
    track = anim.extras["coating"]
    magnitude = np.linalg.norm(track.fine_motion(slice(None), region), axis=-1).sum(axis=1)
    return region, int(np.argmax(magnitude)), track


def test_detail_scale_remove_and_window(setup):
    case, r, anim, _ = setup
    region, key, track = _furrow_setup(setup)
    r.set_params(lambda_key=1e4)  # pin the key frame (the paper's 1 damps fine wrinkles on coarse meshes)
    try:
        out = r.edit(anim, detail=DetailEdit(frame=key, vertices=region, operation="scale", factor=2.0, blend=0))
    finally:
        r.set_params(lambda_key=1.0)
    diag = out.provenance["diagnostics"]["last_edit"]
    ts, te = diag["window"]
    assert ts <= key <= te
    new = out.extras["coating"].fine_motion([key], region)[0]
    old = track.fine_motion([key], region)[0]
    np.testing.assert_allclose(new, 2.0 * old, atol=1e-3 * np.abs(old).max())
    outside = np.r_[0:ts, te + 1 : FRAMES]
    np.testing.assert_array_equal(out.vertices[outside], anim.vertices[outside])
    # with the paper's weights the key frame keeps most of a removal
    gone = r.edit(anim, detail={"frame": key, "vertices": region, "operation": "remove"})
    left = np.linalg.norm(gone.extras["coating"].fine_motion([key], region)) / np.linalg.norm(old)
    assert left < 0.7
    assert np.abs(gone.vertices[key] - anim.vertices[key]).max() > 0


def test_detail_paste_and_reshape(setup):
    case, r, anim, _ = setup
    region, key, track = _furrow_setup(setup)
    shift = np.eye(4)
    shift[1, 3] = -2.0  # two centimetres down, in world coordinates at the key frame
    out = r.edit(anim, detail=DetailEdit(frame=key, vertices=region, operation="paste", transform=shift))
    diag = out.provenance["diagnostics"]["last_edit"]
    assert diag["edited_vertices"] > 0 and diag["operation"] == "paste"
    assert np.abs(out.vertices[key] - anim.vertices[key]).max() > 0
    pts = anim.vertices[key]
    uv = case.meta["target_uv"]
    line = np.argsort(np.abs(uv[:, 1] - 0.72) + 10 * (np.abs(uv[:, 0]) > 0.2))[:6]
    line = line[np.argsort(uv[line, 0])]
    curve = pts[line]
    out = r.edit(anim, detail=DetailEdit(frame=key, curve=curve, radius=0.8, operation="reshape", target_curve=curve + [0.0, 0.4, 0.0]))
    assert out.provenance["diagnostics"]["last_edit"]["region_vertices"] > 0


def test_edit_errors(setup):
    case, r, anim, v = setup
    with pytest.raises(ConfigError):
        r.edit(anim, points=[(3, v, anim.vertices[3, v])], mode="everything")
    with pytest.raises(IndexRangeError):
        r.edit(anim, points=[(FRAMES, v, anim.vertices[3, v])])
    with pytest.raises(IndexRangeError):
        r.edit(anim, points=[(3, 10**7, anim.vertices[3, v])])
    with pytest.raises(NonFiniteError):
        r.edit(anim, points=[(3, v, [np.nan, 0.0, 0.0])])
    with pytest.raises(InputError):
        r.edit(anim)
    with pytest.raises(InputError):
        r.edit(anim, points=[(3, v, anim.vertices[3, v])], detail={"frame": 3, "vertices": [v]})
    with pytest.raises(InputError, match="window"):
        r.edit(anim, points=[(3, v, anim.vertices[3, v])], window=(10, 20), mode="weights")
    other = fr.Animation(vertices=anim.vertices)
    with pytest.raises(InputError, match="not produced"):
        r.edit(other, points=[(3, v, anim.vertices[3, v])])
    with pytest.raises(ConfigError):
        r.edit(anim, detail={"frame": 3, "vertices": [v], "operation": "melt"})
    with pytest.raises(InputError):
        r.edit(anim, detail={"frame": 3, "vertices": [v], "operation": "paste"})
