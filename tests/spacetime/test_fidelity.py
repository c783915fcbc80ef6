"""Default spacetime against per-frame fits on the cross-rig case (different identity,
topology, units and shape meanings; sparse held weights; no head motion).

Measured when written (300 frames, RMS % of face height): bounded per-frame [0, 1] 0.244,
unconstrained per-frame 0.266, default spacetime on markers 0.175 (0.243 without examples),
on the dense mesh 0.161. Bounds below leave room for noise, not for a regression to the
baselines."""

import numpy as np
import pytest

import faceretarget as fr


@pytest.fixture(scope="module")
def cases():
    return {
        kind: fr.cases.cross_rig(n_frames=300, source_kind=kind) for kind in ("markers", "mesh")
    }


def errors(case, name, **params):
    anim = fr.get(name, **params).fit(case.source, case.target).retarget(case.source)
    got, want = np.asarray(anim.vertices), np.asarray(case.truth.vertices)
    height = np.ptp(want[0][:, 1])
    rms = np.sqrt(np.mean(np.sum((got - want) ** 2, axis=-1))) / height
    vel = (
        np.sqrt(np.mean(np.sum((np.diff(got, axis=0) - np.diff(want, axis=0)) ** 2, axis=-1)))
        / height
    )
    return rms, vel, anim


@pytest.fixture(scope="module")
def bounded_pf(cases):
    return errors(cases["markers"], "spacetime_rangepf", lower=0.0, upper=1.0)


def test_markers_beat_the_bounded_per_frame_fit(cases, bounded_pf):
    rms, vel, anim = errors(cases["markers"], "spacetime")
    assert rms < 0.9 * bounded_pf[0], (rms, bounded_pf[0])
    assert vel < bounded_pf[1], (vel, bounded_pf[1])
    assert anim.provenance["diagnostics"]["fraction_outside_bounds"] < 0.01
    assert anim.provenance["diagnostics"]["examples"]


def test_dense_source_beats_the_bounded_per_frame_fit_on_markers(cases, bounded_pf):
    rms, vel, anim = errors(cases["mesh"], "spacetime")
    assert anim.provenance["diagnostics"]["samples"] == "dense"
    assert rms < 0.75 * bounded_pf[0], (rms, bounded_pf[0])
    assert vel < bounded_pf[1]


@pytest.mark.parametrize("change", [dict(example_weight=0.0), dict(bounds=None)])
def test_each_ingredient_lowers_the_error(cases, change):
    """Dropping the examples or the bounds raises the error (each is doing work)."""
    full = errors(cases["markers"], "spacetime")[0]
    without = errors(cases["markers"], "spacetime", **change)[0]
    assert without > 1.05 * full, (change, full, without)


def test_no_head_motion_is_invented(cases):
    anim = (
        fr.get("spacetime")
        .fit(cases["markers"].source, cases["markers"].target)
        .retarget(cases["markers"].source)
    )
    rot = np.asarray(anim.head_motion)[:, :3, :3]
    angle = np.degrees(np.arccos(np.clip((np.trace(rot, axis1=1, axis2=2) - 1) / 2, -1, 1)))
    assert angle.max() < 0.05


def test_head_motion_carried_across_units(cases):
    """Source in metres with head motion onto a target in centimetres: the head's translation
    is converted to the target's unit (it was applied in metres: 1.1-6.8% error)."""
    moving = fr.cases.cross_rig(n_frames=120, head_motion=True, source_kind="markers")
    still = fr.cases.cross_rig(n_frames=120, source_kind="markers")
    with_motion = errors(moving, "spacetime")[0]
    without = errors(still, "spacetime")[0]
    assert with_motion < 1.15 * without, (with_motion, without)
