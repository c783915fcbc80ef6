"""Cross-topology correspondence that is right or says so (issue 14): a closed-eye head with a
mouth bag and another outline onto the open-eye ICT face."""

import warnings

import numpy as np
import pytest

from faceretarget import Landmarks, cases, config
from faceretarget.correspond import QualityReport, resample_to_topology
from faceretarget.errors import CorrespondenceError, CorrespondenceWarning


@pytest.fixture(scope="module")
def case():
    return cases.cross_topology(n_frames=2)


@pytest.fixture(scope="module")
def fit(case):
    src, tgt = case.source.performance.reference, case.target.neutral
    with warnings.catch_warnings():
        warnings.simplefilter("error", CorrespondenceWarning)  # a good fit warns about nothing
        return resample_to_topology(src, case.source.landmarks, tgt, case.target.landmarks)


def test_no_flipped_triangle_on_the_face_interior(case, fit):
    mesh, report = fit
    assert report.flipped_triangles == 0
    assert report.details["interior_triangles"] > 0.6 * mesh.n_triangles
    # parts with no counterpart are not matched: most of the mouth bag and the skirt
    region = case.meta["source_region"]
    matched = report.details["matched"]
    assert matched[region == 0].mean() > 0.9
    assert matched[region == 2].mean() < 0.5 and matched[region == 3].mean() < 0.5
    assert report.details["loops_paired"] == [
        -1
    ]  # the source's outline (cut, skirt) is not the target's
    assert report.problems() == []


def test_face_lands_where_it_belongs(case, fit):
    """Face vertices of the source are ICT points: the right answer is the same point on the target."""
    mesh, _ = fit
    tgt = case.target.neutral
    truth = case.meta["source_weights"] @ tgt.vertices
    face = case.meta["source_region"] == 0
    err = np.linalg.norm(mesh.vertices - truth, axis=1)[face] / tgt.height
    # before: the outline loop was pulled onto the target's (forehead cut up 4 cm, skirt onto the neck):
    # mean 1.2%, max 19% of the face height, 359 flipped triangles
    assert err.mean() < 0.008 and err.max() < 0.04, (err.mean(), err.max())


def test_matching_loops_are_still_paired():
    case = cases.synthetic(resolution=1000, target_resolution=2500, n_frames=1)
    _, report = resample_to_topology(
        case.source.performance.reference,
        case.source.landmarks,
        case.target.neutral,
        case.target.landmarks,
    )
    assert sorted(report.details["loops_paired"]) == [0, 1, 2, 3]


def _report(**details):
    base = dict(
        interior_triangles=1000,
        matched_residual_mean=0.0,
        uncovered_inner_share=0.0,
        regions={
            "flipped": {"eyes": 3, "mouth": 1},
            "landmarks": {"jaw": 2},
            "uncovered": {"forehead": 50},
            "residual": {},
        },
    )
    base.update(details)
    fields = dict(
        residual_mean=0.0,
        residual_max=0.0,
        coverage_max=0.0,
        landmark_error=0.0,
        flipped_triangles=0,
        rejected=0,
        iterations=1,
        scale=1.0,
    )
    for k in list(base):
        if k in fields:
            fields[k] = base.pop(k)
    return QualityReport(**fields, details=base)


def test_thresholds_warn_then_raise_and_name_the_regions():
    assert _report().check("m") is not None  # nothing to say
    with pytest.warns(
        CorrespondenceWarning,
        match=r"coating: .*4 triangles of the face interior.*\(eyes: 3, mouth: 1\)",
    ):
        _report(flipped_triangles=4).check("coating")
    limit = int(config.CORRESPONDENCE_FLIPPED_ERROR * 1000) + 1
    with pytest.raises(CorrespondenceError, match=r"coating: .*eyes: 3"):
        _report(flipped_triangles=limit).check("coating")
    with pytest.warns(CorrespondenceWarning, match=r"landmark.*\(jaw: 2\)"):
        _report(
            landmark_error=0.5
            * (config.CORRESPONDENCE_LANDMARK_WARN + config.CORRESPONDENCE_LANDMARK_ERROR)
        ).check()
    with pytest.raises(CorrespondenceError, match="landmark"):
        _report(landmark_error=2 * config.CORRESPONDENCE_LANDMARK_ERROR).check()
    with pytest.warns(CorrespondenceWarning, match=r"not reached.*\(forehead: 50\)"):
        _report(uncovered_inner_share=2 * config.CORRESPONDENCE_UNCOVERED_WARN).check()
    with pytest.raises(CorrespondenceError, match="not reached"):
        _report(uncovered_inner_share=0.9).check()
    with pytest.warns(CorrespondenceWarning, match="off its surface"):
        _report(matched_residual_mean=2 * config.CORRESPONDENCE_RESIDUAL_WARN).check()
    assert "problems" in _report(flipped_triangles=4).as_dict()


def test_wrong_landmarks_warn_at_the_mouth(case):
    """Lip landmarks shifted along the lips: the fit folds there, and says so."""
    src, tgt = case.source.performance.reference, case.target.neutral
    ids = case.target.landmarks.vertex_ids.copy()
    ids[48:68] = np.roll(ids[48:68], 3)
    with pytest.warns(CorrespondenceWarning, match=r"face interior.*mouth"):
        _, report = resample_to_topology(
            src, case.source.landmarks, tgt, Landmarks(ids, names=case.target.landmarks.names)
        )
    assert report.flipped_triangles > 0
    # check=False: the same report, no warning
    with warnings.catch_warnings():
        warnings.simplefilter("error", CorrespondenceWarning)
        resample_to_topology(
            src,
            case.source.landmarks,
            tgt,
            Landmarks(ids, names=case.target.landmarks.names),
            check=False,
        )
