"""Every registered retargeter (built-in and installed third-party) passes the conformance kit.

``KNOWN`` lists the (retargeter, check) pairs that do not pass yet, each with what was
measured; they run as xfails (strict: a fix that makes one pass fails here until its entry
is removed).
"""
import pytest

import faceretarget as fr
from faceretarget.testing import parametrize_with_checks

RETARGETERS = [fr.info(entry["name"]).cls for entry in fr.available()]

KNOWN: dict[tuple[str, str], str] = {
    ("coating", "check_unit_invariance"): "1.3e-3 of face height at source x0.01; 1.6e-3 for a rigid move of the source",
    ("coating", "check_declared_needs"): "needs landmarks on both faces when topologies differ, undeclared",
    ("deformation_transfer", "check_unit_invariance"): "6.2e-4 of face height at source x0.01; 1.3e-3 for a rigid move",
    ("deformation_transfer", "check_declared_needs"): "needs landmarks on both faces when topologies differ, undeclared",
}


#: Strict once the entries above are settled; not strict while their fixes are landing.
STRICT = False


@parametrize_with_checks(RETARGETERS)
def test_conformance(retargeter, check, request):
    name = getattr(retargeter, "name", type(retargeter).__name__)
    reason = KNOWN.get((name, check.__name__))
    if reason:
        request.applymarker(pytest.mark.xfail(reason=reason, strict=STRICT))
    check(retargeter)
