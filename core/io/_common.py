"""Helpers shared by the format modules: typed errors naming the file, the memory
budget, safe text and npy/npz access (never pickle), JSON and natural sorting."""

from __future__ import annotations

import functools
import math
import os
import re
import stat
import warnings
import zipfile
from collections.abc import Callable, Iterator
from pathlib import Path
from typing import IO, Any, TypeVar

import numpy as np
import numpy.typing as npt

from .. import config
from .._types import PathLike
from ..errors import (
    FaceRetargetError,
    FileFormatError,
    FormatMismatchError,
    InputError,
    OutputError,
    ResourceLimitError,
)
from ._atomic import note_input

_T = TypeVar("_T")
_E = TypeVar("_E", bound=FileFormatError | None)

__all__ = [
    "bad",
    "check_budget",
    "check_regular",
    "open_regular",
    "guarded_reader",
    "read_bytes",
    "read_text",
    "natural_key",
    "fmt_float",
    "read_npz",
    "npy_header",
    "load_npy",
    "split_arrays",
    "join_arrays",
    "fps_from_times",
    "sniff",
    "format_mismatch",
    "mismatch_error",
]

_SIZE_UNITS = ("B", "KiB", "MiB", "GiB", "TiB")

#: text formats read whole (small sidecars whose parse is not measured): bytes of memory
#: one byte of text may cost
TEXT_MEMORY_FACTOR = 4
#: small text files parsed whole into Python objects (landmark lists and feature lines,
#: JSON or TXT; the sidecar of a mesh folder): peak per byte of the file, measured by
#: tests/io/test_text_memory.py on the smallest entries (21x for ids of 4 digits; the
#: test fails above this factor). Large text formats (OBJ, OFF, ASCII PLY/STL, TRC, CSV)
#: are streamed instead: their peak is their result plus one chunk's work (CHUNK_FACTOR).
TEXT_TOKEN_FACTOR = 32
#: bytes held per chunk by the streaming text readers (OBJ, OFF, ASCII PLY/STL, TRC, CSV)
CHUNK_BYTES = 1 << 18
#: the streaming readers' working memory for one chunk (its lines, their tokens, the
#: parsed block) per byte of two chunks: what they hold beyond their result, measured on
#: the smallest lines by tests/io/test_text_memory.py (at most 8.3 MiB, 16.6x, for the
#: weights CSV; the test fails above this factor)
CHUNK_FACTOR = 24


def chunk_work(fh: IO[bytes]) -> float:
    """Working memory of a streaming text reader on open file ``fh``, beyond its result
    (checked against the budget with the result's size): one chunk's work, or less for a
    file smaller than a chunk (a chunk may carry a partial line: up to two chunks' text)."""
    size = os.fstat(fh.fileno()).st_size
    return float(CHUNK_FACTOR * min(size, 2 * CHUNK_BYTES))


def bad(path: PathLike | None, what: str) -> FileFormatError:
    """A :class:`FileFormatError` whose message starts with the file name."""
    return FileFormatError(f"{path}: {what}")


def to_float32(values: npt.ArrayLike, what: str, dtype: str = "<f4") -> np.ndarray:
    """``values`` converted for a float32 format (``dtype`` sets the byte order). Raises
    :class:`OutputError` if a value lies beyond float32's range (it would be stored as inf);
    NaN (a missing marker sample) passes."""
    with np.errstate(over="ignore"):
        out = np.asarray(values).astype(dtype)
    if np.isinf(out).any() and not np.isinf(np.asarray(values)).any():
        limit = float(np.finfo(np.float32).max)
        raise OutputError(
            f"{what}: values beyond float32's range (|x| > {limit:.3g}) cannot be stored in this format; "
            "rescale the data or write a float64 format (.npz, .obj)"
        )
    return out


def human_size(n: float) -> str:
    n = float(n)
    for unit in _SIZE_UNITS:
        if n < 1024 or unit == _SIZE_UNITS[-1]:
            return f"{n:.0f} {unit}" if unit == "B" else f"{n:.1f} {unit}"
        n /= 1024
    return f"{n:.1f} TiB"


def check_budget(path: PathLike, nbytes: float, what: str) -> None:
    """Refuse (before allocating) when ``nbytes`` exceeds :func:`faceretarget.config.memory_budget`."""
    budget = config.memory_budget()
    if not math.isfinite(float(nbytes)) or nbytes > budget:
        raise ResourceLimitError(
            f"{path}: {what} would need {human_size(nbytes)}, more than the memory budget of {human_size(budget)}; "
            f"if the file is genuine, raise {config.ENV_MEMORY_BUDGET} (e.g. {config.ENV_MEMORY_BUDGET}=32G)"
        )


def guarded_reader(fn: Callable[..., _T]) -> Callable[..., _T]:
    """Wrap a ``read(path, **options)`` so every failure is a typed error naming the file.

    The path is recorded as an input (writers will not replace it); a missing path is a
    FileFormatError; faceretarget's own InputErrors (raised by the model constructors on
    wrong counts or NaN) become FileFormatErrors prefixed by the file name; any other
    exception from a parser or third-party library becomes a FileFormatError too.
    """

    @functools.wraps(fn)
    def read(path: PathLike, **options: Any) -> _T:
        p = Path(path)
        check_regular(p, folder_ok=True)
        note_input(p)
        try:
            with warnings.catch_warnings():
                warnings.simplefilter("ignore")
                with np.errstate(all="ignore"):
                    return fn(p, **options)
        except InputError as exc:
            message = str(exc)
            raise _mismatch_or(
                p, FileFormatError(message if message.startswith(str(p)) else f"{p}: {message}")
            ) from None
        except FormatMismatchError:
            raise
        except FileFormatError:  # a file of another kind fails its parser: say what it is
            mismatch = _mismatch_or(p, None)
            if mismatch is None:
                raise
            raise mismatch from None
        except FaceRetargetError:
            raise
        except MemoryError:
            raise ResourceLimitError(
                f"{p}: ran out of memory while reading; the file is too large for this machine"
            ) from None
        except RecursionError:
            raise FileFormatError(f"{p}: nested too deeply to read") from None
        except Exception as exc:  # parsers and third-party libraries raise anything on bad input
            detail = str(exc).strip().splitlines()[0] if str(exc).strip() else ""
            raise _mismatch_or(
                p,
                FileFormatError(
                    f"{p}: not a readable file of this format ({type(exc).__name__}{': ' + detail[:200] if detail else ''})"
                ),
            ) from None

    return read


def _mismatch_or(path: Path, error: _E) -> FormatMismatchError | _E:
    """The :class:`FormatMismatchError` naming what ``path`` really is, when its content is
    another kind of file than its extension says (:func:`format_mismatch`); else ``error``."""
    if not path.is_file():
        return error
    mismatch = mismatch_error(path)
    return error if mismatch is None else mismatch


_KINDS = (
    (stat.S_ISFIFO, "a FIFO (named pipe)"),
    (stat.S_ISCHR, "a character device"),
    (stat.S_ISBLK, "a block device"),
    (stat.S_ISSOCK, "a socket"),
)


def _not_regular(path: PathLike, st: os.stat_result) -> FileFormatError:
    what = next((name for test, name in _KINDS if test(st.st_mode)), "not a regular file")
    via = " (through a symbolic link)" if os.path.islink(path) else ""
    return FileFormatError(
        f"{path}: is {what}{via}, not a regular file; faceretarget reads only regular files "
        "(a pipe or device could hang or never end): save the data to a file and pass that"
    )


def check_regular(path: PathLike, *, folder_ok: bool = False) -> os.stat_result:
    """Refuse (FileFormatError) a path that is missing or not a regular file (a FIFO, a
    device such as /dev/zero, a socket; links are followed) without opening it, so it can
    never hang or read forever. Folders pass when ``folder_ok``."""
    try:
        st = os.stat(path)
    except FileNotFoundError:
        raise FileFormatError(f"{path}: no such file or folder") from None
    except OSError as exc:
        raise FileFormatError(f"{path}: cannot be read ({exc.strerror or exc})") from None
    if stat.S_ISREG(st.st_mode) or (folder_ok and stat.S_ISDIR(st.st_mode)):
        return st
    if stat.S_ISDIR(st.st_mode):
        raise FileFormatError(f"{path}: is a folder; expected a file")
    raise _not_regular(path, st)


def open_regular(path: PathLike) -> IO[bytes]:
    """``path`` opened for binary reading, refused unless it is a regular file.

    The file is opened non-blocking (a FIFO swapped in after a check cannot hang the
    open) and checked on the open descriptor, so nothing but a regular file is ever read.
    """
    check_regular(path)
    flags = os.O_RDONLY | getattr(os, "O_NONBLOCK", 0) | getattr(os, "O_CLOEXEC", 0)
    try:
        fd = os.open(path, flags)
    except OSError as exc:
        raise FileFormatError(f"{path}: cannot be opened ({exc.strerror or exc})") from None
    try:
        st = os.fstat(fd)
        if not stat.S_ISREG(st.st_mode):
            raise _not_regular(path, st)
        if hasattr(os, "set_blocking"):
            os.set_blocking(fd, True)
        return os.fdopen(fd, "rb")
    except BaseException:
        os.close(fd)
        raise


def read_bytes(path: Path, what: str = "reading the file", *, factor: float = 1.0) -> bytes:
    """The whole file, after checking its size (times ``factor``, the parse's cost per
    byte) against the memory budget. Never reads more than the size checked: a file
    that grows while read (or reports a false size) is refused."""
    with open_regular(path) as fh:
        size = os.fstat(fh.fileno()).st_size
        check_budget(path, size * factor, what)
        data = fh.read(size + 1)
    if len(data) > size:
        raise ResourceLimitError(
            f"{path}: the file grew while it was read (more than its {size} bytes); read it once it is complete"
        )
    return data


def read_text(path: Path, *, allow_empty: bool = False, factor: float = TEXT_MEMORY_FACTOR) -> str:
    """The file as text (UTF-8, BOM stripped, Latin-1 fallback); binary data is refused.

    ``factor``: what parsing the text costs in memory per byte of file (checked against
    the budget before reading); parsers that split the text into lines or tokens pass
    :data:`TEXT_TOKEN_FACTOR`."""
    data = read_bytes(path, "parsing this text file", factor=factor)
    if not data.strip() and not allow_empty:
        raise bad(path, "the file is empty")
    if b"\x00" in data:
        raise bad(path, "holds binary data (NUL bytes), not text")
    try:
        return data.decode("utf-8-sig")
    except UnicodeDecodeError:
        return data.decode("latin-1")


def iter_chunks(fh: IO[bytes], size: int = 1 << 20) -> Iterator[bytes]:
    """Binary chunks of an open file, each ending at a line end (the last one at the end
    of the file): text readers parse a file chunk by chunk, holding one chunk at a time."""
    rest = b""
    try:  # a small file is read in one block of its own size (not a whole chunk's buffer)
        size = max(1, min(size, os.fstat(fh.fileno()).st_size + 1))
    except (OSError, AttributeError, ValueError):
        pass
    while True:
        block = fh.read(size)
        if not block:
            if rest:
                yield rest
            return
        block = rest + block
        cut = block.rfind(b"\n")
        if cut < 0:
            rest = block
            if len(rest) > 64 * size:
                check_budget(
                    getattr(fh, "name", "the file"), len(rest), "one line of this text file"
                )
            continue
        rest = block[cut + 1 :]
        yield block[: cut + 1]


class TextRows:
    """The non-blank lines of an open text file, one chunk at a time (bytes, stripped or
    with ``strip=False`` only the line end removed, ``comment`` and what follows it cut), for readers that stream a file: the rows of one
    chunk are held at a time. ``lineno`` counts the rows handed out so far."""

    def __init__(
        self, path: PathLike, fh: IO[bytes], *, comment: bytes | None = None, strip: bool = True
    ) -> None:
        self.path, self.comment, self.strip = path, comment, strip
        self._chunks = iter_chunks(fh, CHUNK_BYTES)
        self.work = chunk_work(fh)  #: working memory beyond the result (for the budget)
        self._rows: list[bytes] = []
        self._pos = 0
        self.lineno = 0

    def _fill(self) -> bool:
        while self._pos >= len(self._rows):
            chunk = next(self._chunks, None)
            if chunk is None:
                self._rows, self._pos = [], 0
                return False
            if b"\x00" in chunk:
                raise bad(self.path, "holds binary data (NUL bytes), not text")
            lines = chunk.split(b"\n")
            del chunk
            if self.comment is not None:
                lines = [ln.split(self.comment, 1)[0] if self.comment in ln else ln for ln in lines]
            if self.strip:
                self._rows = [r for r in (ln.strip() for ln in lines) if r]
            else:  # only the line end goes (leading empty cells of a tab-separated row stay)
                self._rows = [ln.rstrip(b"\r") for ln in lines if ln.strip()]
            self._pos = 0
        return True

    def take(self, n: int) -> list[bytes]:
        """Up to ``n`` rows, all from the current chunk (an empty list at the end of the file)."""
        if n <= 0 or not self._fill():
            return []
        out = self._rows[self._pos : self._pos + n]
        self._pos += len(out)
        self.lineno += len(out)
        return out

    def next(self) -> bytes | None:
        """The next row, or None at the end of the file."""
        got = self.take(1)
        return got[0] if got else None

    def rest(self) -> Iterator[list[bytes]]:
        """The remaining rows, chunk by chunk (lists of rows)."""
        while True:
            rows = self.take(1 << 30)
            if not rows:
                return
            yield rows


def number_block(
    rows: list[bytes],
    columns: int,
    dtype: npt.DTypeLike = np.float64,
    *,
    delimiter: str | None = None,
) -> np.ndarray | None:
    """The first ``columns`` values of each row as a ``(len(rows), columns)`` array, parsed
    in C (numpy); None when a row has fewer values or one is not a number (the caller's
    row-by-row parser then says which)."""
    if not rows:
        return np.zeros((0, columns), dtype=dtype)
    try:
        with warnings.catch_warnings():
            warnings.simplefilter("ignore")
            return np.loadtxt(
                rows,
                dtype=dtype,
                usecols=range(columns),
                ndmin=2,
                comments=None,
                delimiter=delimiter,
            )
    except (ValueError, TypeError, OverflowError, IndexError):
        return None


_NAT = re.compile(r"(\d+)")


def natural_key(text: str) -> tuple:
    """Sort key putting ``frame2`` before ``frame10``."""
    return tuple(
        (0, int(t), t) if t.isdigit() else (1, 0, t.lower()) for t in _NAT.split(text) if t
    )


def fmt_float(value: float) -> str:
    """Shortest text that reads back as exactly the same float64."""
    return repr(float(value))


def parse_float(text: str, path: PathLike, where: str) -> float:
    try:
        value = float(text)
    except (TypeError, ValueError):
        raise bad(path, f"{where}: expected a number, got {text[:40]!r}") from None
    return value


def parse_int(text: str, path: PathLike, where: str, *, minimum: int | None = 0) -> int:
    try:
        value = int(text)
    except (TypeError, ValueError):
        raise bad(path, f"{where}: expected a whole number, got {text[:40]!r}") from None
    if minimum is not None and value < minimum:
        raise bad(path, f"{where}: expected a number >= {minimum}, got {value}")
    return value


# ---------------------------------------------------------------------------------------
# npy / npz without pickle, sizes checked before loading
# ---------------------------------------------------------------------------------------
def npy_header(
    fh: IO[bytes], path: PathLike, name: str = ""
) -> tuple[tuple[int, ...], np.dtype, bool]:
    """Read an ``.npy`` header from an open binary file: (shape, dtype, fortran_order)."""
    where = f"array {name!r}" if name else "the npy header"
    try:
        version = np.lib.format.read_magic(fh)
        if version == (1, 0):
            shape, fortran, dtype = np.lib.format.read_array_header_1_0(fh, max_header_size=100000)
        elif version in ((2, 0), (3, 0)):
            shape, fortran, dtype = np.lib.format.read_array_header_2_0(fh, max_header_size=100000)
        else:
            raise bad(path, f"{where}: unsupported npy version {version}")
    except FileFormatError:
        raise
    except Exception as exc:
        raise bad(path, f"{where} is not a valid numpy array header ({exc})") from None
    if dtype.hasobject:
        raise bad(
            path,
            f"{where} holds Python objects; only plain numeric or text arrays are read (never pickle)",
        )
    if any(int(s) < 0 for s in shape):
        raise bad(path, f"{where} declares a negative size {shape}")
    return tuple(int(s) for s in shape), dtype, bool(fortran)


def array_nbytes(shape: tuple[int, ...], dtype: np.dtype) -> int:
    n = 1
    for s in shape:
        n *= int(s)
    return n * max(int(dtype.itemsize), 1)


def read_npz(path: Path) -> dict[str, np.ndarray]:
    """Every array of an ``.npz`` file, after checking the declared sizes against the budget.

    Raises FileFormatError for anything that is not a zip of plain ``.npy`` members.
    """
    if check_regular(path).st_size == 0:
        raise bad(path, "the file is empty")
    try:
        zf = zipfile.ZipFile(path)
    except (zipfile.BadZipFile, OSError, ValueError) as exc:
        raise bad(path, f"not an npz (zip) archive ({exc})") from None
    with zf:
        try:
            infos = zf.infolist()
        except Exception as exc:
            raise bad(path, f"damaged zip directory ({exc})") from None
        if not infos:
            raise bad(path, "the npz archive holds no arrays")
        headers = {}
        total = 0
        for info in infos:
            if not info.filename.endswith(".npy"):
                raise bad(path, f"member {info.filename!r} is not an .npy array")
            key = info.filename[: -len(".npy")]
            try:
                with zf.open(info) as fh:
                    shape, dtype, _ = npy_header(fh, path, key)
            except FileFormatError:
                raise
            except Exception as exc:
                raise bad(path, f"array {key!r} cannot be opened ({exc})") from None
            nbytes = array_nbytes(shape, dtype)
            if info.file_size < nbytes:
                raise bad(
                    path,
                    f"array {key!r} declares {shape} {dtype} ({nbytes} bytes) but its member holds {info.file_size}",
                )
            headers[key] = (shape, dtype)
            total += nbytes
        check_budget(path, total, "the arrays of this npz")
        out = {}
        for key in headers:
            try:
                with zf.open(key + ".npy") as fh:
                    arr = np.lib.format.read_array(fh, allow_pickle=False)
            except Exception as exc:
                raise bad(
                    path, f"array {key!r} is truncated or corrupt ({type(exc).__name__}: {exc})"
                ) from None
            out[key] = arr
    return out


def load_npy(path: Path, *, mmap: bool = True) -> np.ndarray:
    """An ``.npy`` array (memory-mapped when possible), size-checked, never unpickled."""
    with open_regular(path) as fh:
        shape, dtype, _ = npy_header(fh, path)
        offset = fh.tell()
    nbytes = array_nbytes(shape, dtype)
    check_budget(path, nbytes, f"an array of shape {shape}")
    size = path.stat().st_size
    if size < offset + nbytes:
        raise bad(
            path,
            f"truncated: the header declares {shape} {dtype} ({nbytes} bytes) but only {size - offset} bytes follow",
        )
    if dtype.kind in "OV" or dtype.hasobject:
        raise bad(path, "holds structured or object data; expected a plain numeric array")
    if mmap and nbytes > 0:
        return np.load(path, mmap_mode="r", allow_pickle=False)
    return np.load(path, allow_pickle=False)


# ---------------------------------------------------------------------------------------
# JSON with arrays beside it, and timing
# ---------------------------------------------------------------------------------------
ARRAY_REF = "__ndarray__"


def split_arrays(value: Any) -> tuple[Any, list[np.ndarray]]:
    """JSON-ready copy of ``value`` with its numeric/text arrays replaced by
    ``{"__ndarray__": i}`` references, and the list of those arrays (for files that store
    arrays natively next to JSON metadata)."""
    arrays: list[np.ndarray] = []

    def strip(v: Any) -> Any:
        if isinstance(v, np.ndarray):
            if v.dtype.kind in "biufU":
                arrays.append(v)
                return {ARRAY_REF: len(arrays) - 1}
            return strip(v.tolist())
        if isinstance(v, dict):
            return {str(k): strip(x) for k, x in v.items()}
        if isinstance(v, (list, tuple)):
            return [strip(x) for x in v]
        if isinstance(v, np.generic):
            return strip(v.item())
        if isinstance(v, float):
            return v if math.isfinite(v) else str(v)  # strict JSON has no NaN
        if v is None or isinstance(v, (bool, int, str)):
            return v
        return str(v)

    return strip(value), arrays


def join_arrays(tree: Any, fetch: Callable[[int], np.ndarray]) -> Any:
    """Inverse of :func:`split_arrays`: ``fetch(i)`` gives back array ``i``."""
    if isinstance(tree, dict):
        if set(tree) == {ARRAY_REF} and isinstance(tree[ARRAY_REF], int):
            return fetch(tree[ARRAY_REF])
        return {k: join_arrays(x, fetch) for k, x in tree.items()}
    if isinstance(tree, list):
        return [join_arrays(x, fetch) for x in tree]
    return tree


def fps_from_times(times: np.ndarray, default: float) -> float:
    """Frames per second from uniformly spaced sample times (snapped to 1/1000 fps when close)."""
    times = np.asarray(times, dtype=np.float64)
    if times.size < 2:
        return float(default)
    span = float(times[-1] - times[0])
    if not math.isfinite(span) or span <= 0:
        return float(default)
    fps = (times.size - 1) / span
    snapped = round(fps, 3)
    if snapped > 0 and abs(fps - snapped) <= 1e-6 * fps:
        return snapped
    return fps


# ---------------------------------------------------------------------------------------
# format sniffing: what a file actually is, from its first bytes
# ---------------------------------------------------------------------------------------
#: (prefix, family, what it is, usual extension); checked in order on the first bytes
_MAGIC: tuple[tuple[bytes, str, str, str], ...] = (
    (b"\x89PNG\r\n\x1a\n", "png", "a PNG image", ".png"),
    (b"\xff\xd8\xff", "jpeg", "a JPEG image", ".jpg"),
    (b"GIF87a", "gif", "a GIF image", ".gif"),
    (b"GIF89a", "gif", "a GIF image", ".gif"),
    (b"II*\x00", "tiff", "a TIFF image", ".tif"),
    (b"MM\x00*", "tiff", "a TIFF image", ".tif"),
    (b"%PDF-", "pdf", "a PDF document", ".pdf"),
    (b"PK\x03\x04", "zip", "a ZIP archive", ".zip"),
    (b"PK\x05\x06", "zip", "a ZIP archive (empty)", ".zip"),
    (b"\x1f\x8b", "gzip", "a gzip-compressed file", ".gz"),
    (b"7z\xbc\xaf\x27\x1c", "7z", "a 7-Zip archive", ".7z"),
    (b"Rar!\x1a\x07", "rar", "a RAR archive", ".rar"),
    (b"BZh", "bzip2", "a bzip2-compressed file", ".bz2"),
    (b"\xfd7zXZ\x00", "xz", "an xz-compressed file", ".xz"),
    (b"glTF", "glb", "a binary glTF (GLB) file", ".glb"),
    (b"\x93NUMPY", "npy", "a NumPy .npy array", ".npy"),
    (b"POINTCACHE2\x00", "pc2", "a PC2 point cache", ".pc2"),
    (b"Kaydara FBX Binary", "fbx", "an FBX file", ".fbx"),
    (b"SQLite format 3\x00", "sqlite", "an SQLite database", ".sqlite"),
    (b"\x7fELF", "elf", "a compiled program (ELF)", ""),
    (b"\x89HDF\r\n\x1a\n", "hdf5", "an HDF5 file", ".h5"),
    (b"RIFF", "riff", "a RIFF file (WAV audio or AVI video)", ".wav"),
    (b"OggS", "ogg", "an Ogg audio/video file", ".ogg"),
    (b"ID3", "mp3", "an MP3 audio file", ".mp3"),
    (b"# vtk DataFile", "vtk", "a VTK legacy file", ".vtk"),
    (b"$MeshFormat", "msh", "a Gmsh mesh", ".msh"),
)

#: extension -> (what the extension promises, families whose content fits it). A family
#: not listed (or a text file where a binary format is expected) is a mismatch; content
#: nothing recognises (most binary data) never is: the reader's own error stands.
EXPECTED: dict[str, tuple[str, frozenset[str]]] = {
    ".c3d": ("a C3D file", frozenset({"c3d"})),
    ".glb": ("a binary glTF (GLB) file", frozenset({"glb"})),
    ".gltf": ("a glTF file", frozenset({"json", "glb"})),
    ".obj": ("a Wavefront OBJ file", frozenset({"text", "obj"})),
    ".off": ("an OFF file", frozenset({"text", "off"})),
    ".ply": ("a PLY file", frozenset({"ply"})),
    ".stl": ("an STL file", frozenset({"stl", "text"})),
    ".npz": ("a NumPy .npz archive", frozenset({"zip", "npz"})),
    ".npy": ("a NumPy .npy array", frozenset({"npy"})),
    ".pc2": ("a PC2 point cache", frozenset({"pc2"})),
    ".mdd": ("an MDD point cache", frozenset()),
    ".trc": ("a TRC file", frozenset({"text", "trc", "csv"})),
    ".csv": ("a CSV file", frozenset({"text", "csv", "trc"})),
    ".json": ("a JSON file", frozenset({"json"})),
    ".txt": ("a text file", frozenset({"text", "csv", "json", "obj", "off", "trc"})),
    ".vtk": ("a VTK legacy file", frozenset({"vtk"})),
    ".vtu": ("a VTK XML file", frozenset({"vtu"})),
    ".msh": ("a Gmsh mesh", frozenset({"msh", "text"})),
}

#: families that are text: a text file where a binary format is expected is a mismatch
_TEXT_FAMILIES = frozenset(
    {"text", "html", "xml", "svg", "json", "obj", "off", "trc", "csv", "stl-ascii"}
)
_SNIFF_BYTES = 4096


def _sniff_text(head: bytes) -> tuple[str, str, str] | None:
    """(family, what, extension) of text content, or None if ``head`` is not text."""
    if b"\x00" in head:
        return None
    try:
        text = head.decode("utf-8")
    except UnicodeDecodeError as exc:
        if exc.start < len(head) - 4:  # not merely a character cut at the end of the sample
            try:
                text = head.decode("latin-1")
            except UnicodeDecodeError:  # pragma: no cover - latin-1 decodes anything
                return None
            if sum(ch < 32 and ch not in (9, 10, 13, 12) for ch in head) > len(head) // 100:
                return None
        else:
            text = head[: exc.start].decode("utf-8", "replace")
    body = text.lstrip("\ufeff \t\r\n")
    low = body[:512].lower()
    if (
        low.startswith(("<!doctype html", "<html"))
        or "<html" in low[:256]
        or ("<head" in low and "<body" in low)
    ):
        return (
            "html",
            "an HTML web page (a download that saved the page instead of the file?)",
            ".html",
        )
    if low.startswith("<svg") or ("<svg" in low[:256] and low.startswith("<?xml")):
        return "svg", "an SVG image", ".svg"
    if low.startswith("<?xml") or low.startswith("<"):
        return "xml", "an XML document", ".xml"
    if low.startswith(("{", "[")):
        return "json", "JSON text", ".json"
    first = next(
        (ln.strip() for ln in body.splitlines() if ln.strip() and not ln.lstrip().startswith("#")),
        "",
    )
    head_word = first.split(None, 1)[0].lower() if first else ""
    if low.startswith("ply\n") or low.startswith("ply\r"):
        return "ply", "a PLY mesh", ".ply"
    if head_word in ("off", "coff", "noff", "cnoff"):
        return "off", "an OFF mesh", ".off"
    if low.startswith("solid") and "facet" in low:
        return "stl", "an ASCII STL mesh", ".stl"
    if head_word == "pathfiletype":
        return "trc", "a TRC marker file", ".trc"
    if head_word in ("v", "vn", "vt", "f", "mtllib", "o", "g", "usemtl", "s") and any(
        ln.startswith("v ") for ln in body.splitlines()[:50]
    ):
        return "obj", "a Wavefront OBJ mesh", ".obj"
    if first.count(",") >= 1 and all(
        ln.count(",") == first.count(",") for ln in body.splitlines()[1:6] if ln.strip()
    ):
        return "csv", "a CSV table", ".csv"
    return "text", "a text file", ".txt"


def sniff(path: PathLike) -> tuple[str, str, str] | None:
    """What a file actually is, from its first bytes: ``(family, description, usual
    extension)``, e.g. ``("png", "a PNG image", ".png")``, or None when nothing is
    recognised (most binary data without a signature: MDD, binary STL, raw arrays).

    Never reads more than 4 KiB and never raises (an unreadable file is None).
    """
    try:
        with open_regular(Path(path)) as fh:
            size = os.fstat(fh.fileno()).st_size
            head = fh.read(_SNIFF_BYTES)
    except (OSError, FaceRetargetError):
        return None
    if not head:
        return "empty", "an empty file (0 bytes)", ""
    for prefix, family, what, ext in _MAGIC:
        if head.startswith(prefix):
            if family == "zip":
                return _sniff_zip(path, family, what, ext)
            if family == "riff" and head[8:12] in (b"WAVE", b"AVI ", b"WEBP"):
                kind = {
                    b"WAVE": ("a WAV audio file", ".wav"),
                    b"AVI ": ("an AVI video", ".avi"),
                    b"WEBP": ("a WebP image", ".webp"),
                }[head[8:12]]
                return family, kind[0], kind[1]
            return family, what, ext
    if b"<VTKFile" in head[:1024]:  # XML, possibly followed by raw appended data
        return "vtu", "a VTK XML file", ".vtu"
    if head[4:8] == b"ftyp":
        return "mp4", "an MP4/MOV video (or HEIC image)", ".mp4"
    if len(head) >= 2 and 1 <= head[0] < 32 and head[1] == 0x50 and size >= 512:
        return "c3d", "a C3D motion-capture file", ".c3d"
    text = _sniff_text(head)
    if text is not None:
        return text
    if size >= 84 and size == 84 + 50 * int.from_bytes(head[80:84], "little"):
        return "stl", "a binary STL mesh", ".stl"
    return None


def _sniff_zip(path: PathLike, family: str, what: str, ext: str) -> tuple[str, str, str]:
    """A ZIP archive told apart: a NumPy .npz (every member ``.npy``) or an Office/other zip."""
    try:
        with zipfile.ZipFile(path) as zf:
            names = zf.namelist()[:10000]
    except Exception:
        return family, what, ext
    if names and all(n.endswith(".npy") for n in names):
        return "npz", "a NumPy .npz archive", ".npz"
    if "[Content_Types].xml" in names:
        return family, "an Office document (a ZIP archive: .docx, .xlsx, .pptx ...)", ".docx"
    return family, what, ext


def format_mismatch(path: PathLike, expected_ext: str | None = None) -> str | None:
    """``"this looks like a PNG image, not a C3D file"`` when the file's content is
    another kind of file than its extension (or ``expected_ext``) promises, else None.
    Only a confident recognition counts: unknown binary content is never a mismatch."""
    ext = (expected_ext or Path(path).suffix).lower()
    if ext not in EXPECTED:
        return None
    found = sniff(path)
    if found is None:
        return None
    family, what, real_ext = found
    promised, fits = EXPECTED[ext]
    if family in fits or (family == "npz" and "zip" in fits):
        return None
    if family == "empty":  # the reader says so in its own words
        return None
    if family == "text" and fits & _TEXT_FAMILIES:
        return None
    message = f"this looks like {what}, not {promised}"
    if real_ext and real_ext != ext and real_ext in EXPECTED and real_ext != ".txt":
        message += f"; if that is what it is, give it the {real_ext} extension"
    return message


def mismatch_error(
    path: PathLike, expected_ext: str | None = None, detail: str = ""
) -> FormatMismatchError | None:
    """A :class:`FormatMismatchError` naming what ``path`` really is (see
    :func:`format_mismatch`), or None when its content fits its extension."""
    from ..errors import FormatMismatchError

    message = format_mismatch(path, expected_ext)
    if message is None:
        return None
    return FormatMismatchError(f"{path}: {message}" + (f" ({detail})" if detail else ""))
