"""Threading policy for BLAS/LAPACK.

Per-frame and iterative paths (an ADMM iteration, one frame's solve) make many small
dense products, ``(F, M) x (M, M)`` or smaller; OpenBLAS's worker threads cost more than
they save there and, interleaved with numba kernels, make timings 3-20x slower and noisy
(``benchmarks/bench_spacetime.py`` prints the bounded solve both ways). Those paths run
inside :func:`single_threaded_blas`; large factorizations elsewhere keep their threads.
Large batches of such work (chunks of frames) use the cores through Python threads instead,
:func:`worker_count` of them, each chunk on one BLAS thread, so that the numbers do not
depend on the thread count.
"""

from __future__ import annotations

import contextlib
import functools
import os
import threading
from collections.abc import Callable, Iterator, Sequence
from concurrent.futures import ThreadPoolExecutor
from typing import Any, ParamSpec, TypeVar

__all__ = [
    "single_threaded_blas",
    "worker_count",
    "in_threads",
    "in_blocks",
    "blocks",
    "touched_meanwhile",
]

_P = ParamSpec("_P")
_R = TypeVar("_R")

_lock = threading.Lock()
_controller = None
#: Threads inside :func:`single_threaded_blas` now, the limit they share, and the BLAS
#: thread count when the first of them entered (the user's setting, for :func:`worker_count`).
_depth = 0
_limiter: Any = None
_user_threads: int | None = None


def _get_controller() -> Any:
    global _controller
    with _lock:
        if _controller is None:
            try:
                from threadpoolctl import ThreadpoolController
            except ImportError:  # pragma: no cover - a declared dependency
                _controller = False
            else:
                _controller = ThreadpoolController()
    return _controller


def _blas_threads(controller: Any) -> int | None:
    """The largest thread count of the loaded BLAS libraries, None if none is seen."""
    counts = [lib.num_threads for lib in controller.lib_controllers if lib.user_api == "blas"]
    return max(counts) if counts else None


@contextlib.contextmanager
def single_threaded_blas() -> Iterator[None]:
    """Context manager: every loaded BLAS library runs on one thread inside it (a few
    microseconds to enter). The limit is process-wide (threadpoolctl): threads that enter
    at the same time share it, and the last one out restores what the first one found."""
    global _depth, _limiter, _user_threads
    controller = _get_controller()
    if not controller:
        yield
        return
    with _lock:
        if _depth == 0:
            _user_threads = _blas_threads(controller)
            _limiter = _released(lambda: controller.limit(limits=1, user_api="blas"))
        _depth += 1
    try:
        yield
    finally:
        with _lock:
            _depth -= 1
            if _depth == 0:
                _released(_limiter.restore_original_limits)
                _limiter = None


def _released(change: Callable[[], _R]) -> _R:
    """``change()`` of the BLAS limits from whichever thread comes first or leaves last.
    threadpoolctl (3.6+) lets only one thread change a process-wide OpenBLAS pool and
    silently ignores the others; that thread stays in control until it clears it. So
    control is cleared before and after the change."""
    clear = _clear_control()
    clear()
    try:
        return change()
    finally:
        clear()


def _clear_control() -> Callable[[], None]:
    try:
        from threadpoolctl import OpenBLASController
    except ImportError:  # older threadpoolctl: any thread may change the limits
        return lambda: None
    clear = getattr(OpenBLASController, "clear_controlling_thread", None)
    return (lambda: clear(force=True)) if clear is not None else (lambda: None)


def blas_single_threaded(func: Callable[_P, _R]) -> Callable[_P, _R]:
    """Decorator form of :func:`single_threaded_blas`."""

    @functools.wraps(func)
    def wrapper(*args: _P.args, **kwargs: _P.kwargs) -> _R:
        with single_threaded_blas():
            return func(*args, **kwargs)

    return wrapper


def worker_count(n_tasks: int) -> int:
    """Threads for ``n_tasks`` independent pieces of numba / single-threaded BLAS work (the
    kernels release the GIL): the CPUs this process may run on, at most ``n_tasks``, at
    most ``NUMBA_NUM_THREADS`` when set and at most the user's BLAS thread count
    (``OMP_NUM_THREADS=1`` or ``threadpoolctl.threadpool_limits(1)`` around the call: the
    user's way of asking for one core; the library's own :func:`single_threaded_blas` limit
    is not the user's)."""
    try:
        cpus = len(os.sched_getaffinity(0))
    except AttributeError:  # pragma: no cover - not on Linux
        cpus = os.cpu_count() or 1
    controller = _get_controller()
    limit = None
    if controller:
        with _lock:
            limit = _user_threads if _depth > 0 else _blas_threads(controller)
    numba_limit = os.environ.get("NUMBA_NUM_THREADS", "")
    if numba_limit.isdigit() and int(numba_limit) > 0:
        cpus = min(cpus, int(numba_limit))
    return max(1, min(n_tasks, cpus, limit or cpus))


def blocks(n: int, parts: int, align: int = 1) -> list[tuple[int, int]]:
    """At most ``parts`` contiguous ``(start, stop)`` ranges covering ``range(n)``, equal but
    the last, each size a multiple of ``align`` when it exceeds ``align``; none for ``n = 0``."""
    step = -(-n // max(1, parts))
    if step > align:
        step = -(-step // align) * align
    return [(a, min(n, a + step)) for a in range(0, n, max(1, step))]


def in_blocks(
    kernel: Any,
    n: int,
    args: Callable[[int, int], tuple],
    *,
    parts: int | None = None,
    align: int = 1,
) -> list[Any]:
    """``kernel(*args(start, stop))`` for the :func:`blocks` of ``range(n)``, side by side on
    :func:`worker_count` threads (``parts`` blocks if given; one block on a thread that runs
    one of :func:`in_threads`' tasks, which are side by side already): the serial, ``nogil`` numba
    kernel's work split without numba's parallel backend (a ``prange`` kernel took 1-1.4 s
    longer to compile, in every fresh process). Returns the kernel's results in block order.

    The kernel is compiled or loaded for these argument types on the calling thread first:
    numba loading kernels on one thread while another ran others crashed now and then.
    """
    if getattr(_inside, "task", False):
        parts = 1  # already on one of in_threads' threads: no threads of threads
    ranges = blocks(n, worker_count(n) if parts is None else parts, align)
    calls = [args(a, b) for a, b in ranges]
    if not calls:
        return []
    overloads = getattr(kernel, "overloads", None)  # None: a plain function (NUMBA_DISABLE_JIT)
    if overloads is not None:
        sig = tuple(kernel.typeof_pyval(a) for a in calls[0])
        if sig not in overloads:  # compile() takes numba's compiler lock even when compiled
            kernel.compile(sig)
    return in_threads([functools.partial(kernel, *c) for c in calls], len(calls))


def in_threads(tasks: Sequence[Callable[[], _R]], workers: int) -> list[_R]:
    """Run ``tasks`` (work that releases the GIL: numba ``nogil`` kernels, one-thread BLAS,
    QDLDL) on ``workers`` threads, in order on the calling thread when ``workers <= 1``.
    Returns their results in order; the first error is raised once all have ended."""
    if workers <= 1 or len(tasks) <= 1:
        return [task() for task in tasks]
    with ThreadPoolExecutor(min(workers, len(tasks))) as pool:
        futures = [pool.submit(_as_task, task) for task in tasks]
        return [future.result() for future in futures]


#: ``task`` is True on a thread while it runs one of :func:`in_threads`' tasks.
_inside = threading.local()


def _as_task(task: Callable[[], _R]) -> _R:
    _inside.task = True
    try:
        return task()
    finally:
        _inside.task = False


#: Bytes between the writes that fault in a new array's pages (one a 4 KiB page).
_PAGE_BYTES = 4096


def touched_meanwhile(shape: tuple[int, ...]) -> tuple[Any, Callable[[], None]]:
    """A new float64 array of ``shape`` whose pages a background thread faults in (one
    write a page), and the call that waits for it. For a large result that only a later
    step fills, while the step before it runs on one core: the first writes to a fresh
    array (page faults, the kernel zeroing each page) are then off the critical path.
    Contents are unspecified, as with ``np.empty``."""
    import numpy as np

    out = np.empty(shape)
    flat = out.reshape(-1)
    step = _PAGE_BYTES // out.itemsize
    if worker_count(2) < 2 or flat.size < 64 * step:
        return out, lambda: None
    thread = threading.Thread(target=flat[::step].fill, args=(0.0,), daemon=True)
    thread.start()
    return out, thread.join
