"""Static meshes: OBJ, PLY, OFF and STL, read and written with the vertex order kept.

Nothing here merges or splits vertices: OBJ and PLY vertices come out in file order
(UVs and normals are ignored for geometry, so UV seams never split a vertex), quads
and n-gons are fan-triangulated ``(0, k, k+1)``. STL has no shared vertices at all; its
reader joins corners with bit-identical coordinates, numbering them in order of first
appearance (the only possible reading), and the writer stores float32.

Writers are exact for OBJ, OFF (shortest round-trip decimal text) and PLY (binary
float64); STL is exact for float32-representable meshes whose vertices are all used and
numbered in order of first use.
"""

from __future__ import annotations

import os
import re
import struct
from collections.abc import Callable, Iterable, Iterator, Sequence
from pathlib import Path
from typing import IO, Any

import numpy as np

from .._types import PathLike
from ..model import Mesh
from ._atomic import write_bytes
from ._common import (
    CHUNK_BYTES,
    TextRows,
    bad,
    check_budget,
    chunk_work,
    fmt_float,
    guarded_reader,
    iter_chunks,
    number_block,
    open_regular,
    parse_int,
    read_bytes,
    to_float32,
)

__all__ = [
    "mesh_arrays",
    "read_obj",
    "read_ply",
    "read_off",
    "read_stl",
    "write_obj",
    "write_ply",
    "write_off",
    "write_stl",
    "parse_obj",
    "obj_text",
    "fan_triangulate",
]

#: OBJ statements that carry no triangle geometry and are skipped
_OBJ_IGNORED = {
    "vt",
    "vn",
    "vp",
    "o",
    "g",
    "s",
    "mg",
    "usemtl",
    "mtllib",
    "l",
    "p",
    "cstype",
    "deg",
    "bmat",
    "step",
    "curv",
    "curv2",
    "surf",
    "parm",
    "trim",
    "hole",
    "scrv",
    "sp",
    "end",
    "con",
    "bevel",
    "c_interp",
    "d_interp",
    "lod",
    "shadow_obj",
    "trace_obj",
    "ctech",
    "stech",
    "maplib",
    "usemap",
    "call",
    "csh",
}


def fan_triangulate(polygons: list[list[int]]) -> np.ndarray:
    """Triangles ``(T, 3)`` from polygons (lists of >= 3 vertex ids), fan ``(p0, pk, pk+1)``."""
    if not polygons:
        return np.zeros((0, 3), dtype=np.int64)
    sizes = np.fromiter((len(p) for p in polygons), dtype=np.int64, count=len(polygons))
    flat = np.fromiter((i for p in polygons for i in p), dtype=np.int64, count=int(sizes.sum()))
    return _polygons_to_triangles(flat, sizes)


def _clean_polygon(poly: list[int]) -> list[int]:
    """Drop consecutive repeats (and a closing repeat of the first vertex)."""
    out = [poly[0]]
    for i in poly[1:]:
        if i != out[-1]:
            out.append(i)
    if len(out) > 1 and out[-1] == out[0]:
        out.pop()
    return out


#: below this many vertices a sorted triangle packs into one int64 key (V**3 < 2**63)
_KEY_LIMIT = 1 << 21


def _mesh(path: Path, vertices: np.ndarray, triangles: np.ndarray) -> Mesh:
    """The :class:`Mesh` of arrays a reader has checked (ids in range, no corner repeated
    within a triangle). The model's duplicate-triangle check sorts a copy of every id
    (about 6x the triangles at its peak); here each sorted triangle is packed into one
    int64 key, so reading stays within a small multiple of the result."""
    n = int(vertices.shape[0])
    if n < 3:
        raise bad(path, f"a mesh needs at least 3 vertices, the file has {n}")
    if triangles.shape[0] == 0:
        raise bad(path, "holds no faces (a point cloud is not a mesh)")
    if n >= _KEY_LIMIT:
        return Mesh(vertices, triangles, name=path.stem)  # the model checks it
    keys = np.empty(triangles.shape[0], dtype=np.int64)
    step = 1 << 16
    for s in range(0, triangles.shape[0], step):
        b = np.sort(triangles[s : s + step], axis=1)
        keys[s : s + step] = (b[:, 0] * n + b[:, 1]) * n + b[:, 2]
    keys.sort()
    same = keys[1:] == keys[:-1]
    if same.any():
        k = int(keys[1:][same][0])
        dup = [k // (n * n), (k // n) % n, k % n]
        raise bad(
            path,
            f"{int(np.count_nonzero(same))} triangle(s) appear more than once (e.g. vertices {dup}); remove duplicate triangles",
        )
    del keys, same
    return Mesh(vertices, triangles, name=path.stem, _trusted=True)


# ---------------------------------------------------------------------------------------
# OBJ
# ---------------------------------------------------------------------------------------
class _SlowPath(Exception):
    """The vectorized OBJ parser met something unusual; the line-by-line parser decides."""


_SLASH_TAIL = re.compile(r"/\S*")


def _parse_obj_fast(lines: list[str], v0: int = 0) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Vertices (V, 3), flat polygon ids (0-based) and polygon sizes, vectorized, of a run
    of lines after ``v0`` vertices (relative indices count back from there).

    Raises _SlowPath for anything needing a precise diagnosis (bad numbers, unknown
    statements, degenerate faces, relative indices out of range ...).
    """
    prefix = [ln[:2] for ln in lines]
    others = {
        ln.split(None, 1)[0]
        for ln, p in zip(lines, prefix)
        if p not in ("v ", "f ") and ln.strip() and ln[0] != "#"
    }
    if not others <= _OBJ_IGNORED:
        raise _SlowPath
    v_body = [ln[2:] for ln, p in zip(lines, prefix) if p == "v "]
    f_body = [ln[2:] for ln, p in zip(lines, prefix) if p == "f "]
    del lines
    try:
        if v_body:
            vertices = np.fromstring(
                " ".join(v_body), sep=" "
            )  # text mode: C parsing, not deprecated
            if vertices.size != 3 * len(v_body):
                vertices = np.loadtxt(
                    v_body, usecols=(0, 1, 2), dtype=np.float64, ndmin=2, comments=None
                )
        else:
            vertices = np.zeros((0, 3))
        del v_body
        if not f_body:
            return vertices.reshape(-1, 3), np.zeros(0, dtype=np.int64), np.zeros(0, dtype=np.int64)
        # polygons separated by a 0, which OBJ never uses as an index
        ids = np.fromstring(_SLASH_TAIL.sub("", " 0 ".join(f_body)), sep=" ", dtype=np.int64)
    except (ValueError, IndexError, OverflowError):
        raise _SlowPath from None
    vertices = vertices.reshape(-1, 3)
    cuts = np.flatnonzero(ids == 0)
    if cuts.size != len(f_body) - 1:
        raise _SlowPath
    sizes = np.diff(np.concatenate(([-1], cuts, [ids.size]))) - 1
    ids = ids[ids != 0]
    if np.any(sizes < 3):
        raise _SlowPath
    if np.any(ids < 0):
        # relative indices count back from the vertices defined before the face's line
        v_before = v0 + np.cumsum([p == "v " for p in prefix])
        f_lines = np.asarray([i for i, p in enumerate(prefix) if p == "f "])
        before_per_id = np.repeat(v_before[f_lines], sizes)
        ids = np.where(ids < 0, before_per_id + ids, ids - 1)
        if np.any(ids < 0):
            raise _SlowPath
    else:
        ids = ids - 1
    offsets = np.concatenate(([0], np.cumsum(sizes)[:-1]))
    nxt = np.arange(ids.size) + 1
    nxt[np.cumsum(sizes) - 1] = offsets  # each corner's successor, wrapping around its polygon
    if np.any(ids == ids[nxt]):
        raise _SlowPath  # a polygon repeats a vertex: clean it or report it line by line
    if sizes.max() > 3 and _has_repeats(ids, sizes):
        raise _SlowPath
    return vertices, ids, sizes


def _has_repeats(ids: np.ndarray, sizes: np.ndarray) -> bool:
    """Whether any polygon (flat ``ids`` split by ``sizes``) uses a vertex twice."""
    poly = np.repeat(np.arange(sizes.size), sizes)
    pairs = np.stack([poly, ids], axis=1)
    return np.unique(pairs, axis=0).shape[0] != ids.size


def _polygons_to_triangles(ids: np.ndarray, sizes: np.ndarray) -> np.ndarray:
    if np.all(sizes == 3):
        return ids.reshape(-1, 3)
    starts = np.concatenate(([0], np.cumsum(sizes)[:-1]))
    n_tris = sizes - 2
    poly_of_tri = np.repeat(np.arange(sizes.size), n_tris)
    k = np.arange(int(n_tris.sum())) - np.repeat(np.cumsum(n_tris) - n_tris, n_tris)
    base = starts[poly_of_tri]
    return np.stack([ids[base], ids[base + k + 1], ids[base + k + 2]], axis=1)


def obj_arrays(text: str, path: PathLike) -> tuple[np.ndarray, np.ndarray]:
    """Vertices ``(V, 3)`` and fan-triangulated triangles ``(T, 3)`` of OBJ ``text``."""
    vertices, triangles, n_faces = _obj_chunk(text, path, 0, 0)
    return _obj_checked(path, vertices, triangles, n_faces)


def _obj_chunk(
    text: str, path: PathLike, line0: int, v0: int
) -> tuple[np.ndarray, np.ndarray, int]:
    """(vertices, triangles with file-wide 0-based ids, polygon count) of whole OBJ lines
    that follow ``line0`` lines and ``v0`` vertices of the file."""
    if "\\\n" in text:
        text = text.replace("\\\r\n", " ").replace("\\\n", " ")
    lines = text.splitlines()
    if text[:1] in (" ", "\t") or "\n " in text or "\n\t" in text:
        lines = [ln.strip() for ln in lines]
    try:
        vertices, ids, sizes = _parse_obj_fast(lines, v0)
    except _SlowPath:
        del lines
        vertices, polygons = _parse_obj_lines(text, path, line0, v0)
        return vertices, fan_triangulate(polygons), len(polygons)
    return vertices, _polygons_to_triangles(ids, sizes), sizes.size


def _checked_arrays(
    path: PathLike, vertices: np.ndarray, triangles: np.ndarray, n_faces: int
) -> tuple[np.ndarray, np.ndarray]:
    n_vertices = vertices.shape[0]
    if n_vertices == 0:
        raise bad(path, "holds no vertices")
    if n_faces == 0:
        raise bad(path, "holds no faces (a point cloud is not a mesh)")
    if not np.all(np.isfinite(vertices)):
        row = int(np.argwhere(~np.isfinite(vertices))[0][0])
        raise bad(path, f"vertex {row} has a NaN or infinite coordinate")
    if triangles.size and (triangles.min() < 0 or triangles.max() >= n_vertices):
        worst = int(triangles.max()) if triangles.max() >= n_vertices else int(triangles.min())
        raise bad(
            path,
            f"a face uses vertex {worst} but the file has {n_vertices} vertices (0-based ids 0..{n_vertices - 1})",
        )
    return vertices, triangles


def parse_obj(text: str, path: PathLike) -> tuple[np.ndarray, list[list[int]]]:
    """Vertices ``(V, 3)`` and polygons (0-based) of OBJ ``text``, line by line; errors name the line."""
    vertices, polygons = _parse_obj_lines(text, path, 0, 0)
    for poly_id, poly in enumerate(polygons):
        if max(poly) >= len(vertices):
            raise bad(
                path,
                f"face {poly_id + 1} uses vertex {max(poly) + 1} but the file has {len(vertices)} vertices",
            )
    return vertices, polygons


def _parse_obj_lines(
    text: str, path: PathLike, line0: int, v0: int
) -> tuple[np.ndarray, list[list[int]]]:
    """:func:`parse_obj` of lines that follow ``line0`` lines and ``v0`` vertices (no
    check of indices against the vertex count: later lines may add vertices)."""
    if "\\\n" in text:
        text = text.replace("\\\r\n", " ").replace("\\\n", " ")
    vertex_rows: list[list[str]] = []
    polygons: list[list[int]] = []
    for lineno, raw in enumerate(text.splitlines(), line0 + 1):
        line = raw.strip()
        if not line or line[0] == "#":
            continue
        parts = line.split()
        key = parts[0]
        if key == "v":
            if len(parts) < 4:
                raise bad(path, f"line {lineno}: a vertex needs 3 coordinates, got {line[:60]!r}")
            vertex_rows.append(parts[1:4])
        elif key == "f":
            if len(parts) < 4:
                raise bad(
                    path, f"line {lineno}: a face needs at least 3 vertices, got {line[:60]!r}"
                )
            n_now = v0 + len(vertex_rows)
            poly = []
            for token in parts[1:]:
                head = token.split("/", 1)[0]
                try:
                    idx = int(head)
                except ValueError:
                    raise bad(
                        path,
                        f"line {lineno}: bad face vertex {token[:30]!r} (expected an index like 7, 7/3 or 7//2)",
                    ) from None
                if idx > 0:
                    poly.append(idx - 1)
                elif idx < 0:
                    if -idx > n_now:
                        raise bad(
                            path,
                            f"line {lineno}: relative index {idx} points before the first vertex",
                        )
                    poly.append(n_now + idx)
                else:
                    raise bad(
                        path, f"line {lineno}: face index 0 is invalid (OBJ indices start at 1)"
                    )
            poly = _clean_polygon(poly)
            if len(poly) < 3 or len(set(poly)) != len(poly):
                raise bad(path, f"line {lineno}: degenerate face {line[:60]!r} (a vertex repeats)")
            polygons.append(poly)
        elif key not in _OBJ_IGNORED:
            raise bad(
                path, f"line {lineno}: unknown OBJ statement {key[:20]!r}; is this an OBJ file?"
            )
    try:
        vertices = np.array(vertex_rows, dtype=np.float64).reshape(-1, 3)
    except ValueError:
        for k, row in enumerate(vertex_rows, v0 + 1):
            try:
                [float(x) for x in row]
            except ValueError:
                raise bad(
                    path, f"vertex {k}: coordinates {' '.join(row)[:60]!r} are not numbers"
                ) from None
        raise
    return vertices, polygons


_V_LINE = re.compile(rb"^[ \t]*v[ \t]", re.M)
_F_LINE = re.compile(rb"^[ \t]*f[ \t]", re.M)


def _count_lines(chunk: bytes, key: bytes, pattern: re.Pattern) -> int:
    """Lines of ``chunk`` starting with statement ``key`` (b"v" or b"f")."""
    if chunk[:1] in (b" ", b"\t") or b"\n " in chunk or b"\n\t" in chunk:
        return len(pattern.findall(chunk))
    return (
        chunk.count(b"\n" + key + b" ")
        + chunk.count(b"\n" + key + b"\t")
        + (chunk[:2] in (key + b" ", key + b"\t"))
    )


def _decode(chunk: bytes, first: bool) -> str:
    try:
        return chunk.decode("utf-8-sig" if first else "utf-8")
    except UnicodeDecodeError:
        return chunk.decode("latin-1")


def _obj_chunks(fh: IO[bytes]) -> Iterator[bytes]:
    """Whole-line chunks of an OBJ file (a line continued with a backslash stays whole)."""
    pending = b""
    for chunk in iter_chunks(fh, CHUNK_BYTES):
        chunk = pending + chunk
        if chunk.endswith((b"\\\n", b"\\\r\n")):
            pending = chunk
            continue
        pending = b""
        yield chunk
    if pending:
        yield pending


def _obj_file_arrays(path: Path) -> tuple[np.ndarray, np.ndarray]:
    """Vertices and triangles of an OBJ file, streamed: a first pass counts the vertex and
    face lines (the sizes are checked against the budget), a second parses chunk by chunk
    into arrays of exactly that size, so the peak is the result plus one chunk's work."""
    n_v = n_f = 0
    blank = True
    with open_regular(path) as fh:
        for chunk in _obj_chunks(fh):
            if b"\x00" in chunk:
                raise bad(path, "holds binary data (NUL bytes), not text")
            blank = blank and not chunk.strip()
            n_v += _count_lines(chunk, b"v", _V_LINE)
            n_f += _count_lines(chunk, b"f", _F_LINE)
        if blank:
            raise bad(path, "the file is empty")
        check_budget(path, (n_v + n_f) * 24.0 + chunk_work(fh), f"{n_v} vertices and {n_f} faces")
        vertices = np.empty((n_v, 3))
        triangles = np.empty((n_f, 3), dtype=np.int64)
        iv = it = n_faces = line0 = 0
        fh.seek(0)
        for k, chunk in enumerate(_obj_chunks(fh)):
            verts, tris, faces = _obj_chunk(_decode(chunk, k == 0), path, line0, iv)
            line0 += chunk.count(b"\n")
            n_faces += faces
            if iv + len(verts) > len(
                vertices
            ):  # counted differently (cannot happen for plain lines)
                vertices = np.concatenate([vertices[:iv], verts])
            else:
                vertices[iv : iv + len(verts)] = verts
            if it + len(tris) > len(triangles):  # polygons with more than 3 corners
                check_budget(
                    path,
                    (len(triangles) + len(tris)) * 24.0 * 2 + len(vertices) * 24.0,
                    f"{n_v} vertices and {it + len(tris)} triangles",
                )
                triangles = np.concatenate([triangles[:it], tris])
            else:
                triangles[it : it + len(tris)] = tris
            iv += len(verts)
            it += len(tris)
            del verts, tris
    return _obj_checked(path, vertices[:iv], triangles[:it], n_faces)


def _obj_checked(
    path: PathLike, vertices: np.ndarray, triangles: np.ndarray, n_faces: int
) -> tuple[np.ndarray, np.ndarray]:
    if triangles.size and vertices.shape[0] and triangles.max() >= vertices.shape[0]:
        raise bad(
            path,
            f"a face uses vertex {int(triangles.max()) + 1} but the file has {vertices.shape[0]} vertices (OBJ indices start at 1)",
        )
    return _checked_arrays(path, vertices, triangles, n_faces)


@guarded_reader
def read_obj(path: Path, **options: Any) -> Mesh:
    """Read a Wavefront OBJ as a :class:`Mesh` (file vertex order, n-gons fan-triangulated)."""
    return _mesh(path, *_obj_file_arrays(path))


def obj_text(vertices: np.ndarray, triangles: np.ndarray, header: str = "") -> str:
    """OBJ text with exact (shortest round-trip) coordinates and 1-based triangles."""
    lines = [f"# {header}"] if header else []
    lines.extend(
        "v " + " ".join(map(fmt_float, row))
        for row in np.asarray(vertices, dtype=np.float64).tolist()
    )
    lines.extend(
        "f {} {} {}".format(*t) for t in (np.asarray(triangles, dtype=np.int64) + 1).tolist()
    )
    return "\n".join(lines) + "\n"


def _as_mesh(obj: object, what: str) -> Mesh:
    from ..errors import InputError

    if isinstance(obj, Mesh):
        return obj
    raise InputError(f"{what} writes a Mesh, got {type(obj).__name__}")


def write_obj(
    mesh: Mesh, path: PathLike, *, force: bool = False, inputs: Iterable = (), **options: Any
) -> None:
    """Write a :class:`Mesh` as OBJ (atomic)."""
    mesh = _as_mesh(mesh, "the OBJ writer")
    from .._version import __version__

    write_bytes(
        path,
        obj_text(mesh.vertices, mesh.triangles, f"faceretarget {__version__}").encode(),
        inputs=inputs,
        force=force,
    )


# ---------------------------------------------------------------------------------------
# OFF
# ---------------------------------------------------------------------------------------
@guarded_reader
def read_off(path: Path, **options: Any) -> Mesh:
    """Read an OFF file (also COFF/NOFF variants: extra per-vertex values are ignored)."""
    return _mesh(path, *_off_arrays(path))


def _off_arrays(path: Path) -> tuple[np.ndarray, np.ndarray]:
    """Vertices and triangles of an OFF file, streamed: the counts line is checked against
    the budget, then the rows are parsed chunk by chunk into arrays of that size."""
    with open_regular(path) as fh:
        rows = TextRows(path, fh, comment=b"#")
        first = rows.next()
        if first is None:
            raise bad(path, "the file is empty")
        parts = first.split()
        if not re.fullmatch(rb"(ST)?C?N?OFF", parts[0]):
            raise bad(path, "missing the OFF header line (the file must start with 'OFF')")
        head = parts[1:]
        if len(head) < 2:
            counts = rows.next()
            if counts is None:
                raise bad(path, "missing the vertex/face counts line")
            head = counts.split()
        if len(head) < 2:
            raise bad(path, "the counts line needs 'n_vertices n_faces [n_edges]'")
        n_vertices = parse_int(_text(head[0]), path, "vertex count")
        n_faces = parse_int(_text(head[1]), path, "face count")
        check_budget(
            path,
            (n_vertices * 3 + n_faces * 3) * 8.0 + chunk_work(fh),
            f"{n_vertices} vertices and {n_faces} faces",
        )
        vertices = np.empty((n_vertices, 3))
        done = 0
        while done < n_vertices:
            block = rows.take(n_vertices - done)
            if not block:
                break
            values = number_block(block, 3)
            if values is None:
                values = _rows_slow(path, block, done, 3, "vertex", "coordinates")
            vertices[done : done + len(block)] = values
            done += len(block)
            del block, values
        triangles, polygons = _face_rows(
            path, rows, n_faces, lambda i, row: _off_face(path, i, row)
        )
    if done < n_vertices or polygons < n_faces:
        raise bad(
            path,
            f"truncated: declares {n_vertices} vertices and {n_faces} faces but has {done + polygons} data lines",
        )
    return _checked_arrays(path, vertices, triangles, n_faces)


def _text(token: bytes) -> str:
    return token.decode("latin-1")


def _rows_slow(
    path: PathLike, rows: list[bytes], row0: int, width: int, what: str, values: str
) -> np.ndarray:
    """``rows`` parsed one by one (the fast path refused them): errors name the row."""
    out = np.empty((len(rows), width))
    for k, row in enumerate(rows):
        tokens = row.split()
        if len(tokens) < width:
            raise bad(path, f"{what} {row0 + k}: needs {width} {values}")
        try:
            out[k] = [float(t) for t in tokens[:width]]
        except ValueError:
            raise bad(path, f"{what} {row0 + k}: a coordinate is not a number") from None
    return out


def _off_face(path: PathLike, i: int, row: bytes) -> list[int]:
    tokens = row.split()
    k = parse_int(_text(tokens[0]), path, f"face {i}: vertex count")
    if k < 3 or len(tokens) < k + 1:
        raise bad(path, f"face {i}: needs at least 3 vertex ids and as many as it declares ({k})")
    poly = _clean_polygon([parse_int(_text(x), path, f"face {i}") for x in tokens[1 : k + 1]])
    if len(poly) < 3 or len(set(poly)) != len(poly):
        raise bad(path, f"face {i}: degenerate (a vertex repeats)")
    return poly


def _face_rows(
    path: PathLike,
    rows: TextRows,
    n_faces: int,
    slow: Callable[[int, bytes], list[int]],
    fast: bool = True,
) -> tuple[np.ndarray, int]:
    """Triangles of ``n_faces`` face rows, streamed: rows ``3 i0 i1 i2`` are parsed in C
    into the result (when ``fast``), others by ``slow(face id, row)`` (which returns the
    cleaned polygon) and fan-triangulated. Returns (triangles, faces read)."""
    triangles = np.empty((n_faces, 3), dtype=np.int64)
    it = done = 0
    while done < n_faces:
        block = rows.take(n_faces - done)
        if not block:
            break
        ids = number_block(block, 4, np.int64) if fast else None
        if ids is not None and np.all(ids[:, 0] == 3):
            tris = ids[:, 1:]
            repeated = (
                (tris[:, 0] == tris[:, 1]) | (tris[:, 1] == tris[:, 2]) | (tris[:, 0] == tris[:, 2])
            )
            if repeated.any():
                raise bad(
                    path,
                    f"face {done + int(np.flatnonzero(repeated)[0])}: degenerate (a vertex repeats)",
                )
            if tris.size and tris.min() < 0:
                i = int(np.flatnonzero((tris < 0).any(axis=1))[0])
                raise bad(path, f"face {done + i}: negative vertex index {int(tris[i].min())}")
        else:
            polygons = []
            for k, row in enumerate(block):
                poly = slow(done + k, row)
                if min(poly) < 0:
                    raise bad(path, f"face {done + k}: negative vertex index {min(poly)}")
                polygons.append(poly)
            tris = fan_triangulate(polygons)
            del polygons
        if it + len(tris) > len(triangles):  # polygons with more than 3 corners
            check_budget(
                path, (it + len(tris)) * 24.0 * 2 + rows.work, f"{it + len(tris)} triangles"
            )
            triangles = np.concatenate([triangles[:it], tris])
        else:
            triangles[it : it + len(tris)] = tris
        it += len(tris)
        done += len(block)
        del block, ids, tris
    return triangles[:it], done


def write_off(
    mesh: Mesh, path: PathLike, *, force: bool = False, inputs: Iterable = (), **options: Any
) -> None:
    """Write a :class:`Mesh` as OFF text with exact coordinates (atomic)."""
    mesh = _as_mesh(mesh, "the OFF writer")
    lines = ["OFF", f"{mesh.n_vertices} {mesh.n_triangles} 0"]
    lines.extend(" ".join(map(fmt_float, row)) for row in mesh.vertices.tolist())
    lines.extend("3 {} {} {}".format(*t) for t in mesh.triangles.tolist())
    write_bytes(path, ("\n".join(lines) + "\n").encode(), inputs=inputs, force=force)


# ---------------------------------------------------------------------------------------
# PLY
# ---------------------------------------------------------------------------------------
_PLY_TYPES = {
    "char": "i1",
    "int8": "i1",
    "uchar": "u1",
    "uint8": "u1",
    "short": "i2",
    "int16": "i2",
    "ushort": "u2",
    "uint16": "u2",
    "int": "i4",
    "int32": "i4",
    "uint": "u4",
    "uint32": "u4",
    "float": "f4",
    "float32": "f4",
    "double": "f8",
    "float64": "f8",
}


def _ply_header(data: bytes, path: PathLike) -> tuple[str, list[dict], int]:
    if not data.startswith(b"ply"):
        raise bad(path, "missing the 'ply' magic line; not a PLY file")
    end = data.find(b"end_header")
    if end < 0:
        raise bad(path, "the header has no 'end_header' line (truncated or not a PLY file)")
    newline = data.find(b"\n", end)
    body_start = newline + 1 if newline >= 0 else len(data)
    try:
        header = data[:end].decode("ascii")
    except UnicodeDecodeError:
        raise bad(path, "the header is not ASCII text") from None
    fmt = None
    elements: list[dict] = []
    for lineno, line in enumerate(header.splitlines()[1:], 2):
        parts = line.split()
        if not parts or parts[0] in ("comment", "obj_info"):
            continue
        if parts[0] == "format":
            if len(parts) < 3 or parts[1] not in (
                "ascii",
                "binary_little_endian",
                "binary_big_endian",
            ):
                raise bad(path, f"header line {lineno}: unknown format {line[:60]!r}")
            fmt = parts[1]
        elif parts[0] == "element":
            if len(parts) != 3:
                raise bad(path, f"header line {lineno}: expected 'element NAME COUNT'")
            count = parse_int(parts[2], path, f"header line {lineno}: element count")
            elements.append({"name": parts[1], "count": count, "props": []})
        elif parts[0] == "property":
            if not elements:
                raise bad(path, f"header line {lineno}: a property before any element")
            if len(parts) == 5 and parts[1] == "list":
                if (
                    parts[2] not in _PLY_TYPES
                    or parts[3] not in _PLY_TYPES
                    or _PLY_TYPES[parts[2]][0] == "f"
                ):
                    raise bad(path, f"header line {lineno}: bad list types {line[:60]!r}")
                elements[-1]["props"].append((parts[4], _PLY_TYPES[parts[2]], _PLY_TYPES[parts[3]]))
            elif len(parts) == 3 and parts[1] in _PLY_TYPES:
                elements[-1]["props"].append((parts[2], None, _PLY_TYPES[parts[1]]))
            else:
                raise bad(path, f"header line {lineno}: bad property {line[:60]!r}")
        else:
            raise bad(path, f"header line {lineno}: unknown keyword {parts[0][:20]!r}")
    if fmt is None:
        raise bad(path, "the header has no 'format' line")
    return fmt, elements, body_start


def _ply_binary(
    data: bytes, pos: int, elements: list[dict], order: str, path: PathLike
) -> dict[str, dict]:
    out: dict[str, dict] = {}
    for el in elements:
        props, count = el["props"], el["count"]
        if all(p[1] is None for p in props):
            dtype = np.dtype([(f"p{i}", order + p[2]) for i, p in enumerate(props)])
            need = dtype.itemsize * count
            if pos + need > len(data):
                raise bad(
                    path,
                    f"truncated: element {el['name']!r} needs {need} bytes, {len(data) - pos} remain",
                )
            arr = np.frombuffer(data, dtype=dtype, count=count, offset=pos)
            out[el["name"]] = {p[0]: arr[f"p{i}"] for i, p in enumerate(props)}
            pos += need
            continue
        # elements with list properties: fast path when every list has the same length
        values: dict[str, list] = {p[0]: [] for p in props}
        parsed = False
        if len(props) == 1 and count > 0:
            name, ctype, itype = props[0]
            csize = np.dtype(ctype).itemsize
            if pos + csize > len(data):
                raise bad(path, f"truncated inside element {el['name']!r}")
            k = int(np.frombuffer(data, dtype=order + ctype, count=1, offset=pos)[0])
            lists = np.dtype([("n", order + ctype), ("i", order + itype, (k,))]) if k > 0 else None
            if lists is not None and pos + lists.itemsize * count <= len(data):
                arr = np.frombuffer(data, dtype=lists, count=count, offset=pos)
                if np.all(arr["n"] == k):
                    out[el["name"]] = {name: arr["i"]}
                    pos += lists.itemsize * count
                    parsed = True
        if parsed:
            continue
        for _ in range(count):
            for name, ctype, itype in props:
                if ctype is None:
                    size = np.dtype(itype).itemsize
                    if pos + size > len(data):
                        raise bad(path, f"truncated inside element {el['name']!r}")
                    values[name].append(
                        np.frombuffer(data, dtype=order + itype, count=1, offset=pos)[0]
                    )
                    pos += size
                else:
                    csize = np.dtype(ctype).itemsize
                    if pos + csize > len(data):
                        raise bad(path, f"truncated inside element {el['name']!r}")
                    k = int(np.frombuffer(data, dtype=order + ctype, count=1, offset=pos)[0])
                    pos += csize
                    isize = np.dtype(itype).itemsize
                    if k < 0 or pos + k * isize > len(data):
                        raise bad(
                            path, f"truncated or bad list length {k} in element {el['name']!r}"
                        )
                    values[name].append(
                        np.frombuffer(data, dtype=order + itype, count=k, offset=pos)
                    )
                    pos += k * isize
        out[el["name"]] = values
    return out


def _ply_row(path: PathLike, el: dict, row_id: int, row: bytes) -> dict:
    """One ASCII PLY row of element ``el``: property name -> token (or list of tokens)."""
    tokens = row.split()
    pos = 0
    out: dict[str, Any] = {}
    for name, ctype, _itype in el["props"]:
        if pos >= len(tokens):
            raise bad(path, f"element {el['name']!r} row {row_id}: too few values")
        if ctype is None:
            out[name] = tokens[pos]
            pos += 1
        else:
            k = parse_int(
                _text(tokens[pos]), path, f"element {el['name']!r} row {row_id}: list length"
            )
            if pos + 1 + k > len(tokens):
                raise bad(
                    path,
                    f"element {el['name']!r} row {row_id}: list declares {k} values, has {len(tokens) - pos - 1}",
                )
            out[name] = tokens[pos + 1 : pos + 1 + k]
            pos += 1 + k
    return out


def _ply_ascii(
    path: PathLike, rows: TextRows, elements: list[dict], el_v: dict, el_f: dict, fprop: str
) -> tuple[np.ndarray, np.ndarray, int]:
    """(vertices, triangles, faces) of an ASCII PLY body, streamed chunk by chunk."""
    vertices: np.ndarray | None = None
    triangles: np.ndarray | None = None
    n_faces = 0
    for el in elements:
        count = el["count"]
        if el is el_f:

            def face(i: int, row: bytes, el: dict = el) -> list[int]:
                values = _ply_row(path, el, i, row)[fprop]
                try:
                    poly = [int(t) for t in values]
                except (TypeError, ValueError):
                    raise bad(path, "a face vertex index is not a whole number") from None
                if len(poly) < 3:
                    raise bad(path, f"face {i}: needs at least 3 vertices, has {len(poly)}")
                poly = _clean_polygon(poly)
                if len(poly) < 3 or len(set(poly)) != len(poly):
                    raise bad(path, f"face {i}: degenerate (a vertex repeats)")
                return poly

            triangles, n_faces = _face_rows(path, rows, count, face, fast=len(el["props"]) == 1)
            if n_faces < count:
                raise bad(
                    path,
                    f"truncated: element {el['name']!r} declares {count} rows, found {n_faces}",
                )
            continue
        names = [p[0] for p in el["props"]]
        simple = all(p[1] is None for p in el["props"])
        if el is el_v:
            vertices = out_v = np.empty((count, 3))
            cols = [names.index(c) for c in "xyz"]
        done = 0
        while done < count:
            block = rows.take(count - done)
            if not block:
                break
            if el is el_v:
                values = number_block(block, len(names)) if simple else None
                if values is None:
                    values = np.empty((len(block), 3))
                    for k, row in enumerate(block):
                        found = _ply_row(path, el, done + k, row)
                        try:
                            values[k] = [float(found[c]) for c in "xyz"]
                        except (TypeError, ValueError):
                            raise bad(path, "a vertex coordinate is not a number") from None
                    out_v[done : done + len(block)] = values
                else:
                    out_v[done : done + len(block)] = values[:, cols]
                del values
            else:
                for k, row in enumerate(block):  # other elements: checked, not kept
                    _ply_row(path, el, done + k, row)
            done += len(block)
            del block
        if done < count:
            raise bad(
                path, f"truncated: element {el['name']!r} declares {count} rows, found {done}"
            )
    assert vertices is not None and triangles is not None  # el_v, el_f are among elements
    return vertices, triangles, n_faces


def _ply_head(path: PathLike, fh: IO[bytes]) -> bytes:
    """The bytes of a PLY file up to and including the line ending its header."""
    head = b""
    while True:
        block = fh.read(1 << 16)
        head += block
        end = head.find(b"end_header")
        if end >= 0 and (head.find(b"\n", end) >= 0 or not block):
            return head
        if not block or len(head) > 1 << 24:
            return head  # _ply_header says what is missing


@guarded_reader
def read_ply(path: Path, **options: Any) -> Mesh:
    """Read a PLY file (ASCII or binary, any endianness) as a :class:`Mesh`."""
    return _mesh(path, *_ply_arrays(path))


def _ply_arrays(path: Path) -> tuple[np.ndarray, np.ndarray]:
    with open_regular(path) as fh:
        head = _ply_head(path, fh)
        if not head:
            raise bad(path, "the file is empty")
        fmt, elements, body = _ply_header(head, path)
        el_v, el_f, fprop = _ply_layout(path, elements)
        if fmt == "ascii":  # streamed: the text is never held whole
            del head
            check_budget(
                path,
                (el_v["count"] * 3 + el_f["count"] * 3) * 8.0 + chunk_work(fh),
                f"{el_v['count']} vertices and {el_f['count']} faces",
            )
            fh.seek(body)
            vertices, tris, n_faces = _ply_ascii(
                path, TextRows(path, fh), elements, el_v, el_f, fprop
            )
            return _checked_arrays(path, vertices, tris, n_faces)
    data = read_bytes(path)
    fmt, elements, body = _ply_header(data, path)
    el_v, el_f, fprop = _ply_layout(path, elements)
    order = "<" if fmt == "binary_little_endian" else ">"
    parsed = _ply_binary(data, body, elements, order, path)
    try:
        vertices = np.stack(
            [np.asarray(parsed["vertex"][c], dtype=np.float64) for c in "xyz"], axis=1
        )
    except ValueError:
        raise bad(path, "a vertex coordinate is not a number") from None
    return _ply_faces(path, vertices, parsed["face"][fprop])


def _ply_layout(path: PathLike, elements: list[dict]) -> tuple[dict, dict, str]:
    names = [e["name"] for e in elements]
    if "vertex" not in names or "face" not in names:
        raise bad(path, f"needs 'vertex' and 'face' elements, has {names}")
    el_v = elements[names.index("vertex")]
    el_f = elements[names.index("face")]
    check_budget(
        path,
        (el_v["count"] * 3 + el_f["count"] * 4) * 8.0,
        f"{el_v['count']} vertices and {el_f['count']} faces",
    )
    vprops = [p[0] for p in el_v["props"]]
    if not all(c in vprops for c in "xyz"):
        raise bad(path, f"vertex element needs x, y, z properties, has {vprops}")
    fprop = next(
        (
            p[0]
            for p in el_f["props"]
            if p[0] in ("vertex_indices", "vertex_index") and p[1] is not None
        ),
        None,
    )
    if fprop is None:
        raise bad(path, "face element needs a 'vertex_indices' list property")
    return el_v, el_f, fprop


def _ply_faces(
    path: PathLike, vertices: np.ndarray, faces: np.ndarray | Sequence[Sequence[int]]
) -> tuple[np.ndarray, np.ndarray]:
    if isinstance(faces, np.ndarray) and faces.ndim == 2 and faces.shape[1] == 3:
        tris = faces.astype(np.int64)  # triangles: checked as arrays, never as Python lists
        repeated = (
            (tris[:, 0] == tris[:, 1]) | (tris[:, 1] == tris[:, 2]) | (tris[:, 0] == tris[:, 2])
        )
        if repeated.any():
            raise bad(
                path, f"face {int(np.flatnonzero(repeated)[0])}: degenerate (a vertex repeats)"
            )
        if tris.size and tris.min() < 0:
            i = int(np.flatnonzero((tris < 0).any(axis=1))[0])
            raise bad(path, f"face {i}: negative vertex index {int(tris[i].min())}")
        return _checked_arrays(path, vertices, tris, len(tris))
    if isinstance(faces, np.ndarray):
        check_budget(path, faces.size * 64.0, f"{len(faces)} polygons")  # Python lists below
        polygons = faces.astype(np.int64).tolist()
    else:
        try:
            polygons = [[int(i) for i in f] for f in faces]
        except (TypeError, ValueError):
            raise bad(path, "a face vertex index is not a whole number") from None
    cleaned = []
    for i, poly in enumerate(polygons):
        if len(poly) < 3:
            raise bad(path, f"face {i}: needs at least 3 vertices, has {len(poly)}")
        poly = _clean_polygon(poly)
        if len(poly) < 3 or len(set(poly)) != len(poly):
            raise bad(path, f"face {i}: degenerate (a vertex repeats)")
        if min(poly) < 0:
            raise bad(path, f"face {i}: negative vertex index {min(poly)}")
        cleaned.append(poly)
    return _checked_arrays(path, vertices, fan_triangulate(cleaned), len(cleaned))


def ply_bytes(vertices: np.ndarray, triangles: np.ndarray) -> bytes:
    from .._version import __version__

    n_v, n_t = len(vertices), len(triangles)
    header = (
        "ply\nformat binary_little_endian 1.0\n"
        f"comment faceretarget {__version__}\n"
        f"element vertex {n_v}\nproperty double x\nproperty double y\nproperty double z\n"
        f"element face {n_t}\nproperty list uchar int vertex_indices\nend_header\n"
    ).encode("ascii")
    faces = np.zeros(n_t, dtype=[("n", "u1"), ("i", "<i4", (3,))])
    faces["n"] = 3
    faces["i"] = triangles
    return header + np.ascontiguousarray(vertices, dtype="<f8").tobytes() + faces.tobytes()


def write_ply(
    mesh: Mesh, path: PathLike, *, force: bool = False, inputs: Iterable = (), **options: Any
) -> None:
    """Write a :class:`Mesh` as binary little-endian PLY with float64 coordinates (atomic)."""
    mesh = _as_mesh(mesh, "the PLY writer")
    write_bytes(path, ply_bytes(mesh.vertices, mesh.triangles), inputs=inputs, force=force)


# ---------------------------------------------------------------------------------------
# STL
# ---------------------------------------------------------------------------------------
_STL_RECORD = np.dtype([("normal", "<f4", (3,)), ("corners", "<f4", (3, 3)), ("attr", "<u2")])


def _weld(corners: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Join bit-identical corner positions ``(T, 3, 3)``, numbered in order of first appearance."""
    flat = np.ascontiguousarray(corners.reshape(-1, 3), dtype=np.float64)
    keys = flat.view(np.dtype((np.void, flat.dtype.itemsize * 3))).ravel()
    _, first, inverse = np.unique(keys, return_index=True, return_inverse=True)
    order = np.argsort(first, kind="stable")  # unique ids sorted by first appearance
    rank = np.empty_like(order)
    rank[order] = np.arange(order.size)
    vertices = flat[first[order]]
    return vertices, rank[inverse.ravel()].reshape(-1, 3)


@guarded_reader
def read_stl(path: Path, **options: Any) -> Mesh:
    """Read a binary or ASCII STL as a :class:`Mesh` (identical corners joined, first-use order)."""
    return _mesh(path, *_stl_arrays(path))


def _stl_arrays(path: Path) -> tuple[np.ndarray, np.ndarray]:
    with open_regular(path) as fh:
        size = os.fstat(fh.fileno()).st_size
        if size == 0:
            raise bad(path, "the file is empty")
        head = fh.read(84)
    binary = False
    if len(head) >= 84:
        (n_tris,) = struct.unpack("<I", head[80:84])
        binary = size == 84 + 50 * n_tris
    if binary:
        if n_tris == 0:
            raise bad(path, "holds no triangles")
        check_budget(path, n_tris * 9 * 8.0 * 3, f"{n_tris} triangles")
        data = read_bytes(path)
        records = np.frombuffer(data, dtype=_STL_RECORD, count=n_tris, offset=84)
        corners = records["corners"].astype(np.float64)
    else:
        if not head.lstrip().lower().startswith(b"solid"):
            if len(head) >= 84:
                raise bad(
                    path,
                    f"binary STL declares {n_tris} triangles ({84 + 50 * n_tris} bytes) but the file has {size} bytes",
                )
            raise bad(path, "not an STL file (too short for binary STL, and no 'solid' header)")
        corners = _ascii_stl_corners(path)
    if not np.all(np.isfinite(corners)):
        raise bad(path, "a corner has a NaN or infinite coordinate")
    vertices, triangles = _weld(corners)
    repeated = (
        (triangles[:, 0] == triangles[:, 1])
        | (triangles[:, 1] == triangles[:, 2])
        | (triangles[:, 0] == triangles[:, 2])
    )
    if repeated.any():
        raise bad(
            path, f"facet {int(np.flatnonzero(repeated)[0])} has two identical corners (degenerate)"
        )
    return vertices, triangles


_STL_WORDS = re.compile(rb"(?<!\S)(vertex|facet|endloop)(?!\S)")


def _ascii_stl_corners(path: Path) -> np.ndarray:
    """Corners ``(T, 3, 3)`` of an ASCII STL, streamed: a first pass counts the ``vertex``
    words (the result is sized against the budget), a second parses chunk by chunk."""
    with open_regular(path) as fh:
        n = facets = loops = 0
        for chunk in iter_chunks(fh, CHUNK_BYTES):
            if b"\x00" in chunk:
                raise bad(path, "holds binary data (NUL bytes), not text")
            for word in _STL_WORDS.findall(chunk):
                n += word == b"vertex"
                facets += word == b"facet"
                loops += word == b"endloop"
        if not n or n % 3:
            raise bad(path, f"ASCII STL with {n} 'vertex' lines; expected 3 per facet")
        if facets != n // 3 or loops != n // 3:
            raise bad(path, "facet/endloop count does not match the vertex count (truncated?)")
        # the corners, and the weld's sort of them (keys, order, inverse): about 5x the corners
        check_budget(path, n * 24.0 * 5 + chunk_work(fh), f"{n // 3} facets")
        coords = np.empty((n, 3))
        fh.seek(0)
        done = 0
        carry: list[bytes] = []
        for chunk in iter_chunks(fh, CHUNK_BYTES):
            tokens = carry + chunk.split()
            del chunk
            idx = [i for i, t in enumerate(tokens) if t == b"vertex"]
            carry = []
            if idx and idx[-1] + 3 >= len(tokens):  # a vertex continued in the next chunk
                carry = tokens[idx[-1] :]
                idx.pop()
            if done + len(idx) > n:
                raise bad(path, "the file changed while it was read")
            try:
                coords[done : done + len(idx)] = [
                    [float(t) for t in tokens[i + 1 : i + 4]] for i in idx
                ]
            except ValueError:
                raise bad(path, "a 'vertex' line does not hold 3 numbers") from None
            done += len(idx)
            del tokens, idx
        if carry or done != n:
            raise bad(path, "a 'vertex' line does not hold 3 numbers")
    return coords.reshape(-1, 3, 3)


_ARRAY_READERS = {
    ".obj": _obj_file_arrays,
    ".ply": _ply_arrays,
    ".off": _off_arrays,
    ".stl": _stl_arrays,
}


@guarded_reader
def mesh_arrays(path: Path, **options: Any) -> tuple[np.ndarray, np.ndarray]:
    """(vertices, triangles) of an OBJ/PLY/OFF/STL file without building a Mesh.

    For reading many frames of one topology: the caller validates the first frame as a
    Mesh and compares the others' triangles with it.
    """
    reader = _ARRAY_READERS.get(path.suffix.lower())
    if reader is None:
        raise bad(path, f"not one of {', '.join(_ARRAY_READERS)}")
    return reader(path)


def stl_bytes(vertices: np.ndarray, triangles: np.ndarray) -> bytes:
    from ..geometry.mesh_ops import face_normals

    records = np.zeros(len(triangles), dtype=_STL_RECORD)
    records["corners"] = to_float32(vertices, "STL")[triangles]
    records["normal"] = face_normals(np.asarray(vertices, dtype=np.float64), triangles).astype(
        np.float32
    )
    header = b"faceretarget binary STL".ljust(80, b" ")
    return header + struct.pack("<I", len(triangles)) + records.tobytes()


def write_stl(
    mesh: Mesh, path: PathLike, *, force: bool = False, inputs: Iterable = (), **options: Any
) -> None:
    """Write a :class:`Mesh` as binary STL (float32, atomic)."""
    mesh = _as_mesh(mesh, "the STL writer")
    write_bytes(path, stl_bytes(mesh.vertices, mesh.triangles), inputs=inputs, force=force)
