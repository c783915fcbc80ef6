"""The conformance kit of faceretarget.testing on the normalmesh retargeter."""

from faceretarget.plugins.normalmesh.retargeter import NormalMeshRetargeter
from faceretarget.testing import check_retargeter


def test_conformance():
    check_retargeter(NormalMeshRetargeter)
