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
from collections.abc import Callable
from typing import Any, ParamSpec, TypeVar

__all__ = ["single_threaded_blas", "worker_count"]

_P = ParamSpec("_P")
_R = TypeVar("_R")

_lock = threading.Lock()
_controller = None
_default_threads = 1


def _get_controller() -> Any:
    global _controller, _default_threads
    with _lock:
        if _controller is None:
            try:
                from threadpoolctl import ThreadpoolController
            except ImportError:  # pragma: no cover - a declared dependency
                _controller = False
            else:
                _controller = ThreadpoolController()
                blas = [
                    lib.num_threads for lib in _controller.lib_controllers if lib.user_api == "blas"
                ]
                _default_threads = max(blas, default=1)
    return _controller


def single_threaded_blas() -> contextlib.AbstractContextManager[Any]:
    """Context manager: every loaded BLAS library runs on one thread inside it (about 10 us
    to enter). The limit is process-wide (threadpoolctl), restored on exit."""
    controller = _get_controller()
    if not controller:
        return contextlib.nullcontext()
    return controller.limit(limits=1, user_api="blas")


def blas_single_threaded(func: Callable[_P, _R]) -> Callable[_P, _R]:
    """Decorator form of :func:`single_threaded_blas`."""

    @functools.wraps(func)
    def wrapper(*args: _P.args, **kwargs: _P.kwargs) -> _R:
        with single_threaded_blas():
            return func(*args, **kwargs)

    return wrapper


def worker_count(n_tasks: int) -> int:
    """Threads for ``n_tasks`` independent pieces of numba / single-threaded BLAS work (the
    kernels release the GIL): the CPUs this process may run on, at most ``n_tasks``, and 1
    when BLAS was limited to one thread before the library first asked (``OMP_NUM_THREADS=1``,
    ``threadpoolctl.threadpool_limits(1)``: the user's way of asking for one core)."""
    try:
        cpus = len(os.sched_getaffinity(0))
    except AttributeError:  # pragma: no cover - not on Linux
        cpus = os.cpu_count() or 1
    limit = _default_threads if _get_controller() else cpus
    return max(1, min(n_tasks, cpus, limit))
