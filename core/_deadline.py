"""A time limit for code that runs in this process (a third-party plugin's import).

:func:`deadline` arms ``SIGALRM`` so that Python code still running after ``seconds``
is interrupted by :class:`DeadlineExpired` (a ``time.sleep``, a busy loop, a slow
import). It derives from ``BaseException`` and is raised again every second, so plugin
code catching ``Exception`` or ``OSError`` cannot swallow it; a block that caught it
anyway and finished is answered with it on exit. It works in the main
thread of a POSIX process only; elsewhere, or when a C extension owns ``SIGALRM``, it
does nothing. A timer and handler already in place (pytest-timeout, the user's own) are
restored afterwards with the time they had left. Runs of methods are limited
differently, by killing their worker process (:mod:`faceretarget.evaluation._workers`),
since compiled code ignores signals.
"""
from __future__ import annotations

import signal
import threading
import time
from contextlib import contextmanager
from typing import Iterator

__all__ = ["deadline", "DeadlineExpired"]

#: Once expired, the alarm repeats at this interval (seconds) until the block is left.
_REPEAT = 1.0


class DeadlineExpired(BaseException):
    """The block of a :func:`deadline` ran out of time (catch it where the deadline is set)."""


def _usable() -> bool:
    return (
        hasattr(signal, "setitimer")
        and threading.current_thread() is threading.main_thread()
        and signal.getsignal(signal.SIGALRM) is not None  # None: installed from C, cannot be restored
    )


@contextmanager
def deadline(seconds: float | None) -> Iterator[None]:
    """Raise :class:`DeadlineExpired` inside the block if it is still running after
    ``seconds`` (None or 0: no limit)."""
    if not seconds or not _usable():
        yield
        return
    state = {"armed": True, "fired": False}

    def expired(signum, frame):
        if state["armed"]:
            state["fired"] = True
            raise DeadlineExpired(f"still running after {seconds:g} s")

    previous_handler = signal.getsignal(signal.SIGALRM)
    start = time.monotonic()
    previous_delay = previous_interval = 0.0
    try:
        signal.signal(signal.SIGALRM, expired)
        previous_delay, previous_interval = signal.setitimer(signal.ITIMER_REAL, seconds, _REPEAT)
        yield
        if state["fired"]:  # the block caught every DeadlineExpired and went on: still too slow
            raise DeadlineExpired(f"ran past {seconds:g} s")
    finally:
        state["armed"] = False  # an alarm arriving from here on is ignored
        signal.setitimer(signal.ITIMER_REAL, 0)
        signal.signal(signal.SIGALRM, previous_handler)
        if previous_delay:
            left = previous_delay - (time.monotonic() - start)
            signal.setitimer(signal.ITIMER_REAL, max(left, 1e-3), previous_interval)
