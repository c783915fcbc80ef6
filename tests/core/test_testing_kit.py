"""The conformance kit catches each broken invariant (a kit that cannot fail is no kit)."""
import numpy as np
import pytest

import faceretarget as fr
from faceretarget import testing
from faceretarget.geometry import procrustes


class Good(fr.Retargeter):
    """Rigid-aware 'neutral' retargeter: copies the target neutral, carries head motion."""

    name = "good"
    capabilities = fr.Capabilities(sources=("mesh", "markers"), needs=("landmarks",))

    def __init__(self, *, gain=1.0):
        self.gain = gain

    def _fit(self, source, target):
        self.neutral_ = np.array(target.neutral.vertices)
        self.reference_ = np.array(source.marker_reference())

    def _motion(self, source):
        rot, trans, _ = procrustes.fit_rigid(self.reference_, source.marker_positions())
        return procrustes.to_matrix(rot, trans)

    def _retarget(self, source):
        motion = self._motion(source)
        frames = procrustes.apply(motion, self.neutral_)
        return fr.Animation(vertices=frames, head_motion=motion)


class MutatesInput(Good):
    name = "mutates"

    def _fit(self, source, target):
        super()._fit(source, target)
        np.asarray(target.neutral.vertices).flags  # reading is fine...
        arr = target.neutral.__dict__.setdefault("note", np.zeros(1))
        target.feature_lines["added"] = np.array([0, 1])  # ...changing an input is not


class Noisy(Good):
    name = "noisy"

    def _retarget(self, source):
        anim = super()._retarget(source)
        return fr.Animation(vertices=anim.vertices + np.random.default_rng().normal(scale=1e-9, size=anim.vertices.shape))


class IgnoresHeadMotion(Good):
    name = "nohead"

    def _retarget(self, source):
        return fr.Animation(vertices=np.repeat(self.neutral_[None], source.n_frames, axis=0))


class WrongRest(Good):
    name = "wrongrest"

    def _retarget(self, source):
        anim = super()._retarget(source)
        return fr.Animation(vertices=np.asarray(anim.vertices) * 1.1)


class StoresModified(Good):
    name = "modparams"

    def __init__(self, *, gain=1.0):
        self.gain = float(gain) * 2


class UndeclaredNeed(Good):
    name = "undeclared"

    def _fit(self, source, target):
        super()._fit(source, target)
        self.first_example_ = target.examples[0]  # uses examples without declaring them


class ClaimsWeights(Good):
    name = "claimsweights"
    capabilities = fr.Capabilities(sources=("mesh", "markers"), needs=("landmarks",), outputs="weights")


class ClaimsStream(Good):
    name = "claimsstream"
    capabilities = fr.Capabilities(sources=("mesh", "markers"), needs=("landmarks",), stream=True)

    def stream(self, frames):
        for f in frames:
            yield self.neutral_


def test_good_passes_everything():
    testing.check_retargeter(Good)


@pytest.mark.parametrize(
    "cls, check",
    [
        (MutatesInput, testing.check_inputs_unchanged),
        (Noisy, testing.check_deterministic),
        (IgnoresHeadMotion, testing.check_rigid_motion),
        (WrongRest, testing.check_rest_pose),
        (StoresModified, testing.check_params),
        (UndeclaredNeed, testing.check_capabilities),
        (ClaimsWeights, testing.check_capabilities),
        (ClaimsStream, testing.check_stream),
    ],
)
def test_each_check_catches_its_violation(cls, check):
    with pytest.raises(AssertionError):
        check(cls, testing.tiny_case())


def test_parametrize_with_checks_ids():
    mark = testing.parametrize_with_checks([Good])
    ids = [p.id for p in mark.args[1]]
    assert "good-check_rest_pose" in ids and len(ids) == len(testing.CHECKS)


def test_fixture_from_pytest_plugin(faceretarget_case):
    assert faceretarget_case.target.has("blendshapes")


class DropsFrame(Good):
    name = "dropsframe"

    def _retarget(self, source):
        return fr.Animation(vertices=super()._retarget(source).vertices[1:])


class DropsVertex(Good):
    name = "dropsvertex"

    def _retarget(self, source):
        return fr.Animation(vertices=super()._retarget(source).vertices[:, :-1])


class ReturnsArray(Good):
    name = "returnsarray"

    def _retarget(self, source):
        return super()._retarget(source).vertices


@pytest.mark.parametrize(
    "cls, message",
    [
        (DropsFrame, r"dropsframe: returned \d+ frames for a source of \d+"),
        (DropsVertex, r"dropsvertex: returned \d+ vertices per frame but the target has \d+"),
        (ReturnsArray, r"returnsarray: _retarget returned ndarray, not an Animation"),
    ],
)
def test_retarget_refuses_results_off_the_contract(cls, message):
    """Library callers get the shape check too, not only compare/batch/run."""
    case = testing.tiny_case()
    retargeter = cls().fit(case.source, case.target)
    with pytest.raises(fr.errors.PluginOutputError, match=message):
        retargeter.retarget(case.source)
