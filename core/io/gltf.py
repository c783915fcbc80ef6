"""glTF 2.0 (``.glb`` binary and ``.gltf`` JSON): meshes, morph-target rigs and animations.

Reading (any conforming file): the mesh's primitives are joined in order (vertex order
kept, no welding), ``TRIANGLES``/``TRIANGLE_STRIP``/``TRIANGLE_FAN`` modes, indexed or
not, dense or sparse accessors, float or normalized-integer components; morph-target
names come from ``mesh.extras.targetNames``; a weight animation (``path: "weights"``)
becomes an :class:`~faceretarget.model.Animation` over the rig, sampled at its frame
rate (keys resampled to a uniform grid when they are not uniform). Meshes and rigs are
read in scene space: the world transform of the node showing them (``matrix`` or
translation/rotation/scale, parents included) is applied; several meshes in a scene are
merged (or one picked with ``mesh=``, a mesh or node name). An animation's rig stays in
mesh space (its node's motion is the head motion).

Writing (what Blender's and three.js's importers read):

- a **blendshape rig**: one mesh whose primitive has the neutral as ``POSITION``, one
  morph target per shape, ``mesh.extras.targetNames`` and default weights 0;
- a **blendshape animation**: the rig above plus an animation of its weights (LINEAR),
  and the head motion as node translation/rotation channels;
- a **vertex animation** (no rig): one node and mesh per frame under a root node, each
  visible (scale 1) only during its frame through STEP scale channels;
- a plain **mesh**.

POSITION accessors carry ``min``/``max``; sampler inputs are strictly increasing with
``min``/``max``; buffer views are 4-byte aligned (8 for float64 data). Geometry is stored
as float32 (the format's only float type). Provenance, the frame rate and exact float64
copies of the weights and head motion (in buffer views named by ``extras``) go into
``extras.faceretarget``, so a written animation reads back with its weights bit-exact.
"""

from __future__ import annotations

import base64
import json
import math
import os
import struct
from collections.abc import Iterable
from pathlib import Path
from typing import Any, overload

import numpy as np

from .._json import jsonable
from .._types import PathLike
from ..errors import FileFormatError, InputError, OutputError
from ..model import Animation, BlendshapeRig, Mesh, MeshSequence
from ._atomic import note_input, write_bytes
from ._common import (
    bad,
    check_budget,
    check_regular,
    fps_from_times,
    guarded_reader,
    join_arrays,
    open_regular,
    read_bytes,
    split_arrays,
    to_float32,
)

__all__ = [
    "read_gltf_mesh",
    "read_gltf_rig",
    "read_gltf_animation",
    "read_gltf_sequence",
    "write_gltf",
    "gltf_kind",
    "glb_document",
]

GLB_MAGIC = b"glTF"
CHUNK_JSON = 0x4E4F534A
CHUNK_BIN = 0x004E4942
ARRAY_BUFFER = 34962
ELEMENT_ARRAY_BUFFER = 34963
FLOAT, UBYTE, USHORT, UINT = 5126, 5121, 5123, 5125
_COMPONENTS = {5120: "i1", 5121: "u1", 5122: "<i2", 5123: "<u2", 5125: "<u4", 5126: "<f4"}
_NORMALIZE = {5120: 127.0, 5121: 255.0, 5122: 32767.0, 5123: 65535.0}
_N_COMPONENTS = {"SCALAR": 1, "VEC2": 2, "VEC3": 3, "VEC4": 4, "MAT2": 4, "MAT3": 9, "MAT4": 16}
_EXTRAS_KEY = "faceretarget"

#: default frame rate when a foreign file's keys are not uniform and no fps is given
DEFAULT_FPS = 30.0


# =======================================================================================
# Reading
# =======================================================================================
class _Doc:
    """A parsed glTF document with typed, bounds-checked access (errors name the file)."""

    def __init__(self, path: Path, gltf: dict, buffers: list[bytes]) -> None:
        self.path = path
        self.gltf = gltf
        self.buffers = buffers

    # -- typed access ----------------------------------------------------------------
    def fail(self, what: str) -> FileFormatError:
        return bad(self.path, what)

    def get(self, obj: dict, key: str, kind: type, where: str, default: Any = ...) -> Any:
        if key not in obj:
            if default is ...:
                raise self.fail(f"{where} lacks the required '{key}'")
            return default
        value = obj[key]
        if kind is int and (isinstance(value, bool) or not isinstance(value, int)):
            if isinstance(value, float) and value.is_integer():
                return int(value)
            raise self.fail(f"{where}.{key} must be an integer, got {value!r:.40}")
        if kind is not int and not isinstance(value, kind):
            raise self.fail(f"{where}.{key} has the wrong type ({type(value).__name__})")
        return value

    def item(self, array: str, index: Any, where: str) -> dict:
        items = self.gltf.get(array, [])
        if not isinstance(items, list):
            raise self.fail(f"'{array}' must be a list")
        if isinstance(index, bool) or not isinstance(index, int) or not 0 <= index < len(items):
            raise self.fail(
                f"{where} refers to {array}[{index!r:.20}] but the file has {len(items)}"
            )
        value = items[index]
        if not isinstance(value, dict):
            raise self.fail(f"{array}[{index}] must be an object")
        return value

    def count(self, array: str) -> int:
        items = self.gltf.get(array, [])
        if not isinstance(items, list):
            raise self.fail(f"'{array}' must be a list")
        return len(items)

    # -- raw data ----------------------------------------------------------------------
    def view_bytes(self, index: int, where: str) -> tuple[bytes, int, int, int | None]:
        """(buffer, offset, length, stride) of buffer view ``index``, bounds checked."""
        view = self.item("bufferViews", index, where)
        vw = f"bufferViews[{index}]"
        buf_index = self.get(view, "buffer", int, vw)
        if not 0 <= buf_index < len(self.buffers):
            raise self.fail(
                f"{vw} refers to buffers[{buf_index}] but the file has {len(self.buffers)}"
            )
        buf = self.buffers[buf_index]
        offset = self.get(view, "byteOffset", int, vw, 0)
        length = self.get(view, "byteLength", int, vw)
        stride = self.get(view, "byteStride", int, vw, None)
        if offset < 0 or length < 1 or offset + length > len(buf):
            raise self.fail(
                f"{vw} (offset {offset}, length {length}) lies outside buffer {buf_index} ({len(buf)} bytes)"
            )
        if stride is not None and not 4 <= stride <= 252:
            raise self.fail(f"{vw}.byteStride {stride} is outside 4..252")
        return buf, offset, length, stride

    def _read_view_array(
        self, view_index: int, offset: int, count: int, ncomp: int, dtype: np.dtype, where: str
    ) -> np.ndarray:
        buf, v_off, v_len, stride = self.view_bytes(view_index, where)
        if offset < 0:
            raise self.fail(f"{where}.byteOffset is negative")
        elem = dtype.itemsize * ncomp
        stride = stride or elem
        if stride < elem:
            raise self.fail(
                f"{where}: byteStride {stride} is smaller than one element ({elem} bytes)"
            )
        need = offset + stride * (count - 1) + elem
        if need > v_len:
            raise self.fail(
                f"{where}: {count} elements need {need} bytes but its buffer view has {v_len}"
            )
        arr = np.ndarray(
            (count, ncomp),
            dtype=dtype,
            buffer=buf,
            offset=v_off + offset,
            strides=(stride, dtype.itemsize),
        )
        return np.array(arr)

    def accessor(self, index: Any, where: str, *, integer: bool = False) -> np.ndarray:
        """Accessor ``index`` as ``(count, n_components)`` float64 (int64 with ``integer``)."""
        acc = self.item("accessors", index, where)
        aw = f"accessors[{index}]"
        ctype = self.get(acc, "componentType", int, aw)
        if ctype not in _COMPONENTS:
            raise self.fail(f"{aw}.componentType {ctype} is not a glTF component type")
        atype = self.get(acc, "type", str, aw)
        if atype not in _N_COMPONENTS:
            raise self.fail(f"{aw}.type {atype!r:.20} is not a glTF accessor type")
        count = self.get(acc, "count", int, aw)
        if count < 1:
            raise self.fail(f"{aw}.count must be >= 1, got {count}")
        ncomp = _N_COMPONENTS[atype]
        check_budget(self.path, count * ncomp * 8.0, f"{aw} ({count} x {atype})")
        dtype = np.dtype(_COMPONENTS[ctype])
        normalized = bool(self.get(acc, "normalized", bool, aw, False))
        if "bufferView" in acc:
            data = self._read_view_array(
                acc["bufferView"], self.get(acc, "byteOffset", int, aw, 0), count, ncomp, dtype, aw
            )
        else:
            data = np.zeros((count, ncomp), dtype=dtype)
        if "sparse" in acc:
            data = self._apply_sparse(acc["sparse"], data, dtype, ncomp, aw)
        if integer:
            if ctype == FLOAT or normalized:
                raise self.fail(
                    f"{aw} must hold integer indices, but its components are {'normalized' if normalized else 'floats'}"
                )
            return data.astype(np.int64).reshape(count, ncomp)
        out = data.astype(np.float64)
        if normalized:
            if ctype == FLOAT:
                raise self.fail(f"{aw}: float components cannot be 'normalized'")
            out = np.maximum(out / _NORMALIZE[ctype], -1.0)
        if not np.all(np.isfinite(out)):
            raise self.fail(f"{aw} holds NaN or infinite values")
        return out

    def _apply_sparse(
        self, sparse: Any, data: np.ndarray, dtype: np.dtype, ncomp: int, aw: str
    ) -> np.ndarray:
        if not isinstance(sparse, dict):
            raise self.fail(f"{aw}.sparse must be an object")
        sw = f"{aw}.sparse"
        n = self.get(sparse, "count", int, sw)
        if not 1 <= n <= data.shape[0]:
            raise self.fail(f"{sw}.count {n} is outside 1..{data.shape[0]}")
        idx_info = self.get(sparse, "indices", dict, sw)
        val_info = self.get(sparse, "values", dict, sw)
        ictype = self.get(idx_info, "componentType", int, f"{sw}.indices")
        if ictype not in (UBYTE, USHORT, UINT):
            raise self.fail(f"{sw}.indices.componentType must be an unsigned integer type")
        idx = (
            self._read_view_array(
                self.get(idx_info, "bufferView", int, f"{sw}.indices"),
                self.get(idx_info, "byteOffset", int, f"{sw}.indices", 0),
                n,
                1,
                np.dtype(_COMPONENTS[ictype]),
                f"{sw}.indices",
            )
            .ravel()
            .astype(np.int64)
        )
        if np.any(idx >= data.shape[0]) or np.any(np.diff(idx) <= 0):
            raise self.fail(
                f"{sw}.indices must be strictly increasing and below count {data.shape[0]}"
            )
        values = self._read_view_array(
            self.get(val_info, "bufferView", int, f"{sw}.values"),
            self.get(val_info, "byteOffset", int, f"{sw}.values", 0),
            n,
            ncomp,
            dtype,
            f"{sw}.values",
        )
        data = np.array(data)
        data[idx] = values
        return data

    def raw_view(self, spec: Any, where: str) -> np.ndarray:
        """A float64/int64 array stored by our writer: ``{"bufferView", "dtype", "shape"}``."""
        if not isinstance(spec, dict):
            raise self.fail(f"{where} must be an object")
        dtype_name = self.get(spec, "dtype", str, where)
        if dtype_name not in ("<f8", "<i8"):
            raise self.fail(f"{where}.dtype {dtype_name!r:.20} is not supported")
        shape = self.get(spec, "shape", list, where)
        if not all(isinstance(s, int) and s >= 0 for s in shape):
            raise self.fail(f"{where}.shape must be a list of sizes")
        dtype = np.dtype(dtype_name)
        n = int(np.prod(shape)) if shape else 1
        check_budget(self.path, n * 8.0, where)
        if n == 0 and "bufferView" not in spec:
            return np.zeros(shape, dtype=dtype)
        buf, offset, length, _ = self.view_bytes(self.get(spec, "bufferView", int, where), where)
        if n * dtype.itemsize > length:
            raise self.fail(
                f"{where}: shape {shape} needs {n * dtype.itemsize} bytes, the buffer view has {length}"
            )
        return np.frombuffer(buf, dtype=dtype, count=n, offset=offset).reshape(shape).copy()

    # -- meshes --------------------------------------------------------------------------
    def ours(self) -> dict:
        asset = self.gltf.get("asset", {})
        extras = asset.get("extras", {}) if isinstance(asset, dict) else {}
        info = extras.get(_EXTRAS_KEY) if isinstance(extras, dict) else None
        return info if isinstance(info, dict) else {}

    def primitive(
        self, prim: Any, where: str
    ) -> tuple[np.ndarray, np.ndarray, list[np.ndarray | None]]:
        if not isinstance(prim, dict):
            raise self.fail(f"{where} must be an object")
        attrs = self.get(prim, "attributes", dict, where)
        if "POSITION" not in attrs:
            raise self.fail(f"{where} has no POSITION attribute")
        pos = self.accessor(attrs["POSITION"], f"{where}.attributes.POSITION")
        if pos.shape[1] != 3:
            raise self.fail(f"{where}.attributes.POSITION must be VEC3")
        n = pos.shape[0]
        mode = self.get(prim, "mode", int, where, 4)
        if "indices" in prim:
            idx = self.accessor(prim["indices"], f"{where}.indices", integer=True)
            if idx.shape[1] != 1:
                raise self.fail(f"{where}.indices must be SCALAR")
            idx = idx.ravel()
            if idx.size and (idx.max() >= n):
                raise self.fail(
                    f"{where}.indices uses vertex {int(idx.max())} but POSITION has {n}"
                )
        else:
            idx = np.arange(n, dtype=np.int64)
        if mode == 4:
            if idx.size % 3:
                raise self.fail(
                    f"{where}: {idx.size} indices is not a multiple of 3 (mode TRIANGLES)"
                )
            tris = idx.reshape(-1, 3)
        elif mode in (5, 6):
            if idx.size < 3:
                raise self.fail(f"{where}: a strip or fan needs at least 3 indices")
            k = np.arange(idx.size - 2)
            if mode == 5:  # glTF 2.0 spec: triangle i = (p_i, p_{i + 1 + i%2}, p_{i + 2 - i%2})
                tris = np.stack([idx[k], idx[k + 1 + k % 2], idx[k + 2 - k % 2]], axis=1)
            else:
                tris = np.stack([np.full(k.size, idx[0]), idx[k + 1], idx[k + 2]], axis=1)
            keep = (
                (tris[:, 0] != tris[:, 1]) & (tris[:, 1] != tris[:, 2]) & (tris[:, 0] != tris[:, 2])
            )
            tris = tris[keep]  # strips use repeated indices as restarts
        else:
            raise self.fail(f"{where}: primitive mode {mode} (points or lines) is not a surface")
        targets_raw = self.get(prim, "targets", list, where, [])
        targets: list[np.ndarray | None] = []
        for t, target in enumerate(targets_raw):
            tw = f"{where}.targets[{t}]"
            if not isinstance(target, dict):
                raise self.fail(f"{tw} must be an object")
            if "POSITION" in target:
                delta = self.accessor(target["POSITION"], f"{tw}.POSITION")
                if delta.shape != (n, 3):
                    raise self.fail(
                        f"{tw}.POSITION has {delta.shape[0]} x {delta.shape[1]} values; POSITION has {n} x 3"
                    )
                targets.append(delta)
            else:
                targets.append(None)
        return pos, tris, targets

    def mesh(self, index: int) -> tuple[np.ndarray, np.ndarray, np.ndarray | None, dict]:
        """(vertices, triangles, deltas (M, V, 3) or None, mesh dict) of mesh ``index``, primitives joined."""
        mesh = self.item("meshes", index, "the file")
        where = f"meshes[{index}]"
        prims = self.get(mesh, "primitives", list, where)
        if not prims:
            raise self.fail(f"{where} has no primitives")
        verts, tris, deltas, offset = [], [], [], 0
        n_targets = None
        for p, prim in enumerate(prims):
            pos, tri, targets = self.primitive(prim, f"{where}.primitives[{p}]")
            if n_targets is None:
                n_targets = len(targets)
            elif len(targets) != n_targets:
                raise self.fail(
                    f"{where}: primitives have different numbers of morph targets ({n_targets} and {len(targets)})"
                )
            verts.append(pos)
            tris.append(tri + offset)
            deltas.append([np.zeros_like(pos) if d is None else d for d in targets])
            offset += pos.shape[0]
        vertices = np.concatenate(verts)
        triangles = np.concatenate(tris)
        if not n_targets:
            return vertices, triangles, None, mesh
        check_budget(self.path, n_targets * vertices.size * 8.0, f"{n_targets} morph targets")
        stacked = np.stack([np.concatenate([d[k] for d in deltas]) for k in range(n_targets)])
        return vertices, triangles, stacked, mesh

    def target_names(self, mesh: dict, n_targets: int, where: str) -> list[str]:
        extras = mesh.get("extras")
        names = extras.get("targetNames") if isinstance(extras, dict) else None
        if names is None:
            return [f"target{k}" for k in range(n_targets)]
        if not isinstance(names, list) or not all(isinstance(n, str) for n in names):
            raise self.fail(f"{where}.extras.targetNames must be a list of strings")
        if len(names) != n_targets:
            raise self.fail(
                f"{where}.extras.targetNames lists {len(names)} names but the mesh has {n_targets} morph targets"
            )
        return names

    def choose_mesh(self, option: Any, *, with_targets: bool) -> int:
        n = self.count("meshes")
        if n == 0:
            raise self.fail("holds no meshes")
        if option is not None:
            if isinstance(option, int) and 0 <= option < n:
                return option
            for i in range(n):
                if self.item("meshes", i, "the file").get("name") == option:
                    return i
            raise self.fail(
                f"has no mesh {option!r}; meshes: {[self.item('meshes', i, 'the file').get('name', i) for i in range(n)]}"
            )
        if not with_targets:
            return 0
        counts = []
        for i in range(n):
            prims = self.get(self.item("meshes", i, "the file"), "primitives", list, f"meshes[{i}]")
            first = prims[0] if prims and isinstance(prims[0], dict) else {}
            counts.append(len(first.get("targets", []) or []))
        if max(counts) == 0:
            raise self.fail(
                "has no morph targets, so it is not a blendshape rig (read it as a mesh: kind='mesh')"
            )
        return int(np.argmax(counts))


def _parse_glb(data: bytes, path: Path) -> tuple[bytes, bytes | None]:
    if len(data) < 20:
        raise bad(path, f"too short for a GLB file ({len(data)} bytes)")
    magic, version, length = struct.unpack_from("<4sII", data, 0)
    if magic != GLB_MAGIC:
        raise bad(path, "wrong magic: not a binary glTF (GLB) file")
    if version != 2:
        raise bad(path, f"GLB version {version} is not supported (only glTF 2)")
    if length != len(data):
        raise bad(
            path,
            f"the header declares {length} bytes but the file has {len(data)} (truncated or damaged)",
        )
    pos = 12
    json_chunk, bin_chunk = None, None
    while pos + 8 <= length:
        chunk_len, chunk_type = struct.unpack_from("<II", data, pos)
        pos += 8
        if chunk_len > length - pos:
            raise bad(
                path,
                f"a chunk declares {chunk_len} bytes but only {length - pos} remain (truncated)",
            )
        chunk = data[pos : pos + chunk_len]
        if json_chunk is None:
            if chunk_type != CHUNK_JSON:
                raise bad(path, "the first GLB chunk must be JSON")
            json_chunk = chunk
        elif chunk_type == CHUNK_BIN and bin_chunk is None:
            bin_chunk = chunk
        pos += chunk_len
    if json_chunk is None:
        raise bad(path, "no JSON chunk")
    return json_chunk, bin_chunk


def json_cost(raw: bytes) -> float:
    """Bytes of memory parsing JSON text ``raw`` may take: its text (strings such as
    base64 buffers stay one object) plus at most 128 bytes per value (the Python objects
    of numbers, lists and dicts; measured: a list of one-digit numbers costs about 36
    bytes per value)."""
    values = raw.count(b",") + raw.count(b":") + raw.count(b"[") + raw.count(b"{") + 1
    return 2.0 * len(raw) + 128.0 * values


def _parse_json(raw: bytes | str, path: Path) -> dict:
    try:
        doc = json.loads(raw)
    except (ValueError, UnicodeDecodeError) as exc:
        raise bad(path, f"the glTF JSON is not valid JSON ({exc})") from None
    if not isinstance(doc, dict):
        raise bad(path, "the glTF JSON must be an object")
    asset = doc.get("asset")
    if not isinstance(asset, dict) or not str(asset.get("version", "")).startswith("2"):
        raise bad(path, "missing 'asset' with version 2.x; not a glTF 2 file")
    return doc


def _is_glb(path: Path, head: bytes) -> bool:
    return head[:4] == GLB_MAGIC or path.suffix.lower() == ".glb"


def _load(path: Path) -> _Doc:
    data = read_bytes(path)
    if not data:
        raise bad(path, "the file is empty")
    if _is_glb(path, data):
        raw_json, bin_chunk = _parse_glb(data, path)
    else:
        raw_json, bin_chunk = data, None
    check_budget(path, len(data) + json_cost(raw_json), "parsing the glTF JSON")
    gltf = _parse_json(raw_json, path)
    buffers_json = gltf.get("buffers", [])
    if not isinstance(buffers_json, list):
        raise bad(path, "'buffers' must be a list")
    buffers = []
    for i, buf in enumerate(buffers_json):
        if not isinstance(buf, dict):
            raise bad(path, f"buffers[{i}] must be an object")
        declared = buf.get("byteLength")
        if isinstance(declared, bool) or not isinstance(declared, int) or declared < 1:
            raise bad(path, f"buffers[{i}].byteLength must be a positive integer")
        uri = buf.get("uri")
        if uri is None:
            if i != 0 or bin_chunk is None:
                raise bad(path, f"buffers[{i}] has no uri and there is no GLB binary chunk for it")
            blob = bin_chunk
        else:
            blob = _read_uri(path, uri, i)
        if len(blob) < declared:
            raise bad(
                path, f"buffers[{i}] declares {declared} bytes but holds {len(blob)} (truncated)"
            )
        buffers.append(blob)
    return _Doc(path, gltf, buffers)


def _read_uri(path: Path, uri: Any, i: int) -> bytes:
    if not isinstance(uri, str):
        raise bad(path, f"buffers[{i}].uri must be a string")
    if uri.startswith("data:"):
        head, _, payload = uri.partition(",")
        if not head.endswith(";base64"):
            raise bad(path, f"buffers[{i}]: only base64 data URIs are supported")
        check_budget(path, len(payload) * 0.75, f"buffers[{i}]")
        try:
            return base64.b64decode(payload, validate=True)
        except ValueError:
            raise bad(path, f"buffers[{i}]: the base64 data is corrupt") from None
    from urllib.parse import unquote

    rel = unquote(uri)
    root = path.resolve().parent
    target = (root / rel).resolve()
    if os.path.isabs(rel) or "://" in rel or not str(target).startswith(str(root) + os.sep):
        raise bad(
            path,
            f"buffers[{i}].uri {uri!r:.60} points outside the glTF file's folder; only files beside it are read",
        )
    if not os.path.lexists(target):
        raise bad(path, f"buffers[{i}]: the buffer file {rel!r} does not exist")
    check_regular(target)  # a FIFO or a link to a device is refused, never read
    note_input(target)
    return read_bytes(target, f"buffers[{i}] of {path.name} ({rel})")


def _read_json_only(path: Path) -> dict:
    """The glTF JSON without loading buffers (to decide what the file holds)."""
    with open_regular(path) as fh:
        head = fh.read(20)
        if _is_glb(path, head):
            if len(head) < 20 or head[:4] != GLB_MAGIC:
                raise bad(path, "not a binary glTF (GLB) file")
            (chunk_len,) = struct.unpack_from("<I", head, 12)
            check_budget(path, chunk_len, "the glTF JSON chunk")
            raw = fh.read(chunk_len)
            if len(raw) != chunk_len:
                raise bad(path, "truncated JSON chunk")
            check_budget(path, json_cost(raw), "parsing the glTF JSON")
            return _parse_json(raw, path)
    raw = read_bytes(path, "the glTF JSON")
    check_budget(path, json_cost(raw), "parsing the glTF JSON")
    return _parse_json(raw, path)


def gltf_kind(path: PathLike) -> str | None:
    """'animation', 'rig' or 'mesh': what a glTF file holds (None if it cannot be told)."""
    try:
        doc = _read_json_only(Path(path))
    except Exception:
        return None
    info = doc.get("asset", {}).get("extras", {})
    info = info.get(_EXTRAS_KEY, {}) if isinstance(info, dict) else {}
    if isinstance(info, dict) and info.get("kind") in ("animation", "rig", "mesh"):
        return info["kind"]
    anims = doc.get("animations") or []
    if isinstance(anims, list) and any(
        isinstance(a, dict)
        and any(
            isinstance(c, dict)
            and isinstance(c.get("target"), dict)
            and c["target"].get("path") == "weights"
            for c in a.get("channels", []) or []
        )
        for a in anims
    ):
        return "animation"
    meshes = doc.get("meshes") or []
    if isinstance(meshes, list):
        for m in meshes:
            prims = m.get("primitives", []) if isinstance(m, dict) else []
            if isinstance(prims, list) and any(
                isinstance(p, dict) and p.get("targets") for p in prims
            ):
                return "rig"
    return "mesh"


def _local_matrix(doc: _Doc, node: dict, where: str) -> np.ndarray:
    """A node's local transform (``matrix``, column-major, or translation/rotation/scale)."""
    out = np.eye(4)
    if "matrix" in node:
        m = node["matrix"]
        if (
            not isinstance(m, list)
            or len(m) != 16
            or not all(isinstance(v, (int, float)) and not isinstance(v, bool) for v in m)
        ):
            raise doc.fail(f"{where}.matrix must be 16 numbers")
        out = np.array(m, dtype=np.float64).reshape(4, 4).T
    else:

        def vec(key: str, n: int, default: list[float]) -> np.ndarray:
            v = node.get(key, default)
            if (
                not isinstance(v, list)
                or len(v) != n
                or not all(isinstance(x, (int, float)) and not isinstance(x, bool) for x in v)
            ):
                raise doc.fail(f"{where}.{key} must be {n} numbers")
            return np.array(v, dtype=np.float64)

        t, q, sc = (
            vec("translation", 3, [0, 0, 0]),
            vec("rotation", 4, [0, 0, 0, 1]),
            vec("scale", 3, [1, 1, 1]),
        )
        if not np.linalg.norm(q) > 0:
            raise doc.fail(f"{where}.rotation is not a unit quaternion")
        out[:3, :3] = _quat_to_matrix(q[None])[0] * sc[None, :]
        out[:3, 3] = t
    if not np.all(np.isfinite(out)):
        raise doc.fail(f"{where} has a non-finite transform")
    return out


def _instances(doc: _Doc) -> list[tuple[int, int, np.ndarray]]:
    """``(node, mesh, world matrix)`` of every mesh the file's scene shows, in scene order
    (the default scene; without scenes, every root node)."""
    n_nodes = doc.count("nodes")
    if doc.count("scenes"):
        scene_index = doc.get(doc.gltf, "scene", int, "the file", 0)
        scene = doc.item("scenes", scene_index, "the file's 'scene'")
        roots = doc.get(scene, "nodes", list, f"scenes[{scene_index}]", [])
    else:
        children: set[int] = set()
        for i in range(n_nodes):
            kids = doc.item("nodes", i, "the file").get("children", [])
            children.update(k for k in kids if isinstance(k, int)) if isinstance(
                kids, list
            ) else None
        roots = [i for i in range(n_nodes) if i not in children]
    out: list[tuple[int, int, np.ndarray]] = []
    seen: set[int] = set()
    stack = [(r, np.eye(4), "the scene") for r in reversed(roots)]
    while stack:
        index, parent, where = stack.pop()
        node = doc.item("nodes", index, where)
        if index in seen:
            raise doc.fail(
                f"nodes[{index}] appears twice in the node hierarchy (a cycle or a shared child)"
            )
        seen.add(index)
        world = parent @ _local_matrix(doc, node, f"nodes[{index}]")
        if "mesh" in node:
            out.append((index, doc.get(node, "mesh", int, f"nodes[{index}]"), world))
        kids = doc.get(node, "children", list, f"nodes[{index}]", [])
        stack.extend((k, world, f"nodes[{index}].children") for k in reversed(kids))
    return out


@overload
def _transform(
    world: np.ndarray, vertices: np.ndarray, deltas: np.ndarray
) -> tuple[np.ndarray, np.ndarray]: ...
@overload
def _transform(
    world: np.ndarray, vertices: np.ndarray, deltas: None
) -> tuple[np.ndarray, None]: ...
def _transform(
    world: np.ndarray, vertices: np.ndarray, deltas: np.ndarray | None
) -> tuple[np.ndarray, np.ndarray | None]:
    """Vertices (and morph deltas: linear part only) in the scene's space."""
    if np.array_equal(world, np.eye(4)):
        return vertices, deltas
    lin = world[:3, :3]
    v = vertices @ lin.T + world[:3, 3]
    return v, (None if deltas is None else deltas @ lin.T)


def _mesh_names(doc: _Doc) -> list:
    return [doc.item("meshes", i, "the file").get("name", i) for i in range(doc.count("meshes"))]


def _select(
    doc: _Doc, option: Any, instances: list, *, with_targets: bool
) -> tuple[int, np.ndarray]:
    """(mesh index, world matrix) for ``mesh=`` (mesh index, mesh name or node name) or the default."""
    if option is not None and not isinstance(option, int):
        for node, m, world in instances:  # a node name selects that instance
            if doc.item("nodes", node, "the file").get("name") == option:
                return m, world
    index = doc.choose_mesh(option, with_targets=with_targets)
    for _, m, world in instances:
        if m == index:
            return index, world
    return index, np.eye(4)  # a mesh no node shows: its own space


@guarded_reader
def read_gltf_mesh(
    path: Path, *, mesh: int | str | None = None, merge: bool | None = None, **options: Any
) -> Mesh:
    """The mesh a glTF scene shows, in scene space (node transforms applied), primitives
    joined, morph targets ignored.

    Several meshes in the scene: ``merge=True`` (the default) joins them all, each moved by
    its node's world transform, in scene order; ``mesh=`` (a mesh index, mesh name or node
    name) reads just that one; ``merge=False`` reads the first.
    """
    doc = _load(path)
    instances = _instances(doc)
    if mesh is None and merge is not False and len(instances) > 1:
        verts, tris, offset = [], [], 0
        for _, m, world in instances:
            if abs(np.linalg.det(world[:3, :3])) == 0.0:
                continue  # a node scaled to zero is hidden (e.g. a frame of a flip-book animation)
            v, t, _, _ = doc.mesh(m)
            v, _ = _transform(world, v, None)
            verts.append(v)
            tris.append(t + offset)
            offset += v.shape[0]
        return Mesh(np.concatenate(verts), np.concatenate(tris), name=path.stem)
    if mesh is None and instances:
        index, world = instances[0][1], instances[0][2]
    else:
        index, world = _select(doc, mesh, instances, with_targets=False)
    vertices, triangles, _, _ = doc.mesh(index)
    vertices, _ = _transform(world, vertices, None)
    return Mesh(vertices, triangles, name=path.stem)


def _rig_from(doc: _Doc, index: int, world: np.ndarray | None = None) -> BlendshapeRig:
    vertices, triangles, deltas, mesh = doc.mesh(index)
    if deltas is None:
        raise doc.fail(f"meshes[{index}] has no morph targets")
    if world is not None:
        vertices, deltas = _transform(world, vertices, deltas)
    names = doc.target_names(mesh, deltas.shape[0], f"meshes[{index}]")
    bounds = None
    extras = mesh.get("extras")
    ours = extras.get(_EXTRAS_KEY) if isinstance(extras, dict) else None
    if isinstance(ours, dict) and ours.get("bounds") is not None:
        bounds = np.asarray(ours["bounds"], dtype=np.float64)
    neutral = Mesh(
        vertices,
        triangles,
        name=mesh.get("name") if isinstance(mesh.get("name"), str) else doc.path.stem,
    )
    return BlendshapeRig(neutral, deltas, names, bounds=bounds)


@guarded_reader
def read_gltf_rig(path: Path, *, mesh: int | str | None = None, **options: Any) -> BlendshapeRig:
    """A :class:`BlendshapeRig` from the morph targets of a glTF mesh (names from
    ``extras.targetNames``), in scene space (its node's world transform applied; deltas
    by its linear part). ``mesh=`` (mesh index, mesh name or node name) picks one; by
    default the mesh with the most morph targets. A file that also holds an animation
    gives its character this way: ``load(path, kind="rig")``."""
    doc = _load(path)
    index, world = _select(doc, mesh, _instances(doc), with_targets=True)
    return _rig_from(doc, index, world)


def _sample_keys(times: np.ndarray, values: np.ndarray, grid: np.ndarray, step: bool) -> np.ndarray:
    """Values ``(K, C)`` at keys ``times (K,)`` sampled on ``grid (F,)`` (linear or step)."""
    if step:
        idx = np.clip(np.searchsorted(times, grid, side="right") - 1, 0, len(times) - 1)
        return values[idx]
    return np.stack([np.interp(grid, times, values[:, c]) for c in range(values.shape[1])], axis=1)


def _quat_to_matrix(q: np.ndarray) -> np.ndarray:
    """(F, 4) quaternions x, y, z, w -> (F, 3, 3) rotation matrices."""
    q = q / np.linalg.norm(q, axis=1, keepdims=True)
    x, y, z, w = q.T
    return np.stack(
        [
            np.stack([1 - 2 * (y * y + z * z), 2 * (x * y - z * w), 2 * (x * z + y * w)], axis=1),
            np.stack([2 * (x * y + z * w), 1 - 2 * (x * x + z * z), 2 * (y * z - x * w)], axis=1),
            np.stack([2 * (x * z - y * w), 2 * (y * z + x * w), 1 - 2 * (x * x + y * y)], axis=1),
        ],
        axis=1,
    )


def _matrix_to_quat(rot: np.ndarray) -> np.ndarray:
    """(F, 3, 3) rotations -> (F, 4) unit quaternions x, y, z, w (w >= 0)."""
    m = rot
    trace = m[:, 0, 0] + m[:, 1, 1] + m[:, 2, 2]
    cands = np.stack(
        [
            np.stack(
                [
                    m[:, 2, 1] - m[:, 1, 2],
                    m[:, 0, 2] - m[:, 2, 0],
                    m[:, 1, 0] - m[:, 0, 1],
                    1 + trace,
                ],
                axis=1,
            ),
            np.stack(
                [
                    1 + m[:, 0, 0] - m[:, 1, 1] - m[:, 2, 2],
                    m[:, 0, 1] + m[:, 1, 0],
                    m[:, 0, 2] + m[:, 2, 0],
                    m[:, 2, 1] - m[:, 1, 2],
                ],
                axis=1,
            ),
            np.stack(
                [
                    m[:, 0, 1] + m[:, 1, 0],
                    1 + m[:, 1, 1] - m[:, 0, 0] - m[:, 2, 2],
                    m[:, 1, 2] + m[:, 2, 1],
                    m[:, 0, 2] - m[:, 2, 0],
                ],
                axis=1,
            ),
            np.stack(
                [
                    m[:, 0, 2] + m[:, 2, 0],
                    m[:, 1, 2] + m[:, 2, 1],
                    1 + m[:, 2, 2] - m[:, 0, 0] - m[:, 1, 1],
                    m[:, 1, 0] - m[:, 0, 1],
                ],
                axis=1,
            ),
        ],
        axis=1,
    )  # (F, 4 candidates, 4)
    best = np.argmax(np.linalg.norm(cands, axis=2), axis=1)
    q = cands[np.arange(len(m)), best]
    q /= np.linalg.norm(q, axis=1, keepdims=True)
    q *= np.where(q[:, 3:4] < 0, -1.0, 1.0)
    return q


class _Channel:
    def __init__(self, times: np.ndarray, values: np.ndarray, interpolation: str) -> None:
        self.times, self.values, self.interpolation = times, values, interpolation


def _channels(doc: _Doc, node: int) -> dict[str, _Channel]:
    """The animation channels targeting ``node``: path -> keys. Every animation of the file
    counts, the first one animating a path wins: Blender writes an object's motion and its
    shape-key weights as two animations ("FaceAction", "KeyAction") that play together."""
    out: dict[str, _Channel] = {}
    for a in range(doc.count("animations")):
        anim = doc.item("animations", a, "the file")
        samplers = doc.get(anim, "samplers", list, f"animations[{a}]")
        for c, ch in enumerate(doc.get(anim, "channels", list, f"animations[{a}]")):
            cw = f"animations[{a}].channels[{c}]"
            if not isinstance(ch, dict):
                raise doc.fail(f"{cw} must be an object")
            target = doc.get(ch, "target", dict, cw)
            path = str(doc.get(target, "path", str, cw))
            if target.get("node") != node or path in out:
                continue
            s = doc.get(ch, "sampler", int, cw)
            if not 0 <= s < len(samplers) or not isinstance(samplers[s], dict):
                raise doc.fail(f"{cw} refers to sampler {s} but the animation has {len(samplers)}")
            sw = f"animations[{a}].samplers[{s}]"
            times = doc.accessor(doc.get(samplers[s], "input", int, sw), f"{sw}.input").ravel()
            if times.size > 1 and np.any(np.diff(times) <= 0):
                raise doc.fail(f"{sw}.input: key times must be strictly increasing")
            interp = doc.get(samplers[s], "interpolation", str, sw, "LINEAR")
            if interp not in ("LINEAR", "STEP", "CUBICSPLINE"):
                raise doc.fail(
                    f"{sw}.interpolation {interp!r:.20} is not LINEAR, STEP or CUBICSPLINE"
                )
            values = doc.accessor(doc.get(samplers[s], "output", int, sw), f"{sw}.output")
            out[path] = _Channel(times, values, interp)
    return out


def _channel_values(doc: _Doc, ch: _Channel, width: int, where: str) -> np.ndarray:
    """Key values ``(K, width)`` (CUBICSPLINE: the value, not the tangents)."""
    flat = ch.values.reshape(-1)
    k = ch.times.size
    per_key = 3 if ch.interpolation == "CUBICSPLINE" else 1
    if flat.size != k * width * per_key:
        raise doc.fail(
            f"{where}: {flat.size} output values for {k} keys of {width} (expected {k * width * per_key})"
        )
    vals = flat.reshape(k, per_key, width)
    return vals[:, 1] if per_key == 3 else vals[:, 0]


def _node_of_mesh(doc: _Doc, mesh_index: int) -> int | None:
    for i in range(doc.count("nodes")):
        if doc.item("nodes", i, "the file").get("mesh") == mesh_index:
            return i
    return None


def _tree(doc: _Doc, info: dict, key: str) -> dict:
    """``info[key]`` with its array references resolved from ``info[key + "_arrays"]``."""
    tree = info.get(key)
    if not isinstance(tree, dict):
        return {}
    specs = info.get(f"{key}_arrays") or []
    if not isinstance(specs, list):
        raise doc.fail(f"asset.extras.{_EXTRAS_KEY}.{key}_arrays must be a list")

    def fetch(i: int) -> np.ndarray:
        if not 0 <= i < len(specs):
            raise doc.fail(
                f"asset.extras.{_EXTRAS_KEY}.{key} refers to array {i} but {len(specs)} are stored"
            )
        return doc.raw_view(specs[i], f"asset.extras.{_EXTRAS_KEY}.{key}_arrays[{i}]")

    return join_arrays(tree, fetch)


#: highest frame rate accepted from a file or option (above it the value is a corruption)
MAX_FPS = 1e6


def _checked_fps(doc: _Doc, fps: object, what: str) -> float:
    """A frame rate from the file (or ``fps=``): a finite number in (0, MAX_FPS]."""
    if isinstance(fps, bool) or not isinstance(fps, (int, float, np.integer, np.floating)):
        raise doc.fail(f"{what} {fps!r:.40} is not a number")
    value = float(fps)
    if not math.isfinite(value) or not 0 < value <= MAX_FPS:
        raise doc.fail(
            f"{what} {value:g} is not a frame rate (expected a number of frames per second in (0, {MAX_FPS:g}]); pass fps= (--fps) to override it"
        )
    return value


def _animation_from(
    doc: _Doc, mesh_option: int | str | None, fps_option: float | None
) -> Animation:
    info = doc.ours()
    exact = info.get("arrays", {}) if isinstance(info.get("arrays"), dict) else {}
    provenance, extras = (_tree(doc, info, key) for key in ("provenance", "extras"))
    head = doc.raw_view(exact["head_motion"], "head_motion") if "head_motion" in exact else None
    fps = fps_option if fps_option is not None else info.get("fps")
    if info.get("layout") == "frames":
        frames = doc.get(info, "frame_meshes", list, f"asset.extras.{_EXTRAS_KEY}")
        if not frames:
            raise doc.fail("a frame animation with no frames")
        if fps is not None:
            fps = _checked_fps(doc, fps, "the frame rate" if fps_option is None else "fps=")
        first_v, first_t, _, _ = doc.mesh(frames[0])
        check_budget(
            doc.path,
            len(frames) * first_v.size * 8.0,
            f"{len(frames)} frames of {first_v.shape[0]} vertices",
        )
        vertices = np.empty((len(frames),) + first_v.shape)
        vertices[0] = first_v
        for k, m in enumerate(frames[1:], 1):
            v, t, _, _ = doc.mesh(m)
            if v.shape != first_v.shape or not np.array_equal(t, first_t):
                raise doc.fail(f"frame {k} (meshes[{m}]) does not share the topology of frame 0")
            vertices[k] = v
        weights = doc.raw_view(exact["weights"], "weights") if "weights" in exact else None
        names = info.get("weight_names") if weights is not None else None
        return Animation(
            vertices=vertices,
            weights=weights,
            weight_names=names,
            triangles=first_t,
            head_motion=head,
            fps=fps or DEFAULT_FPS,
            provenance=provenance,
            extras=extras,
        )
    # a weight animation over morph targets
    index = doc.choose_mesh(mesh_option, with_targets=True)
    node = _node_of_mesh(doc, index)
    channels = _channels(doc, node) if node is not None else {}
    moving = "translation" in channels or "rotation" in channels
    rig, parent, rest = _animated_rig(doc, index, node, moving)
    if "weights" not in channels:
        raise doc.fail("has no animation of morph-target weights (read it as a rig: kind='rig')")
    ch = channels["weights"]
    keys = _channel_values(doc, ch, rig.n_shapes, "the weights channel")
    times = ch.times

    def uniform_at(rate: float) -> bool:
        return times.size < 2 or bool(np.allclose(np.diff(times), 1.0 / rate, rtol=1e-3, atol=1e-6))

    if fps is None:  # the keys' own rate when they are evenly spaced, else resample at the default
        estimate = fps_from_times(times, DEFAULT_FPS)
        fps = estimate if uniform_at(estimate) else DEFAULT_FPS
    fps = _checked_fps(doc, fps, "the frame rate" if fps_option is None else "fps=")
    uniform = uniform_at(fps)
    if uniform:
        grid = times
    else:
        # the sampling grid comes from the file's key times and frame rate: size it (and
        # everything sampled on it) against the budget before allocating anything
        span = float(times[-1] - times[0])
        n_grid = math.floor(span * fps + 1e-6) + 1
        n_head = 16 if ("translation" in channels or "rotation" in channels) else 0
        check_budget(
            doc.path,
            float(n_grid) * 8.0 * (2 + rig.n_shapes + n_head),
            f"sampling the animation at {fps:g} fps over {span:g} s ({float(n_grid):.4g} frames of {rig.n_shapes} weights)",
        )
        grid = times[0] + np.arange(int(n_grid)) / fps
    weights = keys if uniform else _sample_keys(times, keys, grid, ch.interpolation == "STEP")
    if "weights" in exact:
        exact_w = doc.raw_view(exact["weights"], "weights")
        if exact_w.shape == weights.shape:
            weights = exact_w
    if head is None and moving:
        head = np.tile(rest, (grid.size, 1, 1))  # a channel not animated keeps the node's own value
        if "rotation" in channels:
            rc = channels["rotation"]
            q = _sample_keys(
                rc.times,
                _channel_values(doc, rc, 4, "the rotation channel"),
                grid,
                rc.interpolation == "STEP",
            )
            head[:, :3, :3] = _quat_to_matrix(q)
        if "translation" in channels:
            tc = channels["translation"]
            head[:, :3, 3] = _sample_keys(
                tc.times,
                _channel_values(doc, tc, 3, "the translation channel"),
                grid,
                tc.interpolation == "STEP",
            )
        if not np.array_equal(parent, np.eye(4)):  # in scene space: parent @ [R T](t) @ parent^-1
            head = parent[None] @ head @ np.linalg.inv(parent)[None]
    names = info.get("weight_names") if isinstance(info.get("weight_names"), list) else None
    return Animation(
        weights=weights,
        rig=rig,
        head_motion=head,
        fps=fps,
        weight_names=names,
        provenance=provenance,
        extras=extras,
    )


def _animated_rig(
    doc: _Doc, index: int, node: int | None, moving: bool
) -> tuple[BlendshapeRig, np.ndarray, np.ndarray]:
    """The rig of a weight animation in scene space, the node's parent transform and its rest
    rigid transform ``[R T]`` (4, 4).

    A node without rotation/translation channels: its whole world transform is applied to the
    rig (as ``kind='rig'`` reads it). A moving node (head motion): the rig gets the parents'
    transforms and the node's own scale; rotation and translation become the head motion.
    """
    world = (
        next((w for n, _, w in _instances(doc) if n == node), np.eye(4))
        if node is not None
        else np.eye(4)
    )
    if not moving:
        return _rig_from(doc, index, world), np.eye(4), np.eye(4)
    item = doc.item("nodes", node, "the file")
    rest = _local_matrix(
        doc, {k: item[k] for k in ("translation", "rotation") if k in item}, f"nodes[{node}]"
    )
    scale = (
        np.diag(np.append(np.asarray(item.get("scale", [1.0, 1.0, 1.0]), dtype=np.float64), 1.0))
        if "matrix" not in item
        else np.eye(4)
    )
    parent = (
        world @ np.linalg.inv(_local_matrix(doc, item, f"nodes[{node}]"))
        if "matrix" not in item
        else np.eye(4)
    )
    return _rig_from(doc, index, parent @ scale), parent, rest


@guarded_reader
def read_gltf_animation(
    path: Path, *, mesh: int | str | None = None, fps: float | None = None, **options: Any
) -> Animation:
    """An :class:`Animation`: morph-target weights over the rig, or per-frame meshes we wrote."""
    return _animation_from(_load(path), mesh, fps)


@guarded_reader
def read_gltf_sequence(
    path: Path, *, mesh: int | str | None = None, fps: float | None = None, **options: Any
) -> MeshSequence:
    """The animation of a glTF file as a :class:`MeshSequence` (world vertices per frame)."""
    anim = _animation_from(_load(path), mesh, fps)
    if anim.is_blendshape_based:  # the per-frame vertices are computed here: size them first
        assert anim.rig is not None  # is_blendshape_based
        check_budget(
            path,
            float(anim.n_frames) * anim.rig.neutral.n_vertices * 3 * 8.0 * 2,
            f"{anim.n_frames} frames of {anim.rig.neutral.n_vertices} vertices",
        )
    return MeshSequence(  # triangles None: MeshSequence rejects it with its own error
        anim.vertices,
        anim.triangles,  # type: ignore[arg-type]
        fps=anim.fps,
        name=path.stem,
    )


# =======================================================================================
# Writing
# =======================================================================================
class _Builder:
    """Accumulates the binary buffer, buffer views and accessors of one glTF document."""

    def __init__(self) -> None:
        self.blob = bytearray()
        self.views: list[dict] = []
        self.accessors: list[dict] = []

    def view(self, raw: bytes, *, align: int = 4, target: int | None = None) -> int:
        pad = (-len(self.blob)) % align
        self.blob.extend(b"\x00" * pad)
        view = {"buffer": 0, "byteOffset": len(self.blob), "byteLength": len(raw)}
        if target is not None:
            view["target"] = target
        self.blob.extend(raw)
        self.views.append(view)
        return len(self.views) - 1

    def accessor(
        self,
        data: np.ndarray,
        atype: str,
        *,
        component: int = FLOAT,
        target: int | None = None,
        minmax: bool = False,
        view: int | None = None,
        offset: int = 0,
    ) -> int:
        if component == FLOAT:
            arr = np.ascontiguousarray(to_float32(data, "glTF"))
        else:
            arr = np.ascontiguousarray(data, dtype=_COMPONENTS[component])
        ncomp = _N_COMPONENTS[atype]
        arr = arr.reshape(-1, ncomp)
        if view is None:
            view = self.view(arr.tobytes(), target=target)
        acc = {
            "bufferView": view,
            "componentType": component,
            "count": int(arr.shape[0]),
            "type": atype,
        }
        if offset:
            acc["byteOffset"] = offset
        if minmax:
            acc["min"], acc["max"] = jsonable(arr.min(axis=0)), jsonable(arr.max(axis=0))
        self.accessors.append(acc)
        return len(self.accessors) - 1

    def raw(self, array: np.ndarray) -> dict:
        """Store an exact float64/int64 array; returns the ``extras`` reference to it."""
        arr = np.asarray(array)
        dtype = "<i8" if arr.dtype.kind in "iub" else "<f8"
        arr = np.ascontiguousarray(arr, dtype=dtype)
        if (
            arr.size == 0
        ):  # glTF buffer views hold at least one byte: an empty array is its shape alone
            return {"dtype": dtype, "shape": list(arr.shape)}
        return {
            "bufferView": self.view(arr.tobytes(), align=8),
            "dtype": dtype,
            "shape": list(arr.shape),
        }


def _frame_times(n_frames: int, fps: float) -> np.ndarray:
    times = (np.arange(n_frames, dtype=np.float64) / fps).astype(np.float32)
    if n_frames > 1 and np.any(np.diff(times) <= 0):
        raise OutputError(
            f"{n_frames} frames at {fps} fps cannot be given strictly increasing float32 times"
        )
    return times


def _add_geometry(
    b: _Builder, vertices: np.ndarray, indices_acc: int | None, triangles: np.ndarray
) -> tuple[dict, int]:
    """A primitive dict for one frame/neutral (indices accessor shared when given)."""
    if indices_acc is None:
        indices_acc = b.accessor(
            np.asarray(triangles).ravel(), "SCALAR", component=UINT, target=ELEMENT_ARRAY_BUFFER
        )
    pos = b.accessor(vertices, "VEC3", target=ARRAY_BUFFER, minmax=True)
    return {"attributes": {"POSITION": pos}, "indices": indices_acc, "mode": 4}, indices_acc


def _rig_mesh(b: _Builder, rig: BlendshapeRig, name: str) -> dict:
    prim, _ = _add_geometry(b, rig.neutral.vertices, None, rig.neutral.triangles)
    prim["targets"] = [
        {"POSITION": b.accessor(d, "VEC3", target=ARRAY_BUFFER, minmax=True)} for d in rig.deltas
    ]
    mesh: dict[str, Any] = {
        "name": name,
        "primitives": [prim],
        "weights": [0.0] * rig.n_shapes,
        "extras": {"targetNames": list(rig.names)},
    }
    if rig.bounds is not None:
        mesh["extras"][_EXTRAS_KEY] = {"bounds": rig.bounds.tolist()}
    return mesh


def _head_channels(
    b: _Builder, head: np.ndarray, time_acc: int, node: int, samplers: list, channels: list
) -> None:
    rot = head[:, :3, :3]
    u, _, vt = np.linalg.svd(rot)
    q = _matrix_to_quat(u @ vt)  # nearest rotation (the matrices are rigid up to rounding)
    for path, values, atype in (("translation", head[:, :3, 3], "VEC3"), ("rotation", q, "VEC4")):
        samplers.append(
            {"input": time_acc, "output": b.accessor(values, atype), "interpolation": "LINEAR"}
        )
        channels.append({"sampler": len(samplers) - 1, "target": {"node": node, "path": path}})


def glb_document(
    obj: Mesh | BlendshapeRig | MeshSequence | Animation, *, name: str = "faceretarget"
) -> tuple[dict, bytes]:
    """The glTF JSON and binary buffer for a Mesh, BlendshapeRig, MeshSequence or Animation."""
    from .._version import __version__

    if isinstance(obj, MeshSequence):
        obj = Animation(vertices=obj.vertices, triangles=obj.triangles, fps=obj.fps)
    b = _Builder()
    info: dict[str, Any] = {"version": __version__}
    nodes: list[dict] = []
    meshes: list[dict] = []
    animations: list[dict] = []
    if isinstance(obj, Mesh):
        prim, _ = _add_geometry(b, obj.vertices, None, obj.triangles)
        meshes.append({"name": obj.name or name, "primitives": [prim]})
        nodes.append({"name": obj.name or name, "mesh": 0})
        info["kind"] = "mesh"
    elif isinstance(obj, BlendshapeRig):
        meshes.append(_rig_mesh(b, obj, obj.neutral.name or name))
        nodes.append({"name": obj.neutral.name or name, "mesh": 0})
        info["kind"] = "rig"
    elif isinstance(obj, Animation):
        info.update(kind="animation", fps=obj.fps)
        for key in ("provenance", "extras"):
            tree, arrays = split_arrays(getattr(obj, key))
            info[key] = tree
            if arrays:
                info[f"{key}_arrays"] = [b.raw(a) for a in arrays]
        exact: dict[str, Any] = {}
        times = _frame_times(obj.n_frames, obj.fps)
        if obj.is_blendshape_based:
            assert obj.rig is not None and obj.weights is not None  # is_blendshape_based
            info["layout"] = "morph"
            meshes.append(_rig_mesh(b, obj.rig, name))
            nodes.append({"name": name, "mesh": 0})
            time_acc = b.accessor(times, "SCALAR", minmax=True)
            samplers = [
                {
                    "input": time_acc,
                    "output": b.accessor(obj.weights.ravel(), "SCALAR"),
                    "interpolation": "LINEAR",
                }
            ]
            channels = [{"sampler": 0, "target": {"node": 0, "path": "weights"}}]
            exact["weights"] = b.raw(obj.weights)
            if tuple(obj.weight_names) != tuple(obj.rig.names):
                info["weight_names"] = list(obj.weight_names)
            if obj.head_motion is not None:
                _head_channels(b, obj.head_motion, time_acc, 0, samplers, channels)
            animations.append({"name": "retarget", "samplers": samplers, "channels": channels})
        else:
            if obj.triangles is None:
                raise InputError(
                    "a vertex animation needs triangles to be written as glTF meshes; pass Animation(triangles=...)"
                )
            info["layout"] = "frames"
            vertices = obj.vertices
            indices_acc = None
            frame_meshes, children = [], []
            for k in range(obj.n_frames):
                prim, indices_acc = _add_geometry(
                    b, np.asarray(vertices[k]), indices_acc, obj.triangles
                )
                meshes.append({"name": f"frame_{k:05d}", "primitives": [prim]})
                frame_meshes.append(k)
                node = {"name": f"frame_{k:05d}", "mesh": k}
                if k > 0:
                    node["scale"] = [0.0, 0.0, 0.0]
                nodes.append(node)
                children.append(k)
            nodes.append({"name": name, "children": children})
            info["frame_meshes"] = frame_meshes
            if obj.weights is not None:
                exact["weights"] = b.raw(obj.weights)
                info["weight_names"] = list(obj.weight_names)
            if obj.n_frames > 1:
                animations.append(_visibility_animation(b, times))
        if obj.head_motion is not None:
            exact["head_motion"] = b.raw(obj.head_motion)
        info["arrays"] = exact
    else:
        raise InputError(
            f"glTF writes a Mesh, BlendshapeRig, MeshSequence or Animation, got {type(obj).__name__}"
        )
    root = len(nodes) - 1
    doc: dict[str, Any] = {
        "asset": {
            "version": "2.0",
            "generator": f"faceretarget {__version__}",
            "extras": {_EXTRAS_KEY: info},
        },
        "scene": 0,
        "scenes": [{"nodes": [root]}],
        "nodes": nodes,
        "meshes": meshes,
        "accessors": b.accessors,
        "bufferViews": b.views,
        "buffers": [{"byteLength": len(b.blob)}],
    }
    if animations:
        doc["animations"] = animations
    pad = (-len(b.blob)) % 4
    return doc, bytes(b.blob) + b"\x00" * pad


def _visibility_animation(b: _Builder, times: np.ndarray) -> dict:
    """STEP scale channels showing node k only during frame k."""
    n = times.size
    one, zero = [1.0, 1.0, 1.0], [0.0, 0.0, 0.0]
    out_first = b.accessor(np.array([one, zero]), "VEC3")
    out_last = b.accessor(np.array([zero, one]), "VEC3")
    out_mid = b.accessor(np.array([zero, one, zero]), "VEC3") if n > 2 else None
    key_rows = []
    for k in range(n):
        if k == 0:
            key_rows.append(times[[0, 1]])
        elif k == n - 1:
            key_rows.append(times[[0, k]])
        else:
            key_rows.append(times[[0, k, k + 1]])
    flat = np.concatenate(key_rows).astype(np.float32)
    view = b.view(flat.tobytes())
    samplers, channels, offset = [], [], 0
    for k, keys in enumerate(key_rows):
        acc = b.accessor(keys, "SCALAR", minmax=True, view=view, offset=offset)
        offset += 4 * keys.size
        output = out_first if k == 0 else (out_last if k == n - 1 else out_mid)
        samplers.append({"input": acc, "output": output, "interpolation": "STEP"})
        channels.append({"sampler": k, "target": {"node": k, "path": "scale"}})
    return {"name": "frames", "samplers": samplers, "channels": channels}


def glb_bytes(doc: dict, blob: bytes) -> bytes:
    """Pack a document and its buffer into a GLB container."""
    raw = json.dumps(doc, separators=(",", ":"), allow_nan=False).encode("utf-8")
    raw += b" " * ((-len(raw)) % 4)
    total = 12 + 8 + len(raw) + (8 + len(blob) if blob else 0)
    out = [struct.pack("<4sII", GLB_MAGIC, 2, total), struct.pack("<II", len(raw), CHUNK_JSON), raw]
    if blob:
        out += [struct.pack("<II", len(blob), CHUNK_BIN), blob]
    return b"".join(out)


def final_stem(path: PathLike) -> str:
    """The stem of the file ``path`` will become: a writer handed an atomic temporary
    (``.NAME.PID.TOKEN.frtmp.glb``, or the batch runner's former ``.NAME.frbatch-...``)
    names its nodes and meshes after ``NAME``, never after the temporary."""
    from ._atomic import temp_owner

    p = Path(path)
    owner = temp_owner(p.name)
    return Path(owner[0]).stem if owner is not None else p.stem


def write_gltf(
    obj: Mesh | BlendshapeRig | MeshSequence | Animation,
    path: PathLike,
    *,
    force: bool = False,
    inputs: Iterable = (),
    name: str | None = None,
    **options: Any,
) -> None:
    """Write ``obj`` as ``.glb`` (binary) or ``.gltf`` (JSON with an embedded buffer), atomically."""
    p = Path(path)
    doc, blob = glb_document(obj, name=name or final_stem(p) or "faceretarget")
    if p.suffix.lower() == ".gltf":
        doc["buffers"][0]["uri"] = "data:application/octet-stream;base64," + base64.b64encode(
            blob
        ).decode("ascii")
        data = json.dumps(doc, indent=1, allow_nan=False).encode("utf-8")
    else:
        data = glb_bytes(doc, blob)
    write_bytes(p, data, inputs=inputs, force=force)
