"""Normals stay unit length whatever the scale of the triangle (found by the random fuzz mode)."""

import numpy as np
import pytest

from faceretarget.geometry.mesh_ops import face_normals, unit_rows, vertex_normals


@pytest.mark.parametrize("scale", [1e-160, 1e-161, 1.0, 1e150])
def test_face_and_vertex_normals_are_unit_at_any_scale(scale):
    """1e-160: edge cross products are subnormal (about 1e-320), where a plain norm loses
    most of its digits; the normals must still be unit length."""
    vertices = scale * np.array(
        [[0.0, 0.0, 0.0], [1.0, 0.0, 0.0], [0.3, 0.7, 0.0], [0.2, 0.1, 0.5]]
    )
    triangles = np.array([[0, 1, 2], [0, 3, 1]])
    for normals in (face_normals(vertices, triangles), vertex_normals(vertices, triangles)):
        norms = np.linalg.norm(normals, axis=1)
        assert np.all(np.isfinite(normals)) and np.allclose(norms, 1.0, atol=1e-9), (scale, norms)
    assert np.allclose(face_normals(vertices, triangles)[0], [0, 0, 1])


def test_normals_of_triangles_whose_area_underflows_are_zero():
    vertices = 1e-310 * np.array([[0.0, 0.0, 0.0], [1.0, 0.0, 0.0], [0.3, 0.7, 0.0]])
    assert np.all(face_normals(vertices, np.array([[0, 1, 2]])) == 0)


def test_unit_rows_keeps_zero_rows_and_directions():
    rows = np.array([[0.0, 0.0, 0.0], [3.0, 4.0, 0.0], [-2e-320, 0.0, 0.0]])
    np.testing.assert_allclose(unit_rows(rows), [[0, 0, 0], [0.6, 0.8, 0], [-1, 0, 0]])
