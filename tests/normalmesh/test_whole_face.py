"""The whole target face moves: the dense fallback off the normal mesh, piercing errors on a
real face (ICT-FaceKit), levels from the source's resolution, detail transfer that helps."""

import numpy as np
import pytest

import faceretarget as fr
from faceretarget.plugins.normalmesh import base_mesh as bm

#: Largest share of the normal mesh's vertices with a piercing error, on the target's neutral
#: and per source frame (paper, Table 1: 0.01-0.08%; measured on ICT: 0.00% and 0.12%).
PIERCING_BOUND = 0.005


def _errors(anim, case):
    """(F, V) squared vertex errors and the face height."""
    got, want = np.asarray(anim.vertices, float), np.asarray(case.truth.vertices, float)
    return np.sum((got - want) ** 2, axis=-1), case.target.neutral.height


def _rms(sq, mask=None):
    return float(np.sqrt(np.mean(sq if mask is None else sq[:, mask])))


@pytest.fixture(scope="module")
def ict():
    case = fr.cases.ict(n_frames=16)
    r = fr.get("normalmesh").fit(case.source, case.target)
    return case, r, r.retarget(case.source)


@pytest.fixture(scope="module")
def ict_dt(ict):
    case = ict[0]
    return fr.get("deformation_transfer").fit(case.source, case.target).retarget(case.source)


def test_ict_off_the_normal_mesh_at_least_as_good_as_deformation_transfer(ict, ict_dt):
    """Outside the feature points' hull (forehead, ears, neck) and in the holes of the base mesh
    (eyes, nostrils, lips) the target moves with the dense fallback (measured: 0.029% of the
    face height vs deformation transfer's 0.22%, and 0.79% with the paper's nearest-point rule)."""
    case, r, anim = ict
    off = r.coverage_ <= 0.0
    assert 0.3 < off.mean() < 0.8  # the normal mesh covers the face inside the 68 landmarks
    sq, h = _errors(anim, case)
    sq_dt, _ = _errors(ict_dt, case)
    assert _rms(sq, off) <= _rms(sq_dt, off)
    assert _rms(sq) <= _rms(sq_dt)
    # and far better than leaving those vertices still (the target neutral moved by the head)
    hm = np.asarray(case.truth.head_motion)
    still = (
        np.einsum("fij,pj->fpi", hm[:, :3, :3], np.asarray(case.target.neutral.vertices))
        + hm[:, None, :3, 3]
    )
    sq_still = np.sum((still - np.asarray(case.truth.vertices)) ** 2, axis=-1)
    assert _rms(sq, off) < 0.2 * _rms(sq_still, off)


def test_ict_piercing_errors_are_rare(ict):
    case, r, anim = ict
    diag = anim.provenance["diagnostics"]["piercing_errors"]
    assert diag["target"] <= PIERCING_BOUND * diag["normal_mesh_vertices"], diag
    assert diag["source_share_per_frame"] <= PIERCING_BOUND, diag
    assert diag["source_neutral"] <= PIERCING_BOUND * diag["normal_mesh_vertices"], diag


def test_ict_paper_rules_pierce_far_more():
    """The same face with the paper's rules (neighbour-average repair, no base triangle removed):
    the test above can fail (measured 1.3% of the target's vertices, 1.7% per source frame)."""
    case = fr.cases.ict(n_frames=4)
    r = fr.get("normalmesh", repair="average", max_piercing=1.0).fit(case.source, case.target)
    assert (
        r.piercing_errors_["target"] > PIERCING_BOUND * r.piercing_errors_["normal_mesh_vertices"]
    )


def test_ict_base_mesh_does_not_bridge_the_closed_mouth(ict):
    """The 68 landmarks' inner-lip points lie on the lips' contact line, and the mouth hole is
    deep inside: a base triangle joining an upper and a lower inner-lip point spans a fold
    (over the mesh, its ends are 34-51 times farther apart than in space)."""
    _, r, _ = ict
    names = r.target_feature_points_.names
    upper = {names.index(f"lip_inner_{k}") for k in (2, 3, 4)}
    lower = {names.index(f"lip_inner_{k}") for k in (6, 7, 8)}
    for t in np.concatenate([r.base_triangles_, r.removed_base_triangles_]):
        assert not (upper & set(t.tolist()) and lower & set(t.tolist())), [names[i] for i in t]


def test_bridging_edges_are_found_over_a_fold():
    """Two sheets joined along one side (a folded strip): an edge between the sheets is short in
    space but long over the mesh."""
    n = 8
    x = np.linspace(0, 1, n)
    top = np.stack(np.meshgrid(x, x, indexing="ij"), -1).reshape(-1, 2)
    vertices = np.concatenate(
        [
            np.column_stack([top, np.full(len(top), 0.05)]),
            np.column_stack([top, np.zeros(len(top))]),
        ]
    )
    quads = np.array(
        [
            [i * n + j, (i + 1) * n + j, (i + 1) * n + j + 1, i * n + j + 1]
            for i in range(n - 1)
            for j in range(n - 1)
        ]
    )
    sheet = np.concatenate([quads[:, [0, 1, 2]], quads[:, [0, 2, 3]]])
    seam = np.array(
        [[(n - 1) * n + j, (n - 1) * n + j + 1, n * n + (n - 1) * n + j + 1] for j in range(n - 1)]
        + [
            [(n - 1) * n + j, n * n + (n - 1) * n + j + 1, n * n + (n - 1) * n + j]
            for j in range(n - 1)
        ]
    )
    triangles = np.concatenate([sheet, sheet[:, ::-1] + n * n, seam])
    points = vertices[[0, n - 1, n * n, n * n + n - 1]]
    ids = np.array([0, n - 1, n * n, n * n + n - 1])
    tri = np.array([[0, 1, 2], [1, 3, 2]])  # both join the sheets at the open side
    assert bm.bridging_edges(tri, points, ids, vertices, triangles).all()
    same = np.array([[0, 1, 1]])  # an edge along one sheet (a degenerate triangle is enough here)
    assert not bm.bridging_edges(same, points, ids, vertices, triangles).any()


def test_ict_detail_transfer_does_not_raise_the_error(ict):
    """ICT's expressions have no wrinkles; the detail levels must still not hurt (measured
    0.060% vs 0.120% with base motion only; before the sliding transfer 0.672% vs 0.645%)."""
    case, _, anim = ict
    base_only = (
        fr.get("normalmesh", detail_levels=0).fit(case.source, case.target).retarget(case.source)
    )
    assert _rms(_errors(anim, case)[0]) <= _rms(_errors(base_only, case)[0])


def test_detail_transfer_lowers_the_error_with_wrinkles():
    case = fr.cases.synthetic(seed=5, resolution=1500, n_frames=10)
    errors = {}
    for levels in (-1, 0):
        anim = (
            fr.get("normalmesh", detail_levels=levels)
            .fit(case.source, case.target)
            .retarget(case.source)
        )
        errors[levels] = _rms(_errors(anim, case)[0])
    assert errors[-1] < 0.8 * errors[0], errors  # measured 0.015% vs 0.033%


@pytest.mark.parametrize(
    "options", [dict(), dict(target_resolution=1100)], ids=["same-topology", "other-topology"]
)
def test_fallback_off_the_normal_mesh_beats_deformation_transfer(options):
    """Synthetic faces (the fallback's correspondence: the same vertex, or the RBF warp through
    both normal meshes and the closest source point)."""
    case = fr.cases.synthetic(seed=1, resolution=1500, n_frames=8, **options)
    r = fr.get("normalmesh").fit(case.source, case.target)
    off = r.coverage_ <= 0.0
    assert off.mean() > 0.2
    sq, _ = _errors(r.retarget(case.source), case)
    dt = fr.get("deformation_transfer").fit(case.source, case.target).retarget(case.source)
    nearest = (
        fr.get("normalmesh", fallback="nearest").fit(case.source, case.target).retarget(case.source)
    )
    err, err_dt, err_nearest = (
        _rms(sq, off),
        _rms(_errors(dt, case)[0], off),
        _rms(_errors(nearest, case)[0], off),
    )
    assert err < 0.5 * err_dt and err < 0.5 * err_nearest, (
        err,
        err_dt,
        err_nearest,
    )  # measured 0.002-0.004% vs 0.06% and 0.04%


def test_levels_follow_the_sources_and_targets_resolution():
    """``levels="auto"``: the finest level's edges half the target mesh's, within half to once
    the source mesh's (a target as dense as the source: half the source's edge, so that the
    target's vertices, interpolated from the finest level, keep the wrinkles' depth; a target
    at least twice as coarse: the source's edge, the paper's density)."""
    from faceretarget.geometry.mesh_ops import unique_edges

    def median_edge(points, tri):
        e = unique_edges(tri)
        return float(np.median(np.linalg.norm(points[e[:, 0]] - points[e[:, 1]], axis=1)))

    def finest_over_source(case):
        r = fr.get("normalmesh").fit(case.source, case.target)
        source = case.source.performance.reference
        finest = r.source_normal_mesh_.positions[-1]
        return r.levels_, median_edge(finest, r.hierarchy_.triangles(r.levels_)) / median_edge(
            np.asarray(source.vertices), source.triangles
        )

    found = {}
    for resolution in (800, 3000, 12000):
        case = fr.cases.synthetic(seed=0, resolution=resolution, n_frames=2)
        found[resolution], ratio = finest_over_source(case)
        assert 0.25 < ratio <= 0.65, (resolution, found[resolution], ratio)
    assert found[800] < found[3000] < found[12000], found
    # a target about twice as coarse as the source: the source's own density, one level fewer
    coarse, ratio = finest_over_source(
        fr.cases.synthetic(seed=0, resolution=3000, n_frames=2, target_resolution=700)
    )
    assert coarse == found[3000] - 1 and 0.5 < ratio <= 1.3, (coarse, ratio)
    assert fr.get("normalmesh", levels=2).fit(case.source, case.target).levels_ == 2


def test_removing_much_of_the_base_mesh_warns(monkeypatch):
    """Removed base triangles lose the detail transfer: past a share of the base mesh's area
    (25%; ICT: 8%) a FaceRetargetWarning names them."""
    import faceretarget.plugins.normalmesh.retargeter as module

    case = fr.cases.ict(n_frames=2)
    monkeypatch.setattr(module, "REMOVED_WARNING", 0.01)
    with pytest.warns(fr.errors.FaceRetargetWarning, match="base triangles .* were removed .*nose"):
        r = fr.get("normalmesh").fit(case.source, case.target)
    assert 0.01 < r.coverage_stats_["removed_area_share"] < 0.25
    assert r.example_names_ == tuple(case.target.example_names)


def test_fine_wrinkles_keep_their_depth_on_a_target_as_dense_as_the_source():
    """The wrinkles' own fine-scale motion (high-passed normal motion of the case minus its
    wrinkle-free twin, as the detail metrics see it; seed 0 holds the short glabella and bunny
    lines, 4-5 edges long) keeps most of its depth: gain 0.80, correlation 0.978 with
    ``levels="auto"`` (4 levels here); 0.59 and 0.889 when the finest level only matched the
    source's edges (3 levels: two linear resamplings)."""
    from faceretarget.evaluation.metrics import normal_detail

    case = fr.cases.synthetic(seed=0, resolution=1500, n_frames=90)
    twin = fr.cases.synthetic(seed=0, resolution=1500, n_frames=90, wrinkles=False)
    neutral, tri = np.asarray(case.target.neutral.vertices), case.target.neutral.triangles

    def detail(a, b):
        return normal_detail(
            np.asarray(a.local_vertices) - np.asarray(b.local_vertices), tri, neutral
        )

    truth = detail(case.truth, twin.truth)
    r = fr.get("normalmesh")
    ours = detail(
        r.fit(case.source, case.target).retarget(case.source),
        fr.get("normalmesh").fit(twin.source, twin.target).retarget(twin.source),
    )
    gain = float(np.sum(ours * truth) / np.sum(truth**2))
    assert gain > 0.7, (r.levels_, gain)
    assert np.corrcoef(ours.ravel(), truth.ravel())[0, 1] > 0.95
    assert r.levels_ == 4
