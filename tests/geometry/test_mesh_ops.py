"""Normals stay unit length whatever the scale of the triangle (found by the random fuzz mode)."""

import numpy as np
import pytest

from faceretarget.errors import ShapeError
from faceretarget.geometry.mesh_ops import (
    barycentric_matrix,
    face_normals,
    translated,
    unit_rows,
    vertex_normals,
)


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


def _vertex_normals_numpy(vertices, triangles):
    """The plain numpy formulation: cross products summed per vertex, then unit rows."""
    cross = np.cross(
        vertices[triangles[:, 1]] - vertices[triangles[:, 0]],
        vertices[triangles[:, 2]] - vertices[triangles[:, 0]],
    )
    acc = np.zeros((len(vertices), 3))
    for k in range(3):
        np.add.at(acc, triangles[:, k], cross)
    return unit_rows(acc)


@pytest.mark.parametrize("scale", [1e-160, 1.0, 1e150])
def test_vertex_normals_kernel_matches_numpy(scale):
    """The one vertex-normal kernel (mesh_ops and the per-frame callers) against numpy, at
    any scale, with an isolated vertex (zero) and a NaN vertex (its triangles' corners zero);
    ``out`` is filled and returned."""
    rng = np.random.default_rng(4)
    vertices = scale * rng.normal(size=(300, 3))
    triangles = rng.integers(0, 299, size=(900, 3)).astype(np.int32)  # vertex 299 isolated
    want = _vertex_normals_numpy(vertices, triangles)
    out = np.full((300, 3), 7.0)
    got = vertex_normals(vertices, triangles, out=out)
    assert got is out
    np.testing.assert_allclose(got, want, atol=1e-13, rtol=0)
    assert np.all(got[299] == 0)
    vertices[5] = np.nan
    got = vertex_normals(vertices, triangles)
    touched = np.unique(triangles[(triangles == 5).any(axis=1)])
    assert np.all(got[touched] == 0) and np.isfinite(got).all()
    with pytest.raises(IndexError):
        vertex_normals(vertices, np.array([[0, 1, 300]]))


def test_boundary_edges_match_a_count_of_each_undirected_edge():
    """Against a dictionary count over (smaller, larger) pairs: open grid, a closed
    tetrahedron (no boundary), a strip with repeated and high vertex indices."""
    import collections

    from faceretarget.geometry.mesh_ops import boundary_edges

    def naive(tris):
        count = collections.Counter(
            tuple(sorted(e)) for t in tris for e in ((t[0], t[1]), (t[1], t[2]), (t[2], t[0]))
        )
        return [
            (t[a], t[b])
            for t in tris
            for a, b in ((0, 1), (1, 2), (2, 0))
            if count[tuple(sorted((t[a], t[b])))] == 1
        ]

    n = 5
    grid = [[i * n + j, i * n + j + 1, (i + 1) * n + j] for i in range(n - 1) for j in range(n - 1)]
    grid += [
        [i * n + j + 1, (i + 1) * n + j + 1, (i + 1) * n + j]
        for i in range(n - 1)
        for j in range(n - 1)
    ]
    tetra = [[0, 1, 2], [0, 3, 1], [1, 3, 2], [2, 3, 0]]
    strip = [[10**6, 7, 3], [7, 10**6, 10**6 + 1], [3, 7, 2]]
    for tris in (grid, tetra, strip):
        got = boundary_edges(np.array(tris))
        want = naive(tris)
        assert sorted(tuple(e) for e in got.tolist()) == sorted(want)  # directions kept
    assert boundary_edges(np.zeros((0, 3), dtype=np.int64)).shape == (0, 2)


@pytest.mark.parametrize("shape", [(4, 50, 3), (50, 3), (3,), (2, 3, 7, 3), (0, 5, 3), (2, 0, 3)])
def test_translated_is_the_broadcast_sum_bit_for_bit(shape):
    rng = np.random.default_rng(5)
    points = rng.normal(size=shape).astype(np.float32)
    offset = rng.normal(size=3) * 1e3
    out = translated(points, offset)
    assert out.dtype == np.float64 and out.shape == shape
    np.testing.assert_array_equal(out, points.astype(np.float64) + offset)
    np.testing.assert_array_equal(translated(out, -offset), out - offset)


def test_translated_refuses_points_that_are_not_3d():
    with pytest.raises(ShapeError, match=r"\(\.\.\., V, 3\)"):
        translated(np.zeros((5, 2)), np.zeros(3))
    with pytest.raises(ShapeError, match=r"offset \(3,\)"):
        translated(np.zeros((5, 3)), np.zeros((5, 3)))


def test_unique_edges_are_kept_by_content_and_read_only():
    from naive.coating import grid_mesh

    from faceretarget.geometry import mesh_ops

    _, t = grid_mesh(6, seed=3)
    first = mesh_ops.unique_edges(t)
    want = np.unique(
        np.sort(np.concatenate([t[:, [0, 1]], t[:, [1, 2]], t[:, [2, 0]]]), axis=1), axis=0
    )
    np.testing.assert_array_equal(first, want)
    assert not first.flags.writeable
    assert mesh_ops.unique_edges(t.copy()) is first  # same indices, another array: kept
    other = t.copy()
    other[0] = other[0, [0, 2, 1]]  # the same edges in another order: a new entry, same edges
    np.testing.assert_array_equal(mesh_ops.unique_edges(other), want)
    cut = t[1:]  # a triangle less: other edges
    assert len(mesh_ops.unique_edges(cut)) < len(want)
    assert mesh_ops.unique_edges(t.astype(np.int32)).dtype == np.int32
    for k in range(mesh_ops._EDGE_MEMO_SIZE + 1):  # old entries are dropped
        mesh_ops.unique_edges(t[: 5 + k])
    assert len(mesh_ops._edge_memo) == mesh_ops._EDGE_MEMO_SIZE
    assert mesh_ops.unique_edges(t) is not first


def test_barycentric_matrix_interpolates_points_on_triangles():
    """``barycentric_matrix(corners, bary, V) @ vertices`` is the points, corner by corner;
    a degenerate row (a corner repeated) sums its weights."""
    rng = np.random.default_rng(0)
    vertices = rng.normal(size=(9, 3))
    corners = rng.integers(0, 9, size=(7, 3))
    corners[3] = [4, 4, 2]
    bary = rng.dirichlet([1.0, 1.0, 1.0], size=7)
    m = barycentric_matrix(corners, bary, 9)
    assert m.shape == (7, 9)
    want = sum(bary[:, k, None] * vertices[corners[:, k]] for k in range(3))
    np.testing.assert_allclose(m @ vertices, want, rtol=0, atol=1e-15)
    assert m[3, 4] == bary[3, 0] + bary[3, 1]
