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

Layers (each imports only those below it; none imports the registry at import time):

- :mod:`.sources`: ``load``/``save`` (bundles whole, anything else through the dispatcher),
  ``load_source``/``load_target``; :mod:`.commands`: ``convert``, ``cases export``;
- :mod:`.dispatch`: ``read``/``write``/``formats`` by the format table, which it gets from
  the registry at call time (:func:`.dispatch.table`);
- :mod:`.formats`: the format table: records by extension, kind and priority, the
  readers' sniffers (``Reader.sniff``) and magic bytes (``Reader.magic``), precedence;
- :mod:`.builtin`: the built-in records, registered through the same hooks as a plugin's
  (``faceretarget_readers``/``faceretarget_writers``);
- the format modules, one per family (:mod:`.meshes`, :mod:`.gltf`, :mod:`.sequences`,
  :mod:`.rigs`, :mod:`.markers`, :mod:`.weights`, :mod:`.bundle`, :mod:`.meshio_formats`),
  on :mod:`._common` and :mod:`._atomic`. A format reading a mesh from another file
  (a folder's frames, ``topology=``) calls :func:`.dispatch.read`.

A file is read by the readers for its extension (``"/"`` for a folder) and, where several
kinds share an extension (``.npz``, ``.csv``, ``.glb``, folders), of the kind ``kind=``
names or the readers' sniffers find inside the file. ``format=`` picks a reader/writer by name.

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

from ._atomic import atomic_dir, atomic_file, atomic_path, is_input, note_input, write_bytes
from .dispatch import formats, kind_of, shadow_note
from .sources import (
    _examples,  # noqa: F401 (the CLI's --source-examples)
    load,
    load_bundle,
    load_source,
    load_target,
    read_feature_lines,
    read_landmarks,
    save,
    save_bundle,
)

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
