"""Shared fixtures of the normalmesh tests: small synthetic faces (faceretarget.cases)."""

import numpy as np
import pytest

import faceretarget as fr
from faceretarget.geometry.raycast import RayCaster
from faceretarget.plugins.normalmesh import base_mesh as bm
from faceretarget.plugins.normalmesh.normal_mesh import Surface, feature_point_loops


@pytest.fixture(scope="session")
def human_case():
    """Synthetic actor -> human target, wrinkles on, head motion on."""
    return fr.cases.synthetic(seed=3, resolution=1500, n_frames=10)


@pytest.fixture(scope="session")
def fitted(human_case):
    """The default retargeter fitted on ``human_case``."""
    return fr.get("normalmesh").fit(human_case.source, human_case.target)


@pytest.fixture(scope="session")
def face():
    """The source neutral of a synthetic case, its feature points and automatic base mesh."""
    case = fr.cases.synthetic(seed=0, resolution=1500, n_frames=4)
    mesh = case.source.performance.reference
    v = np.asarray(mesh.vertices)
    pts = case.source.landmarks.positions(v, mesh.triangles)
    caster = RayCaster(v, mesh.triangles)
    tri = bm.automatic_base_triangles(pts, v, mesh.vertex_normals, caster, pts, caster)
    surface = Surface.of(mesh.triangles, len(v))
    return dict(
        case=case,
        mesh=mesh,
        vertices=v,
        points=pts,
        base_triangles=tri,
        surface=surface,
        loops=feature_point_loops(pts, v, surface),
        caster=caster,
        height=mesh.height,
    )
