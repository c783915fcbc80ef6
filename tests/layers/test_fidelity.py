"""Fidelity on the built-in synthetic case with default parameters (the acceptance bound is 5%)."""
import numpy as np
import pytest

import faceretarget as fr
from faceretarget.plugins.layers.retargeter import LayersRetargeter


def _error(anim, case):
    got, want = np.asarray(anim.vertices), np.asarray(case.truth.vertices)
    return np.sqrt(np.mean(np.sum((got - want) ** 2, axis=-1))) / np.ptp(want[0][:, 1])


@pytest.mark.parametrize("target", ["human", "stylized"])
def test_synthetic_case_within_bound(target):
    case = fr.cases.synthetic(resolution=800, n_frames=60, target=target)
    anim = fr.get("layers").fit(case.source, case.target).retarget(case.source)
    assert _error(anim, case) < 0.01  # 5x under the acceptance bound


def test_stable_point_procrustes_beats_plain_on_the_case():
    case = fr.cases.synthetic(resolution=800, n_frames=60)
    stable = LayersRetargeter().fit(case.source, case.target).retarget(case.source)
    plain = LayersRetargeter(rigid_points="all").fit(case.source, case.target).retarget(case.source)
    assert _error(stable, case) < _error(plain, case)
    truth = case.meta["head_motion"]
    assert np.abs(stable.head_motion - truth).max() < np.abs(plain.head_motion - truth).max()
