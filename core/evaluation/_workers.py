"""Supervised worker processes: every call gets a deadline, an overrunning worker is killed.

``compare`` and ``batch`` hand their runs to :func:`run_supervised` as groups of
:class:`Task` (the runs of one plugin module form a group, so its numba kernels compile
once per worker). Up to ``workers`` processes each take a group and run its tasks one by
one; a worker moving on to another owner's tasks is replaced first, so a failure is
always charged to the owner that caused it (a third-party plugin, or the built-ins
together: :func:`plugin_owner`). A task that does not finish within its
``timeout`` has its worker killed with everything it started (a plugin stuck in compiled
code, or one that started helper processes, cannot be stopped any other way) and the
rest of its group goes on in a fresh worker. A worker that dies
(segfault, out of memory, ``os._exit``) is reported the same way. Every task ends in
exactly one :class:`Outcome`.

A worker is a fresh interpreter (``python -c``) prepared the way ``multiprocessing``'s
spawn prepares its children (``sys.path``, working directory, the main module as
``__mp_main__``), talking to the supervisor over a private socket pair; unlike a
``multiprocessing`` child it can also be started inside a daemonic process (a Dask
worker). Each worker is started by a *shepherd* (:mod:`._shepherd`, standard library
only, no plugin code): on Linux a child subreaper, so a helper a plugin starts with
``start_new_session=True`` or a double-forked daemon stays in its process tree; when the
worker ends (killed on SIGTERM from the supervisor, or it exits or dies) the shepherd
stops and kills every descendant, then exits the way the worker did. Elsewhere only the
worker's own session is killed. The worker dies with its shepherd and the shepherd with
its supervisor (Linux: ``PR_SET_PDEATHSIG``; elsewhere they poll). Messages are pickled, as in
``multiprocessing``: only between a supervisor and the workers it started, never from files.
"""

from __future__ import annotations

import os
import signal
import socket
import subprocess
import sys
import threading
import time
import traceback
from collections import deque
from collections.abc import Callable, Hashable, Iterable, Mapping, Sequence
from dataclasses import dataclass
from multiprocessing import spawn
from multiprocessing.connection import Connection, wait
from multiprocessing.reduction import ForkingPickler
from typing import Any

from .. import config
from ..errors import PluginError, PluginTimeoutError

__all__ = ["Task", "Outcome", "run_supervised", "DONE", "ERROR", "TIMEOUT", "DIED"]

DONE, ERROR, TIMEOUT, DIED = "done", "error", "timeout", "died"

#: Longest wait between checks of the workers' exit status (for systems without pidfd).
_POLL_SECONDS = 2.0

#: Exit status of a worker whose connection broke or could not be read.
_BROKEN_CONNECTION = 75

#: The script that starts each worker and kills all its descendants when it ends.
_SHEPHERD = os.path.join(os.path.dirname(os.path.abspath(__file__)), "_shepherd.py")

#: Seconds a shepherd gets to kill its worker's process tree before it is killed itself.
_SHEPHERD_GRACE = 10.0


#: The owner (:class:`Task`) of every built-in plugin's tasks: the built-ins are one
#: distribution (ours: a crash there is our bug whichever built-in ran before), so they share
#: workers; a worker starting afresh (interpreter, imports, cases, cached kernels) cost
#: ~1-2 s of CPU, 7 times in a demo. A third-party plugin's tasks keep a worker of their own.
BUILTIN_OWNER = ("built-in plugins",)


def plugin_owner(plugin: str, builtin: bool) -> Hashable:
    """The :class:`Task` owner of a plugin's tasks: :data:`BUILTIN_OWNER` for a built-in,
    else the plugin itself (a worker never mixes two third-party plugins' tasks)."""
    return BUILTIN_OWNER if builtin else ("plugin", plugin)


@dataclass(frozen=True)
class Task:
    """``fn(*args)`` to run in a worker; ``fn`` and ``args`` must pickle.

    key : identifies the task in its :class:`Outcome`
    timeout : seconds allowed once the worker has loaded the task (None or 0: no limit;
        :func:`faceretarget.config.check_timeout`)
    owner : who is answerable for the task (:func:`plugin_owner`: a third-party plugin, or
        the built-ins together); a worker never runs tasks of two owners
    """

    key: Hashable
    fn: Callable
    args: tuple = ()
    timeout: float | None = None
    owner: Hashable = None

    def __post_init__(self) -> None:
        object.__setattr__(
            self, "timeout", config.check_timeout(self.timeout, f"task {self.key!r}: timeout")
        )


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


def _describe(exc: BaseException) -> str:
    text = " ".join(str(exc).split())
    return f"{type(exc).__name__}: {text}" if text else type(exc).__name__


# ---------------------------------------------------------------------------------------
# Worker side
# ---------------------------------------------------------------------------------------
def _die_with(parent_pid: int) -> None:
    """End this worker (and its process group) when its supervisor is gone."""
    try:  # Linux: the kernel kills this process when the parent exits
        import ctypes

        ctypes.CDLL(None, use_errno=True).prctl(1, signal.SIGKILL, 0, 0, 0)  # PR_SET_PDEATHSIG
    except (OSError, AttributeError):
        pass

    def stop() -> None:
        if hasattr(os, "killpg"):
            os.killpg(0, signal.SIGKILL)
        os._exit(_BROKEN_CONNECTION)

    def watch() -> None:  # elsewhere, and for helper processes: poll the parent
        while os.getppid() == parent_pid:
            time.sleep(1.0)
        stop()

    if os.getppid() != parent_pid:
        stop()
    threading.Thread(target=watch, name="faceretarget-parent-watch", daemon=True).start()


def _serve(conn: Connection) -> None:
    """The worker loop: receive ``(fn, args)``, answer ``("started", t)`` then ``("done", value)``
    or ``("error", message, traceback)``; ``None`` or a closed connection ends it."""
    while True:
        try:
            data = conn.recv_bytes()
        except EOFError:
            return
        except BaseException:  # a broken or unreadable connection cannot be resynchronised
            os._exit(_BROKEN_CONNECTION)
        try:
            message = ForkingPickler.loads(data)  # may import the plugin, build the case...
        except BaseException as exc:
            conn.send(
                (
                    "error",
                    f"the worker could not load the task: {_describe(exc)}",
                    traceback.format_exc(limit=-6),
                )
            )
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
            conn.send(
                (
                    "error",
                    f"the result could not be sent back from the worker: {_describe(exc)}",
                    "",
                )
            )


def _main() -> None:
    """Entry of a worker: ``python -c ... FD PARENT_PID`` (the parent is its shepherd, which
    started it in a session of its own); the first message prepares it."""
    signal.signal(signal.SIGINT, signal.SIG_IGN)  # Ctrl-C is the supervisor's to handle
    _die_with(int(sys.argv[2]))
    conn = Connection(int(sys.argv[1]))
    spawn.prepare(conn.recv())  # sys.path, cwd, the main module (classes defined in scripts)
    _serve(conn)


# ---------------------------------------------------------------------------------------
# Supervisor side
# ---------------------------------------------------------------------------------------
class _Worker:
    """One worker process: its connection, exit watch and current task.

    The process is reaped only in :meth:`kill`, after its group was signalled, so its
    process id cannot have been reused by then.
    """

    def __init__(self, env: Mapping[str, str] | None = None) -> None:
        self.group: deque[Task] | None = None
        self._env = None if env is None else dict(env)
        self._start()

    def _start(self) -> None:
        self.task: Task | None = None
        self.owner: Hashable = None
        self.used = False
        self.sent_at = self.started_at = 0.0
        self._writer: threading.Thread | None = None
        ours, theirs = socket.socketpair()
        code = "from faceretarget.evaluation._workers import _main; _main()"
        fd = theirs.fileno()
        # the shepherd starts the worker (appending its own pid, the worker's parent) and
        # kills every descendant of it when it ends; -I: it needs the standard library only
        argv = [
            sys.executable,
            "-I",
            _SHEPHERD,
            str(os.getpid()),
            f"--fd={fd}",
            sys.executable,
            "-c",
            code,
            str(fd),
        ]
        try:
            self.popen = subprocess.Popen(argv, pass_fds=(fd,), env=self._env)
        finally:
            theirs.close()
        self.pid = self.popen.pid
        self.conn = Connection(ours.detach())
        preparation = spawn.get_preparation_data("faceretarget-worker")
        preparation.pop("authkey", None)  # not needed: the socket pair is private
        main = preparation.get("init_main_from_path")
        if main is not None and not os.path.isfile(main):  # `python -` ('<stdin>'): no file to run
            del preparation["init_main_from_path"]
        self.conn.send(preparation)
        self.sentinel: int | None
        try:  # readable once the process has exited, even if a helper holds its pipes (Linux 5.3+)
            self.sentinel = os.pidfd_open(self.pid)
        except (AttributeError, OSError):
            self.sentinel = None

    def restart(self) -> None:
        """Kill this worker's process and start a fresh one (the group stays)."""
        self.kill()
        self._start()

    def send(self, task: Task, payload: bytes) -> None:
        """Hand over ``task`` (pickled as ``payload``) from a thread: a worker still starting
        up must not block the supervisor, whose deadlines keep running."""
        self.task, self.owner, self.used = task, task.owner, True
        self.sent_at, self.started_at = time.monotonic(), 0.0

        def write() -> None:
            try:
                self.conn.send_bytes(payload)
            except (OSError, TypeError, ValueError):  # the worker died or was killed meanwhile
                pass

        self._writer = threading.Thread(target=write, name="faceretarget-task-writer", daemon=True)
        self._writer.start()

    def status(self) -> os.waitid_result | int | None:
        """The exit status (``os.waitid_result``) without reaping, or None while running."""
        try:
            return os.waitid(os.P_PID, self.pid, os.WEXITED | os.WNOHANG | os.WNOWAIT)
        except ChildProcessError:  # already reaped (by Popen, or by someone else: status unknown)
            return self.popen.returncode if self.popen.returncode is not None else -signal.SIGKILL

    def exited(self) -> bool:
        return self.status() is not None

    def deadline(self) -> float:
        """Monotonic time by which the current task must finish (inf: no limit)."""
        limit = self.task.timeout if self.task is not None else None
        if limit is None:
            return float("inf")
        if self.started_at:
            return self.started_at + limit
        return self.sent_at + max(limit, config.WORKER_STARTUP_SECONDS)

    def exit_note(self) -> str:
        end = time.monotonic() + 1.0
        while not self.exited() and time.monotonic() < end:
            time.sleep(0.02)
        status = self.status()
        if status is None:
            return "its worker process stopped answering"
        if isinstance(status, int):
            code, killed = abs(status), status < 0
        else:
            code, killed = status.si_status, status.si_code != os.CLD_EXITED
        if killed:
            try:
                return f"its worker process was killed by {signal.Signals(code).name}"
            except ValueError:
                return f"its worker process was killed by signal {code}"
        return f"its worker process exited with code {code}"

    def kill(self) -> None:
        """Stop the worker and everything it started, reap its shepherd, close the connection.

        SIGTERM asks the shepherd (still unreaped, so the id is its own) to kill the worker's
        whole process tree; one that does not exit within ``_SHEPHERD_GRACE`` seconds is
        killed (the worker then dies with it: ``PR_SET_PDEATHSIG``, or its parent watch)."""
        if self.popen.returncode is None:
            try:
                os.kill(self.pid, signal.SIGTERM)
            except OSError:
                pass
            try:
                self.popen.wait(_SHEPHERD_GRACE)
            except subprocess.TimeoutExpired:
                try:
                    os.kill(self.pid, signal.SIGKILL)
                except OSError:
                    pass
                try:
                    self.popen.wait(10)
                except subprocess.TimeoutExpired:
                    pass
        try:  # wake a writer blocked on a full socket, so it ends before the fd is closed
            with socket.socket(fileno=os.dup(self.conn.fileno())) as sock:
                sock.shutdown(socket.SHUT_RDWR)
        except OSError:
            pass
        if self._writer is not None:
            self._writer.join()
            self._writer = None
        self.conn.close()
        if self.sentinel is not None:
            os.close(self.sentinel)
            self.sentinel = None

    def close(self) -> None:
        """Ask the worker to finish, then make sure it has."""
        if self._writer is not None:
            self._writer.join(5)
        try:
            self.conn.send(None)
        except OSError:
            pass
        end = time.monotonic() + 5.0
        while not self.exited() and time.monotonic() < end:
            time.sleep(0.02)
        self.kill()


def _check(workers: int, tasks: list[deque[Task]]) -> None:
    config.check_jobs(workers, "run_supervised: workers")


#: Thread counts pinned to 1 in the processes of a pool, so n processes do not each start
#: a thread per core (BLAS and numba threads that spin on 2 cores waste most of the CPU).
THREAD_VARIABLES = (
    "OMP_NUM_THREADS",
    "OPENBLAS_NUM_THREADS",
    "MKL_NUM_THREADS",
    "NUMBA_NUM_THREADS",
)


def single_threaded_environ() -> dict[str, str]:
    """This process's environment with the :data:`THREAD_VARIABLES` the user did not set
    pinned to 1: for child processes. This process's own environment stays as it is (numba
    re-reads ``NUMBA_*`` variables at every compilation and raises if the thread count
    changes once its threads run)."""
    return {**{k: "1" for k in THREAD_VARIABLES}, **os.environ}


def run_supervised(
    groups: Iterable[Sequence[Task]],
    *,
    workers: int,
    on_outcome: Callable[[Outcome], None],
    env: Mapping[str, str] | None = None,
) -> None:
    """Run every task of ``groups`` in at most ``workers`` processes; call ``on_outcome``
    (in this process, in completion order) once per task. ``env``: the workers'
    environment (default this process's; e.g. :func:`single_threaded_environ`).

    The tasks of a group run in order in one worker (a replacement after a kill); a
    worker takes groups of one ``owner`` only (else it is replaced first). A task's clock
    starts when its worker has loaded it (unpickled its function and arguments, which may
    import a plugin or build a case); loading gets ``max(timeout,
    config.WORKER_STARTUP_SECONDS)`` from the hand-over, start-up included.
    """
    queue = deque(deque(group) for group in groups if group)
    _check(workers, list(queue))
    pool: list[_Worker] = []

    def take_group(worker: _Worker) -> bool:
        """Give ``worker`` a new group (one of its owner's if queued); False if none is left."""
        if not queue:
            return False
        same = next((g for g in queue if g[0].owner == worker.owner), None) if worker.used else None
        group = same or queue[0]
        queue.remove(group)
        if worker.used and group[0].owner != worker.owner:
            worker.restart()  # another plugin's tasks: a clean process, so blame stays right
        worker.group = group
        return True

    def next_task(worker: _Worker) -> None:
        """Hand ``worker`` its next task, or close it and drop it from the pool when none is left."""
        while True:
            if not worker.group and not take_group(worker):
                worker.close()
                pool.remove(worker)
                return
            assert worker.group  # take_group gave it one
            task = worker.group.popleft()
            try:
                payload = bytes(ForkingPickler.dumps((task.fn, task.args)))
            except Exception as exc:  # the task does not pickle; nothing was sent
                on_outcome(
                    Outcome(
                        task.key,
                        ERROR,
                        message=f"the task could not be handed to a worker process: {_describe(exc)}",
                    )
                )
                continue
            worker.send(task, payload)
            return

    def add_worker() -> None:
        worker = _Worker(env)
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
        assert worker.task is not None  # a worker in the pool has been sent a task
        outcome = Outcome(
            worker.task.key,
            DIED,
            message=f"{worker.exit_note()} {when}",
            started=bool(worker.started_at),
            seconds=now - worker.sent_at,
        )
        finish(worker, outcome, restart=True)

    def receive(worker: _Worker, now: float) -> None:
        task = worker.task
        assert task is not None  # a worker in the pool has been sent a task
        try:
            data = worker.conn.recv_bytes()
        except (EOFError, OSError):
            died(worker, now)
            return
        try:
            message = ForkingPickler.loads(data)
        except Exception as exc:  # the result pickled in the worker but does not load here
            outcome = Outcome(
                task.key,
                ERROR,
                message=f"its result could not be loaded by the supervising process: {_describe(exc)}",
                started=True,
                seconds=now - worker.sent_at,
            )
            finish(worker, outcome, restart=False)
            return
        if message[0] == "started":
            worker.started_at = message[1]
            return
        if message[0] == "done":
            finish(
                worker,
                Outcome(
                    task.key, DONE, value=message[1], started=True, seconds=now - worker.sent_at
                ),
                restart=False,
            )
        else:
            outcome = Outcome(
                task.key,
                ERROR,
                value=message[2] or None,
                message=message[1],
                started=bool(worker.started_at),
                seconds=now - worker.sent_at,
            )
            finish(worker, outcome, restart=False)

    def overran(worker: _Worker, now: float) -> None:
        task = worker.task
        # only a task with a time limit overruns (its worker's deadline() is inf otherwise)
        assert task is not None and task.timeout is not None
        if worker.started_at:
            note = f"did not finish within its time limit of {task.timeout:g} s"
        else:
            note = f"was not even loaded within {max(task.timeout, config.WORKER_STARTUP_SECONDS):g} s (worker start-up, imports, input data)"
        outcome = Outcome(
            task.key,
            TIMEOUT,
            message=f"{note}; its worker process was stopped",
            started=bool(worker.started_at),
            seconds=now - worker.sent_at,
        )
        finish(worker, outcome, restart=True)

    try:
        while queue and len(pool) < workers:
            add_worker()
        while pool:
            soonest = min(w.deadline() for w in pool)
            handles = [w.conn for w in pool] + [w.sentinel for w in pool if w.sentinel is not None]
            ready = set(
                wait(handles, timeout=min(max(0.0, soonest - time.monotonic()), _POLL_SECONDS))
            )
            now = time.monotonic()
            for worker in list(pool):
                if worker not in pool or worker.task is None:
                    continue
                if worker.conn in ready or worker.conn.poll(0):
                    receive(
                        worker, now
                    )  # one message per round: results before deaths and deadlines
                elif worker.sentinel in ready or worker.exited():
                    died(worker, now)  # e.g. a helper process still holds the connection open
                elif worker.deadline() <= now:
                    overran(worker, now)
            while queue and len(pool) < workers:  # a finished worker's slot, or a group left behind
                add_worker()
    finally:
        for worker in pool:
            worker.kill()
