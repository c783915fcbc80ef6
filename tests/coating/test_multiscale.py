"""Multi-scale decomposition: exact reconstruction, rigid invariance, kernels vs naive loops."""

import numpy as np
import pytest
from naive.coating import coating as naive_coating
from naive.coating import grid_mesh, vertex_frame

from faceretarget.errors import ConfigError, DegenerateGeometryError, ShapeError
from faceretarget.geometry.local_frames import VertexFrames, frame_neighbors, to_local, to_world
from faceretarget.plugins.coating.multiscale import MultiScale


def _mesh(n=14, seed=0):
    v, t = grid_mesh(n, seed=seed)
    wrinkles = 0.01 * np.sin(40 * v[:, 1])
    v[:, 2] += wrinkles
    return v, t


def _rotation(angle=0.8):
    axis = np.array([0.2, 1.0, -0.4])
    axis /= np.linalg.norm(axis)
    k = np.array([[0, -axis[2], axis[1]], [axis[2], 0, -axis[0]], [-axis[1], axis[0], 0]])
    return np.eye(3) + np.sin(angle) * k + (1 - np.cos(angle)) * k @ k


@pytest.mark.parametrize("laplacian", ["uniform", "cotangent"])
@pytest.mark.parametrize("solve_dtype, tol", [(np.float64, 1e-10), (np.float32, 1e-7)])
def test_decomposition_reconstructs_exactly(laplacian, solve_dtype, tol):
    """Exact with float64 solves; with float32 solves (the default) to ~3e-8 of the mesh size."""
    v, t = _mesh()
    ms = MultiScale(
        v, t, iterations=40, laplacian=laplacian, screening=0.1, solve_dtype=solve_dtype
    )
    rng = np.random.default_rng(0)
    frames = v + 0.02 * rng.normal(size=(4,) + v.shape)
    smooth, coating = ms.decompose(frames)
    back = ms.reconstruct(smooth, coating)
    assert np.abs(back - frames).max() < tol * np.abs(v).max()
    work = coating.copy()  # in the coating's memory, the same numbers
    fortran = np.asfortranarray(ms.frames(smooth))  # frames given in any memory order
    np.testing.assert_allclose(
        ms.reconstruct(smooth, coating, fortran), back, rtol=0, atol=1e-12 * np.abs(v).max()
    )
    np.testing.assert_array_equal(ms.reconstruct(smooth, work, overwrite_coating=True), back)
    np.testing.assert_array_equal(
        ms.frames.apply(smooth, coating, inverse=False),
        ms.frames.apply(smooth, coating.copy(), inverse=False, overwrite_vectors=True),
    )
    np.testing.assert_allclose(
        ms.reconstruct(ms.smooth_reference[None], ms.reference_coating[None])[0],
        v,
        rtol=0,
        atol=tol * np.abs(v).max(),
    )


def test_auto_solve_precision_follows_the_condition_bound():
    """float32 Poisson solves only where the screened system is well conditioned."""
    from faceretarget.plugins.coating.multiscale import FLOAT32_CONDITION

    v, t = _mesh()
    for laplacian, screening, dtype in [
        ("uniform", 0.1, np.float32),
        ("cotangent", 0.1, np.float32),
        ("uniform", 0.005, np.float64),
    ]:
        ms = MultiScale(v, t, iterations=5, laplacian=laplacian, screening=screening)
        dense = np.linalg.eigvalsh(ms.poisson.toarray())
        assert dense[-1] / dense[0] <= ms.condition_bound * (1 + 1e-9)  # a true bound
        assert (ms.condition_bound <= FLOAT32_CONDITION) == (dtype == np.float32)
        assert ms.factor.frames_dtype == dtype, (laplacian, screening, ms.condition_bound)


def test_coating_is_invariant_to_rigid_motion():
    v, t = _mesh(seed=1)
    r = _rotation()
    moved = v @ r.T + [0.5, -1.0, 2.0]
    exact = MultiScale(
        v, t, iterations=40, laplacian="uniform", screening=0.1, smooth_dtype=np.float64
    )
    a = exact.decompose(v[None])[1][0]
    b = exact.decompose(moved[None])[1][0]
    np.testing.assert_allclose(b, a, atol=1e-12 * np.abs(v).max())
    fast = MultiScale(v, t, iterations=40, laplacian="uniform", screening=0.1)  # float32 smoothing
    np.testing.assert_allclose(
        fast.decompose(moved[None])[1][0], a, atol=1e-4 * np.abs(a).max()
    )  # float32 rounding
    assert np.abs(a).max() > 1e-3  # the wrinkles are in the coating


def test_coating_matches_per_vertex_loop():
    v, t = _mesh(8, seed=2)
    ms = MultiScale(
        v, t, iterations=10, laplacian="cotangent", screening=0.1, smooth_dtype=np.float64
    )
    frame = v + 0.01 * np.random.default_rng(3).normal(size=v.shape)
    smooth, coating = ms.decompose(frame[None])
    want = naive_coating(frame, smooth[0], t, ms.poisson.toarray(), ms.neighbors)
    np.testing.assert_allclose(coating[0], want, atol=1e-12)


def test_frames_kernel_matches_naive_and_fused_apply():
    v, t = _mesh(7, seed=4)
    nb = frame_neighbors(v, t)
    vf = VertexFrames(t, nb)
    frames = vf(v)
    # the normals are the incident faces' cross products summed in triangle order, bit for bit
    cross = np.cross(v[t[:, 1]] - v[t[:, 0]], v[t[:, 2]] - v[t[:, 0]])
    normals = np.zeros_like(v)
    np.add.at(normals, t.ravel(), np.repeat(cross, 3, axis=0))
    np.testing.assert_array_equal(
        frames[:, :, 2], normals / np.linalg.norm(normals, axis=1, keepdims=True)
    )
    for i in range(len(v)):
        np.testing.assert_allclose(frames[i], vertex_frame(v, t, i, nb[i, 0]), atol=1e-12)
    vec = np.random.default_rng(5).normal(size=v.shape)
    np.testing.assert_allclose(vf.apply(v, vec, inverse=True), to_local(frames, vec), atol=1e-13)
    np.testing.assert_allclose(vf.apply(v, vec, inverse=False), to_world(frames, vec), atol=1e-13)
    np.testing.assert_allclose(to_world(frames, to_local(frames, vec)), vec, atol=1e-13)


def test_frames_refuse_triangle_indices_out_of_range():
    v, t = _mesh(5, seed=6)
    nb = frame_neighbors(v, t)
    for bad in (t - t.min() - 1, t + (len(v) - t.max())):  # one below 0, one past the end
        with pytest.raises(ShapeError, match="triangle indices"):
            VertexFrames(bad, nb)


def test_frames_degenerate_vertex_is_reported():
    v, t = _mesh(5, seed=6)
    nb = frame_neighbors(v, t)
    flat = v.copy()
    flat[:] = flat[0]  # every triangle collapses
    with pytest.raises(DegenerateGeometryError, match="no defined normal"):
        VertexFrames(t, nb)(flat)


def test_bad_settings():
    v, t = _mesh(5)
    with pytest.raises(ConfigError):
        MultiScale(v, t, iterations=5, laplacian="spectral", screening=0.1)
    with pytest.raises(ConfigError):
        MultiScale(v, t, iterations=5, laplacian="uniform", screening=0.0)


@pytest.mark.parametrize("jitter", [0.0, 0.3])
def test_frame_neighbors_match_sorting_every_edge(jitter):
    """The one-pass selection (numba) against sorting all directed edges, on grids, and on
    a fan whose centre sees exact score ties: its two neighbours at +-45 degrees from x,
    the higher id met first (the tie goes to the lower id, not to the first seen), and a
    tie for second place behind a unique best."""
    from naive.coating import frame_neighbors as naive_neighbors
    from naive.coating import grid_mesh

    from faceretarget.errors import NonFiniteError
    from faceretarget.geometry.local_frames import frame_neighbors

    for n in (3, 9):
        v, t = grid_mesh(n, seed=2, jitter=jitter)
        np.testing.assert_array_equal(frame_neighbors(v, t), naive_neighbors(v, t))
    fan = np.array([[1.0, 1.0, 0.0], [0.0, 0.0, 0.0], [1.0, -1.0, 0.0], [2.0, 0.0, 0.0]])
    tris = np.array([[1, 2, 0], [0, 2, 3]])
    got = frame_neighbors(fan, tris)
    np.testing.assert_array_equal(got, naive_neighbors(fan, tris))
    assert got[1].tolist() == [0, 2]
    # centre 2 of a wider fan: best 4 straight along x, then 3 and 0 at +-45 degrees (3 met
    # first: directed edges to higher ids come first)
    star = np.array(
        [[1.0, 1.0, 0.0], [0.0, 2.0, 0.0], [0.0, 0.0, 0.0], [1.0, -1.0, 0.0], [2.0, 0.0, 0.0]]
    )
    tris = np.array([[2, 3, 4], [2, 4, 0], [2, 0, 1]])
    got = frame_neighbors(star, tris)
    np.testing.assert_array_equal(got, naive_neighbors(star, tris))
    assert got[2].tolist() == [4, 0]
    bad = fan.copy()
    bad[3, 0] = np.nan
    with pytest.raises(NonFiniteError):
        frame_neighbors(bad, np.array([[1, 2, 0], [0, 2, 3]]))
