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

Temporary files have one naming scheme, ``.NAME.PID.TOKEN.frtmp`` followed by the
destination's suffix (:func:`temp_path`; old folders moved aside ``.NAME.PID.TOKEN.frold``),
and are locked (``flock``) while written. Leftovers of killed writers (no process of
that pid runs, or nobody holds the lock) are found by :func:`leftovers` and removed (or
restored) by :func:`remove_leftovers`, which every write runs for its destination first
(the batch runner also for outputs it skips).
"""

from __future__ import annotations

import errno
import os
import re
import secrets
import shutil
import stat
from collections.abc import Iterable, Iterator
from contextlib import contextmanager
from pathlib import Path
from typing import IO

from .._types import PathLike
from ..errors import OutputError

try:
    import fcntl
except ImportError:  # pragma: no cover - not on Windows
    _HAS_FCNTL = False
else:
    _HAS_FCNTL = True

__all__ = [
    "note_input",
    "clear_inputs",
    "is_input",
    "recorded_inputs",
    "check_destination",
    "atomic_file",
    "atomic_dir",
    "atomic_path",
    "write_bytes",
    "temp_path",
    "temp_owner",
    "leftovers",
    "remove_leftovers",
]

_TMP_SUFFIX = ".frtmp"
_BACKUP_SUFFIX = ".frold"

#: names of the temporaries this process is writing right now (never cleaned up)
_ACTIVE: set[str] = set()
#: temporaries made by :func:`reserve_temp`: writers write into them directly
_DIRECT: dict[str, Path] = {}

#: realpath -> (st_dev, st_ino) of every path read as an input in this process
_INPUTS: dict[str, tuple[int, int] | None] = {}


def _identity(path: Path) -> tuple[int, int] | None:
    try:
        st = os.stat(path)
    except OSError:
        return None
    return (st.st_dev, st.st_ino)


def note_input(path: PathLike) -> None:
    """Record ``path`` as an input of this process (writers will refuse to replace it)."""
    p = Path(path)
    _INPUTS[os.path.realpath(p)] = _identity(p)
    if p.is_dir():
        for child in p.iterdir():
            if child.is_file():
                _INPUTS[os.path.realpath(child)] = _identity(child)


def recorded_inputs() -> list[str]:
    """The paths recorded as inputs of this process (by :func:`note_input`), resolved."""
    return list(_INPUTS)


def clear_inputs() -> None:
    """Forget every recorded input (for long-running applications that reuse file names)."""
    _INPUTS.clear()


def is_input(path: PathLike, inputs: Iterable = ()) -> bool:
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


def check_destination(
    path: PathLike, *, inputs: Iterable = (), force: bool = False, folder: bool = False
) -> Path:
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
                raise OutputError(
                    f"{p}: refusing to replace a folder holding an input ({child.name}); choose another output folder"
                )
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


def temp_path(dest: PathLike) -> Path:
    """The temporary name for ``dest`` (the one naming scheme of faceretarget):
    ``.NAME.PID.TOKEN.frtmp`` + ``dest``'s suffix, in ``dest``'s folder. The suffix is kept
    so a writer that dispatches on the extension (a plugin's) can be given the temporary
    path; :func:`leftovers` recognises every such name."""
    dest = Path(dest)
    return (
        dest.parent / f".{dest.name}.{os.getpid()}.{secrets.token_hex(4)}{_TMP_SUFFIX}{dest.suffix}"
    )


#: ``.NAME.PID.TOKEN.frtmp[.EXT]`` / ``.NAME.PID.TOKEN.frold``
_TEMP_NAME = re.compile(
    r"^\.(?P<name>.+)\.(?P<pid>\d+)\.(?P<token>[0-9a-f]{8})(?P<tag>\.frtmp|\.frold)(?P<ext>\.[^.]*)?$"
)
#: the batch runner's former scheme ``.NAME.frbatch-PID-TOKEN.EXT`` (still cleaned up)
_LEGACY_NAME = re.compile(
    r"^\.(?P<name>.+?)\.frbatch-(?P<pid>\d+)-(?P<token>[0-9a-f]+)(?P<ext>\.[^.]*)?$"
)


def temp_owner(name: str) -> tuple[str, list[int], str] | None:
    """``(destination name, writer pids, tag)`` of a temporary file name, or None.

    Nested temporaries (a writer's temporary of a temporary, as older versions made in
    batch runs) are unwrapped to the final destination; ``tag`` is ``.frtmp`` or
    ``.frold`` of the outermost name."""
    pids: list[int] = []
    tag: str | None = None
    for _ in range(8):
        m = _TEMP_NAME.match(name) or _LEGACY_NAME.match(name)
        if m is None:
            break
        pids.append(int(m.group("pid")))
        if tag is None:
            tag = m.groupdict().get("tag") or _TMP_SUFFIX
        name = m.group("name")
    if tag is None:  # no name matched (else the first match set it)
        return None
    return name, pids, tag


def _locked(path: Path) -> bool:
    """Whether a live writer holds the lock on temporary ``path`` (never blocks, never
    follows a symlink, never opens anything but a regular file or folder)."""
    try:
        st = os.lstat(path)
    except OSError:
        return False
    if not (stat.S_ISREG(st.st_mode) or stat.S_ISDIR(st.st_mode)):
        return False
    try:
        fd = os.open(
            path,
            os.O_RDONLY
            | os.O_NONBLOCK
            | getattr(os, "O_NOFOLLOW", 0)
            | getattr(os, "O_CLOEXEC", 0),
        )
    except OSError:
        return True  # cannot tell: leave it
    try:
        fcntl.flock(fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
    except OSError:
        return True
    finally:
        os.close(fd)  # closing releases our probe lock
    return False


def _pid_alive(pid: int) -> bool:
    if pid == os.getpid():
        return True
    if not 0 < pid < 2**31:  # no process has it (os.kill(0) would probe our own group)
        return False
    try:
        os.kill(pid, 0)
    except ProcessLookupError:
        return False
    except (PermissionError, OSError, OverflowError):
        return True
    return True


def _stale(entry: Path, pids: list[int], tag: str) -> bool:
    """A temporary whose writer is gone: every process in its name has ended, or (our
    own scheme, the pid since reused) no process holds its lock."""
    if entry.name in _ACTIVE:
        return False
    if not any(_pid_alive(p) for p in pids):
        return True
    own_scheme = _TEMP_NAME.match(entry.name) is not None and len(pids) == 1 and tag == _TMP_SUFFIX
    return own_scheme and pids[0] != os.getpid() and _HAS_FCNTL and not _locked(entry)


def leftovers(folder: PathLike, dest_name: str | None = None) -> list[Path]:
    """Temporaries in ``folder`` left by writers that are gone (of ``dest_name`` only, if
    given): every name of the scheme of :func:`temp_path`, the old folders moved aside
    (``.frold``) and the batch runner's former ``.frbatch-`` names, nested ones included."""
    try:
        entries = list(Path(folder).iterdir())
    except OSError:
        return []
    found = []
    for entry in entries:
        owner = temp_owner(entry.name)
        if owner is None or (dest_name is not None and owner[0] != dest_name):
            continue
        if _stale(entry, owner[1], owner[2]):
            found.append(entry)
    return found


def remove_leftovers(dest: PathLike) -> list[Path]:
    """Clean up after killed writers of ``dest``: delete their temporaries, and put back an
    old folder moved aside if ``dest`` went missing. Returns what was removed or restored."""
    dest = Path(dest)
    done = []
    for entry in leftovers(dest.parent, dest.name):
        owner = temp_owner(entry.name)
        try:
            if owner and owner[2] == _BACKUP_SUFFIX and not os.path.lexists(dest):
                os.replace(entry, dest)
            elif entry.is_dir() and not entry.is_symlink():
                shutil.rmtree(entry)
            else:
                entry.unlink()
            done.append(entry)
        except OSError:
            pass
    return done


_remove_stale = remove_leftovers  # former name


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


def _create_locked(dest: Path, *, folder: bool) -> tuple[Path, int]:
    """Create ``dest``'s temporary (a file, or a folder) and lock it for as long as the
    returned descriptor stays open, so :func:`leftovers` never takes it for a leftover."""
    tmp = temp_path(dest)
    try:
        if folder:
            tmp.mkdir()
            fd = os.open(
                tmp, os.O_RDONLY | getattr(os, "O_DIRECTORY", 0) | getattr(os, "O_CLOEXEC", 0)
            )
        else:
            fd = os.open(
                tmp, os.O_WRONLY | os.O_CREAT | os.O_EXCL | getattr(os, "O_CLOEXEC", 0), 0o666
            )
    except OSError as exc:
        what = "folder" if folder else "file"
        raise OutputError(
            f"{dest}: cannot create a {what} in {dest.parent} ({exc.strerror or exc}); check the folder's permissions"
        ) from None
    if _HAS_FCNTL:
        try:
            fcntl.flock(fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
        except OSError:
            pass  # a file system without locks: the pid in the name still protects it
    _ACTIVE.add(tmp.name)
    return tmp, fd


def _release(tmp: Path, fd: int) -> None:
    _ACTIVE.discard(tmp.name)
    try:
        os.close(fd)
    except OSError:
        pass


def _discard(tmp: Path) -> None:
    try:
        if tmp.is_dir() and not tmp.is_symlink():
            shutil.rmtree(tmp, ignore_errors=True)
        else:
            os.unlink(tmp)
    except OSError:
        pass


@contextmanager
def atomic_file(
    path: PathLike, *, inputs: Iterable = (), force: bool = False, text: bool = False
) -> Iterator[IO]:
    """Open a temporary file that replaces ``path`` when the ``with`` block succeeds.

    On an exception inside the block the temporary file is removed and ``path`` is
    untouched. ``text=True`` opens it in UTF-8 text mode with ``\\n`` newlines. When
    ``path`` is itself a temporary handed out by :func:`atomic_path`, it is written
    directly (its owner replaces the destination).
    """
    direct = _DIRECT.get(os.path.abspath(path))
    if direct is not None:
        with _direct_file(Path(path), direct, inputs, text) as handle:
            yield handle
        return
    dest = check_destination(path, inputs=inputs, force=force)
    remove_leftovers(dest)
    tmp, lock = _create_locked(dest, folder=False)
    try:
        try:
            # opened here, entered below: a failure to create the file is its own error
            handle = open(tmp, "w", encoding="utf-8", newline="\n") if text else open(tmp, "wb")  # noqa: SIM115
        except OSError as exc:
            raise OutputError(
                f"{dest}: cannot create a file in {dest.parent} ({exc.strerror or exc})"
            ) from None
        with _typed_os_errors(dest):
            with handle:
                yield handle
                handle.flush()
                os.fsync(handle.fileno())
            # re-check: an input could have been read while we were writing
            check_destination(dest, inputs=inputs, force=True)
            os.replace(tmp, dest)
    except BaseException:
        _discard(tmp)
        raise
    finally:
        _release(tmp, lock)
    _fsync_dir(dest.parent)


@contextmanager
def _direct_file(tmp: Path, dest: Path, inputs: Iterable, text: bool) -> Iterator[IO]:
    if is_input(dest, inputs):
        raise OutputError(
            f"{dest}: refusing to write over an input file; choose another output path"
        )
    with (
        _typed_os_errors(dest),
        open(tmp, "w", encoding="utf-8", newline="\n") if text else open(tmp, "wb") as handle,
    ):
        yield handle
        handle.flush()
        os.fsync(handle.fileno())


@contextmanager
def atomic_path(path: PathLike, *, inputs: Iterable = (), force: bool = False) -> Iterator[Path]:
    """A temporary path beside file ``path`` for a writer that takes a path (a registered
    writer, maybe a plugin's): what the block writes there replaces ``path`` when the
    block succeeds, after the destination is checked again (inputs read meanwhile, for
    example a topology taken from a sibling file, are refused). faceretarget's own writers
    given the temporary write into it directly. The temporary keeps ``path``'s suffix."""
    dest = check_destination(path, inputs=inputs, force=force)
    remove_leftovers(dest)
    tmp, lock = _create_locked(dest, folder=False)
    key = os.path.abspath(tmp)
    _DIRECT[key] = dest
    try:
        with _typed_os_errors(dest):
            yield tmp
            if not tmp.is_file() or tmp.is_symlink() or tmp.stat().st_size == 0:
                raise OutputError(
                    f"{dest}: the writer wrote nothing (or not a regular file) at {tmp.name}; nothing was replaced"
                )
            fd = os.open(tmp, os.O_RDONLY)
            try:
                os.fsync(fd)
            finally:
                os.close(fd)
            check_destination(dest, inputs=inputs, force=True)
            os.replace(tmp, dest)
    except BaseException:
        _discard(tmp)
        raise
    finally:
        _DIRECT.pop(key, None)
        _release(tmp, lock)
    _fsync_dir(dest.parent)


def write_bytes(path: PathLike, data: bytes, *, inputs: Iterable = (), force: bool = False) -> Path:
    """Atomically write ``data`` to ``path``."""
    with atomic_file(path, inputs=inputs, force=force) as fh:
        fh.write(data)
    return Path(path)


@contextmanager
def atomic_dir(
    path: PathLike,
    *,
    inputs: Iterable = (),
    force: bool = False,
    allowed_suffixes: tuple[str, ...] | None = (),
) -> Iterator[Path]:
    """A temporary folder that replaces folder ``path`` when the ``with`` block succeeds.

    Files written into the yielded folder should be fsync-ed by the caller (use
    :func:`write_file_synced`). With ``force``, an existing destination folder is
    replaced only if it holds nothing but regular files whose suffixes are in
    ``allowed_suffixes`` (so a user folder with other content is never deleted; ``None``
    leaves that check to a writer given the temporary folder). When ``path`` is itself a
    temporary folder handed out by an enclosing ``atomic_dir`` (as :func:`faceretarget.io.save`
    gives writers), it is written directly and the enclosing block replaces the destination.
    """
    direct = _DIRECT.get(os.path.abspath(path))
    if direct is not None:  # a temporary folder handed out by atomic_dir: write into it
        _check_foreign(direct, allowed_suffixes)
        if is_input(direct, inputs):
            raise OutputError(
                f"{direct}: refusing to write over an input; choose another output path"
            )
        with _typed_os_errors(direct):
            yield Path(path)
        return
    dest = check_destination(path, inputs=inputs, force=force, folder=True)
    _check_foreign(dest, allowed_suffixes)
    remove_leftovers(dest)
    tmp, lock = _create_locked(dest, folder=True)
    key = os.path.abspath(tmp)
    _DIRECT[key] = dest
    try:
        with _typed_os_errors(dest):
            yield tmp
            _fsync_dir(tmp)
            check_destination(dest, inputs=inputs, force=True, folder=True)
            _replace_dir(tmp, dest)
    except BaseException:
        shutil.rmtree(tmp, ignore_errors=True)
        raise
    finally:
        _DIRECT.pop(key, None)
        _release(tmp, lock)
    _fsync_dir(dest.parent)


def _check_foreign(dest: Path, allowed_suffixes: tuple[str, ...] | None) -> None:
    """Refuse to replace an existing folder holding anything but regular files with
    ``allowed_suffixes`` (``None``: not checked here; a writer given the temporary folder
    checks it with its own suffixes)."""
    if allowed_suffixes is None or not dest.is_dir():
        return
    foreign = [
        c.name for c in dest.iterdir() if not (c.is_file() and c.suffix.lower() in allowed_suffixes)
    ]
    if foreign:
        raise OutputError(
            f"{dest}: the existing folder holds other content ({', '.join(sorted(foreign)[:5])}); "
            "choose a new or empty output folder"
        )


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
    backup = (
        dest.parent / f".{dest.name}.{os.getpid()}.{secrets.token_hex(4)}{_BACKUP_SUFFIX}"
    )  # temp_path's scheme
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
        raise OutputError(
            f"{dest}: writing failed ({reason}); the previous file, if any, is unchanged"
        ) from None


def write_file_synced(path: Path, data: bytes | str) -> None:
    """Write and fsync one file inside an :func:`atomic_dir` temporary folder."""
    if isinstance(data, str):
        with open(path, "w", encoding="utf-8", newline="\n") as text:
            text.write(data)
            text.flush()
            os.fsync(text.fileno())
    else:
        with open(path, "wb") as binary:
            binary.write(data)
            binary.flush()
            os.fsync(binary.fileno())
