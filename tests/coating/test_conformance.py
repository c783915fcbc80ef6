"""Both retargeters of the coating plugin pass the conformance kit."""

from faceretarget.plugins.coating.retargeter import CoatingRetargeter, DeformationTransferRetargeter
from faceretarget.testing import parametrize_with_checks


@parametrize_with_checks([CoatingRetargeter(), DeformationTransferRetargeter()])
def test_conformance(retargeter, check):
    check(retargeter)
