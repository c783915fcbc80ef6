"""Cross-topology correspondence: landmarks, RBF warp, closest points, non-rigid ICP resampling."""

import numpy as np
import pytest
from naive.correspond import closest_points_brute

from faceretarget import Landmarks, Mesh, cases
from faceretarget.correspond import (
    boundary_loops,
    closest_point_transfer,
    landmark_positions,
    project_landmarks,
    rbf_warp,
    resample_to_topology,
    to_barycentric,
    to_vertex_ids,
    transfer_back,
)
from faceretarget.errors import DegenerateGeometryError, InputError, TopologyMismatchError


@pytest.fixture(scope="module")
def pair():
    """Source actor mesh (1200 vertices) and a human target triangulated at 3000 vertices."""
    return cases.synthetic(resolution=1200, target_resolution=3000, n_frames=2)


def test_closest_point_transfer_matches_brute_force(pair):
    mesh = cases.synthetic(resolution=200, n_frames=1).target.neutral
    rng = np.random.default_rng(1)
    pts = np.vstack(
        [
            mesh.vertices[rng.integers(0, mesh.n_vertices, 60)] + rng.normal(0.0, 0.8, (60, 3)),
            rng.normal(0.0, 15.0, (20, 3)),  # far away, including behind the face
        ]
    )
    corr = closest_point_transfer(pts, mesh)
    want, dist, _ = closest_points_brute(pts, mesh.vertices, mesh.triangles)
    np.testing.assert_allclose(corr.distances, dist, atol=1e-9)
    np.testing.assert_allclose(corr.apply(mesh.vertices), want, atol=1e-9)
    np.testing.assert_allclose(corr.barycentric.sum(axis=1), 1.0, atol=1e-12)
    assert (corr.barycentric >= -1e-12).all()
    # a sequence (F, V, 3) maps frame by frame
    seq = np.stack([mesh.vertices, 2.0 * mesh.vertices])
    out = corr.apply(seq)
    np.testing.assert_allclose(out[1], 2.0 * out[0], atol=1e-9)
    np.testing.assert_allclose(corr.apply(mesh.vertices[:, 0]), out[0, :, 0], atol=1e-12)


def test_landmark_conversions_keep_positions(pair):
    mesh = pair.source.performance.reference
    lm = pair.source.landmarks
    pos = landmark_positions(mesh, lm)
    bary = to_barycentric(lm, mesh)
    assert bary.triangle_ids is not None
    np.testing.assert_allclose(landmark_positions(mesh, bary), pos, atol=1e-12)
    np.testing.assert_array_equal(to_vertex_ids(bary, mesh).vertex_ids, lm.vertex_ids)
    # points on the surface project to themselves; names are kept
    rng = np.random.default_rng(0)
    t = rng.integers(0, mesh.n_triangles, 30)
    w = rng.dirichlet(np.ones(3), 30)
    pts = np.einsum("nk,nkd->nd", w, mesh.vertices[mesh.triangles[t]])
    proj = project_landmarks(mesh, pts, names=[f"p{i}" for i in range(30)])
    np.testing.assert_allclose(landmark_positions(mesh, proj), pts, atol=1e-9)
    assert proj.names[3] == "p3"


def test_rbf_warp_interpolates_and_reproduces_affine_maps():
    rng = np.random.default_rng(2)
    src = rng.normal(size=(20, 3))
    a = np.array([[1.1, 0.2, 0.0], [-0.1, 0.9, 0.3], [0.05, 0.0, 1.2]])
    b = np.array([0.5, -1.0, 2.0])
    warp = rbf_warp(src, src @ a.T + b)
    q = rng.normal(size=(50, 3)) * 3.0
    np.testing.assert_allclose(warp(q), q @ a.T + b, atol=1e-8)
    tgt = src + 0.1 * np.sin(src)
    np.testing.assert_allclose(rbf_warp(src, tgt)(src), tgt, atol=1e-8)
    with pytest.raises(Exception) as err:
        rbf_warp(src, tgt[:5])
    assert "rbf_warp" in str(err.value)


def _deformed_copy(resolution):
    """The actor surface triangulated anew and bent: (mesh, uv, the deformation)."""

    def bend(p):
        out = 1.1 * p.copy()
        out[:, 2] += 0.02 * p[:, 0] ** 2 - 0.01 * p[:, 1] ** 2
        out[:, 0] += 0.3 * np.sin(p[:, 1] / 6.0)
        return out

    case = cases.synthetic(resolution=resolution, n_frames=1)
    uv = case.meta["source_uv"]
    return (
        Mesh(bend(cases.face_surface(uv, "actor")), case.source.performance.triangles),
        case.source.landmarks,
        uv,
        bend,
    )


def test_resample_onto_a_deformed_retriangulated_copy(pair):
    src = pair.source.performance.reference
    target, target_lm, _, bend = _deformed_copy(2500)
    assert target.n_vertices != src.n_vertices
    # the right answer is known: the same parameter point on the bent surface
    truth = bend(cases.face_surface(pair.meta["source_uv"], "actor"))
    # landmarks at exactly corresponding points (barycentric on the target)
    exact = project_landmarks(target, truth[pair.source.landmarks.vertex_ids])
    fitted, report = resample_to_topology(src, pair.source.landmarks, target, exact)
    assert fitted.n_vertices == src.n_vertices and np.array_equal(fitted.triangles, src.triangles)
    assert report.flipped_triangles == 0
    assert report.residual_mean < 1e-6 and report.residual_max < 1e-4
    assert report.coverage_max < 0.01
    assert report.landmark_error < 0.01
    err = np.linalg.norm(fitted.vertices - truth, axis=1) / target.height
    assert err.mean() < 0.002 and err.max() < 0.01, (err.mean(), err.max())
    # vertex-id landmarks of the two triangulations are only nearly corresponding
    fitted2, report2 = resample_to_topology(src, pair.source.landmarks, target, target_lm)
    assert report2.flipped_triangles == 0
    assert np.linalg.norm(fitted2.vertices - truth, axis=1).mean() / target.height < 0.01


@pytest.mark.parametrize("kind", ["human", "stylized"])
def test_resample_synthetic_source_onto_other_target_topology(kind):
    case = cases.synthetic(resolution=1000, target=kind, target_resolution=2500, n_frames=1)
    src, tgt = case.source.performance.reference, case.target.neutral
    fitted, report = resample_to_topology(src, case.source.landmarks, tgt, case.target.landmarks)
    assert report.flipped_triangles == 0
    assert report.residual_max < 0.02 and report.coverage_max < 0.03
    truth = cases.face_surface(case.meta["source_uv"], kind)
    err = np.linalg.norm(fitted.vertices - truth, axis=1) / tgt.height
    assert err.mean() < 0.012, err.mean()
    # boundary loops land on the matching target loops (eyes on eyes, mouth on mouth)
    for name in ("eye_L", "eye_R", "mouth_inner"):
        s_loop, t_loop = case.source.feature_lines[name], case.target.feature_lines[name]
        d = np.linalg.norm(
            fitted.vertices[s_loop][:, None] - tgt.vertices[t_loop][None], axis=2
        ).min(axis=1)
        assert d.max() < 0.02 * tgt.height, name
    # per-vertex results come back to the target's own vertices
    back = transfer_back(fitted, fitted.vertices, tgt)
    gap = np.linalg.norm(back - tgt.vertices, axis=1) / tgt.height
    assert gap.mean() < 1e-3 and gap.max() < 0.03
    uv_back = transfer_back(fitted, case.meta["source_uv"], tgt)
    assert np.abs(uv_back - case.meta["target_uv"]).mean() < 0.02
    frames = transfer_back(fitted, np.stack([fitted.vertices, fitted.vertices + 1.0]), tgt)
    np.testing.assert_allclose(frames[1] - frames[0], 1.0, atol=1e-9)


def test_boundary_loops_of_the_synthetic_face(pair):
    mesh = pair.target.neutral
    loops = boundary_loops(mesh.triangles)
    assert len(loops) == 4
    assert sum(len(l) for l in loops) == len(mesh.boundary_vertices)
    assert sorted(len(l) for l in loops) == sorted(
        len(pair.meta["boundary_loops"]["target"][k])
        for k in ("outline", "eye_L", "eye_R", "mouth_inner")
    )


def test_resample_rejects_bad_landmarks(pair):
    src, tgt = pair.source.performance.reference, pair.target.neutral
    lm_s, lm_t = pair.source.landmarks, pair.target.landmarks
    with pytest.raises(TopologyMismatchError):
        resample_to_topology(src, lm_s, tgt, Landmarks(lm_t.vertex_ids[:10]))
    flat = np.flatnonzero(np.abs(src.vertices[:, 2] - src.vertices[0, 2]) >= 0)[:3]
    with pytest.raises(DegenerateGeometryError):
        resample_to_topology(src, Landmarks(flat), tgt, Landmarks(lm_t.vertex_ids[:3]))
    with pytest.raises(InputError):
        resample_to_topology(src, lm_s, tgt, lm_t, stiffness=(1.0, -1.0))
