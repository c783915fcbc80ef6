"""Ray and closest-point queries (faceretarget.geometry.raycast) against brute force."""

import numpy as np
import pytest
from naive.raycast import cast_rays as naive_cast
from naive.raycast import closest_points as naive_closest

from faceretarget.errors import FaceRetargetError, NonFiniteError, ShapeError
from faceretarget.geometry.raycast import (
    RayCaster,
    build_bvh,
    cast_rays,
    closest_points,
    embree_available,
    triangle_neighbors,
    walk_rays,
)

BACKENDS = ["bvh", "brute"] + (["embree"] if embree_available() else [])


def _bumpy_sphere(subdiv=3):
    import trimesh

    m = trimesh.creation.icosphere(subdiv)
    v = (
        m.vertices
        * (1 + 0.1 * np.sin(4 * m.vertices[:, 0]) * np.cos(3 * m.vertices[:, 1]))[:, None]
    )
    return v, np.asarray(m.faces)


def _open_sheet(n=20, seed=0):
    """A wavy height field over the unit square with a square hole in the middle."""
    x, y = np.meshgrid(np.linspace(0, 1, n), np.linspace(0, 1, n))
    z = 0.1 * np.sin(6 * x) * np.cos(4 * y)
    v = np.c_[x.ravel(), y.ravel(), z.ravel()]
    tris = []
    for i in range(n - 1):
        for j in range(n - 1):
            if 0.4 < (j + 0.5) / (n - 1) < 0.6 and 0.4 < (i + 0.5) / (n - 1) < 0.6:
                continue
            a = i * n + j
            tris += [[a, a + 1, a + n + 1], [a, a + n + 1, a + n]]
    return v, np.array(tris)


@pytest.mark.parametrize("backend", BACKENDS)
@pytest.mark.parametrize("both", [True, False])
def test_lines_agree_with_brute_force(backend, both):
    rng = np.random.default_rng(1)
    for v, f in (_bumpy_sphere(), _open_sheet()):
        o = rng.uniform(v.min(0), v.max(0), size=(400, 3))
        d = rng.normal(size=(400, 3))
        limit = rng.uniform(0.05, 1.5, 400)
        hits = RayCaster(v, f, backend=backend).cast(o, d, both_directions=both, max_distance=limit)
        tri, t, bary = naive_cast(v, f, o, d, both_directions=both, max_distance=limit)
        assert np.array_equal(hits.hit, tri >= 0)
        assert hits.hit.sum() > 50  # the test casts lines that do hit
        ok = tri >= 0
        np.testing.assert_allclose(hits.distance[ok], t[ok], atol=1e-9)
        np.testing.assert_allclose(
            hits.points[ok], (bary[ok, :, None] * v[f[tri[ok]]]).sum(1), atol=1e-9
        )
        if both:
            assert (hits.distance[ok] < 0).any() and (hits.distance[ok] > 0).any()
        else:
            assert (hits.distance[ok] >= 0).all()


def test_closest_points_agree_with_brute_force():
    rng = np.random.default_rng(2)
    for v, f in (_bumpy_sphere(), _open_sheet()):
        p = rng.uniform(v.min(0) - 0.2, v.max(0) + 0.2, size=(300, 3))
        hits = closest_points(v, f, p)
        _, dist, point = naive_closest(v, f, p)
        np.testing.assert_allclose(np.abs(hits.distance), dist, atol=1e-10)
        np.testing.assert_allclose(hits.points, point, atol=1e-9)
        np.testing.assert_allclose(hits.barycentric.sum(1), 1.0, atol=1e-12)


def test_closest_distance_sign_follows_the_normal():
    v, f = _bumpy_sphere()
    p = np.array([[0.0, 0.0, 2.0], [0.0, 0.0, 0.5], [1.8, 0.0, 0.0], [0.3, 0.2, 0.1]])
    hits = closest_points(v, f, p)
    assert np.array_equal(np.sign(hits.distance), [1, -1, 1, -1])


def test_refit_equals_fresh_build():
    v, f = _bumpy_sphere()
    moved = v * 1.3 + np.sin(v[:, [1, 2, 0]])
    refitted = build_bvh(v, f).refit(moved)
    rng = np.random.default_rng(3)
    o, d = rng.normal(size=(500, 3)), rng.normal(size=(500, 3))
    a = RayCaster(moved, f, backend="bvh", bvh=refitted).cast(o, d)
    b = RayCaster(moved, f, backend="bvh").cast(o, d)
    assert np.array_equal(a.triangle, b.triangle)
    np.testing.assert_allclose(a.distance, b.distance, atol=1e-12, equal_nan=True)


def test_walk_from_neighbouring_triangles_finds_the_global_hit():
    v, f = _open_sheet(30)
    rng = np.random.default_rng(4)
    # lines through points of the sheet, started two rings away from the right triangle
    t0 = rng.integers(0, len(f), 300)
    bary = rng.dirichlet(np.ones(3), 300)
    target = np.einsum("pk,pkd->pd", bary, v[f[t0]])
    d = np.array([0.1, -0.05, 1.0]) + rng.normal(scale=0.05, size=(300, 3))
    o = target + 0.05 * d
    nb = triangle_neighbors(f)
    start = nb[nb[t0, 0], 1]
    start = np.where(start >= 0, start, t0)
    walked = walk_rays(v, f, nb, o, d, start, max_distance=1.0)
    glob = cast_rays(v, f, o, d, max_distance=1.0, backend="bvh")
    assert walked.hit.mean() > 0.95
    ok = walked.hit
    assert np.array_equal(walked.triangle[ok], glob.triangle[ok])
    np.testing.assert_allclose(walked.points[ok], target[ok], atol=1e-9)


def test_walk_stops_at_boundaries_and_holes():
    v, f = _open_sheet(20)
    nb = triangle_neighbors(f)
    # a line through the hole, and one outside the sheet: nothing to walk to
    o = np.array([[0.5, 0.5, 0.5], [1.5, 0.5, 0.5]])
    walked = walk_rays(v, f, nb, o, np.array([[0, 0, -1.0], [0, 0, -1.0]]), np.array([0, 0]))
    assert not walked.hit.any()


def test_triangle_neighbors_share_edges():
    v, f = _open_sheet(8)
    nb = triangle_neighbors(f)
    for t in range(len(f)):
        for k in range(3):
            edge = {f[t, (k + 1) % 3], f[t, (k + 2) % 3]}
            others = [s for s in range(len(f)) if s != t and edge <= set(f[s])]
            assert nb[t, k] == (others[0] if others else -1)


def test_bad_input_is_a_typed_error():
    v, f = _bumpy_sphere(1)
    with pytest.raises(ShapeError):
        cast_rays(v, f, np.zeros((3, 2)), np.ones((3, 2)))
    with pytest.raises(ShapeError):
        cast_rays(v, f, np.zeros((3, 3)), np.ones((4, 3)))
    bad = v.copy()
    bad[0, 0] = np.nan
    with pytest.raises(NonFiniteError):
        closest_points(bad, f, np.zeros((1, 3)))
    with pytest.raises(FaceRetargetError):
        RayCaster(v, f, backend="optix")
    with pytest.raises(FaceRetargetError):
        cast_rays(v, f, np.zeros((1, 3)), np.ones((1, 3)), max_distance=-1.0)


def test_zero_direction_misses():
    v, f = _bumpy_sphere(1)
    hits = cast_rays(v, f, np.zeros((2, 3)), np.array([[0.0, 0.0, 0.0], [0.0, 0.0, 1.0]]))
    assert list(hits.hit) == [False, True]
