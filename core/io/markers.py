"""Motion-capture markers: C3D (through the ``c3d`` package), TRC and CSV.

Missing samples become NaN (C3D: a negative residual; TRC/CSV: an empty cell or
``nan``). The neutral reference is the first frame when it is complete; otherwise each
missing marker takes its first observed position (a marker never observed is an error).

CSV layout (read and written): one header row, optional ``frame`` and ``time`` columns,
then ``NAME_x, NAME_y, NAME_z`` per marker (``_x``/``.x``/``:X``/`` X`` suffixes are all
accepted; ``x, y`` only for 2D tracks). Text is written with shortest round-trip
decimals, so CSV and TRC round trips are exact; C3D stores float32.
"""

from __future__ import annotations

import csv
import io
import re
import struct
import warnings
from collections.abc import Callable, Iterable, Iterator
from pathlib import Path
from typing import IO, Any

import numpy as np
import numpy.typing as npt

from .._types import PathLike
from ..errors import FaceRetargetWarning, InputError
from ..model import MarkerSequence
from ._atomic import atomic_file, write_bytes
from ._common import (
    CHUNK_BYTES,
    TEXT_TOKEN_FACTOR,
    TextRows,
    bad,
    check_budget,
    chunk_work,
    fmt_float,
    fps_from_times,
    guarded_reader,
    iter_chunks,
    open_regular,
    parse_float,
    read_text,
    to_float32,
)

__all__ = [
    "read_c3d",
    "read_trc",
    "read_marker_csv",
    "write_c3d",
    "write_trc",
    "write_marker_csv",
    "csv_rows",
    "csv_kind",
    "is_marker_header",
    "META_COLUMNS",
]

_DEFAULT_FPS = 30.0
_AXIS = re.compile(r"^(?P<name>.+?)(?:[_.:/\s-])(?P<axis>[xyzXYZ])$")
#: non-data columns recognised (case-insensitively) in CSV headers
META_COLUMNS = ("frame", "frame#", "time", "timestamp", "timecode", "blendshapecount")
_MISSING = ("", "nan", "-nan", "na", "null")


def _reference(path: PathLike, positions: np.ndarray, names: list[str]) -> np.ndarray:
    """Frame 0, with each missing marker filled by its first observed sample."""
    ref = np.array(positions[0])
    missing = np.isnan(ref[:, 0])
    if missing.any():
        seen = ~np.isnan(positions[..., 0])
        for n in np.flatnonzero(missing):
            frames = np.flatnonzero(seen[:, n])
            if frames.size == 0:
                raise bad(path, f"marker {names[n]!r} is missing in every frame")
            ref[n] = positions[frames[0], n]
    return ref


def _markers(
    path: PathLike,
    positions: np.ndarray,
    names: list[str],
    fps: float,
    reference: npt.ArrayLike | None = None,
) -> MarkerSequence:
    if positions.shape[0] == 0:
        raise bad(path, "holds no frames")
    if reference is None:
        reference = _reference(path, positions, names)
    return MarkerSequence(positions, names=names, fps=fps, reference=reference)


def _cell(text: str, path: PathLike, row: int, column: str) -> float:
    t = text.strip()
    if t.lower() in _MISSING:
        return np.nan
    value = parse_float(t, path, f"row {row}, column {column!r}")
    if not np.isfinite(value):
        raise bad(
            path,
            f"row {row}, column {column!r}: infinite value (write missing samples as empty cells)",
        )
    return value


def _delimiter(first_line: str) -> str:
    return max(",;\t", key=first_line.count)


def _raw_lines(path: Path, fh: IO[bytes]) -> Iterator[bytes]:
    """The file's lines as bytes (line ends kept), a chunk at a time; NUL bytes refused."""
    for chunk in iter_chunks(fh, CHUNK_BYTES):
        if b"\x00" in chunk:
            raise bad(path, "holds binary data (NUL bytes), not text")
        yield from chunk.splitlines(keepends=True)


def _header_of(path: Path, fh: IO[bytes]) -> tuple[list[str], str, int]:
    """(header cells, delimiter, byte offset of the data) from the first non-blank line."""
    offset = 0
    for line in _raw_lines(path, fh):
        offset += len(line)
        text = _decode_line(line, offset == len(line)).strip("\r\n")
        delimiter = _delimiter(text)
        cells = next(csv.reader([text], delimiter=delimiter), [])
        if any(c.strip() for c in cells):
            return [h.strip() for h in cells], delimiter, offset
    raise bad(path, "the file is empty")


def _decode_line(line: bytes, first: bool) -> str:
    try:
        return line.decode("utf-8-sig" if first else "utf-8")
    except UnicodeDecodeError:
        return line.decode("latin-1")


def csv_header(path: Path) -> list[str]:
    """The header row of a CSV file, reading nothing after it (to tell what it holds)."""
    with open_regular(path) as fh:
        return _header_of(path, fh)[0]


def csv_rows(path: Path) -> tuple[list[str], list[list[str]]]:
    """Header and data rows of a (small) CSV file as text (comma, semicolon or tab separated).

    Not used by the readers (they stream with :func:`csv_table`); its memory is not
    measured (Python cells cost more than TEXT_TOKEN_FACTOR per byte of tiny cells)."""
    text = read_text(path, factor=TEXT_TOKEN_FACTOR)
    delimiter = _delimiter(text[:4096].split("\n", 1)[0])
    rows = [
        r for r in csv.reader(io.StringIO(text), delimiter=delimiter) if any(c.strip() for c in r)
    ]
    if not rows:
        raise bad(path, "the file is empty")
    header = [h.strip() for h in rows[0]]
    if len(header) < 2 and len(rows) > 1:
        raise bad(path, "expected a header row with several columns")
    return header, rows[1:]


_EMPTY_CELL = re.compile(rb"(?<=,)[ \t]*(?=,)")


def _data_lines(chunk: bytes, delimiter: bytes) -> list[bytes]:
    """The data rows of a chunk (rows holding only blanks and delimiters are skipped)."""
    blank = b" \t\r" + delimiter
    return [ln.rstrip(b"\r") for ln in chunk.split(b"\n") if ln.strip(blank)]


def _fast_block(lines: list[bytes], delimiter: bytes, width: int) -> np.ndarray | None:
    """The cells of ``lines`` as a (rows, width) float array (empty cell = NaN), parsed in C;
    None when the chunk needs the row-by-row parser (quotes, wrong cell counts, words ...)."""
    body = b"\n".join(lines)
    if b'"' in body:
        return None
    if delimiter != b",":
        if b"," in body:
            return None
        body = body.replace(delimiter, b",")
    body = _EMPTY_CELL.sub(b"nan", b"," + body.replace(b"\n", b",\n,") + b",")
    try:
        values = np.fromstring(body[1:-1].replace(b",\n,", b","), sep=",")
    except ValueError:  # newer numpy: a word among the numbers
        return None
    if values.size != len(lines) * width or np.isinf(values).any():
        return None
    return values.reshape(len(lines), width)


def _slow_block(
    path: PathLike,
    lines: list[bytes],
    delimiter: str,
    header: list[str],
    row0: int,
    text_cols: tuple[int, ...],
) -> tuple[np.ndarray, dict[int, list[str]]]:
    """The row-by-row parser of :func:`csv_table` for one chunk; errors name the row and column."""
    block = np.empty((len(lines), len(header)))
    texts: dict[int, list[str]] = {c: [] for c in text_cols}
    reader = csv.reader((_decode_line(ln, False) for ln in lines), delimiter=delimiter)
    for r, row in enumerate(reader):
        if len(row) != len(header):
            raise bad(path, f"row {row0 + r} has {len(row)} cells but the header has {len(header)}")
        for c, cell in enumerate(row):
            if c in texts:
                texts[c].append(cell.strip())
                block[r, c] = np.nan
                continue
            t = cell.strip()
            block[r, c] = (
                np.nan
                if t.lower() in _MISSING
                else parse_float(t, path, f"row {row0 + r}, column {header[c]!r}")
            )
    return block, texts


def csv_table(
    path: Path,
    pick: Callable[[list[str]], Iterable[int]],
    *,
    text_cols: Callable[[list[str]], Iterable[int]] = lambda header: (),
) -> tuple[list[str], np.ndarray, dict[int, list[str]]]:
    """Stream a CSV file into arrays: ``(header, numeric, texts)``.

    ``pick(header)`` returns the column ids wanted as numbers; ``numeric`` is their
    ``(rows, len(ids))`` float array (an empty or ``nan`` cell is NaN, ``inf`` stays inf
    for the caller to report); ``texts`` maps each id of ``text_cols(header)`` to its cells.
    The file is read twice in chunks (count, then parse into arrays of exactly that size,
    the size checked against the budget first); chunks without quotes or words are parsed
    in C (numpy), others row by row, so the peak is the result plus one chunk's work.
    """
    with open_regular(path) as fh:
        header, delimiter, start = _header_of(path, fh)
        if len(header) < 2:
            raise bad(path, "expected a header row with several columns")
        wanted = list(pick(header))
        texts_wanted = tuple(text_cols(header))
        dsep = delimiter.encode()
        fh.seek(start)
        n_rows = 0
        for chunk in iter_chunks(fh, CHUNK_BYTES):
            if b"\x00" in chunk:
                raise bad(path, "holds binary data (NUL bytes), not text")
            n_rows += len(_data_lines(chunk, dsep))
        width = len(header)
        check_budget(
            path,
            n_rows * (len(wanted) * 8.0 + len(texts_wanted) * 64.0) + chunk_work(fh),
            f"{n_rows} rows of {len(wanted)} numbers",
        )
        numeric = np.empty((n_rows, len(wanted)))
        texts: dict[int, list[str]] = {c: [] for c in texts_wanted}
        fh.seek(start)
        r = 0
        for chunk in iter_chunks(fh, CHUNK_BYTES):
            lines = _data_lines(chunk, dsep)
            block = None if texts_wanted else _fast_block(lines, dsep, width)
            if block is None:
                block, found = _slow_block(path, lines, delimiter, header, r + 2, texts_wanted)
                for c, cells in found.items():
                    texts[c].extend(cells)
            numeric[r : r + len(lines)] = block[:, wanted]
            r += len(lines)
            del block, lines
    return header, numeric[:r], texts


def _marker_columns(header: list[str]) -> tuple[list[str], list[list[int]], list[int]] | None:
    """Marker names, their column ids (x, y[, z]) and meta column ids; None if not a marker header."""
    names: list[str] = []
    columns: list[list[int]] = []
    meta: list[int] = []
    current = None
    for i, col in enumerate(header):
        if col.lower() in META_COLUMNS:
            meta.append(i)
            continue
        m = _AXIS.match(col)
        if not m:
            return None
        name, axis = m.group("name").strip(), "xyz".index(m.group("axis").lower())
        if axis == 0:
            names.append(name)
            columns.append([i])
            current = name
        elif current == name and len(columns[-1]) == axis:
            columns[-1].append(i)
        else:
            return None
    if not names:
        return None
    dims = {len(c) for c in columns}
    if len(dims) != 1 or dims.pop() not in (2, 3):
        return None
    return names, columns, meta


def is_marker_header(header: list[str]) -> bool:
    return _marker_columns(header) is not None


def csv_kind(path: Path) -> str | None:
    """The sniffer of the CSV readers: ``"markers"`` for NAME_x, NAME_y, NAME_z columns,
    else ``"weights"`` (None when the header cannot be read); reads the first row only."""
    try:
        header = csv_header(Path(path))
    except Exception:
        return None
    return "markers" if is_marker_header(header) else "weights"


@guarded_reader
def read_marker_csv(
    path: Path, *, fps: float | None = None, reference: npt.ArrayLike | None = None, **options: Any
) -> MarkerSequence:
    """Markers from a CSV with ``NAME_x, NAME_y, NAME_z`` columns (empty cell = missing)."""
    found: dict[str, Any] = {}

    def pick(header: list[str]) -> list[int]:
        cols = _marker_columns(header)
        if cols is None:
            raise bad(
                path,
                "the header is not a marker layout: expected NAME_x, NAME_y, NAME_z columns (plus optional frame, time)",
            )
        found["names"], found["columns"] = cols[0], cols[1]
        found["time"] = next(
            (i for i, col in enumerate(header) if col.lower() in ("time", "timestamp")), None
        )
        ids = [c for cs in cols[1] for c in cs]
        return ids + ([found["time"]] if found["time"] is not None else [])

    header, table, _ = csv_table(path, pick)
    names, columns = found["names"], found["columns"]
    if table.shape[0] == 0:
        raise bad(path, "holds a header but no frames")
    dim = len(columns[0])
    n_data = len(names) * dim
    if np.isinf(table).any():
        r, c = (int(x) for x in np.argwhere(np.isinf(table))[0])
        col = header[[i for cs in columns for i in cs][c]] if c < n_data else header[found["time"]]
        raise bad(
            path,
            f"row {r + 2}, column {col!r}: infinite value (write missing samples as empty cells)",
        )
    if found["time"] is not None:
        times = table[:, n_data]
        if np.isnan(times).any():
            raise bad(path, f"column {header[found['time']]!r} must hold times in seconds")
        positions = table[:, :n_data].reshape(
            -1, len(names), dim
        )  # a copy only when there is a time column
    else:
        times = None
        positions = table.reshape(-1, len(names), dim)
    if fps is None:
        fps = fps_from_times(times, _DEFAULT_FPS) if times is not None else _DEFAULT_FPS
    return _markers(path, positions, names, fps, reference)


def _final_name(path: PathLike) -> str:
    """The name ``path`` will have once written: a writer handed an atomic temporary
    (``.NAME.PID.TOKEN.frtmp.EXT``) records ``NAME``, never the temporary's name."""
    from ._atomic import temp_owner

    owner = temp_owner(Path(path).name)
    return owner[0] if owner is not None else Path(path).name


def _check_names(names: Iterable[str], what: str, forbidden: str) -> None:
    for n in names:
        if any(ch in n for ch in forbidden):
            raise InputError(
                f"{what}: marker name {n!r} contains a character the format cannot store ({forbidden!r})"
            )


def write_marker_csv(
    markers: MarkerSequence,
    path: PathLike,
    *,
    force: bool = False,
    inputs: Iterable = (),
    **options: Any,
) -> None:
    """Write markers as CSV: ``frame, time, NAME_x, NAME_y[, NAME_z]`` (empty cell = missing)."""
    if not isinstance(markers, MarkerSequence):
        raise InputError(
            f"the marker CSV writer takes a MarkerSequence, got {type(markers).__name__}"
        )
    _check_names(markers.names, "marker CSV", "\n\r")
    axes = "xyz"[: markers.dim]
    buf = io.StringIO()
    w = csv.writer(buf, lineterminator="\n")
    w.writerow(["frame", "time"] + [f"{n}_{a}" for n in markers.names for a in axes])
    pos = np.asarray(markers.positions)
    for f in range(markers.n_frames):
        cells = ["" if np.isnan(v) else fmt_float(v) for v in pos[f].ravel().tolist()]
        w.writerow([str(f), fmt_float(f / markers.fps)] + cells)
    write_bytes(path, buf.getvalue().encode("utf-8"), inputs=inputs, force=force)


# ---------------------------------------------------------------------------------------
# TRC (OpenSim / Motion Analysis, tab separated)
# ---------------------------------------------------------------------------------------
@guarded_reader
def read_trc(
    path: Path, *, fps: float | None = None, reference: npt.ArrayLike | None = None, **options: Any
) -> MarkerSequence:
    """Markers from a TRC file (``DataRate`` gives the fps; empty cells are missing samples)."""
    with open_regular(path) as fh:
        header: list[str] = []
        data_start = 0
        for line in _raw_lines(path, fh):
            data_start += len(line)
            header.append(_decode_line(line, not header).rstrip("\r\n"))
            if len(header) == 5:
                break
        if not header or not header[0].startswith("PathFileType"):
            raise bad(path, "missing the 'PathFileType' first line; not a TRC file")
        if len(header) < 5:
            raise bad(path, "truncated: a TRC file needs 5 header lines")
        keys = header[1].split("\t")
        values = header[2].split("\t")
        if len(keys) != len(values):
            raise bad(path, "header lines 2 and 3 have different numbers of fields")
        info = {k.strip(): v.strip() for k, v in zip(keys, values)}
        for key in ("DataRate", "NumFrames", "NumMarkers"):
            if key not in info:
                raise bad(path, f"the header lacks {key}")
        rate = parse_float(info["DataRate"], path, "DataRate")
        try:
            n_frames, n_markers = int(info["NumFrames"]), int(info["NumMarkers"])
        except ValueError:
            raise bad(path, "NumFrames and NumMarkers must be whole numbers") from None
        if n_frames <= 0 or n_markers <= 0:
            raise bad(
                path, f"declares {n_frames} frames and {n_markers} markers; both must be positive"
            )
        check_budget(
            path,
            n_frames * n_markers * 3 * 8.0 + chunk_work(fh),
            f"{n_frames} frames of {n_markers} markers",
        )
        names = [t.strip() for t in header[3].split("\t")[2:] if t.strip()]
        if len(names) != n_markers:
            raise bad(
                path, f"NumMarkers is {n_markers} but the names line lists {len(names)} markers"
            )
        positions = np.full((n_frames, n_markers, 3), np.nan)
        width = 2 + 3 * n_markers
        fh.seek(data_start)
        rows = TextRows(path, fh, strip=False)
        r = 0
        while True:
            block = rows.take(n_frames + 1 - r)
            if not block:
                break
            if r + len(block) > n_frames:
                raise bad(
                    path, f"NumFrames is {n_frames} but the file has more data rows (wrong count)"
                )
            fast = _fast_block(block, b"\t", width)
            if fast is not None:
                positions[r : r + len(block)] = fast[:, 2:].reshape(-1, n_markers, 3)
            else:
                for k, line in enumerate(block):
                    cells = _decode_line(line, False).split("\t")
                    if len(cells) > width and any(c.strip() for c in cells[width:]):
                        raise bad(
                            path, f"data row {r + k + 1} has {len(cells)} fields; {width} expected"
                        )
                    vals = [_cell(c, path, r + k + 6, "marker data") for c in cells[2:width]]
                    positions[r + k] = np.asarray(
                        vals + [np.nan] * (3 * n_markers - len(vals))
                    ).reshape(n_markers, 3)
            r += len(block)
            del block, fast
        if r != n_frames:
            raise bad(
                path,
                f"NumFrames is {n_frames} but the file has {r} data rows (truncated or wrong count)",
            )
    return _markers(path, positions, names, fps if fps is not None else rate, reference)


def write_trc(
    markers: MarkerSequence,
    path: PathLike,
    *,
    force: bool = False,
    inputs: Iterable = (),
    units: str = "mm",
    **options: Any,
) -> None:
    """Write 3D markers as a tab-separated TRC file (exact decimals; empty cell = missing)."""
    if not isinstance(markers, MarkerSequence):
        raise InputError(f"the TRC writer takes a MarkerSequence, got {type(markers).__name__}")
    if markers.dim != 3:
        raise InputError("TRC stores 3D markers; these are 2D tracks (write them as CSV)")
    _check_names(markers.names, "TRC", "\t\n\r")
    n_f, n_m, fps = markers.n_frames, markers.n_markers, fmt_float(markers.fps)
    lines = [
        f"PathFileType\t4\t(X/Y/Z)\t{_final_name(path)}",
        "DataRate\tCameraRate\tNumFrames\tNumMarkers\tUnits\tOrigDataRate\tOrigDataStartFrame\tOrigNumFrames",
        f"{fps}\t{fps}\t{n_f}\t{n_m}\t{units}\t{fps}\t1\t{n_f}",
        "Frame#\tTime\t" + "\t".join(f"{n}\t\t" for n in markers.names).rstrip("\t"),
        "\t\t" + "\t".join(f"X{i}\tY{i}\tZ{i}" for i in range(1, n_m + 1)),
        "",
    ]
    pos = np.asarray(markers.positions)
    for f in range(n_f):
        cells = ["" if np.isnan(v) else fmt_float(v) for v in pos[f].ravel().tolist()]
        lines.append("\t".join([str(f + 1), fmt_float(f / markers.fps)] + cells))
    write_bytes(path, ("\n".join(lines) + "\n").encode("utf-8"), inputs=inputs, force=force)


# ---------------------------------------------------------------------------------------
# C3D
# ---------------------------------------------------------------------------------------
#: the second byte of every C3D file (the header's "key" 0x50)
C3D_KEY = 0x50


def _c3d_param_frames(reader: Any) -> int | None:
    """POINT:FRAMES (a 16-bit unsigned word, or a float in some writers), or None."""
    param = reader.get("POINT:FRAMES")
    if param is None:
        return None
    value = int(param.float_value) if param.bytes_per_element >= 4 else int(param.uint16_value)
    if value == 65535:  # saturated: long takes store the count elsewhere
        for name in ("TRIAL:ACTUAL_END_FIELD", "POINT:LONG_FRAMES"):
            longer = reader.get(name)
            if longer is not None:
                if name == "TRIAL:ACTUAL_END_FIELD":
                    words = longer.uint16_array
                    return (
                        int(words[0]) + int(words[1]) * 65536 - int(reader.header.first_frame) + 1
                    )
                return (
                    int(longer.float_value)
                    if longer.bytes_per_element >= 4
                    else int(longer.uint16_value)
                )
    return value


def _not_c3d(path: Path, head: bytes) -> str | None:
    """Why ``head`` (the first bytes) is not a C3D header, or None when it could be one."""
    if len(head) >= 2 and head[1] == C3D_KEY and head[0] >= 2:
        return None
    if len(head) >= 2 and head[1] == C3D_KEY:
        return f"the header's parameter-block pointer is {head[0]} (a C3D file's parameters start at block 2 or later)"
    shown = head[:16]
    if shown[:1] in (b"{", b"[") or all(32 <= b < 127 or b in (9, 10, 13) for b in shown):
        what = f"it starts with the text {shown.decode('ascii', 'replace')!r}"
    else:
        what = f"it starts with the bytes {shown[:8].hex(' ')}"
    return (
        f"not a C3D file: a C3D file's second byte is 0x50 ('P'), this one's is "
        f"0x{head[1]:02x} ({head[1]}) and {what}; check the file (or its extension)"
    )


@guarded_reader
def _read_c3d(
    path: Path, *, fps: float | None = None, reference: npt.ArrayLike | None = None, **options: Any
) -> tuple[MarkerSequence, list[str]]:
    import c3d

    size = path.stat().st_size
    if size < 512:
        raise bad(path, f"too short for a C3D file ({size} bytes; the header block alone is 512)")
    notes: list[str] = []
    with open_regular(path) as fh:
        why = _not_c3d(path, fh.read(16))
        if why is not None:
            raise bad(path, why)
        fh.seek(0)
        try:
            reader = c3d.Reader(fh)
        except (AssertionError, ValueError, KeyError, IndexError, struct.error) as exc:
            raise bad(
                path,
                f"the C3D header or parameter section is damaged ({type(exc).__name__}: {str(exc).strip()[:120]})",
            ) from None
        n_points = int(reader.point_used)
        if n_points <= 0:
            raise bad(
                path, f"declares {n_points} markers (POINT:USED); a marker file needs at least one"
            )
        header_frames = int(reader.header.last_frame) - int(reader.header.first_frame) + 1
        param_frames = _c3d_param_frames(reader)
        # what ezc3d does: POINT:FRAMES counts the frames; the header's last-frame word
        # (16 bits, often stale or saturated) only when the parameter is absent
        declared = param_frames if param_frames is not None and param_frames > 0 else header_frames
        if param_frames is not None and param_frames > 0 and param_frames != header_frames:
            notes.append(
                f"the header's frame range ({int(reader.header.first_frame)}..{int(reader.header.last_frame)}, "
                f"{header_frames} frames) disagrees with POINT:FRAMES ({param_frames}); POINT:FRAMES is used, as ezc3d does"
            )
        word = 4 if float(reader.point_scale) < 0 else 2
        per_frame = (n_points * 4 + int(reader.analog_used) * int(reader.analog_per_frame)) * word
        start = (int(reader.header.data_block) - 1) * 512
        if start < 0 or start >= size or per_frame <= 0:
            raise bad(
                path,
                f"the data section starts at byte {start} but the file has {size}; the header is damaged",
            )
        available = (size - start) // per_frame
        n_frames = min(declared, available) if declared > 0 else available
        if 0 < available < declared:
            notes.append(
                f"declares {declared} frames but holds {available} complete ones (truncated?); read the {available} that are there"
            )
        if n_frames <= 0:
            raise bad(
                path,
                f"holds no complete frame of {n_points} markers ({size - start} data bytes, {per_frame} per frame)",
            )
        check_budget(
            path, n_frames * n_points * 3 * 8.0, f"{n_frames} frames of {n_points} markers"
        )
        labels = [str(lab).strip() for lab in list(reader.point_labels)[:n_points]]
        if len(labels) != n_points or any(not lab for lab in labels):
            labels = [lab or f"marker{i}" for i, lab in enumerate(labels)] + [
                f"marker{i}" for i in range(len(labels), n_points)
            ]
        positions = np.full((n_frames, n_points, 3), np.nan)
        count = 0
        for count, (_, points, _) in enumerate(reader.read_frames(copy=False), 1):
            pts = np.asarray(points, dtype=np.float64)
            if pts.shape[0] != n_points or pts.shape[1] < 4:
                raise bad(path, f"frame {count} holds {pts.shape[0]} points; {n_points} declared")
            ok = pts[:, 3] >= 0
            positions[count - 1, ok] = pts[ok, :3]
            if count == n_frames:
                break
        if count < n_frames:  # the c3d package's own frame range ended first
            notes.append(f"{n_frames} frames expected, {count} could be read; read those")
            positions = positions[:count]
            if count == 0:
                raise bad(path, "holds no readable frame")
        rate = float(reader.point_rate)
    if not np.all(np.isfinite(positions[~np.isnan(positions)])):
        raise bad(path, "holds infinite coordinates")
    return _markers(path, positions, labels, fps if fps is not None else rate, reference), notes


def read_c3d(
    path: PathLike,
    *,
    fps: float | None = None,
    reference: npt.ArrayLike | None = None,
    **options: Any,
) -> MarkerSequence:
    """Markers from a C3D file (``c3d`` package); a negative residual marks a missing sample.

    The frame count is read the way ezc3d reads it: ``POINT:FRAMES`` (or, for long takes,
    ``TRIAL:ACTUAL_END_FIELD``/``POINT:LONG_FRAMES``), never more than the complete frames
    the file actually holds; the header's 16-bit last-frame word is used only when the
    parameter is missing. A disagreement, or a file shorter than it declares, is read and
    reported with a :class:`~faceretarget.errors.FaceRetargetWarning`. A file that is not
    C3D at all is a :class:`~faceretarget.errors.FileFormatError` saying so.
    """
    markers, notes = _read_c3d(path, fps=fps, reference=reference, **options)
    for note in notes:
        warnings.warn(f"{path}: {note}", FaceRetargetWarning, stacklevel=2)
    return markers


def write_c3d(
    markers: MarkerSequence,
    path: PathLike,
    *,
    force: bool = False,
    inputs: Iterable = (),
    **options: Any,
) -> None:
    """Write 3D markers as C3D (float32 points; missing samples get residual -1)."""
    import c3d

    if not isinstance(markers, MarkerSequence):
        raise InputError(f"the C3D writer takes a MarkerSequence, got {type(markers).__name__}")
    if markers.dim != 3:
        raise InputError("C3D stores 3D markers; these are 2D tracks (write them as CSV)")
    for n in markers.names:
        if not n.isascii() or not n.isprintable():
            raise InputError(f"C3D labels are ASCII; marker name {n!r} cannot be stored")
    writer = c3d.Writer(point_rate=float(markers.fps), point_scale=-1.0)
    writer.set_point_labels(list(markers.names))
    pos = to_float32(markers.positions, "C3D")
    frames = []
    for f in range(markers.n_frames):
        pts = np.zeros((markers.n_markers, 5), dtype=np.float32)
        missing = np.isnan(pos[f, :, 0])
        pts[~missing, :3] = pos[f, ~missing]
        pts[missing, 3] = -1.0
        frames.append((pts, np.zeros((0, 0), dtype=np.float32)))
    writer.add_frames(frames)
    import warnings

    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        with atomic_file(path, inputs=inputs, force=force) as fh:
            writer.write(fh)
