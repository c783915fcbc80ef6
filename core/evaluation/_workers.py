"""Supervised worker processes: every call gets a deadline, an overrunning worker is killed.

``compare`` and ``batch`` hand their runs to :func:`run_supervised` as groups of
:class:`Task` (the runs of one plugin module form a group, so its numba kernels compile
once per worker). Up to ``workers`` processes each take a group and run its tasks one by
one. A task that does not finish within its ``timeout`` has its worker killed (SIGKILL to
the worker's whole process group: a plugin stuck in compiled code, or one that started
helper processes, cannot be stopped any other way) and the rest of its group goes on in
a fresh worker. A worker that dies (segfault, out of memory, ``os._exit``) is reported
the same way. Every task ends in exactly one :class:`Outcome`.

Workers are ``spawn`` processes (fresh interpreters: no inherited locks or threads).
Inside a daemonic process (a Dask worker), where ``multiprocessing`` may not start
children, a worker is a plain ``subprocess`` talking over a private socket pair. Each
worker leads its own process group and dies with the process that supervises it.
"""
from __future__ import annotations

import multiprocessing as mp
import os
import signal
import socket
import subprocess
import sys
import threading
import time
import traceback
from collections import deque
from dataclasses import dataclass
from multiprocessing.connection import Connection, wait
from multiprocessing.reduction import ForkingPickler
from typing import Any, Callable, Hashable, Iterable, Sequence

from .. import config
from ..errors import ConfigError, PluginError, PluginTimeoutError

__all__ = ["Task", "Outcome", "run_supervised", "DONE", "ERROR", "TIMEOUT", "DIED"]

DONE, ERROR, TIMEOUT, DIED = "done", "error", "timeout", "died"

#: Longest wait between checks of the workers' exit status (for systems without pidfd).
_POLL_SECONDS = 2.0

#: Payloads larger than this are written by a helper thread, so a worker still starting
#: up cannot block the supervisor (a socket buffer holds a few hundred KiB).
_DIRECT_SEND_BYTES = 64 * 1024


@dataclass(frozen=True)
class Task:
    """``fn(*args)`` to run in a worker; ``fn`` and ``args`` must pickle.

    key : identifies the task in its :class:`Outcome`
    timeout : seconds allowed once the worker has loaded the task (None: no limit)
    """

    key: Hashable
    fn: Callable
    args: tuple = ()
    timeout: float | None = None


@dataclass
class Outcome:
    """How a task ended.

    status : ``"done"`` (``value`` holds the return value), ``"error"`` (the call raised, or
        its task or result could not be moved between processes; ``value`` may hold the
        worker's traceback), ``"timeout"`` or ``"died"``; ``message`` says what happened.
    started : whether the worker had loaded the task and begun the call (False: it was
        still starting up or loading the task's modules and data).
    seconds : wall time from handing the task over until the outcome.
    """

    key: Hashable
    status: str
    value: Any = None
    message: str = ""
    started: bool = False
    seconds: float = 0.0

    def error(self) -> PluginError:
        """The failure as an exception: :class:`PluginTimeoutError` for a timeout, else :class:`PluginError`."""
        return (PluginTimeoutError if self.status == TIMEOUT else PluginError)(self.message)


# ---------------------------------------------------------------------------------------
# Worker side
# ---------------------------------------------------------------------------------------
def _describe(exc: BaseException) -> str:
    text = " ".join(str(exc).split())
    return f"{type(exc).__name__}: {text}" if text else type(exc).__name__


def _die_with(parent_pid: int) -> None:
    """End this worker when its supervisor is gone (killed, crashed, shut down)."""
    try:  # Linux: the kernel sends SIGKILL when the parent exits
        import ctypes

        libc = ctypes.CDLL(None, use_errno=True)
        libc.prctl(1, signal.SIGKILL, 0, 0, 0)  # PR_SET_PDEATHSIG
    except (OSError, AttributeError):
        pass

    def watch() -> None:  # elsewhere (and for the instant before prctl): poll the parent
        while os.getppid() == parent_pid:
            time.sleep(1.0)
        os._exit(70)

    if os.getppid() != parent_pid:
        os._exit(70)
    threading.Thread(target=watch, name="faceretarget-parent-watch", daemon=True).start()


def _serve(conn: Connection, parent_pid: int) -> None:
    """The worker loop: receive ``(fn, args)``, answer ``("started", t)`` then ``("done", value)``
    or ``("error", message, traceback)``; ``None`` or a closed connection ends it."""
    signal.signal(signal.SIGINT, signal.SIG_IGN)  # Ctrl-C is the parent's to handle
    try:
        os.setsid()  # own process group: a kill reaches helper processes a plugin starts
    except OSError:
        pass
    _die_with(parent_pid)
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
        conn.send(("started", time.monotonic()))
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
    """Entry of a subprocess worker: ``python -c ... FD PARENT_PID``; the first message is ``sys.path``."""
    conn = Connection(int(sys.argv[1]))
    sys.path[:] = conn.recv()
    _serve(conn, int(sys.argv[2]))


# ---------------------------------------------------------------------------------------
# Parent side
# ---------------------------------------------------------------------------------------
class _Worker:
    """One worker process and its connection, started by multiprocessing or subprocess."""

    def __init__(self):
        self.group: deque[Task] | None = None
        self.task: Task | None = None
        self.sent_at = self.started_at = 0.0
        self._writer: threading.Thread | None = None
        self._start()

    def _start(self) -> None:
        self.task = None
        if mp.current_process().daemon:
            self._start_subprocess()
            return
        ctx = mp.get_context("spawn")
        self.conn, child = ctx.Pipe(duplex=True)
        self.process = ctx.Process(target=_serve, args=(child, os.getpid()), name="faceretarget-worker")
        self.process.start()
        child.close()
        self.popen = None
        self.pid = self.process.pid
        self._watch_exit()

    def _start_subprocess(self) -> None:
        ours, theirs = socket.socketpair()
        code = "from faceretarget.evaluation._workers import _serve_socket; _serve_socket()"
        argv = [sys.executable, "-c", code, str(theirs.fileno()), str(os.getpid())]
        self.popen = subprocess.Popen(argv, pass_fds=(theirs.fileno(),))
        theirs.close()
        self.conn = Connection(ours.detach())
        self.conn.send(list(sys.path))
        self.process = None
        self.pid = self.popen.pid
        self._watch_exit()

    def _watch_exit(self) -> None:
        """``self.sentinel``: a handle that becomes ready when the process exits, even if a
        helper process it started still holds its pipes (a pidfd, Linux 5.3+), else None
        (the supervisor then polls)."""
        try:
            self._pidfd = os.pidfd_open(self.pid)
        except (AttributeError, OSError):
            self._pidfd = None
        self.sentinel = self._pidfd

    def restart(self) -> None:
        """Kill this worker's process and start a fresh one (the group stays)."""
        self.kill()
        self._start()

    def send(self, task: Task, payload: bytes) -> None:
        """Hand over ``task`` (already pickled as ``payload``); big payloads are written by a thread."""
        self.task, self.sent_at, self.started_at = task, time.monotonic(), 0.0
        if len(payload) <= _DIRECT_SEND_BYTES:
            self.conn.send_bytes(payload)
            return

        def write() -> None:
            try:
                self.conn.send_bytes(payload)
            except OSError:  # the worker died or was killed meanwhile; noticed by the supervisor
                pass

        self._writer = threading.Thread(target=write, name="faceretarget-task-writer", daemon=True)
        self._writer.start()

    def exited(self) -> bool:
        return (self.process.exitcode if self.process is not None else self.popen.poll()) is not None

    def deadline(self) -> float:
        """Monotonic time by which the current task must finish (inf: no limit)."""
        limit = self.task.timeout if self.task is not None else None
        if limit is None:
            return float("inf")
        if self.started_at:
            return self.started_at + limit
        return self.sent_at + max(limit, config.WORKER_STARTUP_SECONDS)

    def exit_note(self) -> str:
        self.wait_exit(1)
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
        """Wait up to ``seconds`` for the process to exit (polling: its pipes may outlive it)."""
        end = time.monotonic() + seconds
        while not self.exited() and time.monotonic() < end:
            time.sleep(0.02)

    def kill(self) -> None:
        """SIGKILL the worker and its process group; close the connection."""
        for target in (lambda: os.killpg(self.pid, signal.SIGKILL), lambda: os.kill(self.pid, signal.SIGKILL)):
            try:
                target()
            except (ProcessLookupError, PermissionError, OSError):
                pass
        self.wait_exit(5)
        if self._writer is not None:
            self._writer.join(5)  # it fails fast once the peer is gone; never write into a reused fd
            self._writer = None
        self.conn.close()
        if self._pidfd is not None:
            os.close(self._pidfd)
            self._pidfd = None

    def close(self) -> None:
        """Ask the worker to finish, then make sure it has."""
        try:
            self.conn.send(None)
        except OSError:
            pass
        self.wait_exit(5)
        self.kill()


def _check(workers: int, tasks: list[deque[Task]]) -> None:
    if isinstance(workers, bool) or not isinstance(workers, int) or workers < 1:
        raise ConfigError(f"run_supervised: workers must be an integer >= 1, got {workers!r}")
    for group in tasks:
        for task in group:
            if task.timeout is not None and not (0 < task.timeout < float("inf")):
                raise ConfigError(f"task {task.key!r}: timeout must be None (no limit) or a positive number of seconds, got {task.timeout!r}")


def run_supervised(
    groups: Iterable[Sequence[Task]],
    *,
    workers: int,
    on_outcome: Callable[[Outcome], None],
) -> None:
    """Run every task of ``groups`` in at most ``workers`` processes; call ``on_outcome``
    (in this process, in completion order) once per task.

    The tasks of a group run in order in one worker (a replacement after a kill).
    A task's clock starts when its worker has loaded it (unpickled its function and
    arguments, which may import a plugin or build a case); loading gets
    ``max(timeout, config.WORKER_STARTUP_SECONDS)`` from the hand-over, start-up included.
    """
    queue = deque(deque(group) for group in groups if group)
    _check(workers, list(queue))
    pool: list[_Worker] = []

    def next_task(worker: _Worker) -> None:
        """Hand ``worker`` its next task, or close it and drop it from the pool when none is left."""
        while True:
            while not worker.group:
                if not queue:
                    worker.close()
                    pool.remove(worker)
                    return
                worker.group = queue.popleft()
            task = worker.group.popleft()
            try:
                payload = bytes(ForkingPickler.dumps((task.fn, task.args)))
            except Exception as exc:  # the task does not pickle; nothing was sent
                on_outcome(Outcome(task.key, ERROR, message=f"the task could not be handed to a worker process: {_describe(exc)}"))
                continue
            try:
                worker.send(task, payload)
                return
            except OSError as exc:  # the worker died before it could take the task
                on_outcome(Outcome(task.key, DIED, message=f"{worker.exit_note()} before it could take the task ({_describe(exc)})"))
                worker.restart()

    def add_worker() -> None:
        worker = _Worker()
        pool.append(worker)
        next_task(worker)

    def finish(worker: _Worker, outcome: Outcome, *, restart: bool) -> None:
        on_outcome(outcome)
        if restart:
            if not (worker.group or queue):
                worker.kill()
                pool.remove(worker)
                return
            worker.restart()
        next_task(worker)

    def died(worker: _Worker, now: float) -> None:
        when = "while running it" if worker.started_at else "while loading it"
        outcome = Outcome(worker.task.key, DIED, message=f"{worker.exit_note()} {when}", started=bool(worker.started_at), seconds=now - worker.sent_at)
        finish(worker, outcome, restart=True)

    def receive(worker: _Worker, now: float) -> None:
        task = worker.task
        try:
            message = worker.conn.recv()
        except (EOFError, OSError):
            died(worker, now)
            return
        except Exception as exc:  # the result pickled in the worker but does not load here
            outcome = Outcome(task.key, ERROR, message=f"its result could not be loaded by the supervising process: {_describe(exc)}",
                              started=True, seconds=now - worker.sent_at)
            finish(worker, outcome, restart=False)
            return
        if message[0] == "started":
            worker.started_at = message[1]
            return
        if message[0] == "done":
            finish(worker, Outcome(task.key, DONE, value=message[1], started=True, seconds=now - worker.sent_at), restart=False)
        else:
            outcome = Outcome(task.key, ERROR, value=message[2] or None, message=message[1], started=bool(worker.started_at), seconds=now - worker.sent_at)
            finish(worker, outcome, restart=False)

    def overran(worker: _Worker, now: float) -> None:
        task = worker.task
        if worker.started_at:
            note = f"did not finish within its time limit of {task.timeout:g} s"
        else:
            note = f"was not even loaded within {max(task.timeout, config.WORKER_STARTUP_SECONDS):g} s (worker start-up, imports, input data)"
        outcome = Outcome(task.key, TIMEOUT, message=f"{note}; its worker process was stopped", started=bool(worker.started_at), seconds=now - worker.sent_at)
        finish(worker, outcome, restart=True)

    try:
        while queue and len(pool) < workers:
            add_worker()
        while pool:
            soonest = min(w.deadline() for w in pool)
            handles = [w.conn for w in pool] + [w.sentinel for w in pool if w.sentinel is not None]
            pause = min(max(0.0, soonest - time.monotonic()), _POLL_SECONDS)
            ready = set(wait(handles, timeout=pause))
            now = time.monotonic()
            for worker in list(pool):
                if worker not in pool or worker.task is None:
                    continue
                if worker.conn in ready or worker.conn.poll(0):
                    receive(worker, now)  # one message per round: results before deaths and deadlines
                elif worker.sentinel in ready or worker.exited():
                    died(worker, now)  # e.g. a helper process still holds the connection open
                elif worker.deadline() <= now:
                    overran(worker, now)
            while queue and len(pool) < workers:  # a finished worker's slot, or a group left behind
                add_worker()
    finally:
        for worker in pool:
            worker.kill()
