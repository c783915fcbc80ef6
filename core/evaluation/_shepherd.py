"""The shepherd of one worker process: when the worker ends, nothing it started survives.

Run as a script (standard library only, no plugin code ever runs in it)::

    python _shepherd.py SUPERVISOR_PID WORKER_ARGV...

It starts the worker (``WORKER_ARGV`` plus its own process id, the worker's parent) in
a session of its own and waits. When the worker exits or dies, when the supervisor
sends SIGTERM (a task overran its time limit), or when the supervisor is gone, it kills
every descendant of the worker and then exits the way the worker did (same exit code,
or killed by the same signal), so the supervisor reads the worker's fate from it.

On Linux the shepherd is a *child subreaper* (``prctl(PR_SET_CHILD_SUBREAPER)``): a
helper a plugin started with ``start_new_session=True``, or a daemon that double-forked,
is re-parented to the shepherd instead of to init when its parent dies, so it stays in
the shepherd's process tree, where it is found (``/proc``), stopped (SIGSTOP, so it
cannot fork any more) and killed (SIGKILL). Elsewhere only the worker's own session is
killed (``killpg``): a helper that left it survives.
"""

from __future__ import annotations

import os
import signal
import subprocess
import sys
import time
from types import FrameType

PR_SET_PDEATHSIG = 1
PR_SET_CHILD_SUBREAPER = 36

#: Seconds between checks of the worker and the supervisor.
_POLL = 0.05

#: Exit status when the worker could not be started at all.
_NO_WORKER = 70


def _prctl(option: int, value: int) -> bool:
    if not sys.platform.startswith("linux"):
        return False
    try:
        import ctypes

        return ctypes.CDLL(None, use_errno=True).prctl(option, value, 0, 0, 0) == 0
    except (OSError, AttributeError):
        return False


def _children_map() -> dict[int, list[int]]:
    """parent pid -> child pids, from ``/proc`` (empty where there is none)."""
    out: dict[int, list[int]] = {}
    try:
        names = os.listdir("/proc")
    except OSError:
        return out
    for name in names:
        if not name.isdigit():
            continue
        try:
            with open(f"/proc/{name}/stat", "rb") as f:
                stat = f.read()
        except OSError:  # exited meanwhile
            continue
        try:
            ppid = int(stat.rsplit(b")", 1)[1].split()[1])
        except (IndexError, ValueError):
            continue
        out.setdefault(ppid, []).append(int(name))
    return out


def _descendants(root: int) -> set[int]:
    children = _children_map()
    found, todo = set(), [root]
    while todo:
        for child in children.get(todo.pop(), ()):
            if child not in found:
                found.add(child)
                todo.append(child)
    return found


def _signal(pid: int, sig: int) -> None:
    try:
        os.kill(pid, sig)
    except OSError:
        pass


def kill_tree(worker_pid: int | None) -> None:
    """SIGKILL every descendant of this process (and the worker's session while the worker's
    process id is still its own, i.e. not yet reaped), then reap them."""
    if worker_pid is not None and hasattr(os, "killpg"):
        try:
            os.killpg(worker_pid, signal.SIGKILL)  # its session (on every POSIX system)
        except OSError:
            pass
    me = os.getpid()
    stopped: set[int] = set()
    for _ in range(100):  # stop the tree first, so that nothing forks while it is being killed
        new = _descendants(me) - stopped
        if not new:
            break
        for pid in new:
            _signal(pid, signal.SIGSTOP)
        stopped |= new
    for pid in stopped:
        _signal(pid, signal.SIGKILL)
        _signal(pid, signal.SIGCONT)
    end = time.monotonic() + 10.0
    while time.monotonic() < end:  # reap what was killed (re-parented ones are our children now)
        try:
            pid, _ = os.waitpid(-1, os.WNOHANG)
        except ChildProcessError:
            return
        if pid == 0:
            if not _descendants(me):
                return
            time.sleep(0.01)


def _exit_like(status: int) -> None:
    """Exit with the worker's wait status: the same code, or killed by the same signal."""
    sys.stdout.flush()
    sys.stderr.flush()
    if os.WIFSIGNALED(status):
        sig = os.WTERMSIG(status)
        try:
            import resource

            resource.setrlimit(
                resource.RLIMIT_CORE, (0, 0)
            )  # the worker's crash, not ours: no core file
        except (ImportError, OSError, ValueError):
            pass
        try:
            signal.signal(sig, signal.SIG_DFL)
            signal.pthread_sigmask(signal.SIG_UNBLOCK, {sig})
        except (OSError, ValueError):
            pass
        os.kill(os.getpid(), sig)
        time.sleep(1.0)
        os._exit(128 + sig)
    os._exit(os.WEXITSTATUS(status) if os.WIFEXITED(status) else _NO_WORKER)


def main(argv: list[str]) -> None:
    supervisor = int(argv[0])
    stop = {"requested": False}

    def request_stop(signum: int, frame: FrameType | None) -> None:
        stop["requested"] = True

    def parent_died(signum: int, frame: FrameType | None) -> None:
        if os.getppid() != supervisor:
            stop["requested"] = True

    signal.signal(signal.SIGINT, signal.SIG_IGN)  # Ctrl-C is the supervisor's to handle
    for sig in (signal.SIGTERM, signal.SIGHUP):
        signal.signal(sig, request_stop)
    signal.signal(signal.SIGUSR2, parent_died)
    subreaper = _prctl(PR_SET_CHILD_SUBREAPER, 1)
    _prctl(PR_SET_PDEATHSIG, signal.SIGUSR2)
    if os.getppid() != supervisor:
        os._exit(_NO_WORKER)
    fds = tuple(int(a[len("--fd=") :]) for a in argv[1:] if a.startswith("--fd="))
    command = [a for a in argv[1:] if not a.startswith("--fd=")] + [str(os.getpid())]
    try:
        worker = subprocess.Popen(command, pass_fds=fds, start_new_session=hasattr(os, "setsid"))
    except OSError as exc:
        print(f"faceretarget: the worker process could not be started: {exc}", file=sys.stderr)
        os._exit(_NO_WORKER)
    for fd in fds:
        os.close(fd)
    status: int | None = None
    while status is None:
        if stop["requested"] or os.getppid() != supervisor:
            kill_tree(worker.pid)
            status = signal.SIGKILL  # the worker was stopped from outside: report it killed
            _exit_like(status)
        try:
            while True:  # reap the worker and any re-parented orphan that exited
                pid, code = os.waitpid(-1, os.WNOHANG)
                if pid == 0:
                    break
                if pid == worker.pid:
                    status = code
        except ChildProcessError:
            status = status if status is not None else 0
        if status is None:
            time.sleep(_POLL)
    worker.returncode = 0  # reaped above; keep Popen from waiting for it again
    # the worker's session is killed through the tree (a subreaper keeps it in there); its
    # process id, reaped, may already belong to someone else: only without /proc is it used
    kill_tree(None if (subreaper and os.path.isdir("/proc/self")) else worker.pid)
    _exit_like(status)


if __name__ == "__main__":
    main(sys.argv[1:])
