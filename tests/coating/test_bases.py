"""Greedy basis selection and non-negative weights (eq. 6-8)."""

import numpy as np
import pytest

from faceretarget.errors import ShapeError
from faceretarget.plugins.coating.bases import BasisSpace, blend, select_bases


def _frames(seed=0):
    rng = np.random.default_rng(seed)
    neutral = rng.normal(size=60)
    keys = neutral + 0.5 * rng.normal(size=(3, 60))
    mix = rng.dirichlet(np.ones(4), size=50)  # convex mixes of neutral + 3 key shapes
    frames = mix @ np.vstack([neutral, keys])
    frames[[7, 19, 33]] = keys  # the key shapes appear as frames
    return neutral, keys, frames


def test_selects_the_generating_frames_and_stops():
    neutral, keys, frames = _frames()
    chosen, history = select_bases(frames, neutral, epsilon=1e-6, max_bases=10, height=1.0)
    assert sorted(chosen) == [7, 19, 33]
    assert history[-1] <= 1e-6 and len(history) == 4
    assert all(a >= b for a, b in zip(history, history[1:]))


def test_respects_max_bases_and_epsilon():
    neutral, keys, frames = _frames(1)
    chosen, history = select_bases(frames, neutral, epsilon=1e-12, max_bases=2, height=1.0)
    assert len(chosen) == 1
    loose, hist = select_bases(frames, neutral, epsilon=10.0, max_bases=10, height=1.0)
    assert loose == [] and hist[0] <= 10.0


def test_weights_non_negative_and_blend_reconstructs():
    rng = np.random.default_rng(2)
    bases = rng.normal(size=(4, 30, 3))
    center = bases[0].mean(axis=0)
    w_true = rng.uniform(0.0, 1.0, size=(6, 4))
    w_true[0, 2] = 0.0
    frames = blend(bases, center, w_true)
    space = BasisSpace(bases, center)
    w = space.weights(frames)
    assert (w >= 0).all()
    np.testing.assert_allclose(w, w_true, atol=1e-8)
    np.testing.assert_allclose(blend(bases, center, w), frames, atol=1e-8)


def test_weights_of_raw_frames_through_the_adjoint_filter():
    from naive.coating import grid_mesh

    from faceretarget.geometry.smoothing import TaubinSmoother

    v, t = grid_mesh(8, seed=3)
    rng = np.random.default_rng(4)
    smooth = TaubinSmoother(t, len(v), iterations=10)
    adjoint = TaubinSmoother(t, len(v), iterations=10, adjoint=True)
    raw = v + 0.05 * rng.normal(size=(5,) + v.shape)
    bases = smooth(raw[:3])
    space = BasisSpace(bases, bases[0].mean(axis=0), adjoint=adjoint)
    np.testing.assert_allclose(space.weights_of_raw(raw), space.weights(smooth(raw)), atol=1e-9)


def test_basis_space_keeps_centred_bases_as_given():
    """``centred=True``: the bases minus the centre are the space's matrix without a copy,
    with the weights of the bases given absolute."""
    rng = np.random.default_rng(9)
    bases = rng.normal(size=(4, 30, 3)) + [5.0, -3.0, 8.0]
    center = bases[0].mean(axis=0)
    centred = bases - center
    space = BasisSpace(centred, center, centred=True)
    assert np.shares_memory(space.matrix, centred)
    plain = BasisSpace(bases, center)
    np.testing.assert_array_equal(space.matrix, plain.matrix)
    frames = bases[:2] + 0.01 * rng.normal(size=(2, 30, 3))
    np.testing.assert_array_equal(space.weights(frames), plain.weights(frames))


def _fitted(monkeypatch, cache_bytes):
    """A coating fit on a small synthetic case; returns (retargeter, frames of each smoothing call)."""
    import faceretarget as fr
    from faceretarget.geometry.smoothing import TaubinSmoother
    from faceretarget.plugins.coating import model
    from faceretarget.plugins.coating.retargeter import CoatingRetargeter

    case = fr.cases.synthetic(seed=3, resolution=800, n_frames=40)
    monkeypatch.setattr(model, "CANDIDATE_CACHE_BYTES", cache_bytes)
    calls = []
    smooth = TaubinSmoother.__call__

    def counted(self, points):
        calls.append(np.shape(points)[0] if np.ndim(points) == 3 else 1)
        return smooth(self, points)

    monkeypatch.setattr(TaubinSmoother, "__call__", counted)
    r = CoatingRetargeter(epsilon=1e-9, max_bases=6, chunk_frames=16)
    r.fit(case.source, case.target)
    return r, list(calls)  # a copy: a later _fitted wraps this counter again


def test_bases_from_the_low_rank_smoothing_of_the_candidates(monkeypatch):
    """With the candidates in memory, their displacements are smoothed through their column
    space (``SmoothedDisplacements``: rank-many columns instead of 3 x 40) and the chosen
    bases are read from it: the same basis frames as smoothing every candidate (cache 0),
    bases closer to a float64 smoothing than that path's float32 positions, and the
    weights' adjoint matrix equal to ``G^T (bases - center)`` computed directly."""
    import faceretarget as fr
    from faceretarget.geometry.smoothing import TaubinSmoother

    low, calls_low = _fitted(monkeypatch, 2**30)
    direct, calls_direct = _fitted(monkeypatch, 0)
    assert low.basis_frames_ == direct.basis_frames_ and len(low.basis_frames_) == 5
    m = low.model_
    assert 0 < m.smoothing_rank < 60 and direct.model_.smoothing_rank is None
    # both references in one call; the rank's columns (whole frames); the adjoint of the
    # reference + 5 bases (fewer columns than the rank's); the direct path: 40 candidates
    # in chunks of 16, the 5 basis frames once more, the adjoint
    assert calls_low == [2, -(-m.smoothing_rank // 3), 6], calls_low
    assert calls_direct == [2, 16, 16, 8, 5, 6], calls_direct
    # against float64 smoothing of the same local frames
    case = fr.cases.synthetic(seed=3, resolution=800, n_frames=40)
    motion, _ = low._source_motion(case.source)
    frames = np.asarray(low.basis_frames_)
    local = low.placement_.local(
        motion[frames], np.asarray(case.source.performance.vertices)[frames]
    )
    exact = TaubinSmoother(m.triangles, m.n_vertices, iterations=m.source.smoother.iterations)
    want = exact(local) - exact(m.source.reference)  # the bases' smoothed displacements
    scale = np.abs(want).max()

    def error(model):
        return np.abs(model.source_bases[1:] - model.source_bases[0] - want).max() / scale

    # both paths smooth displacements (G S = G R + G (S - R)); the float32 kernel on
    # absolute positions lost 1.7e-5 of them here, the low-rank path loses ~8e-7
    assert error(m) < 2e-6 and error(direct.model_) < 2e-6, (error(m), error(direct.model_))
    # the selection saw the same samples (to float32 accuracy), not only chose the same frames
    np.testing.assert_allclose(low.model_.selection_rms, direct.model_.selection_rms, rtol=1e-5)
    b = m.source_bases - m.source_center
    lifted = m.source.adjoint(b).reshape(len(b), -1).T
    np.testing.assert_allclose(m.space.adjoint_matrix, lifted, atol=1e-12 * np.abs(lifted).max())
    none = m.smooth_target(np.zeros((0, 6)))  # no frames: an empty chunk
    assert none.shape == (0, m.n_vertices, 3)


def test_bases_when_the_candidates_are_not_low_rank(monkeypatch):
    """Displacements of near full rank take the dense path of ``SmoothedDisplacements``
    (every candidate smoothed, in chunks): the same bases and adjoint as the low-rank path,
    to its tolerance, through the same code in the model."""
    import functools

    from faceretarget.geometry.smoothing import SmoothedDisplacements
    from faceretarget.plugins.coating import model

    low, _ = _fitted(monkeypatch, 2**30)
    monkeypatch.setattr(
        model, "SmoothedDisplacements", functools.partial(SmoothedDisplacements, max_share=0.0)
    )
    dense, calls = _fitted(monkeypatch, 2**30)
    assert dense.model_.smoothing_rank is None and calls[1:4] == [16, 16, 8], calls
    assert dense.basis_frames_ == low.basis_frames_
    a, b = low.model_, dense.model_
    scale = np.abs(a.source_bases - a.source_bases[0]).max()
    np.testing.assert_allclose(b.source_bases, a.source_bases, atol=2e-6 * scale)
    lift = np.abs(a.space.adjoint_matrix).max()
    np.testing.assert_allclose(b.space.adjoint_matrix, a.space.adjoint_matrix, atol=2e-6 * lift)


def _in_layout(bases: np.ndarray, layout: str) -> np.ndarray:
    """``bases (K, V, 3)`` stored frame-major, vertex-major (``(V, K, 3)``) or as deformation
    transfer returns them (``(V, 3, K)``)."""
    order = {"frame-major": (0, 1, 2), "vertex-major": (1, 0, 2), "transfer": (1, 2, 0)}[layout]
    stored = np.ascontiguousarray(np.transpose(bases, order))
    return np.transpose(stored, np.argsort(order))


@pytest.mark.parametrize("frames", [1, 3, 5, 12])
@pytest.mark.parametrize("layout", ["frame-major", "vertex-major", "transfer"])
def test_blend_is_the_centred_sum_without_centring_the_bases(frames, layout):
    """eq. 8 as written (centre + sum of weighted centred bases) against blend, which adds
    the weighted bases and the leftover weight of the centre; weights not summing to 1; the
    bases in any memory layout (the retarget's is deformation transfer's), distinct
    coordinates (a crossed x, y, z would show)."""
    rng = np.random.default_rng(5)
    bases = _in_layout(rng.normal(size=(4, 7, 3)) + [3.0, -2.0, 10.0], layout)
    center = np.array([3.1, -1.9, 9.8])
    weights = rng.uniform(0.0, 0.8, size=(frames, 4))
    want = center + np.einsum("tk,kvd->tvd", weights, bases - center)
    got = blend(bases, center, weights)
    assert got.shape == (frames, 7, 3) and got.flags.c_contiguous
    np.testing.assert_allclose(got, want, rtol=0, atol=1e-13)
    np.testing.assert_array_equal(
        blend(bases, center, np.zeros((1, 4)))[0], np.tile(center, (7, 1))
    )


def test_candidates_are_read_in_steps_below_the_scratch_size(monkeypatch):
    """The candidate frames are read and moved a few at a time so that their float64
    copies stay below ``config.SCRATCH_BLOCK_BYTES`` (glibc serves larger blocks from fresh
    pages every step): 5 frames a step here instead of ``chunk_frames`` = 16, on both
    paths, with the same bases bit for bit."""
    from faceretarget import config
    from faceretarget.plugins.coating import model

    low, _ = _fitted(monkeypatch, 2**30)
    direct, _ = _fitted(monkeypatch, 0)
    m = low.model_.n_vertices
    monkeypatch.setattr(config, "SCRATCH_BLOCK_BYTES", 5 * 24 * m)
    steps = []
    chunks = model.frame_chunks

    def counted(n, step):
        steps.append(step)
        return chunks(n, step)

    monkeypatch.setattr(model, "frame_chunks", counted)
    low_small, _ = _fitted(monkeypatch, 2**30)
    direct_small, calls = _fitted(monkeypatch, 0)
    assert steps == [5, 5], steps
    assert calls[1:9] == [5] * 8, calls
    np.testing.assert_array_equal(low_small.model_.source_bases, low.model_.source_bases)
    np.testing.assert_array_equal(direct_small.model_.source_bases, direct.model_.source_bases)


@pytest.mark.parametrize("layout", ["frame-major", "vertex-major", "transfer"])
def test_blend_of_no_frames_and_weights_of_the_wrong_size(layout):
    bases = _in_layout(np.random.default_rng(6).normal(size=(4, 7, 3)), layout)
    assert blend(bases, np.zeros(3), np.zeros((0, 4))).shape == (0, 7, 3)
    with pytest.raises(ShapeError, match=r"\(C, 4\)"):
        blend(bases, np.zeros(3), np.ones((2, 1)))  # one weight for 4 bases: not broadcast


def test_target_bases_are_kept_once_and_blended_in_place(monkeypatch):
    """The transferred bases are the model's only copy of the target bases: their ``(K, 3V)``
    rows are a view (deformation transfer's layout), which every blend reads as a matrix,
    and the smooth target frames are eq. 8 on them."""
    r, _ = _fitted(monkeypatch, 2**30)
    m = r.model_
    bases = m.target_bases
    rows = bases.reshape(bases.shape[0], -1)
    assert np.shares_memory(rows, bases)
    weights = np.random.default_rng(8).uniform(0.0, 0.5, size=(3, bases.shape[0]))
    want = m.target_center + np.einsum("tk,kvd->tvd", weights, bases - m.target_center)
    scale = np.abs(bases).max()
    np.testing.assert_allclose(m.smooth_target(weights), want, rtol=0, atol=1e-13 * scale)


def test_source_bases_centred_once_and_transferred_as_given_absolute(monkeypatch):
    """The fit keeps the source bases once, centred (the basis space's matrix), and transfers
    them from the centred reference: the target bases of the absolute bases to rounding, and
    ``source_bases`` gives them back absolute, the smooth reference first."""
    r, _ = _fitted(monkeypatch, 2**30)
    m = r.model_
    size = m.n_bases * m.n_vertices * 3
    held = [
        a
        for a in (*vars(m).values(), *vars(m.space).values())
        if isinstance(a, np.ndarray) and a.size == size
    ]
    distinct = [a for i, a in enumerate(held) if not any(np.shares_memory(a, b) for b in held[:i])]
    assert len(distinct) == 3  # the centred source bases, their adjoint filter, the target's
    absolute = m.source_bases
    scale = np.abs(absolute).max()
    np.testing.assert_allclose(absolute[0], m.source.smooth_reference, rtol=0, atol=1e-14 * scale)
    want = m.transfer_bases(absolute)
    moved = np.abs(want - want[0]).max()
    np.testing.assert_allclose(m.target_bases, want, rtol=0, atol=1e-12 * moved)
