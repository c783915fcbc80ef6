"""The built-in formats, registered through the plugin hooks like any plugin's.

This module is the ``builtin_io`` entry point: its ``faceretarget_readers`` and
``faceretarget_writers`` hooks return the records of the native formats (one module per
format family: :mod:`.meshes`, :mod:`.gltf`, :mod:`.sequences`, :mod:`.rigs`,
:mod:`.markers`, :mod:`.weights`, :mod:`.bundle`) and of :mod:`.meshio_formats` (priority
-1, below the native ones). Nothing here is special to the dispatcher: where several kinds
share an extension, each reader declares the sniffer that tells them apart
(``Reader.sniff``, one shared object per family) and the magic bytes of its files
(``Reader.magic``), exactly as a third-party plugin would.

Format modules are imported on first use (``_lazy``), so registering costs no parsing code.
"""

from __future__ import annotations

from collections.abc import Callable
from pathlib import Path
from typing import Any

from ..hookspecs import DATA_KINDS, Reader, Writer, hookimpl

__all__ = ["builtin_readers", "builtin_writers", "faceretarget_readers", "faceretarget_writers"]

_GLTF_EXT = (".glb", ".gltf")


def _lazy(module: str, name: str) -> Callable[..., Any]:
    """A callable importing ``faceretarget.io.<module>.<name>`` on first call."""

    def call(*args: Any, **kwargs: Any) -> Any:
        from importlib import import_module

        return getattr(import_module(f"{__package__}.{module}"), name)(*args, **kwargs)

    call.__name__ = call.__qualname__ = name
    call.__doc__ = f"faceretarget.io.{module}.{name}"
    return call


def _npz_reader(kind: str) -> Callable[..., Any]:
    def read(path: Path, **options: Any) -> Any:
        from .bundle import read_npz_object

        return read_npz_object(path, kind=kind, **options)

    read.__name__ = f"read_npz_{kind}"
    return read


# The sniffers: one object per format family whose readers differ in kind (asked once per file).
SNIFF_FOLDER = _lazy("rigs", "folder_kind")  # rig.json or a neutral mesh -> rig, else sequence
SNIFF_GLTF = _lazy("gltf", "gltf_kind")  # stored kind, weight animation, morph targets, mesh
SNIFF_NPZ = _lazy("bundle", "npz_kind")  # stored kind, else guessed from the array names
SNIFF_CSV = _lazy("markers", "csv_kind")  # NAME_x/_y/_z columns -> markers, else weights

GLB = (b"glTF",)  # gltf.GLB_MAGIC
PLY = (b"ply\n", b"ply\r\n")
NPY = (b"\x93NUMPY",)


def builtin_readers() -> list[Reader]:
    """The readers of this package: the native formats, then meshio's."""
    from .meshio_formats import meshio_readers  # records only; meshio is imported on use

    mesh, seq, rig, animation = "mesh", "mesh_sequence", "rig", "animation"
    readers = [
        Reader(
            "obj",
            mesh,
            (".obj",),
            _lazy("meshes", "read_obj"),
            "Wavefront OBJ (vertex order kept, n-gons fan-triangulated)",
        ),
        Reader(
            "ply", mesh, (".ply",), _lazy("meshes", "read_ply"), "PLY, ASCII or binary", magic=PLY
        ),
        Reader(
            "off",
            mesh,
            (".off",),
            _lazy("meshes", "read_off"),
            "OFF",
            magic=(b"OFF\n", b"OFF\r\n", b"OFF "),
        ),
        Reader(
            "stl",
            mesh,
            (".stl",),
            _lazy("meshes", "read_stl"),
            "STL, binary or ASCII (identical corners joined)",
        ),
        Reader(
            "gltf-mesh",
            mesh,
            _GLTF_EXT,
            _lazy("gltf", "read_gltf_mesh"),
            "glTF/GLB mesh (primitives joined)",
            sniff=SNIFF_GLTF,
            magic=GLB,
        ),
        Reader(
            "npz-mesh",
            mesh,
            (".npz",),
            _npz_reader(mesh),
            "faceretarget npz (or vertices + triangles)",
            sniff=SNIFF_NPZ,
        ),
        Reader(
            "mesh-folder",
            seq,
            ("/",),
            _lazy("sequences", "read_mesh_folder"),
            "folder of per-frame meshes (natural order)",
            sniff=SNIFF_FOLDER,
        ),
        Reader(
            "npy",
            seq,
            (".npy",),
            _lazy("sequences", "read_npy_sequence"),
            "(F, V, 3) array, memory-mapped; topology= gives triangles",
            magic=NPY,
        ),
        Reader(
            "npz-sequence",
            seq,
            (".npz",),
            _npz_reader(seq),
            "faceretarget npz (or vertices (F, V, 3) + triangles)",
            sniff=SNIFF_NPZ,
        ),
        Reader(
            "pc2",
            seq,
            (".pc2",),
            _lazy("sequences", "read_pc2"),
            "PC2 point cache, memory-mapped; topology= gives triangles",
            magic=(b"POINTCACHE2\x00",),
        ),
        Reader(
            "mdd",
            seq,
            (".mdd",),
            _lazy("sequences", "read_mdd"),
            "MDD point cache (big-endian), memory-mapped",
        ),
        Reader(
            "gltf-sequence",
            seq,
            _GLTF_EXT,
            _lazy("gltf", "read_gltf_sequence"),
            "glTF animation as per-frame vertices",
            sniff=SNIFF_GLTF,
            magic=GLB,
        ),
        Reader(
            "rig-folder",
            rig,
            ("/",),
            _lazy("rigs", "read_rig_folder"),
            "folder: neutral mesh + one mesh per blendshape",
            sniff=SNIFF_FOLDER,
        ),
        Reader(
            "gltf-rig",
            rig,
            _GLTF_EXT,
            _lazy("gltf", "read_gltf_rig"),
            "glTF/GLB morph targets, names from extras.targetNames",
            sniff=SNIFF_GLTF,
            magic=GLB,
        ),
        Reader(
            "npz-rig",
            rig,
            (".npz",),
            _npz_reader(rig),
            "faceretarget npz (or neutral + deltas + names + faces)",
            sniff=SNIFF_NPZ,
        ),
        Reader(
            "c3d",
            "markers",
            (".c3d",),
            _lazy("markers", "read_c3d"),
            "C3D motion capture (c3d package)",
        ),
        Reader(
            "trc",
            "markers",
            (".trc",),
            _lazy("markers", "read_trc"),
            "TRC marker trajectories",
            magic=(b"PathFileType",),
        ),
        Reader(
            "csv-markers",
            "markers",
            (".csv",),
            _lazy("markers", "read_marker_csv"),
            "CSV with NAME_x, NAME_y, NAME_z columns",
            sniff=SNIFF_CSV,
        ),
        Reader(
            "npz-markers",
            "markers",
            (".npz",),
            _npz_reader("markers"),
            "faceretarget npz (or positions + names)",
            sniff=SNIFF_NPZ,
        ),
        Reader(
            "csv-weights",
            "weights",
            (".csv",),
            _lazy("weights", "read_weights_csv"),
            "weight curves CSV (Live Link Face or frame,name... layout)",
            sniff=SNIFF_CSV,
        ),
        Reader(
            "npz-weights",
            "weights",
            (".npz",),
            _npz_reader("weights"),
            "faceretarget npz (or weights + names)",
            sniff=SNIFF_NPZ,
        ),
        Reader(
            "gltf-animation",
            animation,
            _GLTF_EXT,
            _lazy("gltf", "read_gltf_animation"),
            "glTF morph-weight animation or per-frame meshes",
            sniff=SNIFF_GLTF,
            magic=GLB,
        ),
        Reader(
            "npz-animation",
            animation,
            (".npz",),
            _npz_reader(animation),
            "faceretarget npz animation",
            sniff=SNIFF_NPZ,
        ),
    ]
    return readers + meshio_readers()


def builtin_writers() -> list[Writer]:
    """The writers of this package: the native formats, then meshio's."""
    from .meshio_formats import meshio_writers  # records only; meshio is imported on use

    npz = _lazy("bundle", "write_npz")
    gltf = _lazy("gltf", "write_gltf")
    return [
        Writer(
            "obj", "mesh", (".obj",), _lazy("meshes", "write_obj"), "Wavefront OBJ, exact decimals"
        ),
        Writer("ply", "mesh", (".ply",), _lazy("meshes", "write_ply"), "binary PLY, float64"),
        Writer("off", "mesh", (".off",), _lazy("meshes", "write_off"), "OFF, exact decimals"),
        Writer("stl", "mesh", (".stl",), _lazy("meshes", "write_stl"), "binary STL, float32"),
        Writer("gltf-mesh", "mesh", _GLTF_EXT, gltf, "glTF/GLB mesh"),
        Writer(
            "gltf-rig", "rig", _GLTF_EXT, gltf, "glTF/GLB morph targets with extras.targetNames"
        ),
        Writer(
            "gltf-animation",
            "animation",
            _GLTF_EXT,
            gltf,
            "glTF/GLB: morph targets + weight animation, or one node per frame",
        ),
        Writer(
            "gltf-sequence",
            "mesh_sequence",
            _GLTF_EXT,
            gltf,
            "glTF/GLB: one node per frame with STEP visibility",
        ),
        Writer(
            "obj-sequence",
            "mesh_sequence",
            ("/",),
            _lazy("sequences", "write_obj_sequence"),
            "folder of OBJ frames + sequence.json",
        ),
        Writer(
            "rig-folder",
            "rig",
            ("/",),
            _lazy("rigs", "write_rig_folder"),
            "folder: neutral.obj + one OBJ per shape + rig.json",
        ),
        Writer(
            "pc2",
            "mesh_sequence",
            (".pc2",),
            _lazy("sequences", "write_pc2"),
            "PC2 point cache (float32)",
        ),
        Writer(
            "mdd",
            "mesh_sequence",
            (".mdd",),
            _lazy("sequences", "write_mdd"),
            "MDD point cache (big-endian float32)",
        ),
        Writer(
            "npy",
            "mesh_sequence",
            (".npy",),
            _lazy("sequences", "write_npy"),
            "(F, V, 3) vertices only",
        ),
        Writer("c3d", "markers", (".c3d",), _lazy("markers", "write_c3d"), "C3D (float32)"),
        Writer("trc", "markers", (".trc",), _lazy("markers", "write_trc"), "TRC, exact decimals"),
        Writer(
            "csv-markers",
            "markers",
            (".csv",),
            _lazy("markers", "write_marker_csv"),
            "CSV frame,time,NAME_x,NAME_y,NAME_z",
        ),
        Writer(
            "csv-weights",
            "weights",
            (".csv",),
            _lazy("weights", "write_weights_csv"),
            "Live Link Face CSV layout",
        ),
        *(
            Writer(
                f"npz-{kind.replace('mesh_', '')}", kind, (".npz",), npz, "faceretarget npz (exact)"
            )
            for kind in DATA_KINDS
        ),
    ] + meshio_writers()


@hookimpl
def faceretarget_readers() -> list[Reader]:
    return builtin_readers()


@hookimpl
def faceretarget_writers() -> list[Writer]:
    return builtin_writers()
