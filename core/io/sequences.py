"""Mesh sequences: a folder of per-frame meshes, ``.npy`` arrays, PC2 and MDD point caches.

Point caches and ``.npy`` files hold only vertex positions; the triangles come from
``topology=`` (a :class:`~faceretarget.model.Mesh`, a mesh file, or a ``(T, 3)`` array)
or, when that is not given, from a mesh file beside the cache with the same stem
(``take.pc2`` + ``take.obj``, as Blender's and Maya's exporters produce).

PC2 (little-endian float32, 32-byte header) and MDD (big-endian: frame count, point
count, frame times in seconds, then float32 frames) are **memory-mapped**: a long
sequence stays on disk and is read frame by frame by whoever uses it. ``.npy`` is
memory-mapped too. Every declared size is checked against the file size (truncation)
and the memory budget before anything is mapped or allocated.

Writers: a folder of OBJ frames (``frame_00000.obj``... plus ``sequence.json`` with the
frame rate), PC2, MDD and ``.npy``, all atomic. PC2/MDD store float32.
"""

from __future__ import annotations

import json
import struct
from collections import Counter
from collections.abc import Iterable
from pathlib import Path
from typing import IO, Any, TypeAlias

import numpy as np
import numpy.typing as npt

from .._types import PathLike
from ..errors import FileFormatError, InputError
from ..model import Animation, Mesh, MeshSequence
from ._atomic import atomic_dir, atomic_file, write_file_synced
from ._common import (
    TEXT_TOKEN_FACTOR,
    bad,
    check_budget,
    fps_from_times,
    guarded_reader,
    load_npy,
    natural_key,
    open_regular,
    read_text,
    to_float32,
)
from .meshes import obj_text

#: The triangles of a points-only file: a Mesh, a mesh file, ``(T, 3)`` triangles, or None
#: (a same-stem mesh beside the file).
Topology: TypeAlias = "Mesh | PathLike | npt.ArrayLike | None"

__all__ = [
    "read_mesh_folder",
    "read_npy_sequence",
    "read_pc2",
    "read_mdd",
    "write_obj_sequence",
    "write_pc2",
    "write_mdd",
    "write_npy",
    "resolve_topology",
    "as_sequence",
    "SEQUENCE_SIDECAR",
    "sibling_topology",
    "POINTS_ONLY",
]

PC2_MAGIC = b"POINTCACHE2\x00"
PC2_HEADER = struct.Struct("<12siiffi")
MDD_HEADER = struct.Struct(">ii")
SEQUENCE_SIDECAR = "sequence.json"
_DEFAULT_FPS = 30.0
_WRITE_CHUNK = 1 << 22  # floats per chunk when streaming a (memory-mapped) sequence to disk


def mesh_extensions() -> tuple[str, ...]:
    """Extensions of every registered single-mesh reader (built-in and plugins)."""
    from .dispatch import table

    return tuple(e for e in table().extensions("read", "mesh") if e != "/")


def _load_mesh(path: Path) -> Mesh:
    from .dispatch import read

    return read(path, kind="mesh")


def frame_arrays(path: Path) -> tuple[np.ndarray, np.ndarray]:
    """(vertices, triangles) of one frame file; built-in formats skip the Mesh checks
    (the caller compares the triangles with a first frame validated as a Mesh)."""
    from .meshes import _ARRAY_READERS, mesh_arrays

    if path.suffix.lower() in _ARRAY_READERS:
        return mesh_arrays(path)
    mesh = _load_mesh(path)
    return mesh.vertices, mesh.triangles


#: formats holding only vertex positions: their reader takes the triangles from a sibling
POINTS_ONLY = (".npy", ".npz", ".pc2", ".mdd")


def sibling_topology(path: PathLike) -> Path | None:
    """The same-stem mesh file beside points-only ``path`` that its reader takes the
    triangles from when no ``topology=`` is given (an input read indirectly), or None."""
    path = Path(path)
    for ext in mesh_extensions():
        sibling = path.with_suffix(ext)
        if sibling != path and sibling.is_file():
            return sibling
    return None


def resolve_topology(path: Path, topology: Topology, n_vertices: int) -> Mesh | np.ndarray:
    """The triangles for a points-only file: ``topology`` or a same-stem mesh beside ``path``."""
    if topology is None:
        topology = sibling_topology(path)
        if topology is None:
            raise InputError(
                f"{path}: this file holds only vertex positions; pass topology= (a mesh file with the same "
                f"vertex order, e.g. --topology neutral.obj) or put {path.stem}.obj beside it"
            )
    if isinstance(topology, (str, Path)):
        topology = _load_mesh(Path(topology))
    if isinstance(topology, Mesh):
        if topology.n_vertices != n_vertices:
            raise FileFormatError(
                f"{path}: holds {n_vertices} points per frame but the topology mesh {topology.name or ''} has "
                f"{topology.n_vertices} vertices; they must match one to one"
            )
        return topology
    tris = np.asarray(topology)
    if tris.ndim != 2 or tris.shape[1] != 3:
        raise InputError(
            f"topology: expected a Mesh, a mesh file or (T, 3) triangles, got shape {tris.shape}"
        )
    return tris


def _sequence(path: Path, vertices: np.ndarray, topology: Topology, fps: float) -> MeshSequence:
    topo = resolve_topology(path, topology, vertices.shape[1])
    triangles = topo.triangles if isinstance(topo, Mesh) else topo
    return MeshSequence(vertices, triangles, fps=fps, name=path.stem)


# ---------------------------------------------------------------------------------------
# Folder of per-frame meshes
# ---------------------------------------------------------------------------------------
def folder_mesh_files(path: Path) -> list[Path]:
    """Mesh files in a folder (hidden files skipped), natural order; one extension only."""
    exts = set(mesh_extensions())
    files = [
        f
        for f in path.iterdir()
        if f.is_file() and not f.name.startswith(".") and f.suffix.lower() in exts
    ]
    if not files:
        raise bad(path, f"the folder holds no mesh files ({', '.join(sorted(exts))})")
    counts = Counter(f.suffix.lower() for f in files)
    if len(counts) > 1:
        raise bad(
            path, f"the folder mixes mesh formats ({dict(counts)}); keep one format per sequence"
        )
    return sorted(files, key=lambda f: natural_key(f.name))


def _sidecar(path: Path, name: str) -> dict:
    side = path / name
    if not side.is_file():
        return {}
    try:
        data = json.loads(read_text(side, allow_empty=True, factor=TEXT_TOKEN_FACTOR))
    except (ValueError, UnicodeDecodeError, OSError) as exc:
        raise bad(side, f"not valid JSON ({exc})") from None
    if not isinstance(data, dict):
        raise bad(side, "must hold a JSON object")
    return data


@guarded_reader
def read_mesh_folder(path: Path, *, fps: float | None = None, **options: Any) -> MeshSequence:
    """A folder of per-frame meshes (same topology, natural file order) as a :class:`MeshSequence`."""
    if not path.is_dir():
        raise bad(path, "expected a folder of per-frame mesh files")
    files = folder_mesh_files(path)
    side = _sidecar(path, SEQUENCE_SIDECAR)
    if "frames" in side:
        names = side["frames"]
        if not isinstance(names, list) or not all(
            isinstance(n, str) and "/" not in n and n == Path(n).name for n in names
        ):
            raise bad(path / SEQUENCE_SIDECAR, "'frames' must list file names inside the folder")
        files = [path / n for n in names]
        missing = [f.name for f in files if not f.is_file()]
        if missing:
            raise bad(path, f"{SEQUENCE_SIDECAR} lists frames that do not exist: {missing[:5]}")
    first = _load_mesh(files[0])
    check_budget(
        path,
        len(files) * first.vertices.size * 8.0,
        f"{len(files)} frames of {first.n_vertices} vertices",
    )
    vertices = np.empty((len(files), first.n_vertices, 3))
    vertices[0] = first.vertices
    for k, f in enumerate(files[1:], 1):
        verts, tris = frame_arrays(f)
        if verts.shape != first.vertices.shape or not np.array_equal(tris, first.triangles):
            raise bad(
                f,
                f"frame {k} has a different topology from {files[0].name} ({verts.shape[0]} vs {first.n_vertices} vertices)",
            )
        vertices[k] = verts
    if fps is None:
        fps = side.get("fps", _DEFAULT_FPS)
    return MeshSequence(vertices, first.triangles, fps=fps, name=side.get("name") or path.name)


def as_sequence(obj: object) -> MeshSequence:
    """A MeshSequence from a MeshSequence or a vertex :class:`Animation` (world vertices)."""
    if isinstance(obj, MeshSequence):
        return obj
    if isinstance(obj, Animation):
        if obj.triangles is None:
            raise InputError("this animation has no triangles; it cannot be written as meshes")
        return MeshSequence(obj.vertices, obj.triangles, fps=obj.fps)
    raise InputError(f"expected a MeshSequence or an Animation, got {type(obj).__name__}")


def write_obj_sequence(
    obj: MeshSequence | Animation,
    path: PathLike,
    *,
    force: bool = False,
    inputs: Iterable = (),
    prefix: str = "frame_",
    **options: Any,
) -> None:
    """Write one OBJ per frame plus ``sequence.json`` (frame rate, order) into folder ``path``."""
    seq = as_sequence(obj)
    digits = max(5, len(str(seq.n_frames - 1)))
    names = [f"{prefix}{k:0{digits}d}.obj" for k in range(seq.n_frames)]
    with atomic_dir(path, inputs=inputs, force=force, allowed_suffixes=(".obj", ".json")) as tmp:
        for k, name in enumerate(names):
            write_file_synced(
                tmp / name, obj_text(np.asarray(seq.vertices[k], dtype=np.float64), seq.triangles)
            )
        meta = {
            "format": "faceretarget.sequence",
            "version": 1,
            "fps": seq.fps,
            "name": seq.name,
            "frames": names,
        }
        write_file_synced(tmp / SEQUENCE_SIDECAR, json.dumps(meta, indent=1))


# ---------------------------------------------------------------------------------------
# .npy
# ---------------------------------------------------------------------------------------
@guarded_reader
def read_npy_sequence(
    path: Path, *, topology: Topology = None, fps: float = _DEFAULT_FPS, **options: Any
) -> MeshSequence:
    """An ``(F, V, 3)`` ``.npy`` array (memory-mapped) with triangles from ``topology``."""
    arr = load_npy(path)
    if arr.ndim != 3 or arr.shape[2] != 3 or arr.shape[0] == 0 or arr.shape[1] == 0:
        raise bad(path, f"expected an (F, V, 3) array of vertex positions, got shape {arr.shape}")
    if arr.dtype.kind != "f":
        raise bad(path, f"expected float coordinates, got dtype {arr.dtype}")
    return _sequence(path, arr, topology, fps)


def write_npy(
    obj: MeshSequence | Animation,
    path: PathLike,
    *,
    force: bool = False,
    inputs: Iterable = (),
    **options: Any,
) -> None:
    """Write the ``(F, V, 3)`` vertices of a sequence/animation as ``.npy`` (dtype kept)."""
    seq = as_sequence(obj)
    with atomic_file(path, inputs=inputs, force=force) as fh:
        np.lib.format.write_array(fh, np.asarray(seq.vertices), allow_pickle=False)


# ---------------------------------------------------------------------------------------
# PC2 and MDD point caches (memory-mapped)
# ---------------------------------------------------------------------------------------
def _header(path: Path, size: int, need: int, what: str) -> bytes:
    if size < need:
        raise bad(
            path,
            f"too short for a {what} header ({size} bytes, need {need})"
            if size
            else "the file is empty",
        )
    with open_regular(path) as fh:
        return fh.read(need)


def _check_cache(
    path: Path, n_frames: int, n_points: int, offset: int, size: int, what: str
) -> None:
    if n_frames <= 0 or n_points <= 0:
        raise bad(
            path,
            f"the {what} header declares {n_frames} frames of {n_points} points; both must be positive",
        )
    nbytes = n_frames * n_points * 12
    check_budget(path, nbytes, f"{n_frames} frames of {n_points} points")
    if size != offset + nbytes:
        state = "truncated" if size < offset + nbytes else "longer than declared"
        raise bad(
            path,
            f"{state}: the header declares {n_frames} frames of {n_points} points ({offset + nbytes} bytes) but the file has {size}",
        )


@guarded_reader
def read_pc2(
    path: Path, *, topology: Topology = None, fps: float = _DEFAULT_FPS, **options: Any
) -> MeshSequence:
    """A PC2 point cache (memory-mapped float32) as a :class:`MeshSequence`."""
    size = path.stat().st_size
    magic, version, n_points, start, rate, n_frames = PC2_HEADER.unpack(
        _header(path, size, PC2_HEADER.size, "PC2")
    )
    if magic != PC2_MAGIC:
        raise bad(path, "wrong magic: not a PC2 point cache (expected 'POINTCACHE2')")
    if version != 1:
        raise bad(path, f"PC2 version {version} is not supported (only 1)")
    _check_cache(path, n_frames, n_points, PC2_HEADER.size, size, "PC2")
    data = np.memmap(
        path, dtype="<f4", mode="r", offset=PC2_HEADER.size, shape=(n_frames, n_points, 3)
    )
    return _sequence(path, data, topology, fps)


@guarded_reader
def read_mdd(
    path: Path, *, topology: Topology = None, fps: float | None = None, **options: Any
) -> MeshSequence:
    """An MDD point cache (big-endian, memory-mapped) as a :class:`MeshSequence`; fps from its frame times."""
    size = path.stat().st_size
    n_frames, n_points = MDD_HEADER.unpack(_header(path, size, MDD_HEADER.size, "MDD"))
    if n_frames <= 0 or n_points <= 0:
        raise bad(
            path,
            f"the MDD header declares {n_frames} frames of {n_points} points; both must be positive",
        )
    offset = MDD_HEADER.size + 4 * n_frames
    _check_cache(path, n_frames, n_points, offset, size, "MDD")
    times = np.fromfile(path, dtype=">f4", count=n_frames, offset=MDD_HEADER.size).astype(
        np.float64
    )
    if not np.all(np.isfinite(times)) or (n_frames > 1 and np.any(np.diff(times) <= 0)):
        raise bad(path, "the frame times are not finite and strictly increasing")
    if fps is None:
        fps = fps_from_times(times, _DEFAULT_FPS)
    data = np.memmap(path, dtype=">f4", mode="r", offset=offset, shape=(n_frames, n_points, 3))
    return _sequence(path, data, topology, fps)


def _stream_frames(fh: IO[bytes], vertices: np.ndarray, dtype: str) -> None:
    step = max(1, _WRITE_CHUNK // max(1, vertices.shape[1] * 3))
    for start in range(0, vertices.shape[0], step):
        fh.write(
            np.ascontiguousarray(
                to_float32(vertices[start : start + step], "point cache", dtype)
            ).tobytes()
        )


def write_pc2(
    obj: MeshSequence | Animation,
    path: PathLike,
    *,
    force: bool = False,
    inputs: Iterable = (),
    **options: Any,
) -> None:
    """Write a sequence/animation as a PC2 point cache (float32, streamed, atomic)."""
    seq = as_sequence(obj)
    with atomic_file(path, inputs=inputs, force=force) as fh:
        fh.write(PC2_HEADER.pack(PC2_MAGIC, 1, seq.n_vertices, 0.0, 1.0, seq.n_frames))
        _stream_frames(fh, seq.vertices, "<f4")


def write_mdd(
    obj: MeshSequence | Animation,
    path: PathLike,
    *,
    force: bool = False,
    inputs: Iterable = (),
    **options: Any,
) -> None:
    """Write a sequence/animation as an MDD point cache (big-endian float32, times in seconds)."""
    seq = as_sequence(obj)
    times = (np.arange(seq.n_frames) / seq.fps).astype(">f4")
    with atomic_file(path, inputs=inputs, force=force) as fh:
        fh.write(MDD_HEADER.pack(seq.n_frames, seq.n_vertices))
        fh.write(times.tobytes())
        _stream_frames(fh, seq.vertices, ">f4")
