"""The serial kernels split into blocks on Python threads (``_threads.in_blocks``) give the
same bits whatever the number of threads: each item's arithmetic does not depend on the split."""

import numpy as np
import pytest
import scipy.sparse as sp
from naive.coating import grid_mesh

from faceretarget import _threads
from faceretarget.geometry import factorized, raycast
from faceretarget.geometry.deformation_gradients import gradient_columns, reference_inverse
from faceretarget.geometry.laplacian import umbrella_operator
from faceretarget.geometry.local_frames import VertexFrames, frame_neighbors
from faceretarget.geometry.smoothing import TaubinSmoother


@pytest.fixture
def threads(monkeypatch):
    """``threads(n)``: the library's thread count is ``n`` from then on."""

    def use(n):
        count = lambda tasks: max(1, min(tasks, n))  # noqa: E731
        for module in (_threads, raycast, factorized):
            monkeypatch.setattr(module, "worker_count", count)

    return use


def _mesh():
    v, t = grid_mesh(48, seed=21)  # 2,304 vertices: above raycast.PARALLEL_MIN queries
    rng = np.random.default_rng(5)
    frames = v + 0.02 * rng.normal(size=(7,) + v.shape)
    return v, t, frames, rng


def _everything(v, t, frames, rng):
    n = len(v)
    out = {}
    smoother = TaubinSmoother(t, n, iterations=4)
    out["taubin"] = smoother(frames)
    out["taubin one"] = smoother(frames[0])
    out["taubin float32"] = TaubinSmoother(t, n, iterations=4, dtype=np.float32)(frames)
    w = umbrella_operator(t, n)
    lap = sp.identity(n) * 2.0 - 0.5 * (w + w.T)  # SPD: |(W + W^T) / 2| <= 1.5
    factor = factorized.SPDFactor(lap.tocsc(), what="test")
    rhs = np.random.default_rng(6).normal(size=(n, 23))
    out["solve"] = factor.solve(rhs)
    out["solve_frames"] = factor.solve_frames(frames, frames[::-1])
    vf = VertexFrames(t, frame_neighbors(v, t))
    out["frames"] = vf(frames)
    out["apply"] = vf.apply(frames, frames[::-1], inverse=False)
    out["coating"] = vf.coating(frames, frames[::-1], lap)
    out["gradients"] = gradient_columns(reference_inverse(v, t), frames, t)
    points = frames[3] + 0.01 * rng.normal(size=v.shape)
    limits = np.linspace(0.0, 0.05, n)[rng.permutation(n)]  # per query: some found, some not
    caster = raycast.RayCaster(v, t, backend="bvh")
    hits = caster.closest(points, max_distance=limits)
    lines = caster.cast(points, np.tile([0.1, 0.2, 1.0], (n, 1)), max_distance=limits)
    assert 0 < hits.hit.sum() < n and 0 < lines.hit.sum() < n
    out["closest"] = (hits.triangle, hits.barycentric, hits.distance)
    out["cast"] = (lines.triangle, lines.barycentric, lines.distance)
    return out


def _flat(x):
    return x if isinstance(x, tuple) else (x,)


def test_every_blocked_kernel_gives_the_same_bits_on_one_two_and_three_threads(threads):
    mesh = _mesh()
    runs = {}
    for n in (1, 2, 3):
        threads(n)
        runs[n] = _everything(*mesh[:3], np.random.default_rng(7))
    for name, want in runs[1].items():
        for n in (2, 3):
            for a, b in zip(_flat(want), _flat(runs[n][name]), strict=True):
                np.testing.assert_array_equal(a, b, err_msg=f"{name} on {n} threads")
    # and the blocks really were split: the one-thread result is not the only one checked
    assert _threads.blocks(3 * 7, 3) == [(0, 7), (7, 14), (14, 21)]


@pytest.mark.parametrize("n_threads", [1, 3])
def test_a_degenerate_mesh_in_the_last_block_is_reported_by_its_number(threads, n_threads):
    from faceretarget.errors import DegenerateGeometryError

    threads(n_threads)
    v, t, frames, _ = _mesh()
    frames[6] = 0.0  # every triangle of the last mesh has zero area
    vf = VertexFrames(t, frame_neighbors(v, t))
    with pytest.raises(DegenerateGeometryError, match="mesh 6"):
        vf(frames)
    with pytest.raises(DegenerateGeometryError, match="mesh 6"):
        vf.apply(frames, frames, inverse=True)
    with pytest.raises(DegenerateGeometryError, match="in mesh 6"):
        gradient_columns(reference_inverse(v, t), frames, t)
