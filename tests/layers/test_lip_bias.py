"""The lip-closure bias (sec. 4): nearly closed actor lips close the character's; open lips stay open."""

import numpy as np
import pytest
from naive.layers import make_problem

from faceretarget.plugins.layers.retargeter import LayersRetargeter

SIZES = (6, 5, 3)  # emotion, speech (pose 0 = closed lips), blink


@pytest.fixture(scope="module")
def lips():
    n_frames, K = 20, sum(SIZES)
    W = np.zeros((n_frames, 3, 3))
    W[:, 0, 0] = W[:, 1, 0] = 1.0  # upper face and eyes: emotion
    W[:, 2, 1] = 1.0  # mouth region: speech
    A = np.zeros((n_frames, K))
    A[:, 0] = 1.0  # neutral emotion
    A[:, SIZES[0] + SIZES[1]] = 1.0  # open eyes
    probe = make_problem(5, sizes=SIZES, n_frames=n_frames, weights=W, coefficients=A)
    speech = probe["actor_poses"]["speech"]
    gaps = np.linalg.norm(speech[:, 0] - speech[:, 1], axis=1)  # markers 0, 1: lip centres
    k_open, k_mid = (
        int(np.argmax(gaps)),
        int(np.argsort(gaps)[1]),
    )  # widest, and the least open viseme
    eps = np.linspace(0.02, 0.12, 10)
    A[:10, SIZES[0]] = 1.0 - eps  # nearly closed: mostly the closed viseme
    A[:10, SIZES[0] + k_mid] = eps
    A[10:, SIZES[0] + k_open] = 1.0  # wide open
    problem = make_problem(5, sizes=SIZES, n_frames=n_frames, weights=W, coefficients=A)
    uv = problem["uv_character"]
    upper = int(np.argmin(((uv - [0.0, -0.55]) ** 2).sum(axis=1)))
    lower = int(np.argmin(((uv - [0.0, -0.65]) ** 2).sum(axis=1)))
    closed = problem["character_poses"]["speech"][0]
    closed_gap = float(np.linalg.norm(closed[upper] - closed[lower]))

    def character_gap(**params):
        params.setdefault(
            "lip_sigma", 0.1
        )  # a wide bias (the default 0.02 acts on closed lips only)
        anim = (
            LayersRetargeter(**params)
            .fit(problem["source"], problem["target"])
            .retarget(problem["source"])
        )
        local = anim.local_vertices
        return np.linalg.norm(local[:, upper] - local[:, lower], axis=1), anim.extras["lip_gamma"]

    return character_gap, closed_gap


@pytest.mark.parametrize("composition, factor", [("convex", 0.3), ("additive", 0.7)])
def test_nearly_closed_lips_close_on_the_character(lips, composition, factor):
    """The paper's bias (convex) pulls the mouth's weights to (0, 1, 0) and the visemes to the
    closed one; the additive one pulls the visemes only and leaves the weights to the data (an
    emotion may stay on closed lips; a closed neutral mouth must stay neutral, not be pressed),
    so it closes a little less."""
    character_gap, closed_gap = lips
    biased, gamma = character_gap(composition=composition)
    plain, gamma_off = character_gap(lip_sigma=0.0, composition=composition)
    assert (gamma[:10] > 0.5).all() and (gamma_off == 0).all()
    excess_biased = biased[:10] - closed_gap
    excess_plain = plain[:10] - closed_gap
    assert excess_plain.mean() > 0  # without the bias the lips stay a little apart
    assert excess_biased.mean() < factor * excess_plain.mean()


def test_open_lips_are_not_closed(lips):
    character_gap, closed_gap = lips
    biased, gamma = character_gap()
    plain, _ = character_gap(lip_sigma=0.0)
    assert gamma[10:].max() < 1e-3
    opening_biased, opening_plain = biased[10:] - closed_gap, plain[10:] - closed_gap
    assert opening_plain.min() > 0.3  # wide open
    assert (
        opening_biased > 0.95 * opening_plain
    ).all()  # (smoothing carries the closed frames' path a little)


def test_bias_settings_are_found_and_reported():
    problem = make_problem(6)
    r = LayersRetargeter().fit(problem["source"], problem["target"])
    assert r.lip_.names == ("lip_upper_center", "lip_lower_center")  # by name
    assert r.actor_.region_names[r.lip_.mouth] == "region2"  # the region covering the lips
    assert r.lip_.closed == r.actor_.pose_index("speech", 0)
    # geometry finds the same pair when the names say nothing
    r2 = LayersRetargeter(lip_markers=None).fit(problem["source"], problem["target"])
    from faceretarget.plugins.layers.solver import _pick_pair

    speech = np.asarray(problem["source"].actor_layers.layers["speech"])
    anonymous = [f"p{i}" for i in range(speech.shape[1])]
    assert _pick_pair(anonymous, speech, 0, None)[:2] == (0, 1)
    assert r2.lip_.upper == 0 and r2.lip_.lower == 1
