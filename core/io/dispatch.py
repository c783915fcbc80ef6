"""Dispatch: ``read`` and ``write`` find the reader or writer for a path in the format table.

The table (:class:`faceretarget.io.formats.FormatTable`) is built from what the plugin
hooks registered (built-ins through :mod:`faceretarget.io.builtin`, like any plugin); the
one function :func:`table` gets it from the registry, importing the registry at call time:
io sits below the registry, and no format module ever imports it.

Reading ``path``: the records for its extension (``"/"`` for a folder), or the one named
by ``format=``; where several kinds share the extension, ``kind=`` or the readers' own
sniffers (``Reader.sniff``) pick the kind; then the first reader by precedence that does
not decline the file reads it. Errors name what a file really is: a registered format by
its magic bytes (``Reader.magic``), or any common file type (:func:`._common.sniff`).

Writing: the writer for the extension and the object's kind, handed a temporary path
that :func:`_write_through` moves into place (never over an input or, without ``force``,
an existing file).
"""

from __future__ import annotations

import os
from collections.abc import Callable, Iterable
from pathlib import Path
from typing import Any

from .._types import PathLike
from ..errors import FileFormatError, InputError, UnknownNameError
from ..hookspecs import DATA_KINDS, Writer
from ._atomic import note_input
from .formats import Entry, FormatTable, shadow_note

__all__ = ["read", "write", "formats", "shadow_note", "kind_of", "table"]


def _registry_table() -> FormatTable:
    from ..registry import registry  # at call time: the registry sits above io

    reg = registry()
    return FormatTable(reg.readers, reg.writers)


#: where :func:`table` gets the format table (an application or a test may set another)
table_source: Callable[[], FormatTable] = _registry_table


def table() -> FormatTable:
    """The format table of every loaded plugin's readers and writers (built-ins included)."""
    return table_source()


def _ext(path: Path, *, writing: bool = False) -> str:
    """The dispatch key: the lower-case suffix, or "/" for a folder (when writing: a path
    without a suffix or ending in a separator)."""
    if writing:
        return "/" if not path.suffix or str(path).endswith(("/", "\\")) else path.suffix.lower()
    return "/" if path.is_dir() else path.suffix.lower()


def _looks_like(formats: FormatTable, path: Path) -> str | None:
    """What ``path`` is when its extension says otherwise: a registered format whose magic
    bytes it starts with (``"a ply file (reader 'ply', .ply)"``), or a common file type
    (``"a PNG image"``); None when nothing is recognised."""
    if not path.is_file():
        return None
    ext = path.suffix.lower()
    for entry in formats.identify(path):
        if ext not in entry.extensions:
            exts = "/".join(x for x in entry.extensions if x != "/")
            return (
                f"a {entry.name} file ({entry.record.description}; {exts}, format={entry.name!r})"
            )
    from ._common import sniff

    found = sniff(path)
    if found is not None and found[0] not in ("empty", "text"):
        return found[1]
    return None


def _reader_order(
    formats: FormatTable, path: Path, kind: str | None, fmt: str | None
) -> list[Entry]:
    """The readers to try for ``path``, in order (the first that does not decline reads it)."""
    from .._validate import did_you_mean

    if fmt is not None:
        named = formats.named("read", fmt)
        if named:
            return named[:1]
        names = formats.names("read")
        raise UnknownNameError(
            f"no reader named {fmt!r}{did_you_mean(fmt, names)}; readers: {', '.join(names)}"
        )
    ext = _ext(path)
    candidates = formats.candidates("read", ext)
    if not candidates:
        known = formats.extensions("read")
        what = (
            "folders" if ext == "/" else (f"'{ext}' files" if ext else "files without an extension")
        )
        found = _looks_like(formats, path)
        looks = f" (it looks like {found})" if found else ""
        hint = did_you_mean(ext, known) if ext not in ("/", "") else ""
        raise FileFormatError(
            f"{path}: no reader for {what}{looks}{hint}; readable: {', '.join(known)}"
        )
    kinds = sorted({e.kind for e in candidates})
    if kind is not None:
        if kind not in DATA_KINDS:
            raise UnknownNameError(
                f"unknown kind {kind!r}{did_you_mean(kind, DATA_KINDS)}; kinds: {', '.join(DATA_KINDS)}"
            )
        if kind not in kinds:
            raise FileFormatError(
                f"{path}: '{ext}' files cannot be read as {kind}; they can be read as {', '.join(kinds)}"
            )
    elif len(kinds) > 1:
        kind = formats.sniff_kind(path, candidates) or candidates[0].kind
    return [e for e in candidates if kind in (None, e.kind)]


def _read_with(formats: FormatTable, readers: list[Entry], path: Path, options: dict) -> Any:
    """Read ``path`` with the first of ``readers`` that does not decline it: a reader
    declines through its ``accepts(path)`` returning False, or by raising
    :class:`~faceretarget.errors.FormatMismatchError`. When all decline, the error of the
    first reader that read and declined is raised (naming the others), else one saying
    what the file looks like."""
    from ..errors import FormatMismatchError
    from ._common import format_mismatch

    declined: list[str] = []
    first_error: FormatMismatchError | None = None
    for reader in (e.record for e in readers):
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
    if looks is None:
        found = _looks_like(formats, path)
        looks = f"this looks like {found}" if found else None
    raise FormatMismatchError(
        f"{path}: {looks + '; ' if looks else ''}every reader for it declined it: {tried}"
    )


def read(
    path: PathLike, kind: str | None = None, *, format: str | None = None, **options: Any
) -> Any:
    """Read ``path`` with the registered reader for its extension (or folder); see
    :func:`faceretarget.io.load`, which also returns faceretarget bundles whole."""
    from ._common import check_regular

    p = Path(path)
    check_regular(p, folder_ok=True)  # a FIFO or device is refused before anything opens it
    note_input(p)  # whichever reader reads it (a plugin's too), no writer may replace it
    formats = table()
    return _read_with(formats, _reader_order(formats, p, kind, format), p, options)


def kind_of(obj: Any) -> str:
    """The data kind of a model object ('mesh', 'mesh_sequence', 'rig', 'markers', 'weights', 'animation')."""
    from ..model import Animation, BlendshapeRig, MarkerSequence, Mesh, MeshSequence, WeightSequence

    for cls, kind in (
        (Mesh, "mesh"),
        (MeshSequence, "mesh_sequence"),
        (BlendshapeRig, "rig"),
        (MarkerSequence, "markers"),
        (WeightSequence, "weights"),
        (Animation, "animation"),
    ):
        if isinstance(obj, cls):
            return kind
    raise InputError(
        f"cannot save a {type(obj).__name__}; expected a Mesh, MeshSequence, BlendshapeRig, MarkerSequence, WeightSequence or Animation"
    )


def _coerce(obj: Any, kind: str, want: set[str]) -> tuple[Any, str | None]:
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


def write(
    obj: Any,
    path: PathLike,
    *,
    force: bool = False,
    inputs: Iterable = (),
    format: str | None = None,
    **options: Any,
) -> Path:
    """Write a model object with the registered writer for the path's extension (or the one
    named ``format``), atomically; see :func:`faceretarget.io.save`, which also writes bundles."""
    p = Path(path)
    kind = kind_of(obj)
    formats = table()
    if format is not None:
        candidates = formats.named("write", format)
        if not candidates:
            raise UnknownNameError(
                f"no writer named {format!r}; writers: {', '.join(formats.names('write'))}"
            )
    else:
        ext = _ext(p, writing=True)
        candidates = formats.candidates("write", ext)
        if not candidates:
            raise FileFormatError(
                f"{p}: no writer for '{ext}' files; writable: {', '.join(formats.extensions('write'))}"
            )
    matching = [e for e in candidates if e.kind == kind]
    if not matching:
        coerced, new_kind = _coerce(obj, kind, {e.kind for e in candidates})
        if coerced is None:
            raise FileFormatError(
                f"{p}: a {kind} cannot be written as '{p.suffix or 'folder'}'; that format stores "
                f"{', '.join(sorted({e.kind for e in candidates}))}"
            )
        obj, matching = coerced, [e for e in candidates if e.kind == new_kind]
    _write_through(formats, matching[0], obj, p, force=force, inputs=inputs, options=options)
    return p


def _write_through(
    formats: FormatTable,
    entry: Entry,
    obj: Any,
    dest: Path,
    *,
    force: bool,
    inputs: Iterable,
    options: dict,
) -> None:
    """The one way any writer, built-in or a plugin's, reaches the disk: it is handed a
    temporary path beside ``dest`` (an empty file with ``dest``'s suffix, or an empty
    folder for a folder format) and, when it returns, the core checks the destination
    again and moves the result into place (:func:`atomic_path` / :func:`atomic_dir`). So no
    writer can replace an existing file without ``force`` or any input of this process,
    and a crash never leaves a partial file. A writer that writes the destination or an
    input itself instead of its temporary is a :class:`~faceretarget.errors.PluginOutputError`
    and its result is discarded."""
    from ._atomic import atomic_dir, atomic_path

    writer: Writer = entry.record
    folder = _ext(dest, writing=True) == "/" and "/" in writer.extensions
    inputs = list(inputs)
    if folder:
        allowed = None if entry.builtin else _plugin_folder_suffixes(formats, writer)
        context = atomic_dir(dest, inputs=inputs, force=force, allowed_suffixes=allowed)
    else:
        context = atomic_path(dest, inputs=inputs, force=force)
    with context as tmp:
        watched = _watch(dest, inputs)
        writer.write(obj, tmp, force=True, inputs=inputs, **options)
        touched = [path for path, before in watched.items() if _stamp(path) != before]
        if touched:
            from ..errors import PluginOutputError

            raise PluginOutputError(
                f"writer {writer.name!r} ({entry.origin}) wrote {', '.join(map(str, touched[:3]))} itself instead of the "
                f"temporary path it was given ({tmp.name}); its output was discarded. A writer must write only the path "
                "it is handed: faceretarget moves it into place (see docs/plugins.md, 'Readers and writers')"
            )


def _plugin_folder_suffixes(formats: FormatTable, writer: Writer) -> tuple[str, ...]:
    """Suffixes of the files an existing folder may hold for a plugin's folder writer to
    replace it: the file formats registered for the same kind (never other content)."""
    exts = {
        x for kind in (writer.kind, "mesh") for x in formats.extensions("write", kind) if x != "/"
    }
    return tuple(sorted(exts | {".json"}))


def _stamp(path: Path) -> tuple[int, int, int, int] | None:
    try:
        st = os.stat(path)
    except OSError:
        return None
    return (st.st_dev, st.st_ino, st.st_size, st.st_mtime_ns)


def _watch(dest: Path, inputs: Iterable[PathLike]) -> dict:
    """``{path: stamp}`` of the destination and every input: what a writer must not touch."""
    from ._atomic import recorded_inputs

    paths = {dest, *(Path(i) for i in inputs), *(Path(i) for i in recorded_inputs())}
    return {p: _stamp(p) for p in paths if p == dest or not p.is_dir()}


def formats() -> list[dict[str, Any]]:
    """Every registered reader and writer: direction, name, kind, extensions, description,
    origin, ``priority``, and precedence among records of one extension and kind:
    ``shadowed_by`` (``{extension: name of the record that wins}``; a shadowed reader
    still gets the files the winner declines) and ``shadows`` (``{extension: [names]}``)."""
    return table().rows()
