"""Automatic base connectivity and the example-based base map."""

import numpy as np
import pytest

from faceretarget.errors import DegenerateGeometryError
from faceretarget.geometry.raycast import RayCaster
from faceretarget.plugins.normalmesh import base_mesh as bm
from faceretarget.plugins.normalmesh.base_retarget import fit_base_map


def _inside_polygon(points, polygon):
    """Even-odd rule: which 2D ``points`` lie inside the closed ``polygon``."""
    x, y = points[:, 0:1], points[:, 1:2]
    x0, y0 = polygon[:, 0], polygon[:, 1]
    x1, y1 = np.roll(x0, -1), np.roll(y0, -1)
    crosses = ((y0 > y) != (y1 > y)) & (
        x < x0 + (y - y0) * (x1 - x0) / np.where(y1 != y0, y1 - y0, 1.0)
    )
    return crosses.sum(axis=1) % 2 == 1


def test_automatic_base_avoids_the_holes_and_faces_out(face):
    case, tri = face["case"], face["base_triangles"]
    uv = case.meta["source_uv"]
    lm_uv = uv[case.source.landmarks.vertex_ids]
    # central regions (an edge between two feature points on a convex hole's rim is a chord
    # across the hole: the normal mesh moves that edge's vertices onto the rim)
    s = np.linspace(0.25, 0.5, 6)
    w = np.array([(a, b, 1 - a - b) for a in s for b in s if a + b <= 0.75])
    samples = np.einsum("sk,tkd->tsd", w, lm_uv[tri]).reshape(-1, 2)
    for name in ("eye_L", "eye_R", "mouth_inner"):
        hole = uv[case.meta["boundary_loops"]["source"][name]]
        assert not _inside_polygon(samples, hole).any(), name
    outline = uv[case.meta["boundary_loops"]["source"]["outline"]]
    assert _inside_polygon(samples, outline).all()
    # every feature point is used and all triangles face along the surface
    assert np.array_equal(np.unique(tri), np.arange(len(face["points"])))
    normals = bm.point_normals(
        case.source.landmarks, face["mesh"].vertex_normals, face["mesh"].triangles
    )
    bm.check_base_triangles(tri, face["points"], normals, "source", case.source.landmarks.names)
    # both holes' rims are followed by base edges between feature points on them
    assert (face["loops"] >= 0).sum() >= 16


def test_collinear_feature_points_cannot_be_triangulated(face):
    v = face["vertices"]
    line = np.stack([np.linspace(-1, 1, 6), np.zeros(6), np.full(6, v[:, 2].max())], axis=1)
    caster = RayCaster(v, face["mesh"].triangles)
    with pytest.raises(DegenerateGeometryError, match="triangulated|line"):
        bm.automatic_base_triangles(line, v, face["mesh"].vertex_normals, caster, line, caster)


def test_feature_points_beside_the_surface_give_no_base(face):
    far = face["points"] + np.array([3.0 * face["height"], 0.0, 0.0])
    with pytest.raises(DegenerateGeometryError, match="surface"):
        bm.automatic_base_triangles(
            far, face["vertices"], face["mesh"].vertex_normals, face["caster"], far, face["caster"]
        )


def test_base_map_interpolates_examples_and_rests_at_zero():
    rng = np.random.default_rng(0)
    n, m = 10, 6
    sn = rng.normal(size=(n, 3))
    rot = np.linalg.qr(rng.normal(size=(3, 3)))[0]
    rot *= np.sign(np.linalg.det(rot))
    tn = 1.5 * sn @ rot.T + 2.0
    sx = sn + 0.1 * rng.normal(size=(m, n, 3))
    tx = tn + 0.2 * rng.normal(size=(m, n, 3))
    exact = fit_base_map(sn, tn, sx, tx, rbf_c=1.0, rbf_smoothing=0.0)
    np.testing.assert_allclose(exact(sx - sn), tx - tn, atol=1e-6)
    np.testing.assert_allclose(exact(np.zeros((1, n, 3))), 0.0, atol=1e-12)
    smooth = fit_base_map(sn, tn, sx, tx, rbf_c=1.0, rbf_smoothing=0.05)
    np.testing.assert_allclose(smooth(np.zeros((1, n, 3))), 0.0, atol=1e-12)
    assert np.sqrt(np.mean((smooth(sx - sn) - (tx - tn)) ** 2)) < 0.25 * np.sqrt(
        np.mean((tx - tn) ** 2)
    )
    # with the neutral as the only example the map is the neutral-to-neutral similarity
    only = fit_base_map(sn, tn, sn[None], tn[None], rbf_c=1.0, rbf_smoothing=0.05)
    d = rng.normal(size=(3, n, 3))
    np.testing.assert_allclose(only(d), 1.5 * d @ rot.T, atol=1e-9)
