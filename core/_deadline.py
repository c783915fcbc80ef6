"""A time limit for code that runs in this process (a third-party plugin's import), that
the code cannot disable.

:func:`deadline` stops a block still running after ``seconds``, in four layers, each a
backstop for the one before:

1. ``SIGALRM`` (main thread of a POSIX process): a :class:`DeadlineExpired` is raised in
   the block (a ``time.sleep``, a busy loop, a slow import), and again every second, so
   code catching ``Exception`` cannot swallow it. A timer and handler already in place
   (pytest-timeout, the user's own) are restored afterwards with the time they had left.
2. A watchdog thread: :class:`DeadlineExpired` is injected into the thread running the
   block (``PyThreadState_SetAsyncExc``; works from any thread, and when the block has
   ignored or replaced ``SIGALRM``), and the main thread is woken from a sleep by
   ``SIGURG``, which has a handler of its own for the block's duration.
3. With ``hard`` (a message): ``grace`` seconds later, if the block still has not ended
   (it ignores or blocks every signal and sleeps in C), the watchdog thread writes
   ``hard`` to stderr and ends the process (``os._exit(HARD_EXIT_STATUS)``).
4. Inside :func:`watchdog_process`: ``grace`` seconds after that, a separate process
   writes ``hard`` and SIGKILLs this one, for a block that holds the GIL in compiled code
   forever (no thread of this process can run).

Layers 1 and 2 leave the program running (the caller skips the plugin); 3 and 4 end it,
with a message naming the plugin, instead of hanging. Code running in this process can
still defeat them on purpose (killing the watchdog process, ``ctypes``): the only
complete isolation is a process of its own, as for runs of methods, which are limited by
killing their worker (:mod:`faceretarget.evaluation._workers`).
"""

from __future__ import annotations

import ctypes
import os
import signal
import subprocess
import sys
import threading
import time
from collections.abc import Iterator
from contextlib import contextmanager
from types import FrameType

__all__ = ["deadline", "watchdog_process", "DeadlineExpired", "HARD_EXIT_STATUS", "grace_for"]

#: Once expired, the alarm repeats at this interval (seconds) until the block is left.
_REPEAT = 1.0

#: Interval (seconds) of the watchdog thread's injections after the deadline.
_INJECT_EVERY = 0.25

#: Exit status of a process ended by layer 3 (the command line's "error" status).
HARD_EXIT_STATUS = 2

#: The signal that wakes the main thread from a sleep (default action: ignored).
_WAKE = getattr(signal, "SIGURG", None)

_WATCHDOG_SCRIPT = os.path.join(os.path.dirname(os.path.abspath(__file__)), "_watchdog.py")
_process: subprocess.Popen | None = None
_process_lock = threading.Lock()


class DeadlineExpired(BaseException):
    """The block of a :func:`deadline` ran out of time (catch it where the deadline is set)."""


def grace_for(seconds: float) -> float:
    """Seconds between two layers of a :func:`deadline` of ``seconds``."""
    return min(30.0, max(2.0, seconds / 4))


def _alarm_usable() -> bool:
    return (
        hasattr(signal, "setitimer")
        and threading.current_thread() is threading.main_thread()
        and signal.getsignal(signal.SIGALRM)
        is not None  # None: installed from C, cannot be restored
    )


def _wake_usable() -> bool:
    return (
        _WAKE is not None
        and hasattr(signal, "pthread_kill")
        and threading.current_thread() is threading.main_thread()
        and signal.getsignal(_WAKE) is not None
    )


def _inject(thread_id: int, exc: type | None) -> None:
    """Raise ``exc`` in thread ``thread_id`` at its next bytecode (None: cancel a pending one)."""
    try:
        ctypes.pythonapi.PyThreadState_SetAsyncExc(
            ctypes.c_ulong(thread_id), ctypes.py_object(exc) if exc else None
        )
    except (AttributeError, ctypes.ArgumentError):  # not CPython
        pass


@contextmanager
def watchdog_process() -> Iterator[None]:
    """Within this block, :func:`deadline` calls with ``hard`` also arm a watchdog process
    (layer 4). One process serves the whole block; it ends with it."""
    global _process
    with _process_lock:
        outer = _process is not None
        if not outer:
            try:
                _process = subprocess.Popen(
                    [sys.executable, "-I", _WATCHDOG_SCRIPT, str(os.getpid())],
                    stdin=subprocess.PIPE,
                    stdout=subprocess.DEVNULL,
                )
            except OSError:  # cannot start processes here: layers 1-3 only
                _process = None
    try:
        yield
    finally:
        if not outer:
            with _process_lock:
                proc, _process = _process, None
            if proc is not None:
                assert proc.stdin is not None  # started with stdin=PIPE
                try:
                    proc.stdin.close()
                except OSError:
                    pass
                try:
                    proc.wait(5)
                except subprocess.TimeoutExpired:
                    proc.kill()
                    proc.wait()


def _tell_process(line: str) -> None:
    proc = _process
    if proc is None:
        return
    assert proc.stdin is not None  # started with stdin=PIPE
    try:
        proc.stdin.write(line.encode("ascii") + b"\n")
        proc.stdin.flush()
    except (OSError, ValueError):
        pass


@contextmanager
def deadline(
    seconds: float | None, *, hard: str | None = None, grace: float | None = None
) -> Iterator[None]:
    """Raise :class:`DeadlineExpired` inside the block if it is still running after
    ``seconds`` (None or 0: no limit). With ``hard``, a block that cannot be interrupted
    ends the process ``grace`` seconds later (default :func:`grace_for`), printing ``hard``."""
    if not seconds:
        yield
        return
    grace = grace_for(seconds) if grace is None else grace
    state = {"armed": True, "fired": False}
    lock = threading.Lock()
    done = threading.Event()
    target = threading.get_ident()
    alarm = _alarm_usable()
    wake = _WAKE if _wake_usable() else None  # the waking signal, when usable
    message = (hard.rstrip("\n") + "\n").encode("utf-8", "replace") if hard else b""

    def expired(signum: int, frame: FrameType | None) -> None:
        if not state["armed"] or (signum != signal.SIGALRM and not state["fired"]):
            return  # too late, or a SIGURG that is not the watchdog's
        state["fired"] = True
        raise DeadlineExpired(f"still running after {seconds:g} s")

    def watch() -> None:
        if done.wait(seconds):
            return
        end = time.monotonic() + grace
        while time.monotonic() < end:
            with lock:
                if not state["armed"]:
                    return
                state["fired"] = True
                _inject(target, DeadlineExpired)
                if wake is not None:
                    try:
                        signal.pthread_kill(target, wake)
                    except OSError:
                        pass
            if done.wait(_INJECT_EVERY):
                return
        if hard:
            with lock:
                if state["armed"]:
                    try:
                        os.write(2, message)
                    finally:
                        os._exit(HARD_EXIT_STATUS)

    previous_handler = signal.getsignal(signal.SIGALRM) if alarm else None
    previous_wake = signal.getsignal(wake) if wake is not None else None
    start = time.monotonic()
    previous_delay = previous_interval = 0.0
    completed = False
    try:
        if alarm:
            signal.signal(signal.SIGALRM, expired)
            previous_delay, previous_interval = signal.setitimer(
                signal.ITIMER_REAL, seconds, _REPEAT
            )
        if wake is not None:
            signal.signal(wake, expired)
        if hard:
            _tell_process(f"arm {seconds + 2 * grace:.3f} {message.hex()}")
        threading.Thread(target=watch, name="faceretarget-deadline", daemon=True).start()
        yield
        completed = True
    finally:
        while True:  # a DeadlineExpired arriving while this runs must not leave anything armed
            try:
                with lock:
                    state["armed"] = (
                        False  # an alarm or injection from here on is ignored / cancelled
                    )
                    done.set()
                    _inject(target, None)
                if hard:
                    _tell_process("disarm")
                if alarm:
                    signal.setitimer(signal.ITIMER_REAL, 0)
                    signal.signal(signal.SIGALRM, previous_handler)
                if wake is not None:
                    signal.signal(wake, previous_wake)
                if previous_delay:
                    left = previous_delay - (time.monotonic() - start)
                    signal.setitimer(signal.ITIMER_REAL, max(left, 1e-3), previous_interval)
                break
            except DeadlineExpired:
                continue
    if (
        completed and state["fired"]
    ):  # the block caught every DeadlineExpired and went on: still too slow
        raise DeadlineExpired(f"ran past {seconds:g} s")
