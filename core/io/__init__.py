"""File formats: readers and writers registered through the plugin hooks.

Public API::

    load(path, kind=None, **options)        # any registered format -> model object
    save(obj, path, force=False, **options) # atomic; never over an input
    load_source(path, **options) -> Source
    load_target(path, landmarks=None, **options) -> TargetRig
    save_bundle(obj, path.npz) / load_bundle(path.npz)
    read_landmarks(path) -> Landmarks
    formats() -> list of (direction, name, kind, extensions, description, origin, precedence)

    # the input-safe atomic writer, for plugin writers and applications alike
    with atomic_path(dest, force=False, inputs=()) as tmp: ...   # write tmp; it replaces dest
    with atomic_file(dest) as fh: ...                            # an open temporary file
    with atomic_dir(dest) as tmp_folder: ...                     # a folder, swapped in whole
    write_bytes(dest, data); note_input(path); is_input(path)

Writing contract: :func:`save` hands every writer, built-in or a plugin's, a temporary
path beside the destination and moves the result into place itself, so no writer can
replace an existing file without ``force`` or an input of this process (files a reader
opened, and ``inputs=``). Readers may decline a file (``Reader.accepts`` returning False,
or raising :class:`~faceretarget.errors.FormatMismatchError`) and declare precedence
(``Reader.priority``; built-ins 0, ties to built-ins); see docs/plugins.md.

Readers and writers are looked up in ``faceretarget.registry.registry()`` (so a plugin's
``faceretarget_readers``/``faceretarget_writers`` hooks add formats): by the file
extension (``"/"`` for a folder) and, where several kinds share an extension (``.npz``,
``.csv``, ``.glb``, folders), by ``kind=`` or by looking inside the file. ``format=``
picks a reader/writer by name.

Built-in formats (kind: extensions):

- mesh: .obj .ply .off .stl .glb .gltf .npz; through meshio (priority -1, :mod:`.meshio_formats`):
  .vtk .vtu .msh .mesh .meshb .inp .bdf .fem .nas (read only) .avs .post .dato .vol
- mesh_sequence: folder of meshes, .npy, .npz, .pc2, .mdd (memory-mapped), .glb/.gltf
- rig: folder (neutral + one mesh per shape), .glb/.gltf (morph targets), .npz
- markers: .c3d .trc .csv .npz
- weights: .csv (Live Link Face layout and plain), .npz
- animation: .glb/.gltf, .npz (also written as OBJ sequence / PC2 / MDD / npy / CSV)
"""
from __future__ import annotations

import json
import os
from pathlib import Path
from typing import Any

from ..errors import FileFormatError, InputError, UnknownNameError
from ..hookspecs import DATA_KINDS, Reader, Writer, hookimpl
from ._atomic import atomic_dir, atomic_file, atomic_path, is_input, note_input, write_bytes

__all__ = [
    "load",
    "save",
    "load_source",
    "load_target",
    "save_bundle",
    "load_bundle",
    "read_landmarks",
    "read_feature_lines",
    "formats",
    "shadow_note",
    "kind_of",
    "atomic_path",
    "atomic_dir",
    "atomic_file",
    "write_bytes",
    "note_input",
    "is_input",
]

_MESH_EXT = (".obj", ".ply", ".off", ".stl")
_GLTF_EXT = (".glb", ".gltf")


def _lazy(module: str, name: str):
    """A callable importing ``faceretarget.io.<module>.<name>`` on first call (keeps `list` light)."""

    def call(*args, **kwargs):
        from importlib import import_module

        return getattr(import_module(f"{__name__}.{module}"), name)(*args, **kwargs)

    call.__name__ = name
    call.__qualname__ = name
    call.__doc__ = f"faceretarget.io.{module}.{name}"
    return call


def _npz_reader(kind: str):
    def read(path, **options):
        from .bundle import read_npz_object

        return read_npz_object(path, kind=kind, **options)

    read.__name__ = f"read_npz_{kind}"
    return read


def builtin_readers() -> list[Reader]:
    """The readers of this package (registered through the ``faceretarget_readers`` hook)."""
    r = [
        Reader("obj", "mesh", (".obj",), _lazy("meshes", "read_obj"), "Wavefront OBJ (vertex order kept, n-gons fan-triangulated)"),
        Reader("ply", "mesh", (".ply",), _lazy("meshes", "read_ply"), "PLY, ASCII or binary"),
        Reader("off", "mesh", (".off",), _lazy("meshes", "read_off"), "OFF"),
        Reader("stl", "mesh", (".stl",), _lazy("meshes", "read_stl"), "STL, binary or ASCII (identical corners joined)"),
        Reader("gltf-mesh", "mesh", _GLTF_EXT, _lazy("gltf", "read_gltf_mesh"), "glTF/GLB mesh (primitives joined)"),
        Reader("npz-mesh", "mesh", (".npz",), _npz_reader("mesh"), "faceretarget npz (or vertices + triangles)"),
        Reader("mesh-folder", "mesh_sequence", ("/",), _lazy("sequences", "read_mesh_folder"), "folder of per-frame meshes (natural order)"),
        Reader("npy", "mesh_sequence", (".npy",), _lazy("sequences", "read_npy_sequence"), "(F, V, 3) array, memory-mapped; topology= gives triangles"),
        Reader("npz-sequence", "mesh_sequence", (".npz",), _npz_reader("mesh_sequence"), "faceretarget npz (or vertices (F, V, 3) + triangles)"),
        Reader("pc2", "mesh_sequence", (".pc2",), _lazy("sequences", "read_pc2"), "PC2 point cache, memory-mapped; topology= gives triangles"),
        Reader("mdd", "mesh_sequence", (".mdd",), _lazy("sequences", "read_mdd"), "MDD point cache (big-endian), memory-mapped"),
        Reader("gltf-sequence", "mesh_sequence", _GLTF_EXT, _lazy("gltf", "read_gltf_sequence"), "glTF animation as per-frame vertices"),
        Reader("rig-folder", "rig", ("/",), _lazy("rigs", "read_rig_folder"), "folder: neutral mesh + one mesh per blendshape"),
        Reader("gltf-rig", "rig", _GLTF_EXT, _lazy("gltf", "read_gltf_rig"), "glTF/GLB morph targets, names from extras.targetNames"),
        Reader("npz-rig", "rig", (".npz",), _npz_reader("rig"), "faceretarget npz (or neutral + deltas + names + faces)"),
        Reader("c3d", "markers", (".c3d",), _lazy("markers", "read_c3d"), "C3D motion capture (c3d package)"),
        Reader("trc", "markers", (".trc",), _lazy("markers", "read_trc"), "TRC marker trajectories"),
        Reader("csv-markers", "markers", (".csv",), _lazy("markers", "read_marker_csv"), "CSV with NAME_x, NAME_y, NAME_z columns"),
        Reader("npz-markers", "markers", (".npz",), _npz_reader("markers"), "faceretarget npz (or positions + names)"),
        Reader("csv-weights", "weights", (".csv",), _lazy("weights", "read_weights_csv"), "weight curves CSV (Live Link Face or frame,name... layout)"),
        Reader("npz-weights", "weights", (".npz",), _npz_reader("weights"), "faceretarget npz (or weights + names)"),
        Reader("gltf-animation", "animation", _GLTF_EXT, _lazy("gltf", "read_gltf_animation"), "glTF morph-weight animation or per-frame meshes"),
        Reader("npz-animation", "animation", (".npz",), _npz_reader("animation"), "faceretarget npz animation"),
    ]
    from .meshio_formats import meshio_readers  # VTK, Gmsh, ... below the native readers; meshio imported on use

    return r + meshio_readers()


def builtin_writers() -> list[Writer]:
    """The writers of this package (registered through the ``faceretarget_writers`` hook)."""
    from .meshio_formats import meshio_writers  # VTK, Gmsh, ... below the native writers; meshio imported on use

    npz = _lazy("bundle", "write_npz")
    gltf = _lazy("gltf", "write_gltf")
    return [
        Writer("obj", "mesh", (".obj",), _lazy("meshes", "write_obj"), "Wavefront OBJ, exact decimals"),
        Writer("ply", "mesh", (".ply",), _lazy("meshes", "write_ply"), "binary PLY, float64"),
        Writer("off", "mesh", (".off",), _lazy("meshes", "write_off"), "OFF, exact decimals"),
        Writer("stl", "mesh", (".stl",), _lazy("meshes", "write_stl"), "binary STL, float32"),
        Writer("gltf-mesh", "mesh", _GLTF_EXT, gltf, "glTF/GLB mesh"),
        Writer("gltf-rig", "rig", _GLTF_EXT, gltf, "glTF/GLB morph targets with extras.targetNames"),
        Writer("gltf-animation", "animation", _GLTF_EXT, gltf, "glTF/GLB: morph targets + weight animation, or one node per frame"),
        Writer("gltf-sequence", "mesh_sequence", _GLTF_EXT, gltf, "glTF/GLB: one node per frame with STEP visibility"),
        Writer("obj-sequence", "mesh_sequence", ("/",), _lazy("sequences", "write_obj_sequence"), "folder of OBJ frames + sequence.json"),
        Writer("rig-folder", "rig", ("/",), _lazy("rigs", "write_rig_folder"), "folder: neutral.obj + one OBJ per shape + rig.json"),
        Writer("pc2", "mesh_sequence", (".pc2",), _lazy("sequences", "write_pc2"), "PC2 point cache (float32)"),
        Writer("mdd", "mesh_sequence", (".mdd",), _lazy("sequences", "write_mdd"), "MDD point cache (big-endian float32)"),
        Writer("npy", "mesh_sequence", (".npy",), _lazy("sequences", "write_npy"), "(F, V, 3) vertices only"),
        Writer("c3d", "markers", (".c3d",), _lazy("markers", "write_c3d"), "C3D (float32)"),
        Writer("trc", "markers", (".trc",), _lazy("markers", "write_trc"), "TRC, exact decimals"),
        Writer("csv-markers", "markers", (".csv",), _lazy("markers", "write_marker_csv"), "CSV frame,time,NAME_x,NAME_y,NAME_z"),
        Writer("csv-weights", "weights", (".csv",), _lazy("weights", "write_weights_csv"), "Live Link Face CSV layout"),
    ] + [Writer(f"npz-{kind.replace('mesh_', '')}", kind, (".npz",), npz, "faceretarget npz (exact)") for kind in DATA_KINDS] + meshio_writers()


@hookimpl
def faceretarget_readers():
    return builtin_readers()


@hookimpl
def faceretarget_writers():
    return builtin_writers()


# ---------------------------------------------------------------------------------------
# dispatch
# ---------------------------------------------------------------------------------------
def _registry():
    from ..registry import registry

    return registry()


def _ext(path: Path, *, writing: bool = False) -> str:
    """The dispatch key: the lower-case suffix, or "/" for a folder (when writing: a path
    without a suffix or ending in a separator)."""
    if writing:
        return "/" if not path.suffix or str(path).endswith(("/", "\\")) else path.suffix.lower()
    return "/" if path.is_dir() else path.suffix.lower()


def _sniff(path: Path, ext: str) -> str | None:
    """What a built-in ambiguous format holds, by looking inside (None if unknown)."""
    if ext == "/":
        from .rigs import NEUTRAL_NAMES, RIG_SIDECAR

        names = {p.stem.lower() for p in path.iterdir() if p.is_file()}
        return "rig" if (path / RIG_SIDECAR).is_file() or names & set(NEUTRAL_NAMES) else "mesh_sequence"
    if ext in _GLTF_EXT:
        from .gltf import gltf_kind

        return gltf_kind(path)
    if ext == ".npz":
        from .bundle import npz_kind

        return npz_kind(path)
    if ext == ".csv":
        from .markers import csv_header, is_marker_header

        try:
            header = csv_header(path)  # the first row only
        except Exception:
            return None
        return "markers" if is_marker_header(header) else "weights"
    return None


def _ranked(records: list, info_of: dict) -> list:
    """``records`` in precedence order: highest ``priority`` first; on a tie built-ins
    first, then plugins in the order they were loaded."""
    order = {id(r): i for i, r in enumerate(records)}
    return sorted(records, key=lambda r: (-getattr(r, "priority", 0), not info_of[id(r)].builtin, order[id(r)]))


def _reader_order(path: Path, kind: str | None, fmt: str | None) -> list[Reader]:
    """The readers to try for ``path``, in order (the first that does not decline reads it)."""
    from .._validate import did_you_mean

    pairs = _registry().readers
    info_of = {id(r): info for r, info in pairs}
    readers = [r for r, _ in pairs]
    if fmt is not None:
        for r in readers:
            if r.name == fmt:
                return [r]
        names = sorted({r.name for r in readers})
        raise UnknownNameError(f"no reader named {fmt!r}{did_you_mean(fmt, names)}; readers: {', '.join(names)}")
    ext = _ext(path)
    candidates = [r for r in readers if ext in r.extensions]
    if not candidates:
        known = sorted({e for r in readers for e in r.extensions})
        what = "folders" if ext == "/" else (f"'{ext}' files" if ext else "files without an extension")
        looks = ""
        if path.is_file():
            from ._common import sniff

            found = sniff(path)
            if found is not None and found[0] not in ("empty", "text"):
                looks = f" (it looks like {found[1]})"
        hint = did_you_mean(ext, known) if ext not in ("/", "") else ""
        raise FileFormatError(f"{path}: no reader for {what}{looks}{hint}; readable: {', '.join(known)}")
    if kind is not None:
        if kind not in DATA_KINDS:
            raise UnknownNameError(f"unknown kind {kind!r}{did_you_mean(kind, DATA_KINDS)}; kinds: {', '.join(DATA_KINDS)}")
        matching = [r for r in candidates if r.kind == kind]
        if not matching:
            raise FileFormatError(
                f"{path}: '{ext}' files cannot be read as {kind}; they can be read as {', '.join(sorted({r.kind for r in candidates}))}"
            )
        return _ranked(matching, info_of)
    if len({r.kind for r in candidates}) > 1:
        try:
            sniffed = _sniff(path, ext)
        except (OSError, FileFormatError):  # unreadable or another kind of file: the reader says so
            sniffed = None
        same = [r for r in candidates if r.kind == sniffed]
        if same:
            return _ranked(same, info_of)
        first_kind = candidates[0].kind
        return _ranked([r for r in candidates if r.kind == first_kind], info_of)
    return _ranked(candidates, info_of)


def _choose_reader(path: Path, kind: str | None, fmt: str | None) -> Reader:
    """The reader of highest precedence for ``path`` (before any declines)."""
    return _reader_order(path, kind, fmt)[0]


def _read_with(readers: list[Reader], path: Path, options: dict) -> Any:
    """Read ``path`` with the first of ``readers`` that does not decline it: a reader
    declines through its ``accepts(path)`` returning False, or by raising
    :class:`~faceretarget.errors.FormatMismatchError`. When all decline, the error of the
    first reader that read and declined is raised (naming the others), else one saying
    what the file looks like."""
    from ..errors import FormatMismatchError
    from ._common import format_mismatch

    declined: list[str] = []
    first_error: FormatMismatchError | None = None
    for reader in readers:
        if reader.accepts is not None:
            try:
                ok = bool(reader.accepts(path))
                why = "its accepts() said no"
            except Exception as exc:  # a broken accepts() declines, and says why
                ok, why = False, f"its accepts() raised {type(exc).__name__}: {exc}"
            if not ok:
                declined.append(f"{reader.name} ({why})")
                continue
        try:
            return reader.read(path, **options)
        except FormatMismatchError as exc:
            declined.append(reader.name)
            first_error = first_error or exc
    tried = ", ".join(declined)
    if first_error is not None:
        if len(declined) == 1:
            raise first_error
        raise FormatMismatchError(f"{first_error}; no reader took it (tried {tried})") from None
    looks = format_mismatch(path) if path.is_file() else None
    raise FormatMismatchError(f"{path}: {looks + '; ' if looks else ''}every reader for it declined it: {tried}")


def load(path, kind: str | None = None, *, format: str | None = None, **options) -> Any:
    """Read ``path`` with the registered reader for its extension (or folder).

    ``kind`` ('mesh', 'mesh_sequence', 'rig', 'markers', 'weights', 'animation') picks
    among formats sharing an extension; without it the file is looked into. A
    faceretarget bundle (``.npz`` holding a Source, TargetRig or case) is returned whole
    when no kind is asked. Options go to the reader (e.g. ``topology=``, ``fps=``).
    Errors are :class:`~faceretarget.errors.FileFormatError` naming the file.
    """
    from ._common import check_regular

    p = Path(path)
    check_regular(p, folder_ok=True)  # a FIFO or device is refused before anything opens it
    note_input(p)  # whichever reader reads it (a plugin's too), no writer may replace it
    if kind is None and format is None and _ext(p) == ".npz":
        from .bundle import BUNDLE_TYPES, npz_kind

        stored = npz_kind(p)
        if stored is None or stored in BUNDLE_TYPES:  # a bundle, or let the npz reader say what is wrong
            return load_bundle(p)
    return _read_with(_reader_order(p, kind, format), p, options)


def kind_of(obj: Any) -> str:
    """The data kind of a model object ('mesh', 'mesh_sequence', 'rig', 'markers', 'weights', 'animation')."""
    from ..model import Animation, BlendshapeRig, MarkerSequence, Mesh, MeshSequence, WeightSequence

    for cls, kind in (
        (Mesh, "mesh"), (MeshSequence, "mesh_sequence"), (BlendshapeRig, "rig"), (MarkerSequence, "markers"),
        (WeightSequence, "weights"), (Animation, "animation"),
    ):
        if isinstance(obj, cls):
            return kind
    raise InputError(f"cannot save a {type(obj).__name__}; expected a Mesh, MeshSequence, BlendshapeRig, MarkerSequence, WeightSequence or Animation")


def _coerce(obj: Any, kind: str, want: set[str]):
    """``obj`` as one of the kinds ``want`` (animation <-> sequence, animation -> weights)."""
    from ..model import Animation, MeshSequence, WeightSequence

    if kind == "animation":
        if "animation" in want:
            return obj, "animation"
        if "mesh_sequence" in want and obj.triangles is not None:
            return MeshSequence(obj.vertices, obj.triangles, fps=obj.fps), "mesh_sequence"
        if "weights" in want and obj.weights is not None:
            return WeightSequence(obj.weights, obj.weight_names, fps=obj.fps), "weights"
    if kind == "mesh_sequence" and "animation" in want:
        return Animation(vertices=obj.vertices, triangles=obj.triangles, fps=obj.fps), "animation"
    return None, None


def save(obj: Any, path, *, force: bool = False, inputs=(), format: str | None = None, **options) -> Path:
    """Write ``obj`` with the registered writer for the path's extension, atomically.

    A path without an extension is a folder (OBJ sequence or rig folder). Source,
    TargetRig and case objects go to :func:`save_bundle` (``.npz``). Refuses
    (:class:`~faceretarget.errors.OutputError`) to replace an input of this process or
    one listed in ``inputs``, and an existing file unless ``force``.
    """
    p = Path(path)
    from ..model import Source, TargetRig

    if isinstance(obj, (Source, TargetRig)) or _is_case(obj):
        return save_bundle(obj, p, force=force, inputs=inputs, **options)
    kind = kind_of(obj)
    writers = [w for w, _ in _registry().writers]
    if format is not None:
        chosen = [w for w in writers if w.name == format]
        if not chosen:
            raise UnknownNameError(f"no writer named {format!r}; writers: {', '.join(sorted({w.name for w in writers}))}")
        candidates = chosen
    else:
        ext = _ext(p, writing=True)
        candidates = [w for w in writers if ext in w.extensions]
        if not candidates:
            known = sorted({e for w in writers for e in w.extensions})
            raise FileFormatError(f"{p}: no writer for '{ext}' files; writable: {', '.join(known)}")
    matching = [w for w in candidates if w.kind == kind]
    if not matching:
        coerced, new_kind = _coerce(obj, kind, {w.kind for w in candidates})
        if coerced is None:
            raise FileFormatError(
                f"{p}: a {kind} cannot be written as '{p.suffix or 'folder'}'; that format stores "
                f"{', '.join(sorted({w.kind for w in candidates}))}"
            )
        obj, matching = coerced, [w for w in candidates if w.kind == new_kind]
    info_of = {id(w): info for w, info in _registry().writers}
    writer = _ranked(matching, info_of)[0]
    _write_through(writer, info_of[id(writer)], obj, p, force=force, inputs=inputs, options=options)
    return p


def _write_through(writer: Writer, info, obj: Any, dest: Path, *, force: bool, inputs, options: dict) -> None:
    """The one way any writer, built-in or a plugin's, reaches the disk: it is handed a
    temporary path beside ``dest`` (an empty file with ``dest``'s suffix, or an empty
    folder for a folder format) and, when it returns, the core checks the destination
    again and moves the result into place (:func:`atomic_path` / :func:`atomic_dir`). So no
    writer can replace an existing file without ``force`` or any input of this process,
    and a crash never leaves a partial file. A writer that writes the destination or an
    input itself instead of its temporary is a :class:`~faceretarget.errors.PluginOutputError`
    and its result is discarded."""
    from ._atomic import atomic_dir, atomic_path

    folder = _ext(dest, writing=True) == "/" and "/" in writer.extensions
    inputs = list(inputs)
    if folder:
        context = atomic_dir(dest, inputs=inputs, force=force, allowed_suffixes=None if info.builtin else _plugin_folder_suffixes(writer))
    else:
        context = atomic_path(dest, inputs=inputs, force=force)
    with context as tmp:
        watched = _watch(dest, inputs)
        writer.write(obj, tmp, force=True, inputs=inputs, **options)
        touched = [path for path, before in watched.items() if _stamp(path) != before]
        if touched:
            from ..errors import PluginOutputError

            raise PluginOutputError(
                f"writer {writer.name!r} ({info.origin}) wrote {', '.join(map(str, touched[:3]))} itself instead of the "
                f"temporary path it was given ({tmp.name}); its output was discarded. A writer must write only the path "
                "it is handed: faceretarget moves it into place (see docs/plugins.md, 'Readers and writers')"
            )


def _plugin_folder_suffixes(writer: Writer) -> tuple[str, ...]:
    """Suffixes of the files an existing folder may hold for a plugin's folder writer to
    replace it: the file formats registered for the same kind (never other content)."""
    return tuple(sorted({e for w, _ in _registry().writers if w.kind in (writer.kind, "mesh") for e in w.extensions if e != "/"} | {".json"}))


def _stamp(path: Path):
    try:
        st = os.stat(path)
    except OSError:
        return None
    return (st.st_dev, st.st_ino, st.st_size, st.st_mtime_ns)


def _watch(dest: Path, inputs) -> dict:
    """``{path: stamp}`` of the destination and every input: what a writer must not touch."""
    from ._atomic import recorded_inputs

    paths = {dest, *(Path(i) for i in inputs), *(Path(i) for i in recorded_inputs())}
    return {p: _stamp(p) for p in paths if p == dest or not p.is_dir()}


# ---------------------------------------------------------------------------------------
# bundles, sources and targets
# ---------------------------------------------------------------------------------------
def save_bundle(obj: Any, path, *, force: bool = False, inputs=(), **options) -> Path:
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


def load_bundle(path) -> Any:
    """Read any faceretarget ``.npz`` (Source, TargetRig, case bundle, or a model object)."""
    from .bundle import read_npz_object

    p = Path(path)
    if p.exists() and p.suffix.lower() != ".npz":
        raise FileFormatError(f"{p}: bundles are .npz files")
    return read_npz_object(p)


def _is_case(obj) -> bool:
    from ..model import Source, TargetRig

    return isinstance(getattr(obj, "source", None), Source) and isinstance(getattr(obj, "target", None), TargetRig)


def read_landmarks(spec, *, key: str | None = None):
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
            names = arrays.get(f"{k}_names")
            return Landmarks(arrays[k].astype("int64") if arrays[k].dtype.kind in "iu" else arrays[k], names=None if names is None else names.tolist())
        raw = read_text(path, factor=TEXT_TOKEN_FACTOR)
        if suffix == ".json":
            try:
                data = json.loads(raw)
            except ValueError as exc:
                raise bad(path, f"not valid JSON ({exc})") from None
            if isinstance(data, list):
                return Landmarks(data)
            if isinstance(data, dict) and "triangle_ids" in data:
                return Landmarks(triangle_ids=data["triangle_ids"], barycentric=data.get("barycentric"), names=data.get("names"))
            if isinstance(data, dict) and "vertex_ids" in data:
                return Landmarks(data["vertex_ids"], names=data.get("names"))
            if isinstance(data, dict) and data and all(isinstance(v, int) and not isinstance(v, bool) for v in data.values()):
                return Landmarks(list(data.values()), names=list(data))
            raise bad(path, "expected a list of vertex ids, {vertex_ids, names}, {triangle_ids, barycentric, names} or {name: id}")
        ids, names = [], []
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
                raise bad(path, f"line {lineno}: expected 'ID', 'NAME ID' or 'ID NAME', got {line.strip()[:60]!r}")
        if names and len(names) != len(ids):
            raise bad(path, "either every landmark line has a name or none has")
        if not ids:
            raise bad(path, "holds no landmark ids")
        return Landmarks(ids, names=names or None)

    return read(Path(text))


def read_feature_lines(spec) -> dict:
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


def _examples(spec) -> tuple[Any, Any]:
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
    def read(path: Path):
        arrays = read_npz(path)
        if "examples" not in arrays:
            raise bad(path, "needs an 'examples' array (M, P, 3) and optionally 'example_names'")
        names = arrays.get("example_names")
        return arrays["examples"], None if names is None else names.tolist()

    return read(p)


def _weights_onto_rig(weights, rig, path, mapping, preset):
    """Weight curves renamed/combined onto the rig's shapes (Live Link Face head/eye rotation
    columns are set aside with a warning; any other curve without a counterpart is an error)."""
    import warnings

    from ..naming import load_mapping, map_names
    from .weights import LIVE_LINK_EXTRA

    explicit = dict(load_mapping(mapping) if isinstance(mapping, (str, Path)) else (mapping or {}))
    rotations = [n for n in weights.names if n in LIVE_LINK_EXTRA and n not in rig.names and n not in explicit]
    if rotations:
        warnings.warn(f"{path}: head/eye rotation columns are not blendshapes and are not used: {', '.join(rotations)}", stacklevel=3)
        explicit.update({n: "" for n in rotations})
    m = map_names(weights.names, rig.names, preset=preset, mapping=explicit).require_complete(f"{path}: weight curves")
    return m.apply(weights)


def load_source(path, *, kind: str | None = None, landmarks=None, rig=None, head_motion=None, feature_lines=None,
                examples=None, mapping=None, preset: str = "auto", **options):
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

    from ..model import Animation, BlendshapeRig, MarkerSequence, MeshSequence, Source, WeightSequence

    obj = load(path, kind=kind, **options)
    if _is_case(obj):
        obj = obj.source
    if isinstance(obj, Source):
        return obj
    if isinstance(obj, Animation):
        obj = MeshSequence(obj.vertices, obj.triangles, fps=obj.fps) if obj.triangles is not None else WeightSequence(obj.weights, obj.weight_names, fps=obj.fps)
    if not isinstance(obj, (MarkerSequence, MeshSequence, WeightSequence)):
        raise FileFormatError(f"{path}: holds a {type(obj).__name__}, not a performance (markers, mesh sequence or weight curves)")
    if isinstance(rig, (str, Path)):
        rig = load(rig, kind="rig")
    if rig is not None and not isinstance(rig, BlendshapeRig):
        raise InputError(f"load_source: rig must be a BlendshapeRig or a rig file, got {type(rig).__name__}")
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


def load_target(path, landmarks=None, *, feature_lines=None, examples=None, kind: str | None = None, **options):
    """A :class:`~faceretarget.model.TargetRig` from a rig or mesh file (or a bundle).

    ``path``: a blendshape rig (folder, glTF with morph targets, npz) or a plain mesh;
    a faceretarget bundle (target or case) is returned as stored, with ``landmarks``
    replacing its landmarks when given. ``landmarks``: a JSON/TXT file of vertex ids,
    ``file.npz:KEY``, or ids; ``feature_lines``: JSON; ``examples``: see :func:`load_source`.
    """
    from ..model import BlendshapeRig, Mesh, TargetRig

    obj = load(path, kind=kind, **options)
    if _is_case(obj):
        obj = obj.target
    lm = read_landmarks(landmarks) if landmarks is not None else None
    lines = read_feature_lines(feature_lines) if feature_lines is not None else None
    ex, ex_names = _examples(examples)
    if isinstance(obj, TargetRig):
        if lm is None and lines is None and ex is None:
            return obj
        changes = {"landmarks": lm or obj.landmarks}
        if lines is not None:
            changes["feature_lines"] = lines
        if ex is not None:
            changes.update(examples=ex, example_names=ex_names)
        return obj.replace(**changes)
    if isinstance(obj, BlendshapeRig):
        return TargetRig(obj.neutral, blendshapes=obj, landmarks=lm, feature_lines=lines, examples=ex, example_names=ex_names, name=Path(path).stem)
    if isinstance(obj, Mesh):
        return TargetRig(obj, landmarks=lm, feature_lines=lines, examples=ex, example_names=ex_names, name=Path(path).stem)
    raise FileFormatError(f"{path}: holds a {type(obj).__name__}, not a character (a rig or a mesh)")


def formats() -> list[dict[str, Any]]:
    """Every registered reader and writer: direction, name, kind, extensions, description,
    origin, ``priority``, and precedence among records of one extension and kind:
    ``shadowed_by`` (``{extension: name of the record that wins}``; a shadowed reader
    still gets the files the winner declines) and ``shadows`` (``{extension: [names]}``)."""
    reg = _registry()
    rows = []
    for direction, items in (("read", reg.readers), ("write", reg.writers)):
        info_of = {id(rec): info for rec, info in items}
        groups: dict[tuple[str, str], list] = {}
        for rec, _ in items:
            for ext in rec.extensions:
                groups.setdefault((ext, rec.kind), []).append(rec)
        shadowed_by: dict[int, dict[str, str]] = {}
        shadows: dict[int, dict[str, list[str]]] = {}
        for (ext, _), recs in groups.items():
            ranked = _ranked(recs, info_of)
            for loser in ranked[1:]:
                shadowed_by.setdefault(id(loser), {})[ext] = ranked[0].name
                shadows.setdefault(id(ranked[0]), {}).setdefault(ext, []).append(loser.name)
        for rec, info in items:
            rows.append({
                "direction": direction, "name": rec.name, "kind": rec.kind, "extensions": list(rec.extensions),
                "description": rec.description, "origin": info.origin, "builtin": info.builtin,
                "priority": getattr(rec, "priority", 0), "declines": getattr(rec, "accepts", None) is not None,
                "shadowed_by": shadowed_by.get(id(rec), {}), "shadows": shadows.get(id(rec), {}),
            })
    return rows


def shadow_note(row: dict[str, Any]) -> str:
    """One line on a :func:`formats` row's precedence, e.g. ``"shadowed by obj (.obj)"`` or
    ``"wins over obj (.obj)"``; empty when it shares no extension and kind with another."""
    parts = []
    if row["shadowed_by"]:
        by = ", ".join(f"{name} ({ext})" for ext, name in sorted(row["shadowed_by"].items()))
        later = "; gets only files the winner declines" if row["direction"] == "read" else ""
        parts.append(f"shadowed by {by}{later}")
    if row["shadows"]:
        parts.append("wins over " + ", ".join(f"{'/'.join(names)} ({ext})" for ext, names in sorted(row["shadows"].items())))
    return "; ".join(parts)
