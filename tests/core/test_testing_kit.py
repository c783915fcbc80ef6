"""The conformance kit catches each broken invariant (a kit that cannot fail is no kit)."""

import numpy as np
import pytest

import faceretarget as fr
from faceretarget import testing
from faceretarget.geometry import procrustes


class Good(fr.Retargeter):
    """Rigid-aware 'neutral' retargeter: copies the target neutral, carries head motion."""

    name = "good"
    capabilities = fr.Capabilities(
        sources=("mesh", "markers"), needs=("landmarks", "source_landmarks")
    )

    def __init__(self, *, gain=1.0):
        self.gain = gain

    def _fit(self, source, target):
        self.neutral_ = np.array(target.neutral.vertices)
        self.reference_ = np.array(source.marker_reference())
        # source frame -> target frame (similarity through the landmarks): head motion is
        # carried in the target's units and frame, whatever the source's
        at_target = target.landmarks.positions(target.neutral.vertices, target.neutral.triangles)
        rot, trans, scale = procrustes.fit_rigid(self.reference_, at_target[None], scale=True)
        self.to_target_ = procrustes.to_matrix(rot, trans, scale)[0]

    def _motion(self, source):
        rot, trans, _ = procrustes.fit_rigid(self.reference_, source.marker_positions())
        motion = procrustes.to_matrix(rot, trans)
        return self.to_target_ @ motion @ np.linalg.inv(self.to_target_)

    def _retarget(self, source):
        motion = self._motion(source)
        frames = procrustes.apply(motion, self.neutral_)
        return fr.Animation(vertices=frames, head_motion=motion)


class MutatesInput(Good):
    name = "mutates"

    def _fit(self, source, target):
        super()._fit(source, target)
        np.asarray(target.neutral.vertices).flags  # noqa: B018 -- reading is fine...
        target.neutral.__dict__.setdefault("note", np.zeros(1))
        target.feature_lines["added"] = np.array([0, 1])  # ...changing an input is not


class Noisy(Good):
    name = "noisy"

    def _retarget(self, source):
        anim = super()._retarget(source)
        return fr.Animation(
            vertices=anim.vertices
            + np.random.default_rng().normal(scale=1e-9, size=anim.vertices.shape)
        )


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
    capabilities = fr.Capabilities(
        sources=("mesh", "markers"), needs=("landmarks",), outputs="weights"
    )


class ClaimsStream(Good):
    name = "claimsstream"
    capabilities = fr.Capabilities(sources=("mesh", "markers"), needs=("landmarks",), stream=True)

    def stream(self, frames):
        for _f in frames:
            yield self.neutral_


class SourceUnits(Good):
    """Carries source displacements to the target unscaled (a detail scale from absolute sizes)."""

    name = "sourceunits"

    def _retarget(self, source):
        anim = super()._retarget(source)
        moved = source.marker_positions() - self.reference_
        return fr.Animation(
            vertices=np.asarray(anim.vertices) + moved.mean(axis=1, keepdims=True),
            head_motion=anim.head_motion,
        )


class WorldFrame(Good):
    """Returns the target neutral shifted to the source's centroid (a frame mix-up)."""

    name = "worldframe"

    def _retarget(self, source):
        anim = super()._retarget(source)
        shift = self.reference_.mean(axis=0) - self.neutral_.mean(axis=0)
        return fr.Animation(
            vertices=np.asarray(anim.vertices) + 1e-3 * shift, head_motion=anim.head_motion
        )


class SameTopologyOnly(Good):
    """Maps source vertex i to target vertex i: the neutral comes out wrong on another topology."""

    name = "sametopology"

    def _retarget(self, source):
        anim = super()._retarget(source)
        out = np.array(anim.vertices)
        if source.kind == "mesh":
            ref = np.asarray(source.performance.reference.vertices)
            n = min(len(ref), out.shape[1])
            out[:, :n] += 0.01 * (ref[:n] - self.neutral_[:n])
        return fr.Animation(vertices=out, head_motion=anim.head_motion)


class HiddenNeed(Good):
    """Declares no source landmarks but needs them when the topologies differ (and says so only in fit)."""

    name = "hiddenneed"
    capabilities = fr.Capabilities(sources=("mesh",), needs=("landmarks",))

    def _fit(self, source, target):
        if source.landmarks is None:
            raise fr.errors.CapabilityError(
                "hiddenneed: needs landmarks on a source of another topology"
            )
        super()._fit(source, target)


class DeclaredConditionalNeed(HiddenNeed):
    """The same need, stated by why_not: passes."""

    name = "conditionalneed"

    @classmethod
    def why_not(cls, source, target):
        reason = super().why_not(source, target)
        if (
            reason is None
            and target is not None
            and source.kind == "mesh"
            and source.landmarks is None
        ):
            return "conditionalneed needs a Source with landmarks"
        return reason


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
        (SourceUnits, testing.check_unit_invariance),
        (WorldFrame, testing.check_unit_invariance),
        (SameTopologyOnly, testing.check_cross_topology_neutral),
        (HiddenNeed, testing.check_declared_needs),
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


def test_new_checks_pass_a_correct_retargeter():
    """The broken retargeters above fail for their defect only: the same code done right passes."""
    case = testing.tiny_case()
    testing.check_unit_invariance(Good, case)
    testing.check_cross_topology_neutral(Good, case)
    testing.check_declared_needs(DeclaredConditionalNeed, case)


def test_unit_check_reports_the_move_and_size():
    with pytest.raises(
        AssertionError, match=r"source x0\.01: result differs by [0-9.e-]+ of the face height"
    ):
        testing.check_unit_invariance(SourceUnits, testing.tiny_case())


def test_cross_topology_case_differs_in_topology():
    case = testing.tiny_cross_topology_case()
    src, tgt = case.source.performance.reference, case.target.neutral
    assert src.n_vertices != tgt.n_vertices and case.source.n_frames == 6
    assert (
        len(fr.correspond.boundary_loops(src.triangles))
        == 1
        < len(fr.correspond.boundary_loops(tgt.triangles))
    )


def test_declared_needs_names_the_variant():
    with pytest.raises(AssertionError, match="other topology, source without landmarks"):
        testing.check_declared_needs(HiddenNeed, testing.tiny_case())
