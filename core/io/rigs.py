"""Blendshape rigs as a folder of meshes: the neutral plus one file per shape.

The neutral is the file named in ``rig.json`` (written by :func:`write_rig_folder`), or
given as ``neutral=``, or the one whose stem is ``neutral``/``base``/``basis``/``rest``/
``default`` (case-insensitive). Every other mesh file is a shape named by its stem, in
natural order. ``rig.json`` also keeps the exact shape names (file names are sanitized),
their order and the weight bounds. Each shape must share the neutral's topology; the
rig stores ``shape - neutral`` as its deltas.
"""

from __future__ import annotations

import json
import re
from collections.abc import Iterable
from pathlib import Path
from typing import Any

import numpy as np

from .._types import PathLike
from ..errors import InputError
from ..model import BlendshapeRig, Mesh
from ._atomic import atomic_dir, write_file_synced
from ._common import bad, check_budget, guarded_reader
from .meshes import obj_text
from .sequences import _load_mesh, _sidecar, folder_mesh_files, frame_arrays

__all__ = [
    "read_rig_folder",
    "write_rig_folder",
    "folder_kind",
    "NEUTRAL_NAMES",
    "RIG_SIDECAR",
    "exact_positions",
]

NEUTRAL_NAMES = ("neutral", "base", "basis", "rest", "default")
RIG_SIDECAR = "rig.json"


def folder_kind(path: Path) -> str:
    """The sniffer of the folder readers: ``"rig"`` for a folder with ``rig.json`` or a
    neutral mesh (neutral/base/basis/rest/default), else ``"mesh_sequence"``."""
    path = Path(path)
    names = {p.stem.lower() for p in path.iterdir() if p.is_file()}
    return (
        "rig" if (path / RIG_SIDECAR).is_file() or names & set(NEUTRAL_NAMES) else "mesh_sequence"
    )


def _neutral_file(path: Path, files: list[Path], neutral: str | None) -> Path:
    if neutral is not None:
        for f in files:
            if neutral in (f.name, f.stem):
                return f
        raise bad(
            path,
            f"no mesh file named {neutral!r} for the neutral; files: {[f.name for f in files][:10]}",
        )
    found = [f for f in files if f.stem.lower() in NEUTRAL_NAMES]
    if len(found) != 1:
        raise bad(
            path,
            "cannot tell which file is the neutral: name it neutral.obj (or base/basis/rest/default), "
            f"or pass neutral=FILE; found {[f.name for f in found] or 'none'}",
        )
    return found[0]


@guarded_reader
def read_rig_folder(path: Path, *, neutral: str | None = None, **options: Any) -> BlendshapeRig:
    """A :class:`BlendshapeRig` from a folder holding a neutral mesh and one mesh per shape."""
    if not path.is_dir():
        raise bad(path, "expected a folder with a neutral mesh and one mesh per blendshape")
    side = _sidecar(path, RIG_SIDECAR)
    bounds = None
    if side:
        where = path / RIG_SIDECAR
        shapes = side.get("shapes")
        if not isinstance(side.get("neutral"), str) or not isinstance(shapes, list) or not shapes:
            raise bad(where, "needs 'neutral' (a file name) and 'shapes' (a list of {name, file})")
        if not all(
            isinstance(s, dict)
            and isinstance(s.get("name"), str)
            and isinstance(s.get("file"), str)
            for s in shapes
        ):
            raise bad(where, "every entry of 'shapes' needs a 'name' and a 'file'")
        files = [side["neutral"]] + [s["file"] for s in shapes]
        if any(Path(f).name != f or f.startswith(".") for f in files):
            raise bad(where, "file names must be plain names inside the folder")
        neutral_file = path / side["neutral"]
        shape_files = [path / s["file"] for s in shapes]
        names = [s["name"] for s in shapes]
        if side.get("bounds") is not None:
            bounds = np.asarray(side["bounds"], dtype=np.float64)
    else:
        files = folder_mesh_files(path)
        neutral_file = _neutral_file(path, files, neutral)
        shape_files = [f for f in files if f != neutral_file]
        names = [f.stem for f in shape_files]
    if not shape_files:
        raise bad(path, "the folder holds a neutral but no blendshape files")
    base = _load_mesh(neutral_file)
    check_budget(
        path,
        len(shape_files) * base.vertices.size * 8.0,
        f"{len(shape_files)} shapes of {base.n_vertices} vertices",
    )
    deltas = np.empty((len(shape_files), base.n_vertices, 3))
    for k, f in enumerate(shape_files):
        verts, tris = frame_arrays(f)
        if verts.shape != base.vertices.shape or not np.array_equal(tris, base.triangles):
            raise bad(
                f,
                f"shape {names[k]!r} has a different topology from the neutral ({verts.shape[0]} vs {base.n_vertices} vertices)",
            )
        deltas[k] = verts - base.vertices
    neutral_mesh = Mesh(
        base.vertices,
        base.triangles,
        name=side.get("name") if isinstance(side.get("name"), str) else path.name,
    )
    return BlendshapeRig(neutral_mesh, deltas, names, bounds=bounds)


def exact_positions(neutral: np.ndarray, delta: np.ndarray) -> np.ndarray:
    """Absolute positions ``p`` with ``p - neutral == delta`` bit for bit wherever such a float exists.

    ``neutral + delta`` is nudged by a few ulps where needed, so a rig read from shape
    files (deltas ``shape - neutral``) is written back to the same files exactly.
    """
    pos = neutral + delta
    wrong = (pos - neutral) != delta
    for _ in range(4):
        if not wrong.any():
            break
        direction = np.where((pos - neutral) < delta, np.inf, -np.inf)
        pos[wrong] = np.nextafter(pos[wrong], direction[wrong])
        wrong = (pos - neutral) != delta
    return pos


_SAFE = re.compile(r"[^A-Za-z0-9_.-]+")


def _file_names(names: tuple[str, ...]) -> list[str]:
    used = {"neutral.obj", "rig.json"}
    out = []
    for name in names:
        stem = _SAFE.sub("_", name).strip("._") or "shape"
        candidate, k = f"{stem}.obj", 2
        while candidate.lower() in used:
            candidate, k = f"{stem}_{k}.obj", k + 1
        used.add(candidate.lower())
        out.append(candidate)
    return out


def write_rig_folder(
    rig: BlendshapeRig,
    path: PathLike,
    *,
    force: bool = False,
    inputs: Iterable = (),
    **options: Any,
) -> None:
    """Write ``neutral.obj``, one OBJ per shape and ``rig.json`` into folder ``path`` (atomic)."""
    if not isinstance(rig, BlendshapeRig):
        raise InputError(f"the rig-folder writer takes a BlendshapeRig, got {type(rig).__name__}")
    files = _file_names(rig.names)
    neutral = rig.neutral.vertices
    with atomic_dir(path, inputs=inputs, force=force, allowed_suffixes=(".obj", ".json")) as tmp:
        write_file_synced(tmp / "neutral.obj", obj_text(neutral, rig.neutral.triangles))
        for k, f in enumerate(files):
            write_file_synced(
                tmp / f, obj_text(exact_positions(neutral, rig.deltas[k]), rig.neutral.triangles)
            )
        meta = {
            "format": "faceretarget.rig",
            "version": 1,
            "name": rig.neutral.name,
            "neutral": "neutral.obj",
            "shapes": [{"name": n, "file": f} for n, f in zip(rig.names, files)],
            "bounds": None if rig.bounds is None else rig.bounds.tolist(),
        }
        write_file_synced(tmp / RIG_SIDECAR, json.dumps(meta, indent=1, ensure_ascii=False))
