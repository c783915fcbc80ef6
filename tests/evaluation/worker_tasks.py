"""Task functions for the supervised-worker tests (importable by name in worker processes)."""

import os
import time


def add(a, b):
    return a + b


def fail(message):
    raise ValueError(message)


def sleep(seconds):
    time.sleep(seconds)
    return "woke up"


def spin():
    """A busy loop that never returns (a plugin stuck in Python code)."""
    n = 0
    while True:
        n += 1


def die(code):
    os._exit(code)


def unsendable():
    return lambda: None  # cannot be pickled back to the parent


def exit_call():
    raise SystemExit(5)


def pid():
    return os.getpid()


def _refuse_to_load():
    raise RuntimeError("this object cannot be loaded in a worker")


class Unloadable:
    """Pickles fine, fails to unpickle (like a class whose module the worker cannot import)."""

    def __reduce__(self):
        return (_refuse_to_load, ())


class LoadsOnlyInWorkers:
    """Pickles in the worker, fails to unpickle in the supervising process."""

    def __reduce__(self):
        return (_refuse_to_load, ())


def result_that_does_not_load():
    return LoadsOnlyInWorkers()


def fork_helper_then_die(pid_file):
    """Start a helper process (as a library might), then die: the helper keeps the
    worker's connection open, so only the process sentinel shows the death."""
    child = os.fork()
    if child == 0:
        time.sleep(60)
        os._exit(0)
    with open(pid_file, "w") as f:
        f.write(str(child))
    os._exit(4)


def nbytes(array):
    return int(array.nbytes)


def worker_pid_then_spin(pid_file):
    with open(pid_file, "w") as f:
        f.write(str(os.getpid()))
    spin()


def environ(names):
    return {k: os.environ.get(k) for k in names}
