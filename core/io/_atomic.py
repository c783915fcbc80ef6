"""Atomic writes that never overwrite an input.

Every writer of :mod:`faceretarget.io` goes through :func:`atomic_file` (one file) or
:func:`atomic_dir` (a folder of files). The data is written to a temporary file in the
*same* folder, flushed and ``fsync``-ed, then moved over the destination with
``os.replace``, so a reader (or a crash, even SIGKILL) sees either the previous file or
the complete new one, never a partial file. A folder replacing an existing folder is
swapped in with one atomic exchange (``renameat2(RENAME_EXCHANGE)`` on Linux,
``renamex_np(RENAME_SWAP)`` on macOS); elsewhere the old folder is moved aside first
and put back by the next write if the process died in between. Operating-system
failures while writing (disk full, file too large) are :class:`OutputError`.

Writing is refused (:class:`~faceretarget.errors.OutputError`) when the destination

- is a file read as an input by this process (every reader calls :func:`note_input`),
  or is listed in ``inputs=`` (compared by device and inode, so links are caught too);
  ``force`` does not lift this;
- already exists and ``force`` is false.

Temporary files are named ``.NAME.PID.TOKEN.frtmp`` (old folders moved aside
``.frold``); leftovers of killed writers (whose process no longer runs) are removed (or
restored) on the next write to the same destination.
"""
from __future__ import annotations

import errno
import os
import secrets
import shutil
from contextlib import contextmanager
from pathlib import Path
from typing import IO, Iterable, Iterator

from ..errors import OutputError

__all__ = ["note_input", "clear_inputs", "is_input", "check_destination", "atomic_file", "atomic_dir", "write_bytes"]

_TMP_SUFFIX = ".frtmp"
_BACKUP_SUFFIX = ".frold"

#: realpath -> (st_dev, st_ino) of every path read as an input in this process
_INPUTS: dict[str, tuple[int, int] | None] = {}


def _identity(path: Path) -> tuple[int, int] | None:
    try:
        st = os.stat(path)
    except OSError:
        return None
    return (st.st_dev, st.st_ino)


def note_input(path) -> None:
    """Record ``path`` as an input of this process (writers will refuse to replace it)."""
    p = Path(path)
    _INPUTS[os.path.realpath(p)] = _identity(p)
    if p.is_dir():
        for child in p.iterdir():
            if child.is_file():
                _INPUTS[os.path.realpath(child)] = _identity(child)


def clear_inputs() -> None:
    """Forget every recorded input (for long-running applications that reuse file names)."""
    _INPUTS.clear()


def is_input(path, inputs: Iterable = ()) -> bool:
    """Whether ``path`` is (the same file as) an input read by this process or listed in ``inputs``."""
    p = Path(path)
    real = os.path.realpath(p)
    ident = _identity(p)
    known = dict(_INPUTS)
    for extra in inputs:
        known[os.path.realpath(extra)] = _identity(Path(extra))
    if real in known:
        return True
    return ident is not None and ident in set(v for v in known.values() if v is not None)


def check_destination(path, *, inputs: Iterable = (), force: bool = False, folder: bool = False) -> Path:
    """Validate a destination before writing; returns it as a :class:`Path`.

    Raises :class:`OutputError` when it is an input, exists without ``force``, is of
    the wrong kind (a folder where a file is expected or the reverse), or its parent
    folder does not exist.
    """
    p = Path(path)
    inputs = list(inputs)
    if is_input(p, inputs):
        raise OutputError(f"{p}: refusing to write over an input file; choose another output path")
    if folder and p.is_dir():
        for child in p.iterdir():
            if is_input(child, inputs):
                raise OutputError(f"{p}: refusing to replace a folder holding an input ({child.name}); choose another output folder")
    parent = p.parent if str(p.parent) else Path(".")
    if not parent.is_dir():
        raise OutputError(f"{p}: the folder {parent} does not exist; create it first")
    if p.exists() or p.is_symlink():
        if folder and not p.is_dir():
            raise OutputError(f"{p}: exists and is not a folder; choose another output path")
        if not folder and p.is_dir():
            raise OutputError(f"{p}: is a folder; give a file name")
        if not force:
            raise OutputError(f"{p}: already exists; pass force=True (--force) to replace it")
    return p


def _tmp_name(dest: Path) -> Path:
    return dest.parent / f".{dest.name}.{os.getpid()}.{secrets.token_hex(4)}{_TMP_SUFFIX}"


def _pid_alive(pid: int) -> bool:
    try:
        os.kill(pid, 0)
    except ProcessLookupError:
        return False
    except (PermissionError, OSError):
        return True
    return True


def _remove_stale(dest: Path) -> None:
    """Clean up after killed writers of ``dest`` (their process is gone): delete their
    temporaries, and put back an old folder moved aside if ``dest`` went missing."""
    prefix = f".{dest.name}."
    try:
        entries = list(dest.parent.iterdir())
    except OSError:
        return
    for entry in entries:
        name = entry.name
        suffix = next((s for s in (_TMP_SUFFIX, _BACKUP_SUFFIX) if name.endswith(s)), None)
        if suffix is None or not name.startswith(prefix):
            continue
        middle = name[len(prefix) : -len(suffix)].split(".")
        if len(middle) != 2 or not middle[0].isdigit() or _pid_alive(int(middle[0])):
            continue
        try:
            if suffix == _BACKUP_SUFFIX and not dest.exists():
                os.replace(entry, dest)
            elif entry.is_dir() and not entry.is_symlink():
                shutil.rmtree(entry)
            else:
                entry.unlink()
        except OSError:
            pass


def _fsync_dir(folder: Path) -> None:
    try:
        fd = os.open(folder, os.O_RDONLY)
    except OSError:
        return
    try:
        os.fsync(fd)
    except OSError:
        pass
    finally:
        os.close(fd)


@contextmanager
def atomic_file(path, *, inputs: Iterable = (), force: bool = False, text: bool = False) -> Iterator[IO]:
    """Open a temporary file that replaces ``path`` when the ``with`` block succeeds.

    On an exception inside the block the temporary file is removed and ``path`` is
    untouched. ``text=True`` opens it in UTF-8 text mode with ``\\n`` newlines.
    """
    dest = check_destination(path, inputs=inputs, force=force)
    _remove_stale(dest)
    tmp = _tmp_name(dest)
    try:
        handle = open(tmp, "x", encoding="utf-8", newline="\n") if text else open(tmp, "xb")
    except OSError as exc:
        raise OutputError(f"{dest}: cannot create a file in {dest.parent} ({exc.strerror or exc})") from None
    try:
        with _typed_os_errors(dest):
            with handle:
                yield handle
                handle.flush()
                os.fsync(handle.fileno())
            # re-check: an input could have been read while we were writing
            check_destination(dest, inputs=inputs, force=True)
            os.replace(tmp, dest)
    except BaseException:
        try:
            os.unlink(tmp)
        except OSError:
            pass
        raise
    _fsync_dir(dest.parent)


def write_bytes(path, data: bytes, *, inputs: Iterable = (), force: bool = False) -> Path:
    """Atomically write ``data`` to ``path``."""
    with atomic_file(path, inputs=inputs, force=force) as fh:
        fh.write(data)
    return Path(path)


@contextmanager
def atomic_dir(path, *, inputs: Iterable = (), force: bool = False, allowed_suffixes: tuple[str, ...] = ()) -> Iterator[Path]:
    """A temporary folder that replaces folder ``path`` when the ``with`` block succeeds.

    Files written into the yielded folder should be fsync-ed by the caller (use
    :func:`write_file_synced`). With ``force``, an existing destination folder is
    replaced only if it holds nothing but regular files whose suffixes are in
    ``allowed_suffixes`` (so a user folder with other content is never deleted).
    """
    dest = check_destination(path, inputs=inputs, force=force, folder=True)
    if dest.is_dir():
        foreign = [c.name for c in dest.iterdir() if not (c.is_file() and c.suffix.lower() in allowed_suffixes)]
        if foreign:
            raise OutputError(
                f"{dest}: the existing folder holds other content ({', '.join(sorted(foreign)[:5])}); "
                "choose a new or empty output folder"
            )
    _remove_stale(dest)
    tmp = _tmp_name(dest)
    try:
        tmp.mkdir()
    except OSError as exc:
        raise OutputError(f"{dest}: cannot create a folder in {dest.parent} ({exc.strerror or exc})") from None
    try:
        with _typed_os_errors(dest):
            yield tmp
            _fsync_dir(tmp)
            check_destination(dest, inputs=inputs, force=True, folder=True)
            _replace_dir(tmp, dest)
    except BaseException:
        shutil.rmtree(tmp, ignore_errors=True)
        raise
    _fsync_dir(dest.parent)


def _replace_dir(tmp: Path, dest: Path) -> None:
    """Put folder ``tmp`` at ``dest`` atomically: a plain rename when ``dest`` is absent or
    empty, else an atomic exchange (``tmp`` then holds the old folder, deleted after)."""
    try:
        os.replace(tmp, dest)
        return
    except OSError as exc:
        if not dest.is_dir() or exc.errno not in (errno.ENOTEMPTY, errno.EEXIST):
            raise
    if _exchange(tmp, dest):
        shutil.rmtree(tmp, ignore_errors=True)
        return
    # no atomic exchange on this system: move the old folder aside under a name the next
    # write recognises and restores if we die before the new folder is in place
    backup = dest.parent / f".{dest.name}.{os.getpid()}.{secrets.token_hex(4)}{_BACKUP_SUFFIX}"
    os.replace(dest, backup)
    os.replace(tmp, dest)
    shutil.rmtree(backup, ignore_errors=True)


def _exchange(a: Path, b: Path) -> bool:
    """Swap two paths atomically (Linux ``renameat2(RENAME_EXCHANGE)``, macOS
    ``renamex_np(RENAME_SWAP)``); False when the system or file system cannot."""
    try:
        import ctypes

        libc = ctypes.CDLL(None, use_errno=True)
    except (OSError, ImportError):
        return False
    fa, fb = os.fsencode(a), os.fsencode(b)
    if hasattr(libc, "renameat2"):
        result = libc.renameat2(-100, fa, -100, fb, 2)  # AT_FDCWD, RENAME_EXCHANGE
    elif hasattr(libc, "renamex_np"):
        result = libc.renamex_np(fa, fb, 2)  # RENAME_SWAP
    else:
        return False
    if result == 0:
        return True
    err = ctypes.get_errno()
    if err in (errno.ENOSYS, errno.EINVAL, errno.ENOTSUP, errno.EOPNOTSUPP):
        return False
    raise OSError(err, os.strerror(err), str(b))


@contextmanager
def _typed_os_errors(dest: Path) -> Iterator[None]:
    """Turn an operating-system failure while writing (disk full, file too large, no
    permission) into an :class:`OutputError` naming the destination."""
    try:
        yield
    except OutputError:
        raise
    except OSError as exc:
        reason = exc.strerror or str(exc) or type(exc).__name__
        raise OutputError(f"{dest}: writing failed ({reason}); the previous file, if any, is unchanged") from None


def write_file_synced(path: Path, data: bytes | str) -> None:
    """Write and fsync one file inside an :func:`atomic_dir` temporary folder."""
    mode = "w" if isinstance(data, str) else "wb"
    kwargs = {"encoding": "utf-8", "newline": "\n"} if isinstance(data, str) else {}
    with open(path, mode, **kwargs) as fh:
        fh.write(data)
        fh.flush()
        os.fsync(fh.fileno())
