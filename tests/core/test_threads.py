"""The threading policy: per-frame and iterative paths run BLAS on one thread, the rest keep theirs."""

import threading
import time

import numpy as np
import pytest
from threadpoolctl import threadpool_info, threadpool_limits

import faceretarget as fr
from faceretarget import _threads
from faceretarget._threads import in_threads, single_threaded_blas, worker_count
from faceretarget.plugins.spacetime import solver


def blas_threads():
    return {i["filepath"]: i["num_threads"] for i in threadpool_info() if i["user_api"] == "blas"}


def test_single_threaded_blas_limits_and_restores():
    before = blas_threads()
    with single_threaded_blas():
        assert set(blas_threads().values()) == {1}
    assert blas_threads() == before


@pytest.fixture
def four_cpus(monkeypatch):
    monkeypatch.setattr(_threads.os, "sched_getaffinity", lambda pid: {0, 1, 2, 3}, raising=False)


def test_worker_count_uses_the_cpus_up_to_the_users_blas_threads(four_cpus, monkeypatch):
    with threadpool_limits(3, user_api="blas"):
        assert worker_count(10) == 3
        assert worker_count(2) == 2
        with single_threaded_blas():  # the library's own limit is not the user's
            assert worker_count(10) == 3
    with threadpool_limits(1, user_api="blas"):  # OMP_NUM_THREADS=1: one core asked for
        assert worker_count(10) == 1
        with single_threaded_blas():
            assert worker_count(10) == 1
    with threadpool_limits(4, user_api="blas"):  # a limit around an earlier call does not stick
        assert worker_count(10) == 4
    monkeypatch.setattr(_threads.os, "sched_getaffinity", lambda pid: {0}, raising=False)
    assert worker_count(10) == 1
    assert worker_count(0) == 1


def test_worker_count_without_a_blas_in_sight_uses_the_cpus(four_cpus, monkeypatch):
    class Openmp:  # threadpoolctl sees an OpenMP runtime but no BLAS (Accelerate, an unknown build)
        user_api, internal_api, num_threads = "openmp", "openmp", 4

    class Controller:
        lib_controllers = [Openmp()]

    monkeypatch.setattr(_threads, "_controller", Controller())
    assert worker_count(10) == 4


def test_in_threads_returns_in_order_and_raises_after_all_ended():
    here = threading.get_ident()
    barrier = threading.Barrier(2, timeout=10)  # one after the other would break it
    ended = []

    def task(i):
        barrier.wait() if i < 2 else None
        ended.append(i)
        return i, threading.get_ident()

    got = in_threads([lambda i=i: task(i) for i in range(4)], 2)
    assert [i for i, _ in got] == [0, 1, 2, 3]
    assert len({t for _, t in got}) == 2 and here not in {t for _, t in got}
    assert [
        t for _, t in in_threads([lambda i=i: (i, threading.get_ident()) for i in range(3)], 1)
    ] == [here] * 3

    def boom():
        raise ValueError("first")

    def slow():
        time.sleep(0.2)
        ended.append("slow")

    ended.clear()
    with pytest.raises(ValueError, match="first"):
        in_threads([boom, slow], 2)
    assert ended == ["slow"], "the error waits for the other tasks"


def test_concurrent_limits_restore_the_blas_threads():
    """Two threads in single_threaded_blas at once, leaving in the order they came in: the
    BLAS threads are those from before (each saving and restoring alone left 1 for good, and
    so did a restore from another thread than the one that set the limit)."""
    before = blas_threads()
    a_in, b_in, a_out, b_out = (threading.Event() for _ in range(4))
    inside = []

    def a():
        with single_threaded_blas():
            a_in.set()
            b_in.wait(10)
            inside.append(set(blas_threads().values()))
        a_out.set()
        b_out.wait(10)  # alive while b restores (threadpoolctl lets the thread that set decide)

    def b():
        a_in.wait(10)
        with single_threaded_blas():
            b_in.set()
            a_out.wait(10)
            inside.append(set(blas_threads().values()))  # a has left: the limit still holds
        b_out.set()

    threads = [threading.Thread(target=f) for f in (a, b)]
    for t in threads:
        t.start()
    for t in threads:
        t.join()
    try:
        assert inside == [{1}, {1}]
        assert blas_threads() == before
    finally:
        threadpool_limits(max(before.values()), user_api="blas")  # repaired for the other tests


def test_spacetime_admm_and_layers_frames_run_on_one_blas_thread(monkeypatch):
    seen = []
    real = solver._admm_structured

    def spy(*args, **kwargs):
        seen.append(set(blas_threads().values()))
        return real(*args, **kwargs)

    monkeypatch.setattr(solver, "_admm_structured", spy)
    case = fr.cases.cross_rig(n_frames=40, source_kind="markers")
    fr.get("spacetime").fit(case.source, case.target).retarget(case.source)
    assert seen and all(s == {1} for s in seen)

    from faceretarget.plugins.layers import compose

    seen.clear()
    real_coeffs = compose.region_coefficients

    def spy_coeffs(*args, **kwargs):
        seen.append(set(blas_threads().values()))
        return real_coeffs(*args, **kwargs)

    monkeypatch.setattr(compose, "region_coefficients", spy_coeffs)
    synthetic = fr.cases.synthetic(n_frames=6)
    layers = fr.get("layers").fit(synthetic.source, synthetic.target)
    seen.clear()
    layers.retarget(synthetic.source)
    list(layers.stream(np.asarray(synthetic.source.marker_positions())[:3]))
    assert len(seen) >= 4 and all(s == {1} for s in seen)


@pytest.mark.parametrize("threads", [1, 2])
def test_results_do_not_depend_on_the_blas_threads(threads):
    from threadpoolctl import threadpool_limits

    case = fr.cases.cross_rig(n_frames=60, source_kind="markers")
    r = fr.get("spacetime").fit(case.source, case.target)
    want = r.retarget(case.source).weights
    with threadpool_limits(threads, user_api="blas"):
        got = fr.get("spacetime").fit(case.source, case.target).retarget(case.source).weights
    np.testing.assert_allclose(got, want, rtol=0, atol=1e-12)
