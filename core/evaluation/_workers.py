"""Supervised worker processes: every call gets a deadline, an overrunning worker is killed.

``compare`` and ``batch`` hand their runs to :func:`run_supervised` as groups of
:class:`Task` (the runs of one plugin module form a group, so its numba kernels compile
once per worker). Up to ``workers`` processes each take a group and run its tasks one by
one. A task that does not finish within its ``timeout`` has its worker killed (SIGKILL:
a plugin stuck in compiled code cannot be interrupted any other way) and the rest of
its group goes on in a fresh worker. A worker that dies (segfault, out of memory,
``os._exit``) is reported the same way. Every task ends in exactly one :class:`Outcome`.

Workers are ``spawn`` processes (fresh interpreters: no inherited locks or threads).
Inside a daemonic process (a Dask worker), where ``multiprocessing`` may not start
children, a worker is a plain ``subprocess`` talking over a private socket pair.
"""
from __future__ import annotations

import multiprocessing as mp
import signal
import socket
import subprocess
import sys
import time
import traceback
from collections import deque
from dataclasses import dataclass
from multiprocessing.connection import Connection, wait
from typing import Any, Callable, Hashable, Iterable, Sequence

from .. import config

__all__ = ["Task", "Outcome", "run_supervised", "DONE", "ERROR", "TIMEOUT", "DIED"]

DONE, ERROR, TIMEOUT, DIED = "done", "error", "timeout", "died"


@dataclass(frozen=True)
class Task:
    """``fn(*args)`` to run in a worker; ``fn`` and ``args`` must pickle.

    key : identifies the task in its :class:`Outcome`
    timeout : seconds allowed once the worker has received the task (None: no limit)
    """

    key: Hashable
    fn: Callable
    args: tuple = ()
    timeout: float | None = None


@dataclass
class Outcome:
    """How a task ended.

    status : ``"done"`` (``value`` holds the return value), ``"error"`` (the call raised, or its
        task or result did not pickle), ``"timeout"`` or ``"died"``; ``message`` says what happened.
    started : whether the worker had received the task (False: it was still starting up or
        importing the task's module when it ran out of time or died).
    seconds : wall time from handing the task to the worker until the outcome.
    """

    key: Hashable
    status: str
    value: Any = None
    message: str = ""
    started: bool = False
    seconds: float = 0.0


# ---------------------------------------------------------------------------------------
# Worker side
# ---------------------------------------------------------------------------------------
def _describe(exc: BaseException) -> str:
    text = " ".join(str(exc).split())
    return f"{type(exc).__name__}: {text}" if text else type(exc).__name__


def _serve(conn: Connection) -> None:
    """The worker loop: receive ``(fn, args)``, answer ``("started",)`` then ``("done", value)``
    or ``("error", message, traceback)``; ``None`` or a closed connection ends it."""
    signal.signal(signal.SIGINT, signal.SIG_IGN)  # Ctrl-C is the parent's to handle
    while True:
        try:
            message = conn.recv()
        except (EOFError, OSError):
            return
        except Exception as exc:  # the task did not unpickle, e.g. its module cannot be imported here
            conn.send(("error", f"the worker could not load the task: {_describe(exc)}", traceback.format_exc(limit=-6)))
            continue
        if message is None:
            return
        fn, args = message
        conn.send(("started",))
        try:
            value = fn(*args)
        except BaseException as exc:  # incl. SystemExit from a plugin: reported, the worker stays
            conn.send(("error", _describe(exc), traceback.format_exc(limit=-6)))
            continue
        try:
            conn.send(("done", value))  # pickled completely before anything is sent
        except Exception as exc:
            conn.send(("error", f"the result could not be sent back from the worker: {_describe(exc)}", ""))


def _serve_socket() -> None:
    """Entry of a subprocess worker: ``python -c ... FD``; the first message is ``sys.path``."""
    conn = Connection(int(sys.argv[1]))
    sys.path[:] = conn.recv()
    _serve(conn)


# ---------------------------------------------------------------------------------------
# Parent side
# ---------------------------------------------------------------------------------------
class _Worker:
    """One worker process and its connection, started by multiprocessing or subprocess."""

    def __init__(self):
        self.group: deque[Task] | None = None
        self.task: Task | None = None
        self.sent_at = self.started_at = 0.0
        self._start()

    def _start(self) -> None:
        if mp.current_process().daemon:
            self._start_subprocess()
            return
        ctx = mp.get_context("spawn")
        self.conn, child = ctx.Pipe(duplex=True)
        self.process = ctx.Process(target=_serve, args=(child,), name="faceretarget-worker")
        self.process.start()
        child.close()
        self.popen = None

    def restart(self) -> None:
        """Kill this worker's process and start a fresh one (the group stays)."""
        self.kill()
        self.task = None
        self._start()

    def _start_subprocess(self) -> None:
        ours, theirs = socket.socketpair()
        code = "from faceretarget.evaluation._workers import _serve_socket; _serve_socket()"
        self.popen = subprocess.Popen([sys.executable, "-c", code, str(theirs.fileno())], pass_fds=(theirs.fileno(),))
        theirs.close()
        self.conn = Connection(ours.detach())
        self.conn.send(list(sys.path))
        self.process = None

    def send(self, task: Task) -> None:
        self.task, self.sent_at, self.started_at = task, time.monotonic(), 0.0
        self.conn.send((task.fn, task.args))

    def deadline(self) -> float:
        """Monotonic time by which the current task must finish (inf: no limit)."""
        limit = self.task.timeout
        if limit is None:
            return float("inf")
        if self.started_at:
            return self.started_at + limit
        return self.sent_at + max(limit, config.WORKER_STARTUP_SECONDS)

    def exit_note(self) -> str:
        code = self.process.exitcode if self.process is not None else self.popen.poll()
        if code is None:
            return "its worker process stopped answering"
        if code < 0:
            try:
                return f"its worker process was killed by {signal.Signals(-code).name}"
            except ValueError:
                return f"its worker process was killed by signal {-code}"
        return f"its worker process exited with code {code}"

    def wait_exit(self, seconds: float) -> None:
        if self.process is not None:
            self.process.join(seconds)
        else:
            try:
                self.popen.wait(seconds)
            except subprocess.TimeoutExpired:
                pass

    def kill(self) -> None:
        if self.process is not None:
            if self.process.is_alive():
                self.process.kill()
            self.process.join(5)
        elif self.popen.poll() is None:
            self.popen.kill()
            self.popen.wait(5)
        self.conn.close()

    def close(self) -> None:
        """Ask the worker to finish, then make sure it has."""
        try:
            self.conn.send(None)
        except OSError:
            pass
        self.wait_exit(5)
        self.kill()


def run_supervised(
    groups: Iterable[Sequence[Task]],
    *,
    workers: int,
    on_outcome: Callable[[Outcome], None],
) -> None:
    """Run every task of ``groups`` in at most ``workers`` processes; call ``on_outcome``
    (in this process, in completion order) once per task.

    The tasks of a group run in order in one worker (a replacement after a kill).
    Each task's clock starts when its worker acknowledges it; before that (spawn and
    import of the task's module) it has ``max(timeout, config.WORKER_STARTUP_SECONDS)``.
    """
    queue = deque(deque(group) for group in groups if group)
    pool: list[_Worker] = []

    def next_task(worker: _Worker) -> bool:
        """Hand ``worker`` its next task; False (and the worker closed and gone) when none is left."""
        while True:
            while not worker.group:
                if not queue:
                    worker.close()
                    pool.remove(worker)
                    return False
                worker.group = queue.popleft()
            task = worker.group.popleft()
            try:
                worker.send(task)
                return True
            except OSError as exc:  # the worker died before it could take the task
                on_outcome(Outcome(task.key, DIED, message=f"{worker.exit_note()} before it could take the task ({_describe(exc)})"))
                worker.restart()
            except Exception as exc:  # the task does not pickle; nothing was sent
                on_outcome(Outcome(task.key, ERROR, message=f"the task could not be handed to a worker process: {_describe(exc)}"))

    def add_worker() -> None:
        worker = _Worker()
        pool.append(worker)
        next_task(worker)

    def replace(worker: _Worker) -> None:
        worker.restart()
        next_task(worker)

    try:
        while queue and len(pool) < workers:
            add_worker()
        while pool:
            now = time.monotonic()
            soonest = min(w.deadline() for w in pool)
            ready = wait([w.conn for w in pool], timeout=None if soonest == float("inf") else max(0.0, soonest - now))
            now = time.monotonic()
            for worker in [w for w in pool if w.conn in ready]:
                task = worker.task
                try:
                    message = worker.conn.recv()
                except (EOFError, OSError):
                    worker.wait_exit(1)
                    on_outcome(Outcome(task.key, DIED, message=f"{worker.exit_note()} while running it",
                                       started=bool(worker.started_at), seconds=now - worker.sent_at))
                    replace(worker)
                    continue
                if message[0] == "started":
                    worker.started_at = now
                    continue
                if message[0] == "done":
                    outcome = Outcome(task.key, DONE, value=message[1], started=True, seconds=now - worker.sent_at)
                else:
                    outcome = Outcome(task.key, ERROR, message=message[1], started=bool(worker.started_at), seconds=now - worker.sent_at)
                    outcome.value = message[2] or None  # the worker's traceback, for --debug
                on_outcome(outcome)
                next_task(worker)
            for worker in [w for w in pool if w.deadline() <= now]:
                task = worker.task
                if worker.started_at:
                    note = f"did not finish within its time limit of {task.timeout:g} s"
                else:
                    allowed = max(task.timeout, config.WORKER_STARTUP_SECONDS)
                    note = f"did not even start within {allowed:g} s (importing its module?)"
                on_outcome(Outcome(task.key, TIMEOUT, message=f"{note}; its worker process was stopped",
                                   started=bool(worker.started_at), seconds=now - worker.sent_at))
                replace(worker)
            while queue and len(pool) < workers:  # a finished worker's slot, or a group left behind
                add_worker()
    finally:
        for worker in pool:
            worker.kill()
