"""The temporal smoothing of Eq. 7 smooths, and without it each frame is solved on its own."""

import numpy as np
import pytest
from naive.layers import make_problem

import faceretarget as fr
from faceretarget.plugins.layers import solver
from faceretarget.plugins.layers.retargeter import LayersRetargeter

LEVELS = (0.0, 0.005, 0.02, 0.1, 0.5)


def _second_difference_energy(vertices) -> float:
    v = np.asarray(vertices, dtype=np.float64)
    return float(np.mean(np.sum((v[2:] - 2.0 * v[1:-1] + v[:-2]) ** 2, axis=-1)))


def _noisy_layers_problem():
    """Known head motion, 3% marker noise (of the face size 10): the layers alone (no residual)."""
    p = make_problem(21, n_frames=40, noise=0.03, composition="additive")
    s = p["source"]
    return fr.Source(s.performance, head_motion=p["head_motion"], actor_layers=s.actor_layers), p[
        "target"
    ]


def _noisy_cross_rig():
    """The cross-rig markers (metres) with 1 mm noise: layers + residual, head motion estimated."""
    case = fr.cases.cross_rig(n_frames=120, source_kind="markers")
    s = case.source
    x = s.marker_positions() + 0.001 * np.random.default_rng(3).normal(
        size=s.marker_positions().shape
    )
    perf = fr.MarkerSequence(
        x, names=s.performance.names, reference=s.marker_reference(), fps=s.fps
    )
    return fr.Source(perf, actor_layers=s.actor_layers), case.target


def energies(source, target, levels=LEVELS):
    return [
        _second_difference_energy(
            LayersRetargeter(smoothing=lam).fit(source, target).retarget(source).local_vertices
        )
        for lam in levels
    ]


def smoothing_smooths(values) -> bool:
    """Second-difference energy strictly falling as the smoothing rises, by a clear margin overall."""
    return all(b < a for a, b in zip(values, values[1:])) and values[-1] < 0.5 * values[0]


@pytest.mark.parametrize(
    "make", [_noisy_layers_problem, _noisy_cross_rig], ids=["layers", "cross-rig+residual"]
)
def test_more_smoothing_gives_smoother_output(make):
    source, target = make()
    values = energies(source, target)
    assert smoothing_smooths(values), values


def test_the_check_fails_when_the_smoothing_term_is_dropped(monkeypatch):
    """Mutant: the solver ignores its smoothing weight (the term of Eq. 7 dropped)."""
    real = solver.extract

    def no_smoothing(*args, **kwargs):
        kwargs["smoothing"] = 0.0
        return real(*args, **kwargs)

    monkeypatch.setattr(solver, "extract", no_smoothing)
    source, target = _noisy_layers_problem()
    assert not smoothing_smooths(energies(source, target))


def _per_frame(retargeter, source):
    """Each frame retargeted alone (a one-frame source)."""
    perf = source.performance
    frames = []
    for f in range(perf.n_frames):
        one = fr.MarkerSequence(
            perf.positions[f : f + 1], names=perf.names, reference=perf.reference
        )
        frames.append(
            np.asarray(
                retargeter.retarget(
                    fr.Source(
                        one,
                        head_motion=source.head_motion[f : f + 1],
                        actor_layers=source.actor_layers,
                    )
                ).vertices
            )[0]
        )
    return np.stack(frames)


def reproduces_per_frame(batch, per_frame) -> bool:
    size = np.ptp(per_frame[..., 1])
    return bool(np.abs(batch - per_frame).max() <= 1e-5 * size)


def test_no_smoothing_reproduces_the_per_frame_solution():
    source, target = _noisy_layers_problem()
    r = LayersRetargeter(smoothing=0.0).fit(source, target)
    batch = np.asarray(r.retarget(source).vertices)
    assert reproduces_per_frame(batch, _per_frame(r, source))
    # with smoothing, a frame depends on the ones before it
    r.set_params(smoothing=0.1)
    assert not reproduces_per_frame(np.asarray(r.retarget(source).vertices), _per_frame(r, source))


def test_the_per_frame_check_fails_when_zero_smoothing_still_smooths(monkeypatch):
    """Mutant: a smoothing term that stays on at smoothing = 0."""
    real = solver.extract

    def always_smoothing(*args, **kwargs):
        kwargs["smoothing"] = max(kwargs.get("smoothing", 0.0), 0.1)
        return real(*args, **kwargs)

    source, target = _noisy_layers_problem()
    r = LayersRetargeter(smoothing=0.0).fit(source, target)
    monkeypatch.setattr(solver, "extract", always_smoothing)
    assert not reproduces_per_frame(np.asarray(r.retarget(source).vertices), _per_frame(r, source))
