"""Threading policy for BLAS/LAPACK.

Per-frame and iterative paths (an ADMM iteration, one frame's solve) make many small
dense products, ``(F, M) x (M, M)`` or smaller; OpenBLAS's worker threads cost more than
they save there and, interleaved with numba kernels, make timings 3-20x slower and noisy
(``benchmarks/bench_spacetime.py`` prints the bounded solve both ways). Those paths run
inside :func:`single_threaded_blas`; large factorizations elsewhere keep their threads, and a
large product inside such a path takes them back with :func:`default_threaded_blas`.
Results are identical: only the number of BLAS threads changes.
"""

from __future__ import annotations

import contextlib
import functools
import threading
from collections.abc import Callable
from typing import Any, ParamSpec, TypeVar

__all__ = ["single_threaded_blas", "default_threaded_blas"]

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


def default_threaded_blas() -> contextlib.AbstractContextManager[Any]:
    """Context manager: BLAS back to the thread count it had when first asked (for one large
    product inside a single-threaded path, e.g. a chunk of frames times a character's blocks)."""
    controller = _get_controller()
    if not controller:
        return contextlib.nullcontext()
    return controller.limit(limits=_default_threads, user_api="blas")


def blas_single_threaded(func: Callable[_P, _R]) -> Callable[_P, _R]:
    """Decorator form of :func:`single_threaded_blas`."""

    @functools.wraps(func)
    def wrapper(*args: _P.args, **kwargs: _P.kwargs) -> _R:
        with single_threaded_blas():
            return func(*args, **kwargs)

    return wrapper
