"""The character side (Eq. 5) and the projection onto blendshapes, against plain numpy/scipy."""

import threading

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


@pytest.fixture(scope="module")
def with_residual():
    problem = make_problem(14, n_frames=65, soft=True)  # 65 = 4 x 16 + 1: a last chunk of one frame
    target = problem["target"]
    deltas = np.random.default_rng(5).normal(size=(7, *np.asarray(target.neutral.vertices).shape))
    deltas[:, ::3] = 0.0  # the residual moves some vertices only
    character = build_character(
        target.layers, target.neutral.vertices, problem["source"].actor_layers, extra=deltas
    )
    beta = compose.region_coefficients(
        problem["weights"], problem["coefficients"], problem["layer_of"]
    )
    return character, beta, problem["head_motion"]


def test_world_vertices_chunks_run_on_threads_with_one_blas_thread(with_residual, monkeypatch):
    from threadpoolctl import threadpool_info

    from faceretarget.plugins.layers import _kernels

    character, beta, motion = with_residual
    monkeypatch.setattr(compose, "CHUNK", 16)
    monkeypatch.setattr(compose, "worker_count", lambda n: min(n, 3))
    seen, real = [], _kernels.assemble

    def spy(*args):
        blas = {i["num_threads"] for i in threadpool_info() if i["user_api"] == "blas"}
        seen.append((threading.get_ident(), frozenset(blas)))
        return real(*args)

    monkeypatch.setattr(_kernels, "assemble", spy)
    compose.world_vertices(character, beta, motion)  # called directly: no retargeter's limit
    assert len({t for t, _ in seen}) >= 2, "the chunks never left one thread"
    assert all(b == {1} for _, b in seen), seen


def test_world_vertices_with_a_residual_block_do_not_depend_on_the_threads(
    with_residual, monkeypatch
):
    character, beta, motion = with_residual
    assert len(character.regions) > beta.shape[1], "a residual block"
    monkeypatch.setattr(compose, "CHUNK", 16)
    m = character.regions[-1][1].shape[0]
    extra = np.random.default_rng(2).normal(size=(beta.shape[0], m))
    extra[-1, : m // 2 + 1] = 0.0  # the one-frame chunk takes the sparse path
    got = {}
    for w in (1, 2, 3):
        monkeypatch.setattr(compose, "worker_count", lambda n, w=w: min(n, w))
        got[w] = compose.world_vertices(character, beta, motion, extra=extra)
    for w in (2, 3):
        np.testing.assert_array_equal(got[w], got[1])
    monkeypatch.setattr(compose, "CHUNK", 13)  # 65 = 5 x 13: no one-frame chunk
    dense = compose.world_vertices(character, beta, motion, extra=extra)
    np.testing.assert_allclose(got[1], dense, rtol=0, atol=1e-12 * np.abs(dense).max())


def test_world_vertices_into_the_callers_array(with_residual):
    """``out=`` receives exactly the vertices of a fresh result; a wrong ``out`` is refused."""
    from faceretarget.errors import ShapeError

    character, beta, motion = with_residual
    want = compose.world_vertices(character, beta, motion)
    out = np.full_like(want, np.nan)
    assert compose.world_vertices(character, beta, motion, out=out) is out
    np.testing.assert_array_equal(out, want)
    with pytest.raises(ShapeError, match="out must be"):
        compose.world_vertices(character, beta, motion, out=out[:, :-1])


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


@pytest.fixture(scope="module")
def whole_shot():
    """A fitted retargeter (its target has blendshapes: a residual block) and its 20-frame
    result computed the plain way: one solve of every frame, then Eq. 5."""
    case = fr.cases.synthetic(resolution=300, n_frames=20)
    fitted = LayersRetargeter().fit(case.source, case.target)
    markers, tracks, known, _ = fitted._inputs(case.source)
    obs, params, residual, _ = fitted._solve(markers, tracks, known)
    beta = compose.region_coefficients(params.weights, params.coefficients, fitted.actor_.layer_of)
    motion = fitted._character_motion(obs.head_motion)
    want = compose.world_vertices(fitted.character_, beta, motion, extra=residual)
    return case, fitted, params, residual, motion, want


class _Idle:
    """An executor that never runs what it is given (each future stays pending)."""

    def __init__(self, workers):
        pass

    def __enter__(self):
        return self

    def __exit__(self, *exc):
        return False

    def submit(self, fn, *args, **kwargs):
        import concurrent.futures

        return concurrent.futures.Future()


@pytest.mark.parametrize(
    "block, writer", [(3, "thread"), (7, "thread"), (1000, "thread"), (3, "idle")]
)
def test_retarget_solves_blocks_while_another_thread_writes_their_vertices(
    whole_shot, block, writer, monkeypatch
):
    """``LayersRetargeter._solve_into``: blocks of frames solved in one chain (the smoothing's
    state carried from block to block) while a writer thread computes each solved block's
    vertices, and what the writer has not started written on the calling thread (``idle``: all
    of it). The same vertices, head motion and extras as the whole-shot solve."""
    from faceretarget.plugins.layers import retargeter as module

    case, fitted, params, residual, motion, want = whole_shot
    assert residual is not None, "the residual block is covered"
    monkeypatch.setattr(module, "SOLVE_BLOCK", block)
    if writer == "idle":
        monkeypatch.setattr(module, "ThreadPoolExecutor", _Idle)
    anim = fitted.retarget(case.source)
    tol = 1e-12 * np.abs(want).max()
    np.testing.assert_allclose(anim.vertices, want, rtol=0, atol=tol)
    np.testing.assert_allclose(anim.head_motion, motion, rtol=0, atol=1e-12)
    np.testing.assert_allclose(anim.extras["layer_weights"], params.weights, rtol=0, atol=1e-12)
    np.testing.assert_allclose(anim.extras["objective"], params.objective, rtol=1e-12, atol=0)
    np.testing.assert_allclose(anim.extras["residual_weights"], residual, rtol=0, atol=1e-12)
    assert anim.provenance["diagnostics"]["mean_iterations"] == float(np.mean(params.iterations))


def test_retarget_raises_what_the_writer_thread_raised(whole_shot, monkeypatch):
    from faceretarget.plugins.layers import retargeter as module

    case, fitted = whole_shot[:2]
    monkeypatch.setattr(module, "SOLVE_BLOCK", 5)
    real, calls = compose.world_vertices, []

    def failing(*args, **kwargs):
        calls.append(threading.get_ident())
        if len(calls) == 2:
            raise RuntimeError("the writer failed")
        return real(*args, **kwargs)

    monkeypatch.setattr(compose, "world_vertices", failing)
    with pytest.raises(RuntimeError, match="the writer failed"):
        fitted.retarget(case.source)


def test_retarget_raises_what_a_block_solve_raised_and_stops_writing(whole_shot, monkeypatch):
    """A block whose solve fails ends the call with its error, and the writes still queued
    then are cancelled: here the writer is held in block 1's write until block 3 fails, so
    block 2's write is queued and must never run."""
    from faceretarget.plugins.layers import retargeter as module

    case, fitted = whole_shot[:2]
    monkeypatch.setattr(module, "SOLVE_BLOCK", 5)
    failed, written = threading.Event(), []

    def write(character, beta, motion, extra=None, out=None, workers=None):
        failed.wait(10)
        written.append(out.shape[0])

    monkeypatch.setattr(compose, "world_vertices", write)
    calls = []

    def solve(self, *args, **kwargs):
        calls.append(1)
        if len(calls) == 3:
            failed.set()
            raise RuntimeError("block 3 failed")
        return LayersRetargeter._solve(self, *args, **kwargs)

    monkeypatch.setattr(fitted, "_solve", solve.__get__(fitted))
    with pytest.raises(RuntimeError, match="block 3 failed"):
        fitted.retarget(case.source)
    assert len(written) <= 1, "a write queued before the failure ran after it"
