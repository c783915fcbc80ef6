"""Numba's on-disk cache shared by concurrent processes never fails a call.

Every kernel of faceretarget and its plugins is ``numba.njit(cache=True)``. Two processes
that compile and save the same kernels at once (two ``faceretarget demo`` runs, the
workers of ``compare --jobs 2``) can make numba's cache *save* fail after the kernel
compiled fine: a caller compiled in this process that links a callee loaded from the
cache another process has just written raises an untyped ``RuntimeError: no compiled
object yet`` while it is serialised, and a save can meet a file replaced under it
(``OSError``). The kernel itself is compiled and registered before numba saves it
(``Dispatcher.compile`` adds the overload first), so the only thing lost is the cache
entry: :func:`install` makes such a save a no-op (the next process compiles and saves
again) and a cache entry that cannot be loaded a miss (the kernel is compiled). The first
miss of one of our kernels prints :data:`COMPILE_NOTICE` (one line, stderr; once for the
processes of one run).

:func:`install` (called by ``import faceretarget``) patches numba when it is imported,
or at once if it already is; it never imports numba itself. Other errors, and any
error of a kernel's compilation, are raised as before.
"""

from __future__ import annotations

import importlib.abc
import importlib.util
import os
import sys
import tempfile
import threading
import time
from collections.abc import Callable, Sequence
from importlib.machinery import ModuleSpec
from types import ModuleType
from typing import Any

__all__ = ["install", "installed"]

_TARGET = "numba.core.caching"
_MARK = "_faceretarget_guarded"
_LOCK = threading.Lock()


def _is_save_race(exc: BaseException) -> bool:
    return isinstance(exc, OSError) or (
        isinstance(exc, RuntimeError) and "no compiled object" in str(exc)
    )


def _patch(caching: ModuleType) -> None:
    cache = getattr(caching, "Cache", None)
    if cache is None or getattr(cache, _MARK, False):
        return
    save, load = cache.save_overload, cache.load_overload

    def save_overload(self: Any, sig: Any, data: Any) -> Any:
        try:
            return save(self, sig, data)
        except (RuntimeError, OSError) as exc:
            if not _is_save_race(exc):
                raise
            return None  # compiled and in use; only this cache entry is not written

    def load_overload(self: Any, sig: Any, target_context: Any) -> Any:
        try:
            found = load(self, sig, target_context)
        except (
            Exception
        ):  # an entry half-replaced by another process, or unreadable: compile instead
            found = None
        if found is None:
            _notice_compiling(getattr(self, "_py_func", None))
        return found

    init = cache.__init__

    def __init__(self: Any, py_func: Callable[..., Any]) -> None:
        init(self, py_func)
        cache_file = getattr(self, "_cache_file", None)
        if cache_file is not None and _ours(py_func):
            cache_file._source_stamp = (cache_file._source_stamp, kernel_stamp())

    save_overload.__doc__, load_overload.__doc__ = save.__doc__, load.__doc__
    cache.save_overload, cache.load_overload, cache.__init__ = (
        save_overload,
        load_overload,
        __init__,
    )
    setattr(cache, _MARK, True)


def _ours(py_func: object) -> bool:
    return (getattr(py_func, "__module__", "") or "").startswith("faceretarget")


def _kernel_files() -> list[str]:
    """Every numba kernel module of faceretarget and its built-in plugins (``_*kernels.py``)."""
    roots = [os.path.dirname(os.path.abspath(__file__))]
    spec = importlib.util.find_spec("faceretarget.plugins")
    roots += list(spec.submodule_search_locations or []) if spec is not None else []
    found: set[str] = set()
    for root in roots:
        for folder, _, files in os.walk(root):
            found.update(
                os.path.join(folder, f)
                for f in files
                if f.startswith("_") and f.endswith("kernels.py")
            )
    return sorted(found)


_stamp: tuple | None = None


def kernel_stamp() -> tuple:
    """(name, mtime, size) of every kernel module, added to each of our kernels' cache stamp.

    numba keys a cached kernel on its own file only, so a kernel that calls a shared one
    (a plugin's solver calling ``geometry._nnls_kernels.cholesky``) would keep the old
    callee after that file changes; with this stamp any kernel file's change recompiles all.
    """
    global _stamp
    if _stamp is None:
        entries = []
        for path in _kernel_files():
            try:
                st = os.stat(path)
            except OSError:
                continue
            entries.append((path, st.st_mtime, st.st_size))
        _stamp = tuple(entries)
    return _stamp


#: Printed on stderr when the first of our kernels is not in the cache: once per process,
#: and once for all the processes of one run (``faceretarget demo``'s workers compile in
#: parallel) through a time-stamped marker file.
COMPILE_NOTICE = (
    "faceretarget: compiling numerical kernels for this machine, once (about a minute of CPU in all, more on a busy "
    "machine; later runs load them from the cache). `faceretarget warmup` does it ahead."
)
#: Another process's notice younger than this (seconds) silences this one.
NOTICE_QUIET_SECONDS = 600.0
_MARKER = os.path.join(
    tempfile.gettempdir(), f"faceretarget-compile-notice-{getattr(os, 'getuid', lambda: 0)()}"
)
_noticed = False


def _notice_compiling(py_func: object) -> None:
    global _noticed
    if _noticed or not _ours(py_func):
        return
    _noticed = True
    try:
        recent = time.time() - os.path.getmtime(_MARKER) < NOTICE_QUIET_SECONDS
    except OSError:
        recent = False
    if recent:
        return
    try:
        with open(_MARKER, "a"):
            os.utime(_MARKER)
    except OSError:
        pass  # a read-only temp folder: every process prints, as before
    print(COMPILE_NOTICE, file=sys.stderr, flush=True)


class _Finder(importlib.abc.MetaPathFinder):
    """Patches ``numba.core.caching`` right after it is first imported."""

    def find_spec(
        self, fullname: str, path: Sequence[str] | None, target: ModuleType | None = None
    ) -> ModuleSpec | None:
        if fullname != _TARGET:
            return None
        for finder in sys.meta_path:
            if finder is self or not hasattr(finder, "find_spec"):
                continue
            spec = finder.find_spec(fullname, path, target)
            if spec is not None:
                break
        else:
            return None
        loader = spec.loader
        if loader is None or not hasattr(loader, "exec_module"):
            return spec
        original = loader.exec_module
        real = loader

        class Loader(importlib.abc.Loader):
            def create_module(self, spec: ModuleSpec) -> ModuleType | None:
                return real.create_module(spec)

            def exec_module(self, module: ModuleType) -> None:
                original(module)
                _patch(module)

        spec.loader = Loader()
        return spec


def installed() -> bool:
    """Whether numba's cache is guarded in this process (False until numba is imported)."""
    module = sys.modules.get(_TARGET)
    return bool(module is not None and getattr(getattr(module, "Cache", None), _MARK, False))


def install() -> None:
    """Guard numba's cache now if numba is imported, else as soon as it is (idempotent)."""
    with _LOCK:
        module = sys.modules.get(_TARGET)
        if module is not None:
            _patch(module)
            return
        if not any(isinstance(f, _Finder) for f in sys.meta_path):
            sys.meta_path.insert(0, _Finder())
