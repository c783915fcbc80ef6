"""The cross-topology resampling does not depend on units or placement (issue 14, item 1).

Before: scaling the target by 0.01 moved the resampled vertices by 2e-4 of the face height
on average (6e-3 at worst; x100: 1e-4), a rigid move by as much: a closest point on a crease
edge took the face normal of whichever adjacent triangle the search returned, so rounding
flipped accept / reject decisions, and the ICP amplified them; the landmark warp took
distances as |a|^2 + |b|^2 - 2 a.b (rounding ~sqrt(eps) near a landmark) with an absolute
ridge. Now both faces are fitted in one canonical frame and every decision is continuous.
"""

import numpy as np
import pytest

from faceretarget import cases
from faceretarget.correspond import rbf_warp, resample_to_topology
from faceretarget.model import Mesh

#: Agreement asked of the resampled vertices, relative to the face height (measured: ~5e-15).
TOL = 1e-9


def _rotation(axis, degrees):
    a = np.asarray(axis, dtype=np.float64)
    a = a / np.linalg.norm(a)
    k = np.array([[0.0, -a[2], a[1]], [a[2], 0.0, -a[0]], [-a[1], a[0], 0.0]])
    t = np.deg2rad(degrees)
    return np.eye(3) + np.sin(t) * k + (1.0 - np.cos(t)) * (k @ k)


@pytest.fixture(scope="module")
def pair():
    case = cases.cross_topology(n_frames=2)
    src, tgt = case.source.performance.reference, case.target.neutral
    base = resample_to_topology(src, case.source.landmarks, tgt, case.target.landmarks, check=False)
    return case, base


def _moves(centre, height):
    rotation = _rotation([0.3, 1.0, 0.2], 25.0)
    shift = np.array([1.0, -2.0, 0.5]) * height
    out = [
        (
            f"x{s:g}",
            lambda v, s=s: (v - centre) * s + centre,
            lambda v, s=s: (v - centre) / s + centre,
        )
        for s in (0.01, 100.0, 1000.0)
    ]
    out.append(("rigid", lambda v: v @ rotation.T + shift, lambda v: (v - shift) @ rotation))
    return out


def _agree(label, got, want, report, base_report, height):
    err = np.linalg.norm(got - want, axis=1).max() / height
    assert err < TOL, f"{label}: resampled vertices differ by {err:.3g} of the face height"
    assert np.array_equal(report.details["matched"], base_report.details["matched"]), label
    assert (
        report.rejected == base_report.rejected
        and report.flipped_triangles == base_report.flipped_triangles
    ), label
    for key in ("residual_mean", "landmark_error"):
        assert getattr(report, key) == pytest.approx(
            getattr(base_report, key), rel=1e-6, abs=1e-12
        ), (label, key)


def test_target_in_other_units_or_placement_gives_the_same_resampling(pair):
    case, (base, base_report) = pair
    src, tgt = case.source.performance.reference, case.target.neutral
    height = tgt.height
    centre = np.asarray(tgt.vertices).mean(axis=0)
    for label, forward, back in _moves(centre, height):
        moved = Mesh(forward(np.asarray(tgt.vertices)), tgt.triangles)
        mesh, report = resample_to_topology(
            src, case.source.landmarks, moved, case.target.landmarks, check=False
        )
        # in the target's own (moved) units, then mapped back: the same surface points
        _agree(
            f"target {label}",
            back(np.asarray(mesh.vertices)),
            np.asarray(base.vertices),
            report,
            base_report,
            height,
        )
        # the report's lengths follow the target's units
        scale = np.linalg.norm(forward(np.ones((1, 3))) - forward(np.zeros((1, 3)))) / np.sqrt(3.0)
        assert report.scale == pytest.approx(base_report.scale * scale, rel=1e-9)


def test_source_in_other_units_or_placement_gives_the_same_resampling(pair):
    case, (base, base_report) = pair
    src, tgt = case.source.performance.reference, case.target.neutral
    centre = np.asarray(src.vertices).mean(axis=0)
    for label, forward, _ in _moves(centre, src.height):
        moved = Mesh(forward(np.asarray(src.vertices)), src.triangles)
        mesh, report = resample_to_topology(
            moved, case.source.landmarks, tgt, case.target.landmarks, check=False
        )
        _agree(
            f"source {label}",
            np.asarray(mesh.vertices),
            np.asarray(base.vertices),
            report,
            base_report,
            tgt.height,
        )


def test_rbf_warp_commutes_with_similarities():
    rng = np.random.default_rng(3)
    src = rng.normal(size=(30, 3))
    tgt = src + 0.2 * rng.normal(size=(30, 3))
    # points on and next to the landmarks, where |a|^2 + |b|^2 - 2 a.b loses half the digits
    points = np.concatenate(
        [src, src + 1e-7 * rng.normal(size=src.shape), rng.normal(size=(50, 3))]
    )
    base = rbf_warp(src, tgt)(points)
    assert np.abs(base[:30] - tgt).max() < 1e-6
    rotation = _rotation([1.0, 0.2, -0.4], 70.0)
    for s in (1e-3, 1e3):
        moved_src = s * src @ rotation.T + 5.0
        got = rbf_warp(moved_src, tgt)(s * points @ rotation.T + 5.0)
        assert np.abs(got - base).max() < 1e-9
        got = rbf_warp(src, s * tgt @ rotation.T - 2.0)(points)
        assert np.abs((got + 2.0) @ rotation / s - base).max() < 1e-9
