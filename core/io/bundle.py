"""The faceretarget ``.npz`` formats: every model object, and complete bundles.

A file is a plain (uncompressed) numpy ``.npz`` — no pickle anywhere — with two
bookkeeping arrays: ``format`` = ``"faceretarget.<type>"`` and ``version``. Types:
``mesh``, ``mesh_sequence``, ``markers``, ``weights``, ``rig``, ``layers``,
``animation`` and the bundles ``source``, ``target`` and ``case`` which store every part
(performance, head motion, landmarks, feature lines, examples, source rig, actor layers,
2D tracks; neutral, blendshapes, layered poses and masks; ground truth and metadata).

Array keys are paths (``target/blendshapes/deltas``); names are unicode arrays; dicts
of arrays (feature lines, layers) are stored as a ``names`` array plus ``0``, ``1``...
entries; provenance and metadata that are not arrays are JSON text.

Foreign ``.npz`` files without a ``format`` key are read by their keys (``vertices`` +
``triangles``/``faces``; ``neutral`` + ``deltas``/``expression_deltas`` + ``names``/
``expression_names``, as in the ICT-FaceKit export; ``positions`` + ``names``;
``weights`` + ``names``).
"""

from __future__ import annotations

import json
from collections.abc import Iterable
from pathlib import Path
from typing import Any

import numpy as np

from .._types import PathLike
from ..errors import InputError
from ..model import (
    Animation,
    BlendshapeRig,
    Landmarks,
    LayeredRig,
    MarkerSequence,
    Mesh,
    MeshSequence,
    Source,
    TargetRig,
    WeightSequence,
)
from ._atomic import atomic_file
from ._common import bad, guarded_reader, join_arrays, read_npz, split_arrays

__all__ = [
    "VERSION",
    "encode",
    "decode",
    "write_npz",
    "read_npz_object",
    "npz_type",
    "TYPES",
    "type_of",
]

VERSION = 1
PREFIX = "faceretarget."
TYPES = (
    "mesh",
    "mesh_sequence",
    "markers",
    "weights",
    "rig",
    "layers",
    "animation",
    "source",
    "target",
    "case",
)
BUNDLE_TYPES = ("source", "target", "case")


def type_of(obj: Any) -> str:
    """The npz type name of a model object (``case`` for anything with source and target)."""
    for cls, name in (
        (Mesh, "mesh"),
        (MeshSequence, "mesh_sequence"),
        (MarkerSequence, "markers"),
        (WeightSequence, "weights"),
        (BlendshapeRig, "rig"),
        (LayeredRig, "layers"),
        (Animation, "animation"),
        (Source, "source"),
        (TargetRig, "target"),
    ):
        if isinstance(obj, cls):
            return name
    if isinstance(getattr(obj, "source", None), Source) and isinstance(
        getattr(obj, "target", None), TargetRig
    ):
        return "case"
    raise InputError(
        f"cannot store a {type(obj).__name__} in a faceretarget npz; expected a model object, Source, TargetRig or case"
    )


# ---------------------------------------------------------------------------------------
# encoding
# ---------------------------------------------------------------------------------------
def _text(values: Iterable[object]) -> np.ndarray:
    values = [str(v) for v in values]
    return np.array(values, dtype=str) if values else np.zeros(0, dtype="<U1")


def _put_dict_of_arrays(out: dict, prefix: str, mapping: dict) -> None:
    out[prefix + "names"] = _text(mapping.keys())
    for i, value in enumerate(mapping.values()):
        out[f"{prefix}{i}"] = np.asarray(value)


def _put_tree(out: dict, prefix: str, value: Any) -> None:
    """Store JSON-like ``value`` whose leaves may be arrays: the arrays go to ``prefix/0``,
    ``prefix/1``... and the JSON in ``prefix/json`` refers to them."""
    tree, arrays = split_arrays(value)
    out[prefix + "json"] = np.array(json.dumps(tree, allow_nan=False))
    for i, arr in enumerate(arrays):
        out[f"{prefix}{i}"] = arr


def encode(obj: Any, prefix: str = "") -> dict[str, np.ndarray]:
    """Arrays describing ``obj`` under ``prefix`` (inverse of :func:`decode`)."""
    out: dict[str, np.ndarray] = {}
    p = prefix
    kind = type_of(obj)
    if kind == "mesh":
        out[p + "vertices"] = np.asarray(obj.vertices)
        out[p + "triangles"] = np.asarray(obj.triangles)
        if obj.name is not None:
            out[p + "name"] = np.array(str(obj.name))
    elif kind == "mesh_sequence":
        out[p + "vertices"] = np.asarray(obj.vertices)
        out[p + "triangles"] = np.asarray(obj.triangles)
        out[p + "reference"] = np.asarray(obj.reference.vertices)
        out[p + "fps"] = np.array(obj.fps)
        if obj.name is not None:
            out[p + "name"] = np.array(str(obj.name))
    elif kind == "markers":
        out[p + "positions"] = np.asarray(obj.positions)
        out[p + "names"] = _text(obj.names)
        out[p + "reference"] = np.asarray(obj.reference)
        out[p + "fps"] = np.array(obj.fps)
    elif kind == "weights":
        out[p + "weights"] = np.asarray(obj.weights)
        out[p + "names"] = _text(obj.names)
        out[p + "fps"] = np.array(obj.fps)
    elif kind == "rig":
        out.update(encode(obj.neutral, p + "neutral/"))
        out[p + "deltas"] = np.asarray(obj.deltas)
        out[p + "names"] = _text(obj.names)
        if obj.bounds is not None:
            out[p + "bounds"] = np.asarray(obj.bounds)
    elif kind == "layers":
        _put_dict_of_arrays(out, p + "layers/", obj.layers)
        for i, lname in enumerate(obj.layer_names):
            out[f"{p}pose_names/{i}"] = _text(obj.pose_names[lname])
        out[p + "masks"] = np.asarray(obj.masks)
        out[p + "region_names"] = _text(obj.region_names)
    elif kind == "animation":
        if obj.is_blendshape_based:
            out.update(encode(obj.rig, p + "rig/"))
        else:
            out[p + "vertices"] = np.asarray(obj.vertices)
        if obj.weights is not None:
            out[p + "weights"] = np.asarray(obj.weights)
            out[p + "weight_names"] = _text(obj.weight_names)
        if obj.head_motion is not None:
            out[p + "head_motion"] = np.asarray(obj.head_motion)
        if obj.triangles is not None:
            out[p + "triangles"] = np.asarray(obj.triangles)
        out[p + "fps"] = np.array(obj.fps)
        _put_tree(out, p + "provenance/", obj.provenance)
        _put_tree(out, p + "extras/", obj.extras)
    elif kind == "source":
        perf = obj.performance
        out[p + "performance/type"] = np.array(type_of(perf))
        out.update(encode(perf, p + "performance/"))
        _encode_parts(out, obj, p)
        for part in ("rig", "actor_layers", "tracks2d", "actor_layers_2d"):
            if getattr(obj, part) is not None:
                out.update(encode(getattr(obj, part), f"{p}{part}/"))
    elif kind == "target":
        out.update(encode(obj.neutral, p + "neutral/"))
        _encode_parts(out, obj, p)
        for part in ("blendshapes", "layers"):
            if getattr(obj, part) is not None:
                out.update(encode(getattr(obj, part), f"{p}{part}/"))
    elif kind == "case":
        out.update(encode(obj.source, p + "source/"))
        out.update(encode(obj.target, p + "target/"))
        if getattr(obj, "truth", None) is not None:
            out.update(encode(obj.truth, p + "truth/"))
        _put_tree(out, p + "meta/", dict(getattr(obj, "meta", None) or {}))
        name = getattr(obj, "name", None)
        if name is not None:
            out[p + "name"] = np.array(str(name))
    return out


def _encode_parts(out: dict, obj: Source | TargetRig, p: str) -> None:
    """Parts shared by Source and TargetRig: head motion, landmarks, feature lines, examples, name."""
    head_motion = getattr(obj, "head_motion", None)  # a Source's (a TargetRig has none)
    if head_motion is not None:
        out[p + "head_motion"] = np.asarray(head_motion)
    lm = obj.landmarks
    if lm is not None:
        if lm.vertex_ids is not None:
            out[p + "landmarks/vertex_ids"] = np.asarray(lm.vertex_ids)
        else:
            out[p + "landmarks/triangle_ids"] = np.asarray(lm.triangle_ids)
            out[p + "landmarks/barycentric"] = np.asarray(lm.barycentric)
        out[p + "landmarks/names"] = _text(lm.names)
    if obj.feature_lines:
        _put_dict_of_arrays(out, p + "feature_lines/", obj.feature_lines)
    if obj.examples is not None:
        out[p + "examples"] = np.asarray(obj.examples)
        out[p + "example_names"] = _text(obj.example_names)
    if obj.name is not None:
        out[p + "name"] = np.array(str(obj.name))


# ---------------------------------------------------------------------------------------
# decoding
# ---------------------------------------------------------------------------------------
class _Arrays:
    def __init__(self, arrays: dict[str, np.ndarray], path: PathLike | None) -> None:
        self.arrays, self.path = arrays, path

    def has(self, key: str) -> bool:
        return key in self.arrays

    def has_prefix(self, prefix: str) -> bool:
        return any(k.startswith(prefix) for k in self.arrays)

    def get(self, key: str, default: Any = ...) -> np.ndarray:
        if key not in self.arrays:
            if default is ...:
                raise bad(self.path, f"missing the array {key!r}")
            return default
        return self.arrays[key]

    def text(self, key: str, default: Any = ...) -> Any:
        value = self.get(key, default)
        if value is default and default is not ...:
            return default
        if value.dtype.kind != "U":
            raise bad(self.path, f"array {key!r} must hold text, got {value.dtype}")
        return str(value) if value.ndim == 0 else [str(v) for v in value.tolist()]

    def scalar(self, key: str, default: Any = ...) -> float:
        if key not in self.arrays and default is not ...:
            return default
        value = self.get(key)
        if value.size != 1 or value.dtype.kind not in "iuf":
            raise bad(self.path, f"array {key!r} must be one number")
        return float(value.reshape(()))

    def tree(self, prefix: str) -> Any:
        """The JSON-like value stored by ``_put_tree`` under ``prefix`` ({} if absent)."""
        raw = self.text(prefix + "json", None)
        if raw is None:
            return {}
        try:
            value = json.loads(raw)
        except ValueError:
            raise bad(self.path, f"array {prefix + 'json'!r} is not valid JSON") from None
        return join_arrays(value, lambda i: self.get(f"{prefix}{i}"))

    def dict_of_arrays(self, prefix: str) -> dict[str, np.ndarray]:
        if not self.has(prefix + "names"):
            return {}
        names = self.text(prefix + "names")
        return {n: self.get(f"{prefix}{i}") for i, n in enumerate(names)}


def decode(
    arrays: _Arrays | dict, kind: str, prefix: str = "", path: PathLike | None = None
) -> Any:
    """Rebuild the object of type ``kind`` stored under ``prefix`` (see :func:`encode`)."""
    a = arrays if isinstance(arrays, _Arrays) else _Arrays(arrays, path)
    p = prefix
    if kind == "mesh":
        return Mesh(a.get(p + "vertices"), a.get(p + "triangles"), name=a.text(p + "name", None))
    if kind == "mesh_sequence":
        return MeshSequence(
            a.get(p + "vertices"),
            a.get(p + "triangles"),
            fps=a.scalar(p + "fps"),
            reference=a.get(p + "reference", None),
            name=a.text(p + "name", None),
        )
    if kind == "markers":
        return MarkerSequence(
            a.get(p + "positions"),
            names=a.text(p + "names"),
            fps=a.scalar(p + "fps"),
            reference=a.get(p + "reference", None),
        )
    if kind == "weights":
        return WeightSequence(a.get(p + "weights"), a.text(p + "names"), fps=a.scalar(p + "fps"))
    if kind == "rig":
        return BlendshapeRig(
            decode(a, "mesh", p + "neutral/"),
            a.get(p + "deltas"),
            a.text(p + "names"),
            bounds=a.get(p + "bounds", None),
        )
    if kind == "layers":
        layers = a.dict_of_arrays(p + "layers/")
        pose_names = {n: a.text(f"{p}pose_names/{i}") for i, n in enumerate(layers)}
        return LayeredRig(
            layers,
            a.get(p + "masks"),
            pose_names=pose_names,
            region_names=a.text(p + "region_names"),
        )
    if kind == "animation":
        rig = decode(a, "rig", p + "rig/") if a.has(p + "rig/deltas") else None
        return Animation(
            vertices=None if rig is not None else a.get(p + "vertices"),
            weights=a.get(p + "weights", None),
            rig=rig,
            head_motion=a.get(p + "head_motion", None),
            triangles=a.get(p + "triangles", None),
            fps=a.scalar(p + "fps"),
            weight_names=a.text(p + "weight_names", None),
            provenance=a.tree(p + "provenance/"),
            extras=a.tree(p + "extras/"),
        )
    if kind == "source":
        perf_type = a.text(p + "performance/type")
        if perf_type not in ("markers", "mesh_sequence", "weights"):
            raise bad(a.path, f"unknown performance type {perf_type!r}")
        performance = decode(a, perf_type, p + "performance/")
        parts = _decode_parts(a, p)
        for part, sub in (
            ("rig", "rig"),
            ("actor_layers", "layers"),
            ("tracks2d", "markers"),
            ("actor_layers_2d", "layers"),
        ):
            if a.has_prefix(f"{p}{part}/"):
                parts[part] = decode(a, sub, f"{p}{part}/")
        return Source(performance, **parts)
    if kind == "target":
        neutral = decode(a, "mesh", p + "neutral/")
        parts = _decode_parts(a, p)
        parts.pop("head_motion", None)
        for part, sub in (("blendshapes", "rig"), ("layers", "layers")):
            if a.has_prefix(f"{p}{part}/"):
                parts[part] = decode(a, sub, f"{p}{part}/")
        return TargetRig(neutral, **parts)
    if kind == "case":
        meta = a.tree(p + "meta/")
        truth = decode(a, "animation", p + "truth/") if a.has_prefix(p + "truth/") else None
        from ..cases import Case

        return Case(
            name=a.text(p + "name", None) or Path(str(a.path)).stem,
            source=decode(a, "source", p + "source/"),
            target=decode(a, "target", p + "target/"),
            truth=truth,
            meta=meta,
        )
    raise bad(a.path, f"unknown object type {kind!r}; known: {', '.join(TYPES)}")


def _decode_parts(a: _Arrays, p: str) -> dict[str, Any]:
    parts: dict[str, Any] = {"name": a.text(p + "name", None)}
    if a.has(p + "head_motion"):
        parts["head_motion"] = a.get(p + "head_motion")
    if a.has(p + "landmarks/names"):
        names = a.text(p + "landmarks/names")
        if a.has(p + "landmarks/vertex_ids"):
            parts["landmarks"] = Landmarks(a.get(p + "landmarks/vertex_ids"), names=names)
        else:
            parts["landmarks"] = Landmarks(
                triangle_ids=a.get(p + "landmarks/triangle_ids"),
                barycentric=a.get(p + "landmarks/barycentric"),
                names=names,
            )
    lines = a.dict_of_arrays(p + "feature_lines/")
    if lines:
        parts["feature_lines"] = lines
    if a.has(p + "examples"):
        parts["examples"] = a.get(p + "examples")
        parts["example_names"] = a.text(p + "example_names")
    return parts


# ---------------------------------------------------------------------------------------
# files
# ---------------------------------------------------------------------------------------
def write_npz(
    obj: Any,
    path: PathLike,
    *,
    force: bool = False,
    inputs: Iterable = (),
    compress: bool = False,
    **options: Any,
) -> None:
    """Write any model object, Source, TargetRig or case as a faceretarget ``.npz`` (atomic)."""
    kind = type_of(obj)
    arrays = encode(obj)
    for key, value in arrays.items():
        if value.dtype.hasobject:
            raise InputError(
                f"npz: {key!r} would need pickle (object dtype); only numeric and text arrays are stored"
            )
    arrays["format"] = np.array(PREFIX + kind)
    arrays["version"] = np.array(VERSION)
    with atomic_file(path, inputs=inputs, force=force) as fh:
        # numpy's stubs read **arrays as possibly filling savez's allow_pickle keyword
        (np.savez_compressed if compress else np.savez)(fh, **arrays)  # type: ignore[arg-type]


def npz_type(arrays: dict[str, np.ndarray], path: PathLike) -> str | None:
    """The stored type of a faceretarget npz (None for a foreign npz)."""
    if "format" not in arrays:
        return None
    fmt = arrays["format"]
    if fmt.dtype.kind != "U" or fmt.ndim != 0 or not str(fmt).startswith(PREFIX):
        raise bad(path, "the 'format' array is not a faceretarget format name")
    kind = str(fmt)[len(PREFIX) :]
    if kind not in TYPES:
        raise bad(path, f"unknown faceretarget npz type {kind!r}")
    version = arrays.get("version")
    if version is None or version.size != 1 or version.dtype.kind not in "iu":
        raise bad(path, "missing or bad 'version'")
    if int(version) > VERSION:
        raise bad(
            path,
            f"written by a newer faceretarget (npz version {int(version)}; this one reads up to {VERSION}); upgrade",
        )
    return kind


_ALIASES = {
    "triangles": ("triangles", "faces", "tris"),
    "deltas": ("deltas", "expression_deltas", "blendshapes", "shapes"),
    "names": ("names", "expression_names", "shape_names", "blendshape_names"),
    "positions": ("positions", "markers", "points"),
}


def _first(arrays: dict, group: str) -> np.ndarray | None:
    return next((arrays[k] for k in _ALIASES[group] if k in arrays), None)


def guess_type(arrays: dict[str, np.ndarray]) -> str | None:
    """The type of a foreign npz from its keys (None when it cannot be told)."""
    if "neutral" in arrays and _first(arrays, "deltas") is not None:
        return "rig"
    if "weights" in arrays:
        return "weights"
    if _first(arrays, "positions") is not None:
        return "markers"
    v = arrays.get("vertices")
    if v is not None:
        return "mesh_sequence" if v.ndim == 3 else "mesh"
    if len(arrays) == 1:
        (only,) = arrays.values()
        if only.ndim == 3 and only.shape[-1] == 3:
            return "mesh_sequence"
    return None


def _decode_foreign(arrays: dict, kind: str, path: Path, options: dict) -> Any:
    name = path.stem
    fps = options.get("fps")
    if kind == "rig":
        tris = _first(arrays, "triangles")
        names = _first(arrays, "names")
        if tris is None or names is None:
            raise bad(
                path,
                "a rig npz needs 'neutral', 'deltas' (or 'expression_deltas'), 'names' and 'triangles' (or 'faces')",
            )
        return BlendshapeRig(
            Mesh(arrays["neutral"], tris, name=name),
            _first(arrays, "deltas"),  # type: ignore[arg-type]  # None: BlendshapeRig's error
            [str(n) for n in names.tolist()],
        )
    if kind == "weights":
        if "names" not in arrays:
            raise bad(path, "a weights npz needs 'weights' (F, M) and 'names' (M,)")
        return WeightSequence(
            arrays["weights"],
            [str(n) for n in arrays["names"].tolist()],
            fps=fps or float(arrays.get("fps", 30.0)),
        )
    if kind == "markers":
        names = arrays.get("names")
        return MarkerSequence(
            _first(arrays, "positions"),  # type: ignore[arg-type]  # None: MarkerSequence's error
            names=None if names is None else [str(n) for n in names.tolist()],
            fps=fps or float(arrays.get("fps", 30.0)),
        )
    if kind in ("mesh", "mesh_sequence"):
        vertices = arrays.get("vertices")
        if vertices is None and len(arrays) == 1:
            (vertices,) = arrays.values()
        tris = _first(arrays, "triangles")
        if kind == "mesh":
            if tris is None:
                raise bad(path, "a mesh npz needs 'vertices' and 'triangles' (or 'faces')")
            return Mesh(vertices, tris, name=name)  # type: ignore[arg-type]  # None: Mesh's error
        if vertices is None or vertices.ndim != 3:
            raise bad(path, "a mesh-sequence npz needs 'vertices' of shape (F, V, 3)")
        if tris is None:
            from .sequences import resolve_topology

            topo = resolve_topology(path, options.get("topology"), vertices.shape[1])
            tris = topo.triangles if isinstance(topo, Mesh) else topo
        return MeshSequence(vertices, tris, fps=fps or float(arrays.get("fps", 30.0)), name=name)
    raise bad(path, f"cannot read a foreign npz as {kind!r}")


def _convert(obj: Any, have: str, want: str, path: Path) -> Any:
    """Cross-type reads: an animation as a mesh sequence, a target's rig, a case's parts."""
    if have == want:
        return obj
    if want == "mesh_sequence" and have == "animation":
        return MeshSequence(obj.vertices, obj.triangles, fps=obj.fps)
    if want == "rig" and have == "target" and obj.blendshapes is not None:
        return obj.blendshapes
    if want == "mesh" and have in ("target", "rig"):
        return obj.neutral
    if want == "weights" and have == "animation" and obj.weights is not None:
        return WeightSequence(obj.weights, obj.weight_names, fps=obj.fps)
    raise bad(path, f"holds a {have!r}, which cannot be read as {want!r}")


@guarded_reader
def read_npz_object(path: Path, *, kind: str | None = None, **options: Any) -> Any:
    """Read a faceretarget or foreign ``.npz``; ``kind`` converts (e.g. an animation to a mesh sequence)."""
    arrays = read_npz(path)
    stored = npz_type(arrays, path)
    if stored is None:
        guessed = kind or guess_type(arrays)
        if guessed is None:
            raise bad(
                path,
                f"cannot tell what this npz holds (keys: {sorted(arrays)[:12]}); it has no 'format' key",
            )
        return _decode_foreign(arrays, guessed, path, options)
    obj = decode(_Arrays(arrays, path), stored)
    return obj if kind is None else _convert(obj, stored, kind, path)


def npz_kind(path: PathLike) -> str | None:
    """The stored or guessed type of an npz without building objects (None if unreadable)."""
    import zipfile

    try:
        with zipfile.ZipFile(path) as zf:
            names = [n[:-4] for n in zf.namelist() if n.endswith(".npy")]
            if "format" in names:
                with zf.open("format.npy") as fh:
                    fmt = np.lib.format.read_array(fh, allow_pickle=False)
                text = str(fmt)
                return text[len(PREFIX) :] if text.startswith(PREFIX) else None
            shapes = {}
            for n in names:
                with zf.open(n + ".npy") as fh:
                    from ._common import npy_header

                    shape, dtype, _ = npy_header(fh, path, n)
                    shapes[n] = np.empty((0,) * len(shape), dtype=dtype)
            return guess_type(shapes)
    except Exception:  # unreadable: the reader itself will report what is wrong
        return None
