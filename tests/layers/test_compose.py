"""The character side (Eq. 5) and the projection onto blendshapes, against plain numpy/scipy."""

import numpy as np
import pytest
import scipy.optimize
from naive.layers import make_problem

import faceretarget as fr
from faceretarget.plugins.layers import compose
from faceretarget.plugins.layers.model import build_character
from faceretarget.plugins.layers.retargeter import LayersRetargeter


@pytest.mark.parametrize("workers", [1, 2, 3])
def test_world_vertices_match_the_dense_formula(workers, monkeypatch):
    # 70 frames, chunks of 16: five chunks, dealt out to 1, 2 or 3 threads
    monkeypatch.setattr(compose, "CHUNK", 16)
    monkeypatch.setattr(compose, "worker_count", lambda n: min(n, workers))
    problem = make_problem(14, n_frames=70, soft=True)
    target = problem["target"]
    character = build_character(
        target.layers, target.neutral.vertices, problem["source"].actor_layers
    )
    rng = np.random.default_rng(0)
    W, A = problem["weights"], problem["coefficients"]
    A = A * (rng.random(A.shape) > 0.3)  # some exact zeros
    beta = compose.region_coefficients(W, A, problem["layer_of"])
    got = compose.world_vertices(character, beta, problem["head_motion"])
    neutral = np.asarray(target.neutral.vertices)
    disp = np.concatenate(
        [np.asarray(p) - neutral for p in target.layers.layers.values()]
    )  # (K, V, 3)
    local = neutral + np.einsum("flk,lv,kvd->fvd", beta, np.asarray(target.layers.masks), disp)
    want = (
        np.einsum("fij,fvj->fvi", problem["head_motion"][:, :3, :3], local)
        + problem["head_motion"][:, None, :3, 3]
    )
    np.testing.assert_allclose(got, want, atol=1e-12 * np.abs(want).max())
    np.testing.assert_allclose(
        compose.world_vertices(character, beta), local, atol=1e-12 * np.abs(local).max()
    )
    monkeypatch.setattr(compose, "worker_count", lambda n: 1)
    np.testing.assert_array_equal(
        compose.world_vertices(character, beta, problem["head_motion"]), got
    )


def test_blendshape_projection_is_the_nnls_solution():
    case = fr.cases.synthetic(resolution=300, n_frames=6)
    plain = LayersRetargeter().fit(case.source, case.target).retarget(case.source)
    projected = (
        LayersRetargeter(project_blendshapes=True)
        .fit(case.source, case.target)
        .retarget(case.source)
    )
    rig = case.target.blendshapes
    D = np.asarray(rig.deltas).reshape(rig.n_shapes, -1).T
    local = plain.local_vertices - np.asarray(rig.neutral.vertices)
    for f in range(6):
        ref, _ = scipy.optimize.nnls(D, local[f].ravel())
        cost = lambda w, f=f: float(np.sum((D @ w - local[f].ravel()) ** 2))  # noqa: E731
        assert cost(projected.weights[f]) <= cost(ref) * (1 + 1e-9) + 1e-12
    assert projected.weights.min() >= 0
    assert projected.weight_names == rig.names
