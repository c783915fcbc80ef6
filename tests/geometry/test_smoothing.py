"""Taubin smoothing: numba kernel against a per-vertex loop; batching and precision."""

import numpy as np
import pytest
from naive.coating import grid_mesh
from naive.coating import taubin as naive_taubin

from faceretarget.errors import ShapeError
from faceretarget.geometry.smoothing import TaubinSmoother, taubin_smooth


def test_matches_naive_loop():
    v, t = grid_mesh(7, seed=0)
    np.testing.assert_allclose(
        taubin_smooth(v, t, iterations=6), naive_taubin(v, t, iterations=6), atol=1e-13
    )


def test_batch_of_frames_equals_one_by_one_exactly():
    v, t = grid_mesh(8, seed=1)
    rng = np.random.default_rng(0)
    frames = v + 0.02 * rng.normal(size=(5,) + v.shape)
    for dtype in (np.float64, np.float32):
        smoother = TaubinSmoother(t, len(v), iterations=40, dtype=dtype)
        batch = smoother(frames)
        single = np.stack([smoother(f) for f in frames])
        np.testing.assert_array_equal(batch, single)


def test_float32_close_to_float64():
    v, t = grid_mesh(8, seed=2)
    a = taubin_smooth(v, t, dtype=np.float64)
    b = taubin_smooth(v, t, dtype=np.float32)
    assert np.abs(a - b).max() < 1e-5 * np.abs(v).max()


def test_removes_high_frequencies_and_commutes_with_translation():
    v, t = grid_mesh(21, seed=3, jitter=0.0)
    noise = (
        0.01 * np.where(np.arange(len(v)) % 2 == 0, 1.0, -1.0)[:, None] * np.array([0.0, 0.0, 1.0])
    )
    # the filter is linear: what is left of the checkerboard noise is smooth(v + noise) - smooth(v)
    left = taubin_smooth(v + noise, t) - taubin_smooth(v, t)
    assert np.linalg.norm(left) < 0.05 * np.linalg.norm(noise)
    translated = taubin_smooth(v + np.array([1.0, 2.0, 3.0]), t)
    np.testing.assert_allclose(
        translated - taubin_smooth(v, t), np.broadcast_to([1.0, 2.0, 3.0], v.shape), atol=1e-12
    )


def test_shape_error():
    v, t = grid_mesh(4)
    with pytest.raises(ShapeError):
        TaubinSmoother(t, len(v))(v[:-1])
    with pytest.raises(ShapeError):
        taubin_smooth(v[:, :2], t)


def test_adjoint_filter_is_the_transpose():
    v, t = grid_mesh(9, seed=4)
    rng = np.random.default_rng(1)
    x, b = rng.normal(size=v.shape), rng.normal(size=v.shape)
    forward = TaubinSmoother(t, len(v), iterations=7)
    adjoint = TaubinSmoother(t, len(v), iterations=7, adjoint=True)
    assert np.sum(b * forward(x)) == pytest.approx(np.sum(adjoint(b) * x), rel=1e-12)


# ---- SmoothedDisplacements: smoothing many frames through their column space ------------


def _displacements(v, rank, n_frames, seed, noise=0.0):
    """(C, 3, V) displacements: ``rank`` random smooth-ish fields mixed per frame, + noise."""
    rng = np.random.default_rng(seed)
    fields = rng.normal(size=(rank, len(v)))
    mix = rng.normal(size=(3 * n_frames, rank))
    rows = mix @ fields + noise * rng.normal(size=(3 * n_frames, len(v)))
    return np.ascontiguousarray(rows.reshape(n_frames, 3, len(v)))


def _exact(smoother, d):
    """(C, V, 3): every frame smoothed directly (float64 kernel)."""
    return smoother(np.ascontiguousarray(np.asarray(d, dtype=np.float64).transpose(0, 2, 1)))


def test_low_rank_displacements_are_smoothed_in_their_column_space():
    from faceretarget.geometry.smoothing import SmoothedDisplacements

    v, t = grid_mesh(12, seed=5)
    smoother = TaubinSmoother(t, len(v), iterations=10)
    d = _displacements(v, rank=7, n_frames=20, seed=0)
    want = _exact(smoother, d)
    got = SmoothedDisplacements(smoother, d.copy())
    assert got.rank == 7  # 7 rows smoothed instead of 60
    scale = np.abs(want).max()
    np.testing.assert_allclose(got.frames(np.arange(20)), want, atol=1e-12 * scale)
    ids = np.array([3, 0, 141, 77])
    np.testing.assert_allclose(got.at(ids), want[:, ids], atol=1e-12 * scale)
    np.testing.assert_allclose(got.frames([5, 2]), want[[5, 2]], atol=1e-12 * scale)


def test_low_rank_truncation_honours_the_tolerance():
    """Singular values decaying over six decades: the rank kept is the fewest whose
    discarded part is within ``tol`` (relative Frobenius), and the error is within it."""
    from faceretarget.geometry.smoothing import SmoothedDisplacements

    v, t = grid_mesh(12, seed=6)
    smoother = TaubinSmoother(t, len(v), iterations=10)
    rng = np.random.default_rng(1)
    u, _ = np.linalg.qr(rng.normal(size=(60, 30)))
    w, _ = np.linalg.qr(rng.normal(size=(len(v), 30)))
    sigma = 10.0 ** -np.linspace(0, 6, 30)
    rows = (u * sigma) @ w.T
    d = np.ascontiguousarray(rows.reshape(20, 3, len(v)))
    want = _exact(smoother, d)
    for tol in (1e-2, 1e-4):
        got = SmoothedDisplacements(smoother, d.copy(), tol=tol, max_share=1.0)
        tail = np.sqrt(np.cumsum((sigma**2)[::-1])[::-1] / np.sum(sigma**2))
        assert got.rank == int(np.count_nonzero(tail > tol))
        err = np.linalg.norm(got.frames(np.arange(20)) - want) / np.linalg.norm(d)
        assert tol / 20 < err <= 1.05 * tol, (tol, err)  # not far below either: truncated


def test_full_rank_displacements_are_smoothed_frame_by_frame():
    from faceretarget.geometry.smoothing import SmoothedDisplacements

    v, t = grid_mesh(8, seed=7)
    smoother = TaubinSmoother(t, len(v), iterations=10, dtype=np.float32)
    d = _displacements(v, rank=2, n_frames=6, seed=2, noise=1.0)  # noise: full rank
    want = smoother(np.ascontiguousarray(d.transpose(0, 2, 1)))
    got = SmoothedDisplacements(smoother, d, chunk=4)
    assert got.rank is None
    np.testing.assert_array_equal(got.frames(np.arange(6)), want)  # the same kernel calls
    np.testing.assert_array_equal(got.at([1, 9]), want[:, [1, 9]])


def test_filtered_equals_the_filter_applied_to_the_frames():
    """Another filter (the adjoint) through the column basis equals applying it to the
    smoothed frames, when that is fewer columns (rank 4 < 3 x 5 frames) and when not."""
    from faceretarget.geometry.smoothing import SmoothedDisplacements

    v, t = grid_mesh(10, seed=8)
    smoother = TaubinSmoother(t, len(v), iterations=8)
    adjoint = TaubinSmoother(t, len(v), iterations=8, adjoint=True)
    d = _displacements(v, rank=4, n_frames=12, seed=3)
    got = SmoothedDisplacements(smoother, d)
    assert got.rank == 4
    extra = np.random.default_rng(4).normal(size=(2,) + v.shape)
    for frames in ([0, 3, 4, 9, 11], [7]):  # 4 < 15 columns: the basis; 4 >= 3: direct
        want = adjoint(np.concatenate([extra, got.frames(frames)]))
        out = got.filtered(adjoint, frames, extra)
        assert out.shape == (2 + len(frames),) + v.shape
        np.testing.assert_allclose(out, want, atol=1e-12 * np.abs(want).max())


def test_frames_and_filtered_a_few_frames_at_a_time(monkeypatch):
    """Frames formed a block at a time (scratch for two frames) into the caller's ``out``, and
    ``filtered`` by blocks, give the whole-block numbers; a wrong ``out`` is refused."""
    from faceretarget import config
    from faceretarget.errors import ShapeError
    from faceretarget.geometry.smoothing import SmoothedDisplacements

    v, t = grid_mesh(10, seed=9)
    smoother = TaubinSmoother(t, len(v), iterations=8)
    adjoint = TaubinSmoother(t, len(v), iterations=8, adjoint=True)
    got = SmoothedDisplacements(smoother, _displacements(v, rank=4, n_frames=12, seed=5))
    ids = [11, 0, 7, 3, 3, 9, 1]
    extra = np.random.default_rng(5).normal(size=(1,) + v.shape)
    whole, lifted = got.frames(ids), got.filtered(adjoint, ids, extra)
    monkeypatch.setattr(config, "SCRATCH_BLOCK_BYTES", 2 * 24 * len(v))
    out = np.full((len(ids),) + v.shape, np.nan)
    assert got.frames(ids, out=out) is out
    scale = np.abs(whole).max()
    np.testing.assert_allclose(out, whole, rtol=0, atol=1e-14 * scale)
    np.testing.assert_allclose(
        got.filtered(adjoint, ids, extra), lifted, rtol=0, atol=1e-14 * scale
    )
    with pytest.raises(ShapeError, match="out must be"):
        got.frames(ids, out=out[1:])


def test_smoothed_displacements_edge_cases():
    from faceretarget.errors import NumericalError
    from faceretarget.geometry.smoothing import SmoothedDisplacements

    v, t = grid_mesh(5, seed=9)
    smoother = TaubinSmoother(t, len(v), iterations=3)
    still = SmoothedDisplacements(smoother, np.zeros((4, 3, len(v))))
    assert still.rank == 0
    assert not still.frames([1, 2]).any() and still.at([0]).shape == (4, 1, 3)
    none = SmoothedDisplacements(smoother, np.zeros((0, 3, len(v))))
    assert none.rank == 0 and none.at([1, 2]).shape == (0, 2, 3)
    one = _displacements(v, rank=3, n_frames=1, seed=5)
    np.testing.assert_allclose(
        SmoothedDisplacements(smoother, one.copy()).frames([0]), _exact(smoother, one), atol=1e-12
    )
    with pytest.raises(ShapeError, match="C-contiguous"):
        SmoothedDisplacements(smoother, np.zeros((4, len(v), 3)))  # frames not coordinate-major
    with pytest.raises(ShapeError, match="not C-contiguous"):
        SmoothedDisplacements(smoother, np.zeros((3, len(v), 4)).transpose(0, 2, 1))
    with pytest.raises(ShapeError, match="int64"):  # the dense path would truncate into it
        SmoothedDisplacements(smoother, np.zeros((4, 3, len(v)), dtype=np.int64))
    for bad in (np.nan, np.inf, 1e200):  # a non-finite Gram would read as rank 0: zeros
        d = np.zeros((4, 3, len(v)))
        d[2, 1, 7] = bad
        with pytest.raises(NumericalError, match="non-finite"):
            SmoothedDisplacements(smoother, d)


def test_float32_displacements_take_the_low_rank_path():
    """The coating stores the candidates' displacements in float32: the rank and the
    smoothed rows are those of the float64 data to float32 accuracy."""
    from faceretarget.geometry.smoothing import SmoothedDisplacements

    v, t = grid_mesh(12, seed=12)
    smoother = TaubinSmoother(t, len(v), iterations=10)
    d = _displacements(v, rank=5, n_frames=20, seed=6)
    got = SmoothedDisplacements(smoother, d.astype(np.float32))
    assert got.rank == 5
    want = _exact(smoother, d)
    assert np.abs(got.frames(np.arange(20)) - want).max() < 1e-6 * np.abs(want).max()


def test_the_low_rank_path_only_where_it_pays():
    """Rank 7 of 60 rows: the basis when at most ``max_share`` of the rows (share 0.12: up
    to 7.2 rows), every frame otherwise (share 0.1: 6 rows); more rows than ``max_rows`` or
    than vertices: every frame, without the eigenproblem."""
    from faceretarget.geometry.smoothing import SmoothedDisplacements

    v, t = grid_mesh(12, seed=13)
    smoother = TaubinSmoother(t, len(v), iterations=5)
    d = _displacements(v, rank=7, n_frames=20, seed=7)
    want = _exact(smoother, d)
    for share, rank in ((0.12, 7), (0.1, None)):
        got = SmoothedDisplacements(smoother, d.copy(), max_share=share)
        assert got.rank == rank
        np.testing.assert_allclose(got.frames(np.arange(20)), want, atol=1e-12 * np.abs(want).max())
    assert SmoothedDisplacements(smoother, d.copy(), max_rows=59).rank is None
    small, tt = grid_mesh(4, seed=14)  # 16 vertices, 60 rows
    few = _displacements(small, rank=2, n_frames=20, seed=8)
    assert SmoothedDisplacements(TaubinSmoother(tt, 16, iterations=5), few).rank is None


def test_one_mesh_blocks_equal_wider_blocks_exactly():
    """A block of exactly one mesh's 3 columns takes the kernel's unrolled path: the same
    operations in the same order as wider blocks, so the same bits in either precision."""
    from faceretarget.geometry._laplacian_kernels import taubin_frames

    v, t = grid_mesh(9, seed=15)
    frames = v + 0.05 * np.random.default_rng(3).normal(size=(2,) + v.shape)
    smoother = TaubinSmoother(t, len(v), iterations=6)
    for dtype in (np.float32, np.float64):
        outs = []
        for blocks in ([(0, 3), (3, 6)], [(0, 6)]):  # one mesh each (unrolled); 6 columns
            out = np.empty(frames.shape)
            for c0, c1 in blocks:
                taubin_frames(
                    smoother.indptr,
                    smoother.indices,
                    smoother.weights,
                    frames,
                    out,
                    6,
                    smoother.lam,
                    smoother.mu,
                    c0,
                    c1,
                    np.empty(0, dtype=dtype),
                )
            outs.append(out)
        np.testing.assert_array_equal(outs[0], outs[1])
