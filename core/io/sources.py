"""What users load and save: any model object, bundles, sources and targets.

- :func:`load` / :func:`save`: any registered format (through :mod:`.dispatch`), and
  faceretarget bundles (a Source, TargetRig or case as one ``.npz``, :mod:`.bundle`);
- :func:`load_source`: markers, a mesh sequence, weight curves (mapped onto a rig) or a
  bundle, with landmarks, head motion, feature lines and example poses;
- :func:`load_target`: a rig or a mesh (or a bundle) as a TargetRig with its extras;
- :func:`read_landmarks` (JSON, TXT, ``file.npz:KEY``) and :func:`read_feature_lines` (JSON).
"""

from __future__ import annotations

import json
from collections.abc import Iterable, Mapping
from pathlib import Path
from typing import TYPE_CHECKING, Any, TypeAlias

from ..errors import FileFormatError, InputError
from . import dispatch

if TYPE_CHECKING:
    import numpy as np
    import numpy.typing as npt

    from .._types import PathLike
    from ..model import BlendshapeRig, Landmarks, Source, TargetRig, WeightSequence

#: Example poses: an npz (``examples``, ``example_names``), a folder of meshes, or
#: ``(array (M, P, 3), names)``.
ExamplesSpec: TypeAlias = "str | Path | tuple[npt.ArrayLike, Iterable[str] | None] | None"

__all__ = [
    "load",
    "save",
    "save_bundle",
    "load_bundle",
    "is_case",
    "load_source",
    "load_target",
    "read_landmarks",
    "read_feature_lines",
]


def load(
    path: PathLike, kind: str | None = None, *, format: str | None = None, **options: Any
) -> Any:
    """Read ``path`` with the registered reader for its extension (or folder).

    ``kind`` ('mesh', 'mesh_sequence', 'rig', 'markers', 'weights', 'animation') picks
    among formats sharing an extension; without it the file is looked into. A
    faceretarget bundle (``.npz`` holding a Source, TargetRig or case) is returned whole
    when no kind is asked. Options go to the reader (e.g. ``topology=``, ``fps=``).
    Errors are :class:`~faceretarget.errors.FileFormatError` naming the file.
    """
    p = Path(path)
    if kind is None and format is None and p.suffix.lower() == ".npz" and p.is_file():
        from ._atomic import note_input
        from ._common import check_regular
        from .bundle import BUNDLE_TYPES, npz_kind

        check_regular(p)
        stored = npz_kind(p)
        if (
            stored is None or stored in BUNDLE_TYPES
        ):  # a bundle, or let the npz reader say what is wrong
            note_input(p)
            return load_bundle(p)
    return dispatch.read(p, kind, format=format, **options)


def save(
    obj: Any,
    path: PathLike,
    *,
    force: bool = False,
    inputs: Iterable = (),
    format: str | None = None,
    **options: Any,
) -> Path:
    """Write ``obj`` with the registered writer for the path's extension, atomically.

    A path without an extension is a folder (OBJ sequence or rig folder). Source,
    TargetRig and case objects go to :func:`save_bundle` (``.npz``). Refuses
    (:class:`~faceretarget.errors.OutputError`) to replace an input of this process or
    one listed in ``inputs``, and an existing file unless ``force``.
    """
    from ..model import Source, TargetRig

    if isinstance(obj, (Source, TargetRig)) or is_case(obj):
        return save_bundle(obj, path, force=force, inputs=inputs, **options)
    return dispatch.write(obj, path, force=force, inputs=inputs, format=format, **options)


def save_bundle(
    obj: Any, path: PathLike, *, force: bool = False, inputs: Iterable = (), **options: Any
) -> Path:
    """Write a Source, TargetRig or case (``.source``, ``.target``, ``.truth``, ``.meta``) to one ``.npz``.

    Every part is stored (see :mod:`faceretarget.io.bundle`), so ``load_bundle`` gives
    back an equal object and ``faceretarget run NAME --source s.npz --target t.npz``
    works for every method.
    """
    from .bundle import write_npz

    p = Path(path)
    if p.suffix.lower() != ".npz":
        raise FileFormatError(f"{p}: bundles are .npz files")
    write_npz(obj, p, force=force, inputs=inputs, **options)
    return p


def load_bundle(path: PathLike) -> Any:
    """Read any faceretarget ``.npz`` (Source, TargetRig, case bundle, or a model object)."""
    from .bundle import read_npz_object

    p = Path(path)
    if p.exists() and p.suffix.lower() != ".npz":
        raise FileFormatError(f"{p}: bundles are .npz files")
    return read_npz_object(p)


def is_case(obj: object) -> bool:
    """Whether ``obj`` is a case (a Source ``.source`` and a TargetRig ``.target``)."""
    from ..model import Source, TargetRig

    return isinstance(getattr(obj, "source", None), Source) and isinstance(
        getattr(obj, "target", None), TargetRig
    )


def read_landmarks(
    spec: Landmarks | str | Path | npt.ArrayLike, *, key: str | None = None
) -> Landmarks:
    """Landmarks from a small file: JSON, TXT or an npz key.

    - JSON: ``[12, 40, ...]``; ``{"vertex_ids": [...], "names": [...]}``;
      ``{"triangle_ids": [...], "barycentric": [[a, b, c], ...], "names": [...]}``;
      or ``{"name": vertex_id, ...}``.
    - TXT: one landmark per line, ``ID`` or ``NAME ID`` or ``ID NAME`` (``#`` comments).
    - NPZ: ``file.npz:KEY`` or ``key=`` (default ``landmarks``), optional ``KEY_names``.
    A :class:`~faceretarget.model.Landmarks` or a list of ids is returned as Landmarks.
    """
    from ..model import Landmarks
    from ._common import TEXT_TOKEN_FACTOR, bad, guarded_reader, read_npz, read_text

    if isinstance(spec, Landmarks):
        return spec
    if not isinstance(spec, (str, Path)):
        return Landmarks(spec)
    text = str(spec)
    if key is None and ".npz:" in text:
        text, key = text.rsplit(":", 1)

    @guarded_reader
    def read(path: Path) -> Landmarks:
        suffix = path.suffix.lower()
        if suffix == ".npz":
            arrays = read_npz(path)
            k = key or "landmarks"
            if k not in arrays:
                raise bad(path, f"has no array {k!r}; arrays: {sorted(arrays)[:20]}")
            stored_names = arrays.get(f"{k}_names")
            return Landmarks(
                arrays[k].astype("int64") if arrays[k].dtype.kind in "iu" else arrays[k],
                names=None if stored_names is None else stored_names.tolist(),
            )
        raw = read_text(path, factor=TEXT_TOKEN_FACTOR)
        if suffix == ".json":
            try:
                data = json.loads(raw)
            except ValueError as exc:
                raise bad(path, f"not valid JSON ({exc})") from None
            if isinstance(data, list):
                return Landmarks(data)
            if isinstance(data, dict) and "triangle_ids" in data:
                return Landmarks(
                    triangle_ids=data["triangle_ids"],
                    barycentric=data.get("barycentric"),
                    names=data.get("names"),
                )
            if isinstance(data, dict) and "vertex_ids" in data:
                return Landmarks(data["vertex_ids"], names=data.get("names"))
            if (
                isinstance(data, dict)
                and data
                and all(isinstance(v, int) and not isinstance(v, bool) for v in data.values())
            ):
                return Landmarks(list(data.values()), names=list(data))
            raise bad(
                path,
                "expected a list of vertex ids, {vertex_ids, names}, {triangle_ids, barycentric, names} or {name: id}",
            )
        ids: list[int] = []
        names: list[str] = []
        for lineno, line in enumerate(raw.splitlines(), 1):
            parts = line.split("#", 1)[0].replace(",", " ").split()
            if not parts:
                continue
            if len(parts) == 1 and parts[0].lstrip("-").isdigit():
                ids.append(int(parts[0]))
            elif len(parts) == 2 and parts[1].lstrip("-").isdigit():
                names.append(parts[0])
                ids.append(int(parts[1]))
            elif len(parts) == 2 and parts[0].lstrip("-").isdigit():
                ids.append(int(parts[0]))
                names.append(parts[1])
            else:
                raise bad(
                    path,
                    f"line {lineno}: expected 'ID', 'NAME ID' or 'ID NAME', got {line.strip()[:60]!r}",
                )
        if names and len(names) != len(ids):
            raise bad(path, "either every landmark line has a name or none has")
        if not ids:
            raise bad(path, "holds no landmark ids")
        return Landmarks(ids, names=names or None)

    return read(Path(text))


def read_feature_lines(spec: str | Path | Mapping[str, npt.ArrayLike]) -> dict:
    """Feature lines ``{name: [vertex ids...]}`` from a JSON file (or a dict, returned as is)."""
    from ._common import TEXT_TOKEN_FACTOR, bad, guarded_reader, read_text

    if not isinstance(spec, (str, Path)):
        return dict(spec)

    @guarded_reader
    def read(path: Path) -> dict:
        try:
            data = json.loads(read_text(path, factor=TEXT_TOKEN_FACTOR))
        except ValueError as exc:
            raise bad(path, f"not valid JSON ({exc})") from None
        if not isinstance(data, dict) or not all(isinstance(v, list) for v in data.values()):
            raise bad(path, "expected {line name: [vertex ids ...]}")
        return data

    return read(Path(spec))


def _examples(spec: ExamplesSpec) -> tuple[Any, Any]:
    """(examples (M, P, 3), names) from an npz (examples + example_names), a folder of meshes, or arrays."""
    import numpy as np

    if spec is None:
        return None, None
    if isinstance(spec, tuple) and len(spec) == 2:
        return spec
    p = Path(spec)
    if p.is_dir():
        from .sequences import folder_mesh_files

        files = folder_mesh_files(p)
        meshes = [load(f, kind="mesh") for f in files]
        return np.stack([m.vertices for m in meshes]), [f.stem for f in files]
    from ._common import bad, guarded_reader, read_npz

    @guarded_reader
    def read(path: Path) -> tuple[np.ndarray, list[str] | None]:
        arrays = read_npz(path)
        if "examples" not in arrays:
            raise bad(path, "needs an 'examples' array (M, P, 3) and optionally 'example_names'")
        names = arrays.get("example_names")
        return arrays["examples"], None if names is None else names.tolist()

    return read(p)


def _weights_onto_rig(
    weights: WeightSequence,
    rig: BlendshapeRig,
    path: PathLike,
    mapping: dict[str, Any] | str | Path | None,
    preset: str,
) -> WeightSequence:
    """Weight curves renamed/combined onto the rig's shapes (Live Link Face head/eye rotation
    columns are set aside with a warning; any other curve without a counterpart is an error)."""
    import warnings

    from ..naming import load_mapping, map_names
    from .weights import LIVE_LINK_EXTRA

    explicit = dict(load_mapping(mapping) if isinstance(mapping, (str, Path)) else (mapping or {}))
    rotations = [
        n
        for n in weights.names
        if n in LIVE_LINK_EXTRA and n not in rig.names and n not in explicit
    ]
    if rotations:
        warnings.warn(
            f"{path}: head/eye rotation columns are not blendshapes and are not used: {', '.join(rotations)}",
            stacklevel=3,
        )
        explicit.update({n: "" for n in rotations})
    m = map_names(weights.names, rig.names, preset=preset, mapping=explicit).require_complete(
        f"{path}: weight curves"
    )
    return m.apply(weights)


def load_source(
    path: PathLike,
    *,
    kind: str | None = None,
    landmarks: Landmarks | str | Path | npt.ArrayLike | None = None,
    rig: BlendshapeRig | str | Path | None = None,
    head_motion: str | Path | npt.ArrayLike | None = None,
    feature_lines: str | Path | Mapping[str, npt.ArrayLike] | None = None,
    examples: ExamplesSpec = None,
    mapping: dict[str, Any] | str | Path | None = None,
    preset: str = "auto",
    **options: Any,
) -> Source:
    """A :class:`~faceretarget.model.Source` from user files.

    ``path``: a markers file (C3D/TRC/CSV), a mesh sequence (folder, npy, npz, PC2, MDD,
    glTF animation), a weights CSV, or a faceretarget bundle (a source or a case). Extras:

    - ``landmarks``: for a mesh sequence, points matching the target's landmarks
      (JSON/TXT/npz key, see :func:`read_landmarks`);
    - ``rig``: the source's own blendshape rig (a file or BlendshapeRig), needed with
      weight curves; curve names are matched to the rig's with :func:`faceretarget.naming.map_names`
      (``mapping=``, ``preset=``) and curves without a counterpart raise an error naming them
      (map them to ``""`` to ignore them on purpose);
    - ``head_motion``: ``(F, 4, 4)`` array or ``.npy`` file; ``feature_lines``: JSON or dict;
      ``examples``: npz (``examples``, ``example_names``), folder of meshes or (array, names).
    Other options (``fps``, ``topology``...) go to the reader.
    """
    import numpy as np

    from ..model import (
        Animation,
        BlendshapeRig,
        MarkerSequence,
        MeshSequence,
        Source,
        WeightSequence,
    )

    obj = load(path, kind=kind, **options)
    if is_case(obj):
        obj = obj.source
    if isinstance(obj, Source):
        return obj
    if isinstance(obj, Animation):
        obj = (
            MeshSequence(obj.vertices, obj.triangles, fps=obj.fps)
            if obj.triangles is not None
            # weights None (vertices without triangles): WeightSequence rejects it with its own error
            else WeightSequence(obj.weights, obj.weight_names, fps=obj.fps)  # type: ignore[arg-type]
        )
    if not isinstance(obj, (MarkerSequence, MeshSequence, WeightSequence)):
        raise FileFormatError(
            f"{path}: holds a {type(obj).__name__}, not a performance (markers, mesh sequence or weight curves)"
        )
    if isinstance(rig, (str, Path)):
        rig = load(rig, kind="rig")
    if rig is not None and not isinstance(rig, BlendshapeRig):
        raise InputError(
            f"load_source: rig must be a BlendshapeRig or a rig file, got {type(rig).__name__}"
        )
    if head_motion is None:  # a Live Link Face take carries the head rotation (weights.py)
        head_motion = getattr(obj, "head_motion", None)
    if isinstance(obj, WeightSequence) and rig is not None:
        obj = _weights_onto_rig(obj, rig, path, mapping, preset)
    if isinstance(head_motion, (str, Path)):
        from ._common import guarded_reader, load_npy

        head_motion = guarded_reader(lambda p: np.asarray(load_npy(p, mmap=False)))(head_motion)
    ex, ex_names = _examples(examples)
    return Source(
        obj,
        head_motion=head_motion,
        landmarks=read_landmarks(landmarks) if landmarks is not None else None,
        feature_lines=read_feature_lines(feature_lines) if feature_lines is not None else None,
        examples=ex,
        example_names=ex_names,
        rig=rig,
        name=Path(path).stem,
    )


def load_target(
    path: PathLike,
    landmarks: Landmarks | str | Path | npt.ArrayLike | None = None,
    *,
    feature_lines: str | Path | Mapping[str, npt.ArrayLike] | None = None,
    examples: ExamplesSpec = None,
    kind: str | None = None,
    **options: Any,
) -> TargetRig:
    """A :class:`~faceretarget.model.TargetRig` from a rig or mesh file (or a bundle).

    ``path``: a blendshape rig (folder, glTF with morph targets, npz) or a plain mesh;
    a faceretarget bundle (target or case) is returned as stored, with ``landmarks``
    replacing its landmarks when given. ``landmarks``: a JSON/TXT file of vertex ids,
    ``file.npz:KEY``, or ids; ``feature_lines``: JSON; ``examples``: see :func:`load_source`.
    """
    from ..model import BlendshapeRig, Mesh, TargetRig

    obj = load(path, kind=kind, **options)
    if is_case(obj):
        obj = obj.target
    lm = read_landmarks(landmarks) if landmarks is not None else None
    lines = read_feature_lines(feature_lines) if feature_lines is not None else None
    ex, ex_names = _examples(examples)
    if isinstance(obj, TargetRig):
        if lm is None and lines is None and ex is None:
            return obj
        changes: dict[str, Any] = {"landmarks": lm or obj.landmarks}
        if lines is not None:
            changes["feature_lines"] = lines
        if ex is not None:
            changes.update(examples=ex, example_names=ex_names)
        return obj.replace(**changes)
    if isinstance(obj, BlendshapeRig):
        return TargetRig(
            obj.neutral,
            blendshapes=obj,
            landmarks=lm,
            feature_lines=lines,
            examples=ex,
            example_names=ex_names,
            name=Path(path).stem,
        )
    if isinstance(obj, Mesh):
        return TargetRig(
            obj,
            landmarks=lm,
            feature_lines=lines,
            examples=ex,
            example_names=ex_names,
            name=Path(path).stem,
        )
    raise FileFormatError(
        f"{path}: holds a {type(obj).__name__}, not a character (a rig or a mesh)"
    )
