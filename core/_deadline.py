"""A time limit for code that runs in this process (a third-party plugin's import).

:func:`deadline` arms ``SIGALRM`` so that Python code still running after ``seconds``
is interrupted by an exception (a ``time.sleep``, a busy loop, a slow import). It works
in the main thread of a POSIX process only; elsewhere it does nothing. A timer and
handler already in place (pytest-timeout, the user's own) are restored afterwards with
the time they had left. Runs of methods are limited differently, by killing their worker
process (:mod:`faceretarget.evaluation._workers`), since compiled code ignores signals.
"""
from __future__ import annotations

import signal
import threading
import time
from contextlib import contextmanager
from typing import Callable, Iterator

__all__ = ["deadline"]


def _usable() -> bool:
    return hasattr(signal, "setitimer") and threading.current_thread() is threading.main_thread()


@contextmanager
def deadline(seconds: float | None, make_error: Callable[[], BaseException]) -> Iterator[None]:
    """Raise ``make_error()`` inside the block if it is still running after ``seconds``
    (None or 0: no limit)."""
    if not seconds or not _usable():
        yield
        return

    def expired(signum, frame):
        raise make_error()

    previous_handler = signal.signal(signal.SIGALRM, expired)
    previous_delay, previous_interval = signal.setitimer(signal.ITIMER_REAL, seconds)
    start = time.monotonic()
    try:
        yield
    finally:
        signal.setitimer(signal.ITIMER_REAL, 0)
        signal.signal(signal.SIGALRM, previous_handler)
        if previous_delay:
            left = previous_delay - (time.monotonic() - start)
            signal.setitimer(signal.ITIMER_REAL, max(left, 1e-3), previous_interval)
