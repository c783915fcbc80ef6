"""The spacetime retargeter and its per-frame baselines pass the conformance kit."""

from faceretarget.plugins.spacetime.retargeter import RETARGETERS
from faceretarget.testing import parametrize_with_checks


@parametrize_with_checks(RETARGETERS)
def test_conformance(retargeter, check):
    check(retargeter)
