"""Fig. 7 and fig. 11 of Seol et al. 2012 against Prior PF, starting from the same alpha.

The paper's setting: a target of other proportions (the synthetic stylized face: No Const's
weights leave [-0.5, 1.5] in many frames), markers with optical-capture noise (0.3 mm per
coordinate on a face of 60 mm RMS radius), head motion by per-frame Procrustes (sec. 3.1, computed
here and given to the methods), the PCA prior
of all target blendshapes about their mean (Eq. 3), the paper-exact solver settings
(``naive.spacetime_paper.PAPER``: no bounds, no Sobolev/L1 term, RBF scale-proportion matching).

What the paper claims, and what these tests check:

- fig. 7 (d) vs (e): at the *same* alpha = 0.5, the per-frame prior does not prevent artifacts
  while the prior in the velocity domain "overly restricts animation (the eyes are not
  closed)"; (f): with alpha = 0.01 movement matching reflects the source (the eyes close).
- fig. 8 / 11: the prior in the velocity domain reproduces the source movement with little
  velocity error, the per-frame prior does not. Since the same alpha is a stronger constraint in
  the velocity domain (fig. 7 (e)), the fair comparison raises Prior PF's alpha from the same
  value until its prior energy is no larger than movement matching's (the paper chose each
  method's alpha for the same weight range), and then compares the velocity errors.

Both checks must fail for movement matching replaced by per-frame solves (tested below by
monkeypatching the solver). The order of the velocity errors *at* equal alpha is not a claim
of the paper, and in this setting it is the other way round (strict xfail, with the numbers).
"""

import numpy as np
import pytest
from naive import spacetime as naive
from naive.spacetime_paper import paper

import faceretarget as fr
from faceretarget.plugins.spacetime import retargeter as retargeter_module
from faceretarget.plugins.spacetime import solver

#: The paper's choices beyond naive.spacetime_paper.PAPER (Eq. 3 as printed, sec. 7).
SETTING = dict(prior_center="mean", lower=-0.5, upper=1.5)
#: Optical-capture noise: 0.3 mm per coordinate on a face of 60 mm RMS radius.
NOISE = 0.3 / 60.0


def optical_markers(case, seed=0):
    x = np.asarray(case.source.marker_positions(), dtype=np.float64)
    ref = np.asarray(case.source.marker_reference(), dtype=np.float64)
    sigma = NOISE * np.sqrt(np.mean(np.sum((ref - ref.mean(axis=0)) ** 2, axis=1)))
    x = x + sigma * np.random.default_rng(seed).normal(size=x.shape)
    motion = np.tile(
        np.eye(4), (len(x), 1, 1)
    )  # sec. 3.1: Procrustes of each frame against the neutral
    for f, frame in enumerate(x):
        motion[f, :3, :3] = rot = naive.procrustes_rotation(ref, frame)
        motion[f, :3, 3] = frame.mean(axis=0) - rot @ ref.mean(axis=0)
    return fr.Source(
        fr.MarkerSequence(x, names=case.source.landmarks.names, reference=ref, fps=case.source.fps),
        head_motion=motion,
    )


@pytest.fixture(scope="module")
def setting():
    case = fr.cases.synthetic(resolution=600, n_frames=90, target="stylized")
    return optical_markers(case), case.target


def run(name, alpha, source, target):
    r = paper(name, alpha=alpha, **SETTING).fit(source, target)
    anim = r.retarget(source)
    diag = anim.provenance["diagnostics"]
    return {
        "velocity": diag["velocity_error"],
        "prior": float(r.prior_.energy(anim.weights).sum()),
        "weights": anim.weights,
        "in_range": diag["fraction_in_range"],
        "names": r.rig_.names,
    }


def eyes_closed(result) -> float:
    """Mean over the blink shapes of each one's largest weight (1 = the eyes close fully)."""
    cols = [i for i, n in enumerate(result["names"]) if "blink" in n.lower()]
    assert cols, result["names"]
    return float(np.mean(result["weights"][:, cols].max(axis=0)))


def check_fig7(source, target):
    """Fig. 7: at equal alpha the velocity-domain prior restricts more than the per-frame prior."""
    pf, mm = run("spacetime_priorpf", 0.5, source, target), run("spacetime", 0.5, source, target)
    small = run("spacetime", 0.01, source, target)
    assert mm["prior"] < 0.5 * pf["prior"], (
        mm["prior"],
        pf["prior"],
    )  # (e) restricts more than (d)
    assert eyes_closed(mm) < 0.8 * eyes_closed(pf), (
        eyes_closed(mm),
        eyes_closed(pf),
    )  # (e): "the eyes are not closed"
    assert eyes_closed(mm) < 0.6
    assert eyes_closed(small) > 0.85, eyes_closed(small)  # (f): alpha = 0.01 reflects the source


def check_fig11(source, target, alpha=0.01):
    """Fig. 8 / 11: from the same alpha, Prior PF needs a larger alpha to constrain as much, and then
    adds far more velocity error than movement matching does."""
    base = run("spacetime_noconst", alpha, source, target)["velocity"]
    mm = run("spacetime", alpha, source, target)
    pf = run("spacetime_priorpf", alpha, source, target)
    assert mm["prior"] < pf["prior"], (
        mm["prior"],
        pf["prior"],
    )  # the same alpha constrains more in the velocity domain
    pf_alpha = alpha
    while pf["prior"] > mm["prior"] and pf_alpha < 1e3:
        pf_alpha *= np.sqrt(10.0)
        pf = run("spacetime_priorpf", pf_alpha, source, target)
    assert pf["prior"] <= mm["prior"], "Prior PF never reached movement matching's prior energy"
    added_mm, added_pf = mm["velocity"] - base, pf["velocity"] - base
    assert added_mm < 0.5 * added_pf, (added_mm, added_pf, pf_alpha)
    return added_mm, added_pf, pf_alpha


def test_setting_is_the_papers(setting):
    """The range constraint binds: No Const's weights leave [-0.5, 1.5] in many frames."""
    source, target = setting
    assert run("spacetime_noconst", 0.01, source, target)["in_range"] < 0.95


def test_fig7_velocity_domain_prior_restricts_more_at_equal_alpha(setting):
    check_fig7(*setting)


def test_fig11_movement_matching_beats_prior_pf_from_equal_alpha(setting):
    added_mm, added_pf, pf_alpha = check_fig11(*setting)
    assert pf_alpha > 0.01  # Prior PF had to be made stronger to constrain as much


@pytest.mark.xfail(
    strict=True,
    reason=(
        "measured: at the same alpha = 0.01 in the paper's setting, movement matching adds more velocity error "
        "over No Const than Prior PF (0.18 vs 0.11 on this case), because the same alpha constrains more in "
        "the velocity domain (prior energy 3.9e3 vs 1.5e4; Prior PF reaches 3.9e3 near alpha = 0.3 and then adds 1.5). The paper compares at alphas chosen for the same "
        "weight range (0.01 vs 0.5), not at equal alpha; see test_fig11_movement_matching_beats_prior_pf_from_equal_alpha."
    ),
)
def test_equal_alpha_velocity_error_order(setting):
    source, target = setting
    base = run("spacetime_noconst", 0.01, source, target)["velocity"]
    mm, pf = run("spacetime", 0.01, source, target), run("spacetime_priorpf", 0.01, source, target)
    assert mm["velocity"] - base < pf["velocity"] - base


def per_frame_instead_of_movement(
    system, deltas, known, known_weights, frame_weights=None, terms=None
):
    """The mutant: movement matching replaced by independent per-frame solves with the prior
    (``terms`` left empty: the retargeter computes the energies of these weights)."""
    w = solver.solve_per_frame(system, deltas, use_prior=True)
    w[known] = np.asarray(known_weights)[known]
    return w


@pytest.mark.parametrize("check", [check_fig7, check_fig11])
def test_the_checks_fail_when_movement_matching_is_per_frame(setting, monkeypatch, check):
    source, target = setting
    monkeypatch.setattr(retargeter_module, "solve_movement", per_frame_instead_of_movement)
    mutant = run("spacetime", 0.5, source, target)
    same = run("spacetime_priorpf", 0.5, source, target)
    np.testing.assert_allclose(
        mutant["weights"], same["weights"], atol=1e-9
    )  # the mutant is in place
    with pytest.raises(AssertionError):
        check(source, target)
