"""Parameter extraction (Eq. 6-7): known parameters come back, constraints hold, SLSQP is not beaten."""

import numpy as np
import pytest
from naive.layers import frame_objective, make_problem, slsqp_frame

import faceretarget as fr
from faceretarget.plugins.layers.retargeter import LayersRetargeter
from faceretarget.plugins.layers.solver import observe, uniform_state


def _known_motion(problem):
    s = problem["source"]
    return fr.Source(
        s.performance,
        head_motion=problem["head_motion"],
        actor_layers=s.actor_layers,
        tracks2d=s.tracks2d,
        actor_layers_2d=s.actor_layers_2d,
    )


def _rel_error(anim, problem):
    height = np.ptp(problem["target"].neutral.vertices[:, 1])
    return (
        np.sqrt(np.mean(np.sum((np.asarray(anim.vertices) - problem["truth"]) ** 2, axis=-1)))
        / height
    )


@pytest.mark.parametrize("soft", [True, False])
def test_known_parameters_are_deconstructed_and_transferred(soft):
    """Actor frames made from known (w, alpha): the character equals the one the known values drive."""
    problem = make_problem(0, soft=soft)
    source = _known_motion(problem)
    anim = (
        LayersRetargeter(smoothing=0.0, lip_sigma=0.0, tol=1e-12)
        .fit(source, problem["target"])
        .retarget(source)
    )
    assert _rel_error(anim, problem) < 1e-5
    # the actor is explained to rounding: the model is exact for these frames
    deco = (
        LayersRetargeter(smoothing=0.0, lip_sigma=0.0, tol=1e-12)
        .fit(source, problem["target"])
        .deconstruct(source)
    )
    assert deco["rms_error"].max() < 1e-5 * np.ptp(problem["actor_local"][0][:, 1])


def test_defaults_with_estimated_head_motion_stay_close():
    """Head motion by weighted Procrustes (biased by expression, sec. 7) and default smoothing/bias."""
    problem = make_problem(1, noise=0.005)
    anim = LayersRetargeter().fit(problem["source"], problem["target"]).retarget(problem["source"])
    assert _rel_error(anim, problem) < 0.01


@pytest.mark.parametrize("composition", ["additive", "convex"])
@pytest.mark.parametrize("kwargs", [{}, {"n_tracks": 12}, {"noise": 0.02}])
def test_constraints_hold_on_every_frame(kwargs, composition):
    problem = make_problem(2, composition=composition, **kwargs)
    anim = (
        LayersRetargeter(composition=composition)
        .fit(problem["source"], problem["target"])
        .retarget(problem["source"])
    )
    w = anim.extras["layer_weights"]
    assert (w >= 0).all()
    if composition == "convex":  # the paper: each region's layer weights sum to 1
        np.testing.assert_allclose(w.sum(axis=2), 1.0, rtol=0, atol=1e-13)
    else:  # additive: each weight in [0, 1] on its own
        assert w.max() <= 1.0 and w.sum(axis=2).max() > 1.2
    for coeffs in anim.extras["coefficients"].values():
        assert (coeffs >= 0).all()
        np.testing.assert_allclose(coeffs.sum(axis=1), 1.0, rtol=0, atol=1e-13)
    # the identifiable products w_jl * alpha_jk are in the outputs
    for j, (layer, coeffs) in enumerate(anim.extras["coefficients"].items()):
        np.testing.assert_array_equal(
            anim.extras["weighted_coefficients"][layer], w[:, :, j, None] * coeffs[:, None, :]
        )


@pytest.mark.parametrize(
    "case, composition, projected",
    [
        ("plain", "additive", False),
        ("missing", "additive", False),
        ("tracks", "additive", False),
        ("plain", "convex", False),
        ("missing", "convex", False),
        ("tracks", "convex", False),
        ("plain", "additive", True),
        ("missing", "additive", True),
        ("tracks", "additive", True),
    ],
)
def test_objective_at_or_below_slsqp_reference(case, composition, projected):
    """Each frame, from the same previous state: our objective <= SLSQP's (scipy, full coordinates).

    ``projected``: the solve of an estimated alignment, whose data term is measured modulo
    the alignment's small motions (3D rigid, 2D similarity): the reference projects the
    residual off those motions in the full coordinates.
    """
    kwargs = {"n_tracks": 10} if case == "tracks" else {}
    problem = make_problem(3, n_markers=30, sizes=(4, 3, 2), n_frames=6, noise=0.02, **kwargs)
    source = problem["source"]
    if case == "missing":
        pos = np.array(source.performance.positions)
        pos[2, 5:12] = np.nan
        pos[4, [1, 20]] = np.nan  # a lip marker too: no bias on that frame
        source = fr.Source(
            fr.MarkerSequence(
                pos, names=source.performance.names, reference=source.performance.reference
            ),
            actor_layers=source.actor_layers,
        )
    r = LayersRetargeter(smoothing=0.05, lip_sigma=0.5, tol=1e-12, composition=composition).fit(
        source, problem["target"]
    )
    actor, lip = r.actor_, r.lip_
    markers, tracks, _, _ = r._inputs(source)
    rigid = actor.rigid_projection(True, actor.n2 > 0) if projected else None
    obs = observe(
        actor, lip, markers, tracks, None, rigid_points=r.rigid_points, keep_xhat=True, rigid=rigid
    )
    params, _ = r._extract(obs, rigid=rigid)
    basis, masks = actor.basis_t.T, actor.coord_masks
    gamma = params.gamma
    assert gamma.max() > 0.05  # the bias is active on some frames
    additive = composition == "additive"
    c_d = (1 - gamma) / obs.n_valid
    w_prev, a_prev = uniform_state(actor, additive)
    jac = None if rigid is None else rigid.jac
    for t in range(obs.g.shape[0]):
        c_s = r.smoothing if t else 0.0
        valid = ~obs.missing[t]
        ours = frame_objective(
            obs.xhat[t],
            valid,
            basis,
            masks,
            actor.layer_of,
            params.weights[t],
            params.coefficients[t],
            c_d[t],
            gamma[t],
            c_s,
            lip.mouth,
            lip.speech,
            lip.closed,
            w_prev,
            a_prev,
            additive,
            jac,
        )
        np.testing.assert_allclose(
            params.objective[t], ours, rtol=1e-8, atol=1e-14
        )  # reduced form == full form
        _, _, ref = slsqp_frame(
            obs.xhat[t],
            valid,
            basis,
            masks,
            actor.layer_of,
            c_d[t],
            gamma[t],
            c_s,
            lip.mouth,
            lip.speech,
            lip.closed,
            w_prev,
            a_prev,
            w_prev,
            a_prev,
            additive,
            jac,
        )
        assert ours <= ref * (1 + 1e-6) + 1e-12, f"frame {t}: {ours} > SLSQP {ref}"
        w_prev, a_prev = params.weights[t], params.coefficients[t]


def test_layered_model_beats_single_layers():
    """Fig. 8: the layered reconstruction error is below emotion-only, speech-only and blink-only."""
    problem = make_problem(4, n_frames=30)
    source = _known_motion(problem)
    target = problem["target"]

    def error(actor_layers, char_layers):
        src = fr.Source(
            source.performance, head_motion=source.head_motion, actor_layers=actor_layers
        )
        tgt = fr.TargetRig(target.neutral, layers=char_layers)
        return (
            LayersRetargeter(smoothing=0.0, lip_sigma=0.0)
            .fit(src, tgt)
            .deconstruct(src)["rms_error"]
            .mean()
        )

    full = error(source.actor_layers, target.layers)
    for name in source.actor_layers.layer_names:
        single = error(
            fr.LayeredRig({name: source.actor_layers.layers[name]}, source.actor_layers.masks),
            fr.LayeredRig({name: target.layers.layers[name]}, target.layers.masks),
        )
        assert full < 0.5 * single, f"layered {full} vs {name}-only {single}"
