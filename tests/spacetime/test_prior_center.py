"""The mean-centred prior (Eq. 3 as printed, ``prior_center="mean"``) through the retargeter.

- Its predicted effect: the neutral has the prior energy ``(n - t_mean)^T C^+ (n - t_mean)``
  (``C`` the samples' covariance about their mean), non-zero whenever the mean delta is not
  orthogonal to the span of the centred samples, e.g. with shapes that are linearly dependent
  at the markers (a shape equal to the sum of two others there); so a source at rest is pulled
  toward the mean expression, further inside the shot than at its per-frame boundary frames.
  Centred at the neutral, nothing moves (``Q = K I`` for independent shapes). Measured: the
  pull exists for independent shapes too (a generic rig's mean delta is not orthogonal to the
  centred span), so ``prior.fit_prior``'s note that for independent shapes the two centres
  "differ only in the direction of equal weights" (mean-centred ``Q = K (I - 11^T / K)``) does
  not hold in general; the test below pins the correct prediction.
- Its exact effect: the retargeter's weights equal an assembled whole-sequence solve whose prior
  is computed here from the covariance matrix of the samples about their mean
  (``naive.spacetime_paper``), with an independently computed basis, alpha, ridge and boundary values.
Paper-exact settings (``naive.spacetime_paper.PAPER``).
"""

import numpy as np
import pytest
from naive.spacetime_paper import constrained_resolve, mean_centred_prior, paper, prior_rows

import faceretarget as fr
from faceretarget import config

ALPHA = 1.0


def dependent_target(toy, seed=0):
    """The toy's rig with shape 2 replaced by shape 0 + shape 1 at the landmarks (plus a bump
    elsewhere, so the three shapes still differ on the mesh)."""
    rng = np.random.default_rng(seed)
    mesh = toy.rig.neutral
    deltas = np.array(toy.rig.deltas)
    extra = np.exp(
        -np.sum((mesh.vertices - mesh.vertices[rng.integers(mesh.n_vertices)]) ** 2, axis=1) / 8.0
    )[:, None] * rng.normal(0, 0.5, 3)
    extra[toy.landmarks] = 0.0
    deltas[2] = deltas[0] + deltas[1] + extra
    rig = fr.BlendshapeRig(mesh, deltas, toy.rig.names)
    return fr.TargetRig(mesh, blendshapes=rig, landmarks=toy.target.landmarks), rig


def exact_basis(rig, toy):
    """(3N, M) scale-matched deltas at the markers: the toy's affine map applied to the rig's
    landmark deltas (the linear RBF reproduces affine maps exactly)."""
    return (np.asarray(rig.deltas)[:, toy.landmarks] @ toy.affine.T).reshape(rig.n_shapes, -1).T


def effective_alpha(toy, alpha=ALPHA):
    ref = toy.src_neutral
    size = np.sqrt(np.mean(np.sum((ref - ref.mean(axis=0)) ** 2, axis=1)))
    return (
        alpha * (size / 60.0) ** 2
    )  # face-size normalisation at 30 fps (per frame and movement alike)


def null_ridge(basis):
    """The null-space ridge eps P_0 of the Gram (rank-deficient rigs), from the documented constants."""
    gram = basis.T @ basis
    eps = config.RIDGE_EPS * np.trace(gram) / gram.shape[0]
    lam, vec = np.linalg.eigh(gram)
    null = vec[:, lam <= config.RANK_RTOL * lam[-1]]
    return eps * null @ null.T


def reference(toy, rig, deltas, alpha):
    """Assembled solve with the mean-centred prior of all blendshapes, boundary values from the
    per-frame solve with the same prior."""
    basis = exact_basis(rig, toy)
    neutral = toy.src_neutral.ravel()
    q_mat, q_vec, const = mean_centred_prior(neutral[None] + basis.T, basis, neutral)
    ridge = null_ridge(basis)
    s = deltas.reshape(len(deltas), -1)
    per_frame = np.linalg.solve(
        basis.T @ basis + alpha * q_mat + ridge, (s[[0, -1]] @ basis + alpha * q_vec).T
    ).T
    known = np.zeros(len(deltas), bool)
    known[[0, -1]] = True
    values = np.zeros((len(deltas), rig.n_shapes))
    values[[0, -1]] = per_frame
    a_mat, a_vec = prior_rows(q_mat, q_vec, const)
    return (
        constrained_resolve(
            basis,
            deltas,
            known,
            values,
            prior_factor=a_mat,
            prior_offset=a_vec,
            alpha=alpha,
            ridge=ridge,
        ),
        basis,
        q_mat,
        q_vec,
    )


def retarget(source, target, center, alpha=ALPHA):
    r = paper(alpha=alpha, prior_center=center, remove_head_motion=False).fit(source, target)
    return r, r.retarget(source)


def assert_same_solution(got, want, basis):
    """Equal marker displacements to 1e-8; equal weights to 1e-6 (the direction that no marker sees
    is fixed only by the 1e-9 null-space ridge, so round-off there is amplified about 1e9 times)."""
    assert np.abs((got - want) @ basis.T).max() < 1e-8 * np.abs(want @ basis.T).max()
    assert np.abs(got - want).max() < 1e-6 * np.abs(want).max()


@pytest.fixture
def at_rest(make_toy):
    toy = make_toy(expression=False, n_frames=30)
    target, rig = dependent_target(toy)
    return toy, target, rig


def test_source_at_rest_stays_at_rest_with_the_neutral_centred_prior(at_rest):
    toy, target, _ = at_rest
    _, anim = retarget(toy.source, target, "neutral")
    assert np.abs(anim.weights).max() < 1e-10


def test_source_at_rest_is_pulled_toward_the_mean_with_dependent_shapes(at_rest):
    toy, target, rig = at_rest
    r, anim = retarget(toy.source, target, "mean")
    basis = exact_basis(rig, toy)
    np.testing.assert_allclose(r.basis_, basis, atol=1e-9 * np.abs(basis).max())
    w = anim.weights
    assert np.abs(w).max() > 1e-3  # it moves
    toward = basis.T.mean(axis=0)  # (t_mean - n) at the markers: the mean of the shapes' deltas
    pull = (
        (w @ basis.T) @ toward / (toward @ toward)
    )  # share of the way to the mean face, per frame
    assert np.all(pull > 0.0), pull
    # the boundary frames balance the data (stay at rest) against the prior; inside, only the
    # velocity term holds the face back, so the pull grows toward the middle of the shot
    middle = len(w) // 2
    assert pull[middle] > 1.5 * max(pull[0], pull[-1]), pull
    assert np.all(r.prior_.energy(w) < r.prior_.energy(np.zeros((1, rig.n_shapes)))[0])
    # exactly the predicted amount: the assembled solve with the mean-centred prior
    want, *_ = reference(toy, rig, toy.world - toy.src_neutral, effective_alpha(toy))
    assert r.alpha_effective_ == pytest.approx(effective_alpha(toy), rel=1e-12)
    assert_same_solution(w, want, basis)


def test_mean_centred_retarget_matches_the_assembled_solve(make_toy):
    toy = make_toy(n_frames=40, noise=0.03, extra_source_shapes=2)
    target, rig = dependent_target(toy, seed=1)
    # the same expressive performance, seen through the dependent rig's markers
    source = toy.source
    r, anim = retarget(source, target, "mean")
    want, basis, q_mat, q_vec = reference(
        toy, rig, toy.world - toy.src_neutral, effective_alpha(toy)
    )
    np.testing.assert_allclose(r.prior_.matrix, q_mat, atol=1e-8 * np.abs(q_mat).max())
    np.testing.assert_allclose(r.prior_.vector, q_vec, atol=1e-8 * np.abs(q_mat).max())
    assert_same_solution(anim.weights, want, basis)
    _, neutral = retarget(source, target, "neutral")
    assert np.abs(neutral.weights - anim.weights).max() > 1e-3  # the centre matters here


def test_independent_shapes_rest_pose_energy_is_as_predicted(make_toy):
    """Independent shapes (all of them the prior's samples, K = M): neutral-centred ``Q = K I`` and
    a source at rest stays at rest; mean-centred, the neutral's prior energy is
    ``(n - t_mean)^T C^+ (n - t_mean)`` (here non-zero), and the rest source moves exactly as the
    assembled solve predicts."""
    rest = make_toy(n_frames=30, expression=False)
    k = rest.rig.n_shapes
    neutral, still = retarget(rest.source, rest.target, "neutral")
    np.testing.assert_allclose(neutral.prior_.matrix, k * np.eye(k), atol=1e-8 * k)
    assert np.abs(still.weights).max() < 1e-10
    mean, moved = retarget(rest.source, rest.target, "mean")
    want, basis, q_mat, q_vec = reference(
        rest, rest.rig, rest.world - rest.src_neutral, effective_alpha(rest)
    )
    _, _, const = mean_centred_prior(
        rest.src_neutral.ravel()[None] + basis.T, basis, rest.src_neutral.ravel()
    )
    assert mean.prior_.energy(np.zeros((1, k)))[0] == pytest.approx(const, rel=1e-8)
    assert const > 0.1  # a generic rig: the mean delta is not orthogonal to the centred span
    assert np.abs(moved.weights - want).max() < 1e-8 * np.abs(want).max()
    toward = basis.T.mean(axis=0)
    assert np.all((moved.weights @ basis.T) @ toward > 0)  # toward the mean face
    # the "differ only in the equal-weights direction" reading (Q = K (I - 11^T/K)) does not hold
    assert np.abs(mean.prior_.matrix - k * (np.eye(k) - np.ones((k, k)) / k)).max() > 0.1
