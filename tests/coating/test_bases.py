"""Greedy basis selection and non-negative weights (eq. 6-8)."""

import numpy as np

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


def test_bases_come_from_the_kept_candidate_smoothings(monkeypatch):
    """The chosen bases are the smoothed candidates kept during selection (no second
    smoothing of the basis frames), equal bit for bit to smoothing them again."""
    kept, calls_kept = _fitted(monkeypatch, 2**30)
    again, calls_again = _fitted(monkeypatch, 0)
    assert kept.basis_frames_ == again.basis_frames_ and len(kept.basis_frames_) == 5
    np.testing.assert_array_equal(kept.model_.source_bases, again.model_.source_bases)
    np.testing.assert_array_equal(kept.model_.target_bases, again.model_.target_bases)
    none = kept.model_.smooth_target(np.zeros((0, 6)))  # no frames: an empty chunk
    assert none.shape == (0, kept.model_.n_vertices, 3)
    # 40 candidates in chunks of 16; without the kept ones, the 5 basis frames once more
    assert calls_kept[2:5] == [16, 16, 8], calls_kept
    assert calls_again == calls_kept[:5] + [5] + calls_kept[5:], (calls_kept, calls_again)


def test_blend_is_the_centred_sum_without_centring_the_bases():
    """eq. 8 as written (centre + sum of weighted centred bases) against blend, which adds
    the weighted bases and the leftover weight of the centre; weights not summing to 1."""
    rng = np.random.default_rng(5)
    bases = rng.normal(size=(4, 7, 3)) + [3.0, -2.0, 10.0]
    center = np.array([3.1, -1.9, 9.8])
    weights = rng.uniform(0.0, 0.8, size=(5, 4))
    want = center + np.einsum("tk,kvd->tvd", weights, bases - center)
    got = blend(bases, center, weights)
    assert got.shape == (5, 7, 3)
    np.testing.assert_allclose(got, want, rtol=0, atol=1e-13)
    np.testing.assert_array_equal(
        blend(bases, center, np.zeros((1, 4)))[0], np.tile(center, (7, 1))
    )
