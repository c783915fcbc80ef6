"""Unit invariance of both retargeters of the coating plugin on a source of another topology
(issue 14, item 1): the kit's check on the cross-topology pair, where the target is resampled
in the source's topology (faceretarget.correspond.resample_to_topology).

Before the correspondence was made similarity-invariant: 5.1e-6 (deformation_transfer,
target x0.01) and 5.9e-6 (coating) of the face height, above the kit's 1e-6.
"""

import warnings

import pytest

from faceretarget import cases
from faceretarget.errors import CorrespondenceWarning
from faceretarget.plugins.coating.retargeter import CoatingRetargeter, DeformationTransferRetargeter
from faceretarget.testing import check_unit_invariance


@pytest.fixture(scope="module")
def case():
    return cases.cross_topology(n_frames=8)


@pytest.mark.parametrize(
    "retargeter",
    [DeformationTransferRetargeter(), CoatingRetargeter()],
    ids=["deformation_transfer", "coating"],
)
def test_cross_topology_result_does_not_depend_on_units_or_placement(retargeter, case):
    with warnings.catch_warnings():
        warnings.simplefilter(
            "error", CorrespondenceWarning
        )  # and every scaled fit is as good as the original
        check_unit_invariance(retargeter, case)
