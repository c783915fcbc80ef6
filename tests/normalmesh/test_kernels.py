"""The numba kernels of the plugin against plain numpy."""

import numpy as np
from naive.normalmesh import vertex_normals_naive

from faceretarget._validate import readonly
from faceretarget.geometry.mesh_ops import vertex_normals
from faceretarget.geometry.raycast import RayCaster, triangle_neighbors
from faceretarget.plugins.normalmesh import _kernels as k
from faceretarget.plugins.normalmesh.attach import triangle_frames
from faceretarget.plugins.normalmesh.normal_mesh import make_hierarchy


def _level(face):
    h = make_hierarchy(face["base_triangles"], len(face["points"]), 2)
    step = h.steps[1]
    X = np.ascontiguousarray(h.steps[0].matrix @ face["points"])
    pred = np.ascontiguousarray(step.matrix @ X)
    normals = vertex_normals(pred, step.triangles)
    return step, X, pred, normals


def _frames_numpy(X, normals, edges, n0):
    n = normals[n0:]
    d = X[edges[:, 1]] - X[edges[:, 0]]
    d = d - np.einsum("ij,ij->i", d, n)[:, None] * n
    t1 = d / np.linalg.norm(d, axis=1, keepdims=True)
    return t1, np.cross(n, t1), n


def test_vertex_normals(face):
    """The plugin's normals (the shared kernel of geometry.mesh_ops) against the brute force."""
    step, _, pred, normals = _level(face)
    np.testing.assert_allclose(normals, vertex_normals_naive(pred, step.triangles), atol=1e-12)


def test_place_and_local_coords_invert_each_other(face):
    step, X, pred, normals = _level(face)
    rng = np.random.default_rng(0)
    tangent, offset = rng.normal(size=(step.n_odd, 2)), rng.normal(size=step.n_odd)
    out = pred.copy()
    k.place_odd(pred, normals, step.edges, step.n_coarse, tangent, offset, out)
    t1, t2, n = _frames_numpy(X, normals, step.edges, step.n_coarse)
    want = pred[step.n_coarse :] + t1 * tangent[:, :1] + t2 * tangent[:, 1:] + n * offset[:, None]
    np.testing.assert_allclose(out[step.n_coarse :], want, atol=1e-12)
    np.testing.assert_array_equal(out[: step.n_coarse], pred[: step.n_coarse])
    tb, ob = np.empty_like(tangent), np.empty_like(offset)
    k.local_coords(pred, normals, step.edges, step.n_coarse, out, tb, ob)
    np.testing.assert_allclose(tb, tangent, atol=1e-12)
    np.testing.assert_allclose(ob, offset, atol=1e-12)


def test_flipped_odd(face):
    step, _, pred, _ = _level(face)
    moved = pred.copy()
    rng = np.random.default_rng(1)
    moved[step.n_coarse :] += rng.normal(scale=0.3, size=(step.n_odd, 3))
    flags = np.zeros(step.n_odd, bool)
    k.flipped_odd(moved, pred, step.triangles, step.n_coarse, flags)
    t = step.triangles
    before = np.cross(pred[t[:, 1]] - pred[t[:, 0]], pred[t[:, 2]] - pred[t[:, 0]])
    after = np.cross(moved[t[:, 1]] - moved[t[:, 0]], moved[t[:, 2]] - moved[t[:, 0]])
    want = np.zeros(step.n_odd, bool)
    flipped = t[np.einsum("ij,ij->i", before, after) < 0].ravel()
    want[flipped[flipped >= step.n_coarse] - step.n_coarse] = True
    assert want.any()
    np.testing.assert_array_equal(flags, want)


def test_neighbour_average(face):
    h = make_hierarchy(face["base_triangles"], len(face["points"]), 1)
    indptr, indices = h.rings[0]
    rng = np.random.default_rng(2)
    Y = rng.normal(size=(h.n_vertices(1), 3))
    bad = np.array([60, 70, 80, 81])
    want = Y.copy()
    for _ in range(2):
        new = {v: want[indices[indptr[v] : indptr[v + 1]]].mean(axis=0) for v in bad}
        for v in bad:
            want[v] = new[v]
    k.neighbour_average(Y, bad, indptr, indices, 2)
    np.testing.assert_allclose(Y, want, atol=1e-14)


def test_carry_points(face):
    h = make_hierarchy(face["base_triangles"], len(face["points"]), 2)
    X1 = np.ascontiguousarray(h.steps[0].matrix @ face["points"])
    X2 = np.ascontiguousarray(h.steps[1].matrix @ X1)
    rng = np.random.default_rng(3)
    n = 50
    tri = rng.integers(0, len(h.triangles(2)), n)
    bary = rng.dirichlet(np.ones(3), n)
    ftri = tri >> 2
    local = rng.normal(size=(n, 3))
    out = np.empty((n, 3))
    stacked = np.concatenate([X1, X2])
    frame_corners = h.triangles(1)[ftri]
    frame_corners[::4] = -1  # every fourth offset does not turn
    k.carry_points(stacked, len(X1) + h.triangles(2)[tri], bary, frame_corners, local, out)
    frames = triangle_frames(X1, h.triangles(1), ftri)
    frames[::4] = np.eye(3)
    want = np.einsum("pk,pkd->pd", bary, X2[h.triangles(2)[tri]]) + np.einsum(
        "pk,pkd->pd", local, frames
    )
    np.testing.assert_allclose(out, want, atol=1e-12)


def test_trace_level_matches_a_global_query(face):
    step, X, pred, normals = _level(face)
    v, f = face["vertices"], np.asarray(face["mesh"].triangles)
    caster = RayCaster(v, f, backend="bvh")
    n0 = step.n_coarse
    limit = 1.0 * np.linalg.norm(X[step.edges[:, 1]] - X[step.edges[:, 0]], axis=1)
    glob = caster.cast(pred[n0:], normals[n0:], max_distance=limit)
    # start each walk two triangles away from the answer
    nb = triangle_neighbors(f)
    start = np.where(glob.hit, nb[np.maximum(glob.triangle, 0), 0], -1)
    start = np.where(start >= 0, start, glob.triangle)
    Y, status = pred.copy(), np.empty(step.n_odd, np.int8)
    skip = np.zeros(step.n_odd, bool)
    found = np.empty(step.n_odd, np.int64)
    ro = [
        readonly(a) for a in (v, f, nb, X, pred, normals, step.edges)
    ]  # as the library passes them
    k.trace_level(*ro, n0, skip, start, 1.0, 64, Y, status, found)
    hit = status == k.TRACE_HIT
    assert (found[hit] == glob.triangle[hit]).all()
    assert hit.mean() > 0.9
    np.testing.assert_allclose(Y[n0:][hit], glob.points[hit], atol=1e-9)
    assert (status[~glob.hit] != k.TRACE_HIT).all()
