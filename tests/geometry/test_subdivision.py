"""Loop subdivision as sparse operators (faceretarget.geometry.subdivision)."""

import numpy as np
import pytest
from naive.normalmesh import loop_subdivide_naive

from faceretarget.errors import DegenerateGeometryError, ShapeError
from faceretarget.geometry.mesh_ops import boundary_edges
from faceretarget.geometry.subdivision import apply, loop_hierarchy, loop_step, subdivide


def _grid(n=7, seed=0):
    rng = np.random.default_rng(seed)
    x, y = np.meshgrid(np.linspace(0, 1, n), np.linspace(0, 1, n))
    v = np.c_[x.ravel(), y.ravel(), 0.1 * rng.normal(size=n * n)]
    tris = []
    for i in range(n - 1):
        for j in range(n - 1):
            a = i * n + j
            tris += [[a, a + 1, a + n + 1], [a, a + n + 1, a + n]]
    return v, np.array(tris)


def _sphere():
    import trimesh

    m = trimesh.creation.icosphere(2)
    return np.asarray(m.vertices), np.asarray(m.faces)


@pytest.mark.parametrize("even", ["loop", "keep"])
def test_matches_naive_reference_on_an_open_mesh(even):
    v, f = _grid()
    step = loop_step(f, len(v), even=even)
    want_v, want_t = loop_subdivide_naive(v, f, even)
    np.testing.assert_allclose(step.matrix @ v, want_v, atol=1e-14)
    assert np.array_equal(step.triangles, want_t)


def test_matches_trimesh_on_a_closed_mesh():
    import trimesh
    from scipy.spatial import cKDTree

    v, f = _sphere()
    ours, tris = subdivide(v, f, 2)
    theirs, their_tris = trimesh.remesh.subdivide_loop(v, f, 2)
    assert len(ours) == len(theirs) and len(tris) == len(their_tris)
    assert cKDTree(theirs).query(ours)[0].max() < 1e-12


def test_rows_are_affine_and_frames_batch():
    v, f = _grid()
    step = loop_step(f, len(v))
    np.testing.assert_allclose(np.asarray(step.matrix.sum(axis=1)).ravel(), 1.0, atol=1e-14)
    frames = np.stack([v, 2 * v + 1, v[:, [2, 0, 1]]])
    batched = apply(step, frames)
    for k in range(3):
        np.testing.assert_allclose(batched[k], step.matrix @ frames[k], atol=1e-14)


def test_boundary_depends_only_on_the_boundary_and_stays_on_it():
    v, f = _grid()
    v[:, 2] = 0.0
    step = loop_step(f, len(v))
    moved = v.copy()
    interior = np.setdiff1d(np.arange(len(v)), np.unique(boundary_edges(f)))
    moved[interior, 2] += 1.0  # interior vertices off the plane
    a, b = step.matrix @ v, step.matrix @ moved
    bnd = np.flatnonzero(step.boundary_vertex)
    np.testing.assert_allclose(a[bnd], b[bnd], atol=1e-15)
    assert len(bnd) == len(np.unique(boundary_edges(step.triangles)))
    # the square's sides stay straight (a cubic B-spline of the boundary polygon); only the
    # corners are rounded: 3/4 corner + 1/8 each boundary neighbour
    xy = b[bnd, :2]
    near_corner = (np.minimum(xy, 1 - xy) < 0.2).all(axis=1)
    on_side = (np.isclose(xy, 0.0, atol=1e-12) | np.isclose(xy, 1.0, atol=1e-12)).any(axis=1)
    assert on_side[~near_corner].all() and (~near_corner).sum() > 10
    np.testing.assert_allclose(b[0], 0.75 * v[0] + 0.125 * (v[1] + v[7]), atol=1e-15)


def test_keep_leaves_even_vertices_and_children_stay_inside_parents():
    v, f = _grid()
    v[:, 2] = 0.0
    steps = loop_hierarchy(f, len(v), 3, even="keep")
    x = v
    for s in steps:
        y = s.matrix @ x
        np.testing.assert_array_equal(y[: s.n_coarse], x)
        x = y
    # a level-3 triangle lies inside its base ancestor t >> 6 (planar mesh, midpoint subdivision)
    fine = steps[-1].triangles
    anc = np.arange(len(fine)) >> 6
    centroid = x[fine].mean(axis=1)[:, :2]
    a, b, c = (v[f[anc, k], :2] for k in range(3))
    den = (b[:, 1] - c[:, 1]) * (a[:, 0] - c[:, 0]) + (c[:, 0] - b[:, 0]) * (a[:, 1] - c[:, 1])
    w0 = (
        (b[:, 1] - c[:, 1]) * (centroid[:, 0] - c[:, 0])
        + (c[:, 0] - b[:, 0]) * (centroid[:, 1] - c[:, 1])
    ) / den
    w1 = (
        (c[:, 1] - a[:, 1]) * (centroid[:, 0] - c[:, 0])
        + (a[:, 0] - c[:, 0]) * (centroid[:, 1] - c[:, 1])
    ) / den
    assert (w0 > 0).all() and (w1 > 0).all() and (w0 + w1 < 1).all()


def test_non_manifold_and_bad_input_raise():
    f = np.array([[0, 1, 2], [1, 0, 3], [0, 1, 4]])
    with pytest.raises(DegenerateGeometryError):
        loop_step(f, 5)
    with pytest.raises(ShapeError):
        loop_step(np.zeros((0, 3), int), 3)
    with pytest.raises(ShapeError):
        loop_step(np.array([[0, 1, 2]]), 3, even="butterfly")
    with pytest.raises(ShapeError):
        subdivide(np.zeros((3, 2)), np.array([[0, 1, 2]]))
