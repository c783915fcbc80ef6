"""Head motion from markers (geometry.head_motion) against a brute-force per-frame reference."""

import numpy as np
import pytest
from naive import head_motion as naive
from scipy.spatial.transform import Rotation

from faceretarget import config
from faceretarget.errors import DegenerateGeometryError, InputError, NonFiniteError, ShapeError
from faceretarget.geometry import procrustes
from faceretarget.geometry.head_motion import (
    HeadMotionModel,
    estimate_head_motion,
    rigidity_weights,
)


def angles(motion, truth=None):
    """Largest rotation angle (degrees) of ``motion`` (relative to ``truth``)."""
    rot = (
        motion[:, :3, :3]
        if truth is None
        else np.swapaxes(truth[:, :3, :3], 1, 2) @ motion[:, :3, :3]
    )
    cos = (np.trace(rot, axis1=1, axis2=2) - 1) / 2
    sin = 0.5 * np.linalg.norm(
        np.stack(
            [rot[:, 2, 1] - rot[:, 1, 2], rot[:, 0, 2] - rot[:, 2, 0], rot[:, 1, 0] - rot[:, 0, 1]],
            1,
        ),
        axis=1,
    )
    return np.degrees(np.arctan2(sin, cos))  # accurate near 0 (arccos is not)


def face(
    seed=0, n_markers=40, n_shapes=8, n_frames=30, degrees=0.0, mismatch=0.0, noise=0.0, held=None
):
    """A face-sized (cm) marker problem: reference on a curved cap, smooth local expression
    shapes that leave the upper-middle markers (a "nose bridge") nearly still, smooth
    weights, optional head motion (``degrees`` at most), a mismatched basis (smooth gains
    and rotated directions, as between two rigs) and marker noise.

    Returns reference (N, 3), markers (F, N, 3), the basis to fit with (3N, M), truth (F, 4, 4)."""
    rng = np.random.default_rng(seed)
    u = rng.uniform(-1, 1, (n_markers, 2)) * [7.0, 9.0]
    ref = np.column_stack([u, 6.0 - 0.05 * (u[:, 0] ** 2 + 0.6 * u[:, 1] ** 2)])
    ref[:4] = [
        [0, 2, 6.5],
        [0, 0.5, 7],
        [-2, 1.5, 5.8],
        [2, 1.5, 5.8],
    ]  # nose bridge, eye corners: still
    # expressions around the mouth and jaw (y < -3) and the brows (y = 7.5)
    centres = np.column_stack(
        [
            rng.uniform(-5, 5, n_shapes),
            np.where(np.arange(n_shapes) % 4 == 3, 7.5, rng.uniform(-8, -4, n_shapes)),
        ]
    )
    deltas = np.zeros((n_shapes, n_markers, 3))
    for j in range(n_shapes):
        bump = np.exp(-np.sum((ref[:, :2] - centres[j]) ** 2, axis=1) / (2 * 2.0**2))
        deltas[j] = bump[:, None] * rng.normal(0, 0.8, 3)
    t = np.arange(n_frames)[:, None]
    if held is None:
        weights = 0.5 + 0.5 * np.sin(
            2 * np.pi * t / rng.uniform(8, 30, n_shapes) + rng.uniform(0, 6, n_shapes)
        )
    else:
        weights = np.zeros((n_frames, n_shapes))
        weights[:, held] = np.clip(t[:, 0] / 5.0, 0, 1)
    local = ref + np.einsum("fm,mnk->fnk", weights, deltas)
    basis = deltas
    if mismatch:  # the fitting rig's shapes: spatial gains and rotated directions
        gain = (
            1
            + mismatch
            * np.sin(
                ref[:, :1] * rng.uniform(0.2, 0.5, (1, n_shapes)) + rng.uniform(0, 6, n_shapes)
            ).T
        )
        turn = Rotation.from_rotvec(
            rng.normal(0, 1, (n_shapes, 3)) * np.radians(40 * mismatch)
        ).as_matrix()
        basis = gain[..., None] * np.einsum("mij,mnj->mni", turn, deltas)
    truth = np.tile(np.eye(4), (n_frames, 1, 1))
    if degrees:
        curve = np.sin(2 * np.pi * t / np.array([23.0, 31.0, 17.0]) + rng.uniform(0, 6, 3))
        truth[:, :3, :3] = Rotation.from_rotvec(
            np.radians(degrees) / np.sqrt(3) * curve
        ).as_matrix()
        truth[:, :3, 3] = 0.5 * np.sin(t / np.array([5.0, 7.0, 9.0]))
    markers = np.einsum("fij,fnj->fni", truth[:, :3, :3], local) + truth[:, None, :3, 3]
    markers = markers + rng.normal(0, noise, markers.shape)
    return ref, markers, basis.reshape(n_shapes, -1).T, truth


def naive_estimate(ref, markers, basis, **kw):
    return naive.estimate(
        ref,
        markers,
        basis,
        eps=config.HEAD_MOTION_RIGIDITY,
        ridge_eps=config.RIDGE_EPS,
        floor_rel=config.HEAD_MOTION_NOISE_FLOOR,
        **{"window": config.HEAD_MOTION_WINDOW, **kw},
    )


IDENTITY = np.eye(4)


# ---------------------------------------------------------------------------------------
# recovery and no invented motion
# ---------------------------------------------------------------------------------------
@pytest.mark.parametrize("degrees", [2.0, 15.0])
def test_exact_basis_recovers_head_motion(degrees):
    ref, x, basis, truth = face(degrees=degrees)
    motion, info = estimate_head_motion(ref, x, basis=basis, return_info=True)
    assert info.detected and info.evidence > 100 * config.HEAD_MOTION_SIGNIFICANCE
    assert angles(motion, truth).max() < 1e-6
    np.testing.assert_allclose(motion[:, :3, 3], truth[:, :3, 3], atol=1e-7)


@pytest.mark.parametrize("mismatch, held", [(0.0, None), (0.3, None), (0.3, 0), (0.3, 5)])
def test_no_head_motion_gives_exactly_the_identity(mismatch, held):
    ref, x, basis, _ = face(mismatch=mismatch, held=held)
    motion, info = estimate_head_motion(ref, x, basis=basis, return_info=True)
    assert not info.detected
    assert np.array_equal(motion, np.broadcast_to(IDENTITY, motion.shape))
    if mismatch:  # the fit alone leaks some rotation: the gate is what makes it exact
        assert angles(estimate_head_motion(ref, x, basis=basis, significance=None)).max() > 1e-3


def test_rigidity_weights_cut_the_leak():
    """Uniform marker weights (the weights cancelled through marker_weights) leak more of the
    rig mismatch into the head motion than the rigidity weights (a held expression; see
    tests/spacetime/test_head_motion.py for the rig cases)."""
    ref, x, basis, _ = face(mismatch=0.3, held=0)
    weighted = angles(estimate_head_motion(ref, x, basis=basis, significance=None)).max()
    uniform = angles(
        estimate_head_motion(
            ref, x, basis=basis, significance=None, marker_weights=1 / rigidity_weights(ref, basis)
        )
    ).max()
    assert weighted < 0.8 * uniform


def test_mismatched_basis_still_recovers_real_motion():
    ref, x, basis, truth = face(degrees=8.0, mismatch=0.3)
    motion, info = estimate_head_motion(ref, x, basis=basis, return_info=True)
    assert info.detected
    leak = angles(
        estimate_head_motion(*face(mismatch=0.3)[:2], basis=basis, significance=None)
    ).max()
    assert angles(motion, truth).max() < 2 * leak + 1e-3


def test_plain_procrustes_invents_what_the_estimator_does_not():
    ref, x, basis, _ = face(mismatch=0.3)
    rot, trans, _ = procrustes.fit_rigid(ref, x)
    assert angles(procrustes.to_matrix(rot, trans)).max() > 1.0
    assert np.array_equal(
        estimate_head_motion(ref, x, basis=basis)[:, :3, :3], np.broadcast_to(np.eye(3), rot.shape)
    )


# ---------------------------------------------------------------------------------------
# against the brute-force per-frame reference
# ---------------------------------------------------------------------------------------
@pytest.mark.parametrize("missing", [0.0, 0.2])
def test_matches_brute_force_per_frame_solution(missing):
    """Mismatched basis, noise and missing markers: the vectorized estimator solves the same
    per-frame equations as the brute-force reference (a root finder per frame), and stays
    close to the per-frame least-squares optimum."""
    ref, x, basis, truth = face(n_frames=12, degrees=6.0, mismatch=0.3, noise=0.02)
    if missing:
        drop = np.random.default_rng(3).random(x.shape[:2]) < missing
        x = np.where(drop[..., None], np.nan, x)
    motion, info = estimate_head_motion(ref, x, basis=basis, return_info=True, significance=None)
    want, evidence = naive_estimate(ref, x, basis)
    assert angles(motion, want).max() < 1e-6
    np.testing.assert_allclose(motion[:, :3, 3], want[:, :3, 3], atol=1e-7)
    assert info.evidence == pytest.approx(evidence, rel=0.15)
    optimum, _ = naive_estimate(ref, x, basis, solve=naive.fit_frame)
    assert angles(motion, optimum).max() < 0.1


@pytest.mark.parametrize("degrees", [0.0, 0.3])
def test_gate_statistic_matches_brute_force_near_the_threshold(degrees):
    """The gate's numerator (Schur form) agrees with the exact per-frame energies where the
    decision is close, and the largest window is found."""
    ref, x, basis, truth = face(n_frames=40, degrees=degrees, mismatch=0.3, noise=0.01)
    _, info = estimate_head_motion(
        ref, x, basis=basis, return_info=True, significance=None, window=10
    )
    _, evidence = naive_estimate(ref, x, basis, window=10)
    assert info.evidence == pytest.approx(evidence, rel=0.15)


def test_rigidity_weights_match_brute_force():
    ref, _, basis, _ = face()
    np.testing.assert_allclose(
        rigidity_weights(ref, basis),
        naive.rigidity_weights(ref, basis, config.HEAD_MOTION_RIGIDITY),
        rtol=1e-12,
    )
    w = rigidity_weights(ref, basis)
    assert w[:4].min() > 1.5 * np.median(w)  # the still markers carry the fit


# ---------------------------------------------------------------------------------------
# missing markers, large rotations, units
# ---------------------------------------------------------------------------------------
def test_missing_markers_keep_the_exact_answer():
    ref, x, basis, truth = face(n_frames=40, degrees=10.0)
    rng = np.random.default_rng(5)
    drop = rng.random(x.shape[:2]) < 0.2
    drop[10:25, 4:9] = True  # a block of occluded markers
    x = np.where(drop[..., None], np.nan, x)
    motion = estimate_head_motion(ref, x, basis=basis)
    assert angles(motion, truth).max() < 1e-6


def test_partial_nan_coordinates_count_as_missing():
    ref, x, basis, truth = face(degrees=10.0)
    x[3, 7, 1] = np.nan  # only y missing
    motion = estimate_head_motion(ref, x, basis=basis)
    assert angles(motion, truth).max() < 1e-6


def test_frames_with_few_markers():
    ref, x, basis, truth = face(n_frames=10, degrees=10.0)
    x[4, :-4] = np.nan  # 4 markers left: the 8 expressions can mimic the rigid motion
    motion, info = estimate_head_motion(ref, x, basis=basis, return_info=True)
    assert 4 in info.unidentifiable_frames and np.isfinite(motion).all()
    assert angles(motion[[0, 1, 2, 3, 5]], truth[[0, 1, 2, 3, 5]]).max() < 1e-6
    x[6, 2:] = np.nan
    with pytest.raises(DegenerateGeometryError, match="frame 6"):
        estimate_head_motion(ref, x, basis=basis)


@pytest.mark.parametrize("degrees", [90.0, 175.0])
def test_large_rotations_converge(degrees):
    ref, x, basis, _ = face(n_frames=6)
    rot = Rotation.from_rotvec(
        np.radians(degrees) * np.array([0.3, 0.9, -0.3]) / np.linalg.norm([0.3, 0.9, -0.3])
    ).as_matrix()
    truth = np.tile(np.eye(4), (6, 1, 1))
    truth[:, :3, :3] = rot
    truth[:, :3, 3] = [3.0, -1.0, 2.0]
    moved = x @ rot.T + truth[0, :3, 3]
    assert angles(estimate_head_motion(ref, moved, basis=basis), truth).max() < 1e-6


def cut_to_a_far_pose():
    """8 frames of :func:`face` whose last 4 jump to a pose 170 degrees away: reference,
    moved markers, basis, true motion."""
    ref, x, basis, _ = face(n_frames=8)
    truth = np.tile(np.eye(4), (8, 1, 1))
    truth[4:, :3, :3] = Rotation.from_rotvec(
        np.radians(170.0) * np.array([0.0, 1.0, 0.0])
    ).as_matrix()
    truth[4:, :3, 3] = [4.0, 1.0, -2.0]
    moved = np.einsum("fij,fnj->fni", truth[:, :3, :3], x) + truth[:, None, :3, 3]
    return ref, moved, basis, truth


def test_cut_between_far_apart_head_poses_converges_in_every_frame():
    """Frames start from the previous frame's result; a cut to a pose 170 degrees away must
    still land on the true motion (warm start falls back when it does not converge)."""
    ref, moved, basis, truth = cut_to_a_far_pose()
    assert (
        angles(estimate_head_motion(ref, moved, basis=basis, significance=None), truth).max() < 1e-6
    )


def test_frames_restarted_from_procrustes_keep_their_motion_through_the_gate():
    """Too few steps for the cut's frames to converge from the previous pose: they restart
    from weighted Procrustes, and the gate sees their motion (their rigid coordinates come
    from the restart), so the motion is detected and kept."""
    ref, moved, basis, truth = cut_to_a_far_pose()
    motion, info = estimate_head_motion(ref, moved, basis=basis, max_iter=6, return_info=True)
    assert info.detected and info.evidence > 1e3 * config.HEAD_MOTION_SIGNIFICANCE
    assert angles(motion, truth).max() < 1e-6


def test_long_smooth_shot_matches_brute_force_in_every_frame():
    """Frames start from the previous two extrapolated at constant velocity: over a long shot
    the start must not drift (a start built by multiplying rounded rotations drifted off
    orthogonality, x2.4 a frame, and failed after ~40 frames) and every frame lands on the
    per-frame answer."""
    ref, x, basis, _ = face(n_frames=150, degrees=10.0, mismatch=0.3)
    motion = estimate_head_motion(ref, x, basis=basis, significance=None)
    want, _ = naive_estimate(ref, x, basis)
    assert angles(motion, want).max() < 1e-6
    np.testing.assert_allclose(motion[:, :3, 3], want[:, :3, 3], atol=1e-7)
    rot = motion[:, :3, :3]
    identity = np.broadcast_to(np.eye(3), rot.shape)
    np.testing.assert_allclose(rot @ np.swapaxes(rot, 1, 2), identity, atol=1e-12)


def slow_head_turn(n_frames=300):
    """``face()`` expressions under a slow head motion (periods of seconds at 30 fps)."""
    ref, x, basis, _ = face(n_frames=n_frames)
    t = np.arange(n_frames)
    curve = np.column_stack([np.sin(t / 40.0), 0.5 * np.sin(t / 55.0), 0.3 * np.cos(t / 70.0)])
    rot = Rotation.from_rotvec(np.radians(10.0) * curve).as_matrix()
    moved = np.einsum("fij,fnj->fni", rot, x) + (0.3 * np.sin(t / 50.0))[:, None, None]
    return ref, moved, basis, rot


def test_extrapolated_start_saves_a_step():
    """Slow head motion: from the constant-velocity start every frame converges in at most 5
    Gauss-Newton steps (6 from the previous frame's result: mean 4.8 -> 4.0), same answer."""
    ref, moved, basis, rot = slow_head_turn()
    motion, info = estimate_head_motion(ref, moved, basis=basis, return_info=True)
    assert info.detected and info.iterations <= 5
    assert angles(motion[:, :3, :3], rot).max() < 1e-6


@pytest.mark.parametrize(
    "angle", [0.0, 1e-13, 1e-7, 0.3, 2.0, np.pi - 1e-3, np.pi - 1e-7, np.pi - 1e-9, np.pi]
)
def test_log_map_is_the_rotation_vector_up_to_180_degrees(angle):
    """The kernel's log map (the gate's rigid coordinates) against scipy's rotation vector,
    also within 1e-6 of 180 degrees, where the skew part vanishes and the axis comes from
    ``R + I`` (its sign is then arbitrary; the angle is then pi, within that 1e-6)."""
    from faceretarget.geometry._head_motion_kernels import _log_map

    for axis in ([0.48, -0.6, 0.64], [0.0, 0.0, 1.0], [-0.8, 0.6, 0.0]):
        v = angle * np.array(axis)
        rot = Rotation.from_rotvec(v).as_matrix()
        out = np.empty(3)
        _log_map(rot, out)
        want = Rotation.from_matrix(rot).as_rotvec()
        if angle > 3.0 and np.dot(out, want) < 0:
            want = -want
        np.testing.assert_allclose(out, want, rtol=0, atol=1e-6 if angle > 3.0 else 1e-15)


def test_the_gate_gets_the_rigid_coordinates_of_the_fitted_motion(monkeypatch):
    """The Gauss-Newton kernel hands the gate each frame's ``z``: the rotation vector times
    the face size and ``R c + t - c`` (the motion about the weighted centre ``c``)."""
    import faceretarget.geometry.head_motion as hm

    seen = {}
    original = hm._evidence
    monkeypatch.setattr(
        hm,
        "_evidence",
        lambda *a: (seen.update(motion=a[5].copy(), z=a[6].copy()), original(*a))[1],
    )
    ref, x, basis, _ = face(n_frames=20, degrees=6.0)
    model = HeadMotionModel(ref, basis=basis)
    motion, info = model.estimate(x, return_info=True)
    assert info.detected and np.array_equal(seen["motion"], motion)
    rot, trans, c = motion[:, :3, :3], motion[:, :3, 3], model.centre
    np.testing.assert_allclose(
        seen["z"][:, :3], model.size * Rotation.from_matrix(rot).as_rotvec(), rtol=0, atol=1e-14
    )
    np.testing.assert_allclose(seen["z"][:, 3:], rot @ c + trans - c, rtol=0, atol=1e-13)
    assert np.abs(seen["z"]).max() > 0.05 * model.size  # a real motion, not the identity


@pytest.mark.parametrize("angle", [0.0, 1e-9, 1e-5, 0.0099, 0.0101, 0.099, 0.5, 3.0])
def test_rodrigues_to_rounding_on_both_sides_of_its_series(angle):
    """The kernel's rotation of a rotation vector (Taylor series below 0.01 rad, sin / cos
    above) against scipy's, to a few ulps."""
    from faceretarget.geometry._head_motion_kernels import _rodrigues

    v = angle * np.array([0.48, -0.6, 0.64])
    out = np.empty((3, 3))
    _rodrigues(v[0], v[1], v[2], out)
    np.testing.assert_allclose(out, Rotation.from_rotvec(v).as_matrix(), rtol=0, atol=6e-16)


def test_model_reuses_its_gains_and_matches_the_function(monkeypatch):
    """A HeadMotionModel computes the gains of the complete marker set once: a second shot
    does not call ``_gains`` again, and every answer is the function's, bit for bit (also
    with missing markers, whose patterns are not kept)."""
    from faceretarget.geometry import head_motion as hm

    ref, x, basis, _ = face(n_frames=30, degrees=6.0, mismatch=0.3)
    holes = x.copy()
    holes[3, 5] = holes[9, 0] = np.nan
    model = HeadMotionModel(ref, basis=basis)
    calls = []
    original = hm._gains
    monkeypatch.setattr(hm, "_gains", lambda *a: calls.append(1) or original(*a))
    first = model.estimate(x, return_info=True)
    assert len(calls) == 1
    for markers in (x, holes, x[::-1]):
        got, info = model.estimate(markers, return_info=True)
        want, want_info = estimate_head_motion(ref, markers, basis=basis, return_info=True)
        assert np.array_equal(got, want)
        assert info.evidence == want_info.evidence and info.detected == want_info.detected
    assert np.array_equal(first[0], model.estimate(x))
    # the complete set's gains were kept: only the calls of the function and the holes' patterns
    assert len(calls) == 1 + 3 + 1
    basis[:] = 0.0  # the model copied the caller's arrays
    assert np.array_equal(model.estimate(x), first[0])


def test_a_shot_missing_one_marker_throughout_gets_its_own_gains():
    """One pattern of visible markers (not the complete set) is kept under its own key: the
    answer after the complete shot equals the function's."""
    ref, x, basis, _ = face(n_frames=30, degrees=6.0, mismatch=0.3)
    hole = x.copy()
    hole[:, 7] = np.nan
    model = HeadMotionModel(ref, basis=basis)
    model.estimate(x)
    got, info = model.estimate(hole, return_info=True)
    want, want_info = estimate_head_motion(ref, hole, basis=basis, return_info=True)
    assert np.array_equal(got, want) and info.evidence == want_info.evidence


def test_model_owns_its_arrays():
    """The model copies the basis (a pattern it has not seen yet is computed from the copy)
    and hands out copies of its rigidity weights."""
    ref, x, basis, _ = face(n_frames=30, degrees=6.0, mismatch=0.3)
    holes = x.copy()
    holes[3, 5] = np.nan
    model = HeadMotionModel(ref, basis=basis)
    want, info = model.estimate(holes, return_info=True)
    basis[:] = 0.0
    info.marker_weights[:] = 0.0
    again, info = model.estimate(holes, return_info=True)
    assert np.array_equal(again, want) and info.marker_weights.sum() > 0


def test_weak_frames_do_not_depend_on_their_neighbours():
    """A frame where a rigid direction is an expression (here an x translation) keeps its
    weighted-Procrustes start instead of the neighbours' result: the shot gives what each
    frame gives alone."""
    ref, x, basis, _ = face(n_frames=40, degrees=6.0, mismatch=0.3)
    shifted = np.column_stack([basis, np.tile([1.0, 0.0, 0.0], len(ref))])
    shot, info = estimate_head_motion(ref, x, basis=shifted, significance=None, return_info=True)
    assert len(info.unidentifiable_frames) == len(x)
    single = np.concatenate(
        [
            estimate_head_motion(ref, x[f : f + 1], basis=shifted, significance=None)
            for f in range(len(x))
        ]
    )
    np.testing.assert_allclose(shot, single, atol=1e-12)


def test_extrapolated_start_mean_steps(monkeypatch):
    """The slow head turn: 4.02 Gauss-Newton steps a frame on average (4.83 from the previous
    frame's result; 4.14 with the velocity composed on the wrong side, ``R_{f-1} D``)."""
    from faceretarget.geometry import _head_motion_kernels as kernels

    seen = []
    original = kernels.gauss_newton
    monkeypatch.setattr(
        kernels, "gauss_newton", lambda *a: (original(*a), seen.append(a[10].copy()))[0]
    )
    ref, moved, basis, _ = slow_head_turn()
    estimate_head_motion(ref, moved, basis=basis)
    assert seen[0].min() >= 0 and seen[0].mean() < 4.08


@pytest.mark.parametrize("degrees", [0.0, 6.0])
def test_kept_local_displacements_are_remove_bit_for_bit(degrees):
    """``keep_local``: the displacements the gate computed are what removing the returned
    motion gives (identity when none is detected); none when a sample is missing."""
    ref, x, basis, _ = face(n_frames=20, degrees=degrees)
    model = HeadMotionModel(ref, basis=basis)
    motion, info = model.estimate(x, return_info=True, keep_local=True)
    assert info.detected == (degrees > 0)
    assert np.array_equal(info.local, procrustes.remove(motion, x, ref))
    holes = x.copy()
    holes[2, 1, 0] = np.nan
    assert model.estimate(holes, return_info=True, keep_local=True)[1].local is None
    assert model.estimate(x, return_info=True)[1].local is None


def test_remove_matches_the_inverse_matrix_and_keeps_nan():
    rng = np.random.default_rng(3)
    m = np.tile(np.eye(4), (5, 1, 1))
    m[:, :3, :3] = rng.normal(size=(5, 3, 3)) + 3 * np.eye(3)  # general affine, not only rigid
    m[:, :3, 3] = rng.normal(size=(5, 3))
    points = rng.normal(size=(5, 7, 3))
    points[2, 4] = np.nan
    ref = rng.normal(size=(7, 3))
    inverse = np.linalg.inv(m)
    expected = np.einsum("fij,fnj->fni", inverse[:, :3, :3], points) + inverse[:, None, :3, 3]
    np.testing.assert_allclose(procrustes.remove(m, points), expected, atol=1e-12)
    np.testing.assert_allclose(procrustes.remove(m, points, ref), expected - ref, atol=1e-12)
    assert np.isnan(procrustes.remove(m, points)[2, 4]).all()
    m[3, :3, :3] = 0.0
    with pytest.raises(DegenerateGeometryError, match="frame 3"):
        procrustes.remove(m, points)


def test_same_answer_in_any_length_unit():
    ref, x, basis, truth = face(degrees=0.5, mismatch=0.3)
    a, ia = estimate_head_motion(ref, x, basis=basis, return_info=True, significance=None)
    b, ib = estimate_head_motion(
        ref / 100, x / 100, basis=basis / 100, return_info=True, significance=None
    )
    np.testing.assert_allclose(b[:, :3, :3], a[:, :3, :3], atol=1e-10)
    np.testing.assert_allclose(b[:, :3, 3], a[:, :3, 3] / 100, atol=1e-12)
    assert ib.evidence == pytest.approx(ia.evidence, rel=1e-6)


def test_without_basis():
    ref, _, _, truth = face(degrees=10.0)
    rigid = np.einsum("fij,nj->fni", truth[:, :3, :3], ref) + truth[:, None, :3, 3]  # no expression
    assert angles(estimate_head_motion(ref, rigid), truth).max() < 1e-6
    noisy = ref + np.random.default_rng(0).normal(0, 0.01, (30, len(ref), 3))
    assert np.array_equal(estimate_head_motion(ref, noisy), np.broadcast_to(IDENTITY, (30, 4, 4)))


def test_input_errors():
    ref, x, basis, _ = face(n_frames=3)
    with pytest.raises(ShapeError):
        estimate_head_motion(ref, x[:, :5], basis=basis)
    with pytest.raises(ShapeError):
        estimate_head_motion(ref, x, basis=basis[:-1])
    with pytest.raises(ShapeError):
        estimate_head_motion(ref, x, marker_weights=np.ones(3))
    with pytest.raises(InputError):
        estimate_head_motion(ref, x, marker_weights=-np.ones(len(ref)))
    with pytest.raises(InputError):
        estimate_head_motion(ref, x, window=0)
    bad = x.copy()
    bad[1, 2, 0] = np.inf
    with pytest.raises(NonFiniteError):
        estimate_head_motion(ref, bad, basis=basis)
    hole = ref.copy()
    hole[0, 0] = np.nan
    with pytest.raises(NonFiniteError):
        estimate_head_motion(hole, x)
    assert estimate_head_motion(ref, x[:0], basis=basis).shape == (0, 4, 4)
