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


def test_worker_count_honours_numba_num_threads(four_cpus, monkeypatch):
    with threadpool_limits(4, user_api="blas"):
        monkeypatch.setenv("NUMBA_NUM_THREADS", "2")
        assert worker_count(10) == 2
        monkeypatch.setenv("NUMBA_NUM_THREADS", "")
        assert worker_count(10) == 4


@pytest.mark.parametrize("n", [0, 1, 5, 17, 64])
@pytest.mark.parametrize("parts", [1, 2, 3, 8])
@pytest.mark.parametrize("align", [1, 8])
def test_blocks_cover_the_range_once_in_order(n, parts, align):
    got = _threads.blocks(n, parts, align)
    assert [i for a, b in got for i in range(a, b)] == list(range(n))
    assert len(got) <= parts and all(b > a for a, b in got)
    sizes = [b - a for a, b in got]
    assert len(set(sizes[:-1])) <= 1 and (not sizes or sizes[-1] <= sizes[0])
    if align > 1:  # whole SIMD vectors, but the last block
        assert all(size % align == 0 for size in sizes[:-1] if size > align)


KERNEL_ON_CALLER_SCRIPT = """
import threading
import numba as nb
import numpy as np
from faceretarget._threads import in_blocks

@nb.njit(nogil=True)
def fill(out, a, b):
    for i in range(a, b):
        out[i] = i
    return b - a

seen = []
start = threading.Thread.start
def counted(self):
    seen.append(len(fill.signatures))
    return start(self)
threading.Thread.start = counted
out = np.zeros(10)
print(in_blocks(fill, 10, lambda a, b: (out, a, b), parts=3), out.tolist(), seen)
"""


def test_in_blocks_compiles_on_the_callers_thread_and_returns_in_block_order(tmp_path):
    """numba compiling or loading a kernel on a worker thread while another ran kernels
    crashed now and then: the kernel is ready before any thread starts."""
    import subprocess
    import sys

    run = subprocess.run(
        [sys.executable, "-c", KERNEL_ON_CALLER_SCRIPT],
        capture_output=True,
        text=True,
        cwd=tmp_path,
        timeout=300,
    )
    assert run.returncode == 0, run.stderr
    line = run.stdout.strip()
    assert line.startswith("[4, 4, 2]"), line
    assert "[0.0, 1.0, 2.0, 3.0, 4.0, 5.0, 6.0, 7.0, 8.0, 9.0]" in line, line
    threads_seen = line.rsplit("[", 1)[1].rstrip("]")
    assert threads_seen and set(threads_seen.split(", ")) == {"1"}, line


def test_no_kernel_uses_numbas_parallel_backend():
    """Every numba kernel is serial (blocks on Python threads through ``in_blocks``): a
    ``parallel=True`` kernel took 1-1.4 s longer to compile in every fresh process."""
    import pathlib

    import faceretarget.plugins

    roots = {pathlib.Path(fr.__file__).parent, pathlib.Path(faceretarget.plugins.__file__).parent}
    offenders = [
        str(p)
        for root in roots
        for p in sorted(root.rglob("*.py"))
        if "parallel=True" in p.read_text() or "prange(" in p.read_text()
    ]
    assert offenders == [], offenders


def test_in_blocks_on_a_task_thread_runs_one_block_and_takes_plain_functions():
    """No threads of threads (normalmesh casts rays from its chunks' threads); a plain
    function (``NUMBA_DISABLE_JIT=1``) is run as it is."""
    seen = []

    def kernel(a, b):
        seen.append((a, b))
        return b - a

    assert _threads.in_blocks(kernel, 9, lambda a, b: (a, b), parts=3) == [3, 3, 3]
    seen.clear()
    got = in_threads([lambda: _threads.in_blocks(kernel, 9, lambda a, b: (a, b), parts=3)] * 2, 2)
    assert got == [[9], [9]] and seen == [(0, 9), (0, 9)]


def test_touched_meanwhile_gives_an_array_of_the_shape_and_a_wait(monkeypatch):
    """A large array is touched on a thread that the wait joins; small ones, or one worker,
    start no thread. Either way the array is writable and of the shape asked."""
    started = []
    real = threading.Thread

    class Spy(real):
        def start(self):
            started.append(self)
            super().start()

    monkeypatch.setattr(_threads.threading, "Thread", Spy)
    big, wait = _threads.touched_meanwhile((64, 512, 3))
    wait()
    assert big.shape == (64, 512, 3) and big.dtype == np.float64
    if worker_count(2) >= 2:
        assert len(started) == 1 and not started[0].is_alive()  # ended once waited for
    small, wait = _threads.touched_meanwhile((3, 4))
    wait()
    monkeypatch.setattr(_threads, "worker_count", lambda n: 1)
    alone, wait = _threads.touched_meanwhile((64, 512, 3))
    wait()
    assert len(started) <= 1 and small.shape == (3, 4) and alone.shape == (64, 512, 3)


@pytest.mark.parametrize("plugin", ["coating"])
def test_results_wait_for_their_pages_to_be_touched_before_writing(plugin, monkeypatch):
    """The retargeters write their result only after the touching thread has ended: a
    stand-in whose (late) touching happens inside the wait would wipe frames written
    before it, and it must be waited for."""
    import importlib

    module = importlib.import_module(f"faceretarget.plugins.{plugin}.retargeter")
    cls = {"coating": "CoatingRetargeter", "layers": "LayersRetargeter"}[plugin]
    case = fr.cases.synthetic(resolution=300, n_frames=6)
    fitted = getattr(module, cls)().fit(case.source, case.target)
    want = np.asarray(fitted.retarget(case.source).vertices)
    waits = []

    def late(shape):
        out = np.empty(shape)

        def wait():
            if not waits:
                out.reshape(-1)[::512] = 0.0  # the touching, all of it now
            waits.append(True)

        return out, wait

    monkeypatch.setattr(module, "touched_meanwhile", late)
    got = np.asarray(fitted.retarget(case.source).vertices)
    assert waits, "the result was written without waiting for the touching thread"
    np.testing.assert_array_equal(got, want)
