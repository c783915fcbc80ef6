"""Independent glTF checks and builders for the I/O tests (no faceretarget code used).

- :func:`split_glb` parses a GLB container by the spec.
- :func:`validate_gltf` asserts the structural rules viewers (Blender, three.js) rely
  on: indices in range, 4-byte aligned buffer views inside the buffer, accessors inside
  their views with component-size aligned offsets, POSITION accessors with exact
  ``min``/``max``, morph targets consistent with ``extras.targetNames``, animation
  sampler inputs strictly increasing with ``min``/``max`` and outputs of the right size.
- :func:`foreign_glb` builds GLB files the way *other* exporters do (interleaved views,
  uint16 indices, sparse morph targets, strips, normalized weights, uneven key times).
"""

from __future__ import annotations

import json
import struct

import numpy as np

COMPONENT = {5120: "i1", 5121: "u1", 5122: "<i2", 5123: "<u2", 5125: "<u4", 5126: "<f4"}
WIDTH = {"SCALAR": 1, "VEC2": 2, "VEC3": 3, "VEC4": 4, "MAT4": 16}


def split_glb(data: bytes) -> tuple[dict, bytes]:
    """(JSON document, BIN chunk) of a GLB file; asserts the container layout."""
    magic, version, length = struct.unpack_from("<4sII", data, 0)
    assert magic == b"glTF" and version == 2, "GLB header"
    assert length == len(data), "GLB length field equals the file size"
    json_len, json_type = struct.unpack_from("<II", data, 12)
    assert json_type == 0x4E4F534A, "first chunk is JSON"
    assert json_len % 4 == 0, "JSON chunk padded to 4 bytes"
    raw = data[20 : 20 + json_len]
    doc = json.loads(raw.decode("utf-8"))
    blob = b""
    pos = 20 + json_len
    if pos < length:
        bin_len, bin_type = struct.unpack_from("<II", data, pos)
        assert bin_type == 0x004E4942, "second chunk is BIN"
        assert bin_len % 4 == 0, "BIN chunk padded to 4 bytes"
        blob = data[pos + 8 : pos + 8 + bin_len]
        assert pos + 8 + bin_len == length, "nothing after the BIN chunk"
    return doc, blob


def read_accessor(doc: dict, blob: bytes, index: int) -> np.ndarray:
    """Dense accessor data (count, width) from the BIN chunk (no sparse support needed here)."""
    acc = doc["accessors"][index]
    view = doc["bufferViews"][acc["bufferView"]]
    dtype = np.dtype(COMPONENT[acc["componentType"]])
    width = WIDTH[acc["type"]]
    stride = view.get("byteStride", dtype.itemsize * width)
    start = view.get("byteOffset", 0) + acc.get("byteOffset", 0)
    return np.ndarray(
        (acc["count"], width),
        dtype=dtype,
        buffer=blob,
        offset=start,
        strides=(stride, dtype.itemsize),
    ).copy()


def validate_gltf(doc: dict, blob: bytes) -> dict:
    """Assert the structure of a glTF document; returns counts of what it checked."""
    assert doc["asset"]["version"] == "2.0"
    assert doc["buffers"][0]["byteLength"] <= len(blob)
    n_nodes, n_meshes, _n_acc = (
        len(doc.get("nodes", [])),
        len(doc.get("meshes", [])),
        len(doc.get("accessors", [])),
    )
    for scene in doc.get("scenes", []):
        assert all(0 <= n < n_nodes for n in scene["nodes"])
    assert 0 <= doc.get("scene", 0) < len(doc["scenes"])
    for node in doc.get("nodes", []):
        if "mesh" in node:
            assert 0 <= node["mesh"] < n_meshes
        assert all(0 <= c < n_nodes for c in node.get("children", []))
    for i, view in enumerate(doc["bufferViews"]):
        off = view.get("byteOffset", 0)
        assert off % 4 == 0, f"bufferView {i} offset {off} is 4-byte aligned"
        assert off + view["byteLength"] <= doc["buffers"][view["buffer"]]["byteLength"], (
            f"bufferView {i} inside its buffer"
        )
    for i, acc in enumerate(doc["accessors"]):
        view = doc["bufferViews"][acc["bufferView"]]
        size = np.dtype(COMPONENT[acc["componentType"]]).itemsize
        elem = size * WIDTH[acc["type"]]
        assert acc.get("byteOffset", 0) % size == 0, (
            f"accessor {i} offset aligned to its component size"
        )
        stride = view.get("byteStride", elem)
        end = acc.get("byteOffset", 0) + stride * (acc["count"] - 1) + elem
        assert end <= view["byteLength"], f"accessor {i} inside its bufferView"
        if "min" in acc:
            data = read_accessor(doc, blob, i)
            assert np.array_equal(np.asarray(acc["min"], dtype=data.dtype), data.min(axis=0)), (
                f"accessor {i} min"
            )
            assert np.array_equal(np.asarray(acc["max"], dtype=data.dtype), data.max(axis=0)), (
                f"accessor {i} max"
            )
    checked = {"primitives": 0, "targets": 0, "samplers": 0}
    for _m, mesh in enumerate(doc.get("meshes", [])):
        n_targets = None
        for prim in mesh["primitives"]:
            checked["primitives"] += 1
            pos = prim["attributes"]["POSITION"]
            acc = doc["accessors"][pos]
            assert acc["type"] == "VEC3" and acc["componentType"] == 5126
            assert "min" in acc and "max" in acc, "POSITION accessors carry min/max"
            if "indices" in prim:
                idx = read_accessor(doc, blob, prim["indices"])
                assert idx.max() < acc["count"], "indices within POSITION"
                assert prim.get("mode", 4) != 4 or idx.size % 3 == 0
            targets = prim.get("targets", [])
            n_targets = len(targets) if n_targets is None else n_targets
            assert len(targets) == n_targets, "every primitive has the same number of morph targets"
            for t in targets:
                tacc = doc["accessors"][t["POSITION"]]
                assert tacc["count"] == acc["count"] and "min" in tacc and "max" in tacc
                checked["targets"] += 1
        if n_targets:
            assert len(mesh["extras"]["targetNames"]) == n_targets, (
                "targetNames match the morph targets"
            )
            assert len(mesh.get("weights", [0] * n_targets)) == n_targets
    for anim in doc.get("animations", []):
        for sampler in anim["samplers"]:
            checked["samplers"] += 1
            inp = doc["accessors"][sampler["input"]]
            assert inp["type"] == "SCALAR" and inp["componentType"] == 5126
            assert "min" in inp and "max" in inp, "sampler inputs carry min/max"
            times = read_accessor(doc, blob, sampler["input"]).ravel()
            assert times.size == 1 or np.all(np.diff(times) > 0), (
                "sampler input strictly increasing"
            )
            assert sampler.get("interpolation", "LINEAR") in ("LINEAR", "STEP", "CUBICSPLINE")
        for channel in anim["channels"]:
            sampler = anim["samplers"][channel["sampler"]]
            target = channel["target"]
            node = doc["nodes"][target["node"]]
            n_keys = doc["accessors"][sampler["input"]]["count"]
            out = doc["accessors"][sampler["output"]]
            if target["path"] == "weights":
                n_t = len(doc["meshes"][node["mesh"]]["primitives"][0]["targets"])
                assert out["count"] == n_keys * n_t, "weights output = keys x targets"
            else:
                assert out["count"] == n_keys
                assert (
                    out["type"]
                    == {"translation": "VEC3", "scale": "VEC3", "rotation": "VEC4"}[target["path"]]
                )
    return checked


# ---------------------------------------------------------------------------------------
# foreign files
# ---------------------------------------------------------------------------------------
class GLB:
    """A minimal glTF writer that mimics other exporters' choices."""

    def __init__(self):
        self.blob = bytearray()
        self.doc = {
            "asset": {"version": "2.0", "generator": "naive test builder"},
            "bufferViews": [],
            "accessors": [],
            "meshes": [],
            "nodes": [],
        }

    def view(self, raw: bytes, stride: int | None = None) -> int:
        self.blob.extend(b"\0" * ((-len(self.blob)) % 4))
        v = {"buffer": 0, "byteOffset": len(self.blob), "byteLength": len(raw)}
        if stride:
            v["byteStride"] = stride
        self.blob.extend(raw)
        self.doc["bufferViews"].append(v)
        return len(self.doc["bufferViews"]) - 1

    def accessor(
        self, view: int, ctype: int, count: int, atype: str, offset: int = 0, **extra
    ) -> int:
        acc = {"bufferView": view, "componentType": ctype, "count": count, "type": atype, **extra}
        if offset:
            acc["byteOffset"] = offset
        self.doc["accessors"].append(acc)
        return len(self.doc["accessors"]) - 1

    def array(self, arr: np.ndarray, ctype: int, atype: str, **extra) -> int:
        arr = np.ascontiguousarray(arr, dtype=COMPONENT[ctype])
        return self.accessor(self.view(arr.tobytes()), ctype, arr.shape[0], atype, **extra)

    def bytes(self) -> bytes:
        self.blob.extend(b"\0" * ((-len(self.blob)) % 4))
        self.doc["buffers"] = [{"byteLength": len(self.blob)}]
        raw = json.dumps(self.doc).encode()
        raw += b" " * ((-len(raw)) % 4)
        total = 12 + 8 + len(raw) + 8 + len(self.blob)
        return b"".join(
            [
                struct.pack("<4sII", b"glTF", 2, total),
                struct.pack("<II", len(raw), 0x4E4F534A),
                raw,
                struct.pack("<II", len(self.blob), 0x004E4942),
                bytes(self.blob),
            ]
        )
