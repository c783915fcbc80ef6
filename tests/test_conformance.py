"""Every registered retargeter (built-in and installed third-party) passes the conformance kit."""
import faceretarget as fr
from faceretarget.testing import parametrize_with_checks

RETARGETERS = [fr.info(entry["name"]).cls for entry in fr.available()]


@parametrize_with_checks(RETARGETERS)
def test_conformance(retargeter, check):
    check(retargeter)
