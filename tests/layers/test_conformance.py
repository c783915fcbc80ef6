"""The layers retargeter passes the conformance kit, through the registry and as a class."""

import faceretarget as fr
from faceretarget.plugins.layers.retargeter import LayersRetargeter
from faceretarget.testing import check_retargeter


def test_conformance_kit():
    check_retargeter(LayersRetargeter)


def test_registered_under_its_name_and_aliases():
    assert type(fr.get("layers")) is LayersRetargeter
    assert type(fr.get("kholgade2011")) is LayersRetargeter
    assert fr.get("layers", smoothing=0.5).smoothing == 0.5
