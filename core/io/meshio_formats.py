"""Mesh formats read and written through meshio: VTK, VTU, Gmsh, Medit, Abaqus, ...

meshio (https://github.com/nschloe/meshio) reads and writes many simulation mesh
formats. It is used here for the ones faceretarget has no native reader for; OBJ, PLY,
OFF and STL (which meshio reads too) stay with the native readers of
:mod:`faceretarget.io.meshes`, which keep vertex order exactly and stream large files.
Every record has ``priority = -1`` (built-ins have 0), so should a native reader or a
plugin ever claim one of these extensions, it wins and meshio gets only the files it
declines.

meshio is imported on the first read or write of one of these formats, never by
``import faceretarget`` or ``faceretarget list``.

Reading: the file's points become the vertices in file order (none merged, none
dropped); ``triangle`` cells are the triangles, ``quad`` and ``polygon`` cells are
fan-triangulated ``(p0, pk, pk+1)`` as the OBJ reader does. Cells of other types
(volume cells such as ``tetra``, lines, vertices, quadratic elements) are skipped with a
:class:`~faceretarget.errors.FaceRetargetWarning`; a file holding none of the three is a
:class:`~faceretarget.errors.FileFormatError` that names what it holds.

Writing (every format but Nastran): one ``triangle`` cell block, through :func:`faceretarget.io.atomic_file`
(meshio writes into a scratch folder; the result is copied into the atomic temporary),
so a meshio writer never replaces a file without ``force`` or an input of this process.
"""

from __future__ import annotations

import contextlib
import io
import shutil
import tempfile
import warnings
from collections.abc import Callable, Iterable, Iterator
from dataclasses import dataclass, field
from pathlib import Path
from types import ModuleType
from typing import TYPE_CHECKING, Any

import numpy as np
import numpy.typing as npt

from .._types import PathLike
from ..errors import FaceRetargetError, FaceRetargetWarning, FileFormatError
from ..hookspecs import Reader, Writer

if TYPE_CHECKING:
    import meshio

    from ..model import Mesh

__all__ = [
    "MeshioFormat",
    "FORMATS",
    "PRIORITY",
    "meshio_readers",
    "meshio_writers",
    "reader_record",
    "writer_record",
    "read_mesh",
    "write_mesh",
    "surface_triangles",
]

#: precedence of every meshio record: below the built-in readers and writers (0)
PRIORITY = -1

#: cell types that make the surface (others are skipped)
SURFACE_CELLS = ("triangle", "quad", "polygon")

#: how to turn a volume or higher-order mesh into something readable
SURFACE_HINT = (
    "faceretarget reads triangle, quad and polygon cells: extract the boundary surface as linear "
    "triangles (e.g. ParaView 'Extract Surface' then 'Triangulate', or Gmsh with Mesh.ElementOrder = 1 "
    "and only 2D physical groups) and save that"
)

#: parse cost per byte of file (text formats expand to tokens, then to arrays)
PARSE_FACTOR = 32


@dataclass(frozen=True)
class MeshioFormat:
    """One meshio format registered as a faceretarget mesh reader and writer.

    name : registry name (``load(path, format=name)``)
    module : meshio submodule whose ``read(path)`` / ``write(path, mesh, **options)`` is used
    extensions : lower-case single suffixes (faceretarget dispatches on the last suffix only)
    description : one line for ``faceretarget formats``
    write_options : keyword arguments for the meshio writer
    writable : whether a writer is registered too
    magic : byte strings its files start with (``Reader.magic``: names the format in errors)
    """

    name: str
    module: str
    extensions: tuple[str, ...]
    description: str
    write_options: dict = field(default_factory=dict)
    writable: bool = True
    magic: tuple[bytes, ...] = ()


#: the meshio 5.3 formats that read and write triangle surfaces with meshio's own
#: dependencies (no h5py/netCDF4), do not hang on damaged files, and use extensions no
#: native reader claims. Left out: .obj/.ply/.off/.stl (native), .vol.gz/.post.gz/
#: .dato.gz (double suffix), CGNS/H5M/MED/HMF/Exodus (need h5py or netCDF4), MDPA (hangs
#: on truncated files), XDMF (meshio 5.3.5 imports h5py to read or write any XDMF, and
#: its "Binary" data items name other files to read), SU2/UGRID/FLAC3D (writers fail on
#: triangles in meshio 5.3.5),
#: Tecplot (.dat: triangles become degenerate quads), Dolfin XML/WKT/SVG/TetGen.
FORMATS: tuple[MeshioFormat, ...] = (
    MeshioFormat(
        "vtk",
        "vtk",
        (".vtk",),
        "VTK legacy unstructured grid, ASCII or binary (written binary)",
        magic=(b"# vtk DataFile",),
    ),
    MeshioFormat("vtu", "vtu", (".vtu",), "VTK XML unstructured grid (written binary, zlib)"),
    MeshioFormat(
        "gmsh",
        "gmsh",
        (".msh",),
        "Gmsh MSH 2.2/4.0/4.1, ASCII or binary (written 4.1 binary)",
        magic=(b"$MeshFormat",),
    ),
    MeshioFormat(
        "medit",
        "medit",
        (".mesh", ".meshb"),
        "Medit / INRIA mesh, ASCII (.mesh) or binary (.meshb)",
        magic=(b"MeshVersionFormatted",),
    ),
    MeshioFormat("abaqus", "abaqus", (".inp",), "Abaqus input file"),
    # meshio 5.3.5's Nastran writer fails (AssertionError) on many float64 coordinates: read only
    MeshioFormat(
        "nastran",
        "nastran",
        (".bdf", ".fem", ".nas"),
        "Nastran bulk data; read only",
        writable=False,
    ),
    MeshioFormat("avsucd", "avsucd", (".avs",), "AVS-UCD"),
    MeshioFormat("permas", "permas", (".post", ".dato"), "PERMAS"),
    MeshioFormat("netgen", "netgen", (".vol",), "Netgen volume mesh (surface elements)"),
)


# ---------------------------------------------------------------------------------------
# registration (no meshio import here)
# ---------------------------------------------------------------------------------------
def meshio_readers() -> list[Reader]:
    """A mesh reader per format of :data:`FORMATS`."""
    return [reader_record(f) for f in FORMATS]


def meshio_writers() -> list[Writer]:
    """A mesh writer per writable format of :data:`FORMATS`."""
    return [writer_record(f) for f in FORMATS if f.writable]


def reader_record(fmt: MeshioFormat) -> Reader:
    """The registry record reading ``fmt`` through meshio, with ``priority`` :data:`PRIORITY`."""
    return Reader(
        fmt.name,
        "mesh",
        fmt.extensions,
        _reader(fmt),
        f"{fmt.description}; via meshio",
        priority=PRIORITY,
        magic=fmt.magic,
    )


def writer_record(fmt: MeshioFormat) -> Writer:
    """The registry record writing ``fmt`` through meshio, with ``priority`` :data:`PRIORITY`."""
    return Writer(
        fmt.name,
        "mesh",
        fmt.extensions,
        _writer(fmt),
        f"{fmt.description}; via meshio",
        priority=PRIORITY,
    )


def _reader(fmt: MeshioFormat) -> Callable[..., Mesh]:
    def read(path: PathLike, **options: Any) -> Mesh:
        return read_mesh(path, fmt)

    read.__name__ = f"read_{fmt.name}"
    read.__doc__ = f"Read a {fmt.description} file as a Mesh (through meshio)."
    return read


def _writer(fmt: MeshioFormat) -> Callable[..., None]:
    def write(
        mesh: Mesh, path: PathLike, *, force: bool = False, inputs: Iterable = (), **options: Any
    ) -> None:
        write_mesh(mesh, path, fmt, force=force, inputs=inputs)

    write.__name__ = f"write_{fmt.name}"
    write.__doc__ = f"Write a Mesh as {fmt.description} (through meshio, atomic)."
    return write


# ---------------------------------------------------------------------------------------
# meshio, imported on first use
# ---------------------------------------------------------------------------------------
def _meshio_module(fmt: MeshioFormat) -> ModuleType:
    """``meshio.<fmt.module>`` (importing meshio on first use; module names come from :data:`FORMATS`)."""
    try:
        import meshio
    except ImportError as exc:
        raise FileFormatError(
            f"{fmt.name} files are read and written by meshio, which cannot be imported ({exc}); "
            "install it with: pip install 'meshio>=5.3'"
        ) from None
    return getattr(meshio, fmt.module)


@contextlib.contextmanager
def _quiet() -> Iterator[io.StringIO]:
    """Silence what meshio prints (it reports problems on stdout/stderr) and warns."""
    sink = io.StringIO()
    with (
        contextlib.redirect_stdout(sink),
        contextlib.redirect_stderr(sink),
        warnings.catch_warnings(),
    ):
        warnings.simplefilter("ignore")
        yield sink


# ---------------------------------------------------------------------------------------
# reading
# ---------------------------------------------------------------------------------------
def read_mesh(path: PathLike, fmt: MeshioFormat) -> Mesh:
    """A :class:`~faceretarget.model.Mesh` from a meshio-format file.

    Vertices ``(V, 3)`` are the file's points in order (2D points get ``z = 0``);
    triangles ``(T, 3)`` come from triangle, quad and polygon cells (quads and polygons
    fan-triangulated). Other cells are skipped with a FaceRetargetWarning.
    """
    mesh, skipped = _read_guarded(Path(path), fmt=fmt)
    if skipped:
        warnings.warn(
            f"{path}: skipped {skipped} (not surface cells); {SURFACE_HINT}",
            FaceRetargetWarning,
            stacklevel=3,
        )
    return mesh


def _read_guarded(path: Path, *, fmt: MeshioFormat) -> tuple[Mesh, str]:
    from ._common import guarded_reader

    return guarded_reader(_read_checked)(path, fmt=fmt)


def _read_checked(path: Path, *, fmt: MeshioFormat) -> tuple[Mesh, str]:
    """``(Mesh, description of skipped cells or "")``; every failure a typed error."""
    from ._common import check_budget
    from .meshes import _checked_arrays, _mesh

    check_budget(path, path.stat().st_size * float(PARSE_FACTOR), f"parsing this {fmt.name} file")
    data = _meshio_read(path, fmt)
    vertices = _vertices(path, data.points)
    triangles, n_faces, skipped = surface_triangles(data.cells)
    if n_faces == 0:
        raise _no_surface_error(path, fmt, data)
    vertices, triangles = _checked_arrays(path, vertices, triangles, n_faces)
    return _mesh(path, vertices, triangles), skipped


def _meshio_read(path: Path, fmt: MeshioFormat) -> meshio.Mesh:
    """meshio's ``Mesh`` of ``path`` (meshio's own read() would ``sys.exit`` on a bad file)."""
    module = _meshio_module(fmt)
    from meshio import ReadError

    with _quiet() as said:
        try:
            return module.read(str(path))
        except ModuleNotFoundError as exc:  # e.g. HDF5 data in an XDMF file needs h5py
            raise FileFormatError(
                f"{path}: meshio needs the '{exc.name}' package to read this {fmt.name} file; "
                f"install it (pip install {exc.name}) or re-export the file with its data inline"
            ) from None
        except (MemoryError, RecursionError, FaceRetargetError):
            raise  # guarded_reader types them
        except ReadError as exc:
            raise _read_error(path, fmt, str(exc) or said.getvalue() or "ReadError") from None
        except Exception as exc:  # meshio's parsers raise anything on a damaged file
            raise _read_error(path, fmt, f"{type(exc).__name__}: {exc}") from None


def _read_error(path: Path, fmt: MeshioFormat, detail: str) -> FileFormatError:
    """The error for a file meshio refuses, saying what it looks like when that is known."""
    from ._common import sniff

    found = sniff(path)
    looks = (
        f"; it looks like {found[1]}"
        if found is not None and found[0] not in ("text", "xml")
        else ""
    )
    first = detail.strip().splitlines()[0][:200]
    return FileFormatError(f"{path}: not a readable {fmt.name} file (meshio: {first}){looks}")


def _vertices(path: Path, points: npt.ArrayLike) -> np.ndarray:
    """``(V, 3)`` float64 vertices of meshio's ``(V, 2)`` or ``(V, 3)`` points."""
    from ._common import bad

    pts = np.asarray(points)
    if pts.ndim != 2 or pts.shape[1] not in (2, 3) or pts.dtype.kind not in "fiu":
        raise bad(
            path, f"points of shape {pts.shape} ({pts.dtype}); expected (V, 3) or (V, 2) numbers"
        )
    pts = pts.astype(np.float64)
    if pts.shape[1] == 2:
        pts = np.concatenate([pts, np.zeros((pts.shape[0], 1))], axis=1)
    return pts


def surface_triangles(cells: Iterable[meshio.CellBlock]) -> tuple[np.ndarray, int, str]:
    """Triangles ``(T, 3)`` of meshio cell blocks, the number of faces they came from,
    and a description of the blocks skipped (``"12 tetra, 4 line cells"`` or ``""``).

    ``triangle`` blocks are taken as they are; ``quad`` and ``polygon`` blocks
    ``(n, k)`` are fan-triangulated ``(p0, pj, pj+1)``, in block order.
    """
    from .meshes import _polygons_to_triangles

    parts: list[np.ndarray] = []
    n_faces = 0
    skipped: dict[str, int] = {}
    for block in cells:
        data = np.asarray(block.data)
        if block.type not in SURFACE_CELLS or data.ndim != 2 or data.shape[1] < 3:
            skipped[block.type] = skipped.get(block.type, 0) + len(data)
            continue
        ids = data.astype(np.int64)
        sizes = np.full(ids.shape[0], ids.shape[1], dtype=np.int64)
        parts.append(_polygons_to_triangles(ids.ravel(), sizes))
        n_faces += ids.shape[0]
    triangles = np.concatenate(parts) if parts else np.zeros((0, 3), dtype=np.int64)
    return triangles, n_faces, _cell_summary(skipped)


def _cell_summary(counts: dict[str, int]) -> str:
    return ", ".join(f"{n} {kind}" for kind, n in counts.items()) + (" cells" if counts else "")


def _no_surface_error(path: Path, fmt: MeshioFormat, data: meshio.Mesh) -> FileFormatError:
    """The error for a file with no triangle, quad or polygon cells: what it holds and what to do."""
    counts: dict[str, int] = {}
    for block in data.cells:
        counts[block.type] = counts.get(block.type, 0) + len(block.data)
    holds = _cell_summary(counts) or "no cells at all (a point cloud)"
    return FileFormatError(
        f"{path}: this {fmt.name} file has {len(data.points)} points and {holds}, no surface to read; {SURFACE_HINT}"
    )


# ---------------------------------------------------------------------------------------
# writing
# ---------------------------------------------------------------------------------------
def write_mesh(
    mesh: Mesh, path: PathLike, fmt: MeshioFormat, *, force: bool = False, inputs: Iterable = ()
) -> None:
    """Write a :class:`~faceretarget.model.Mesh` ``(V, 3)`` / ``(T, 3)`` as one triangle
    cell block, atomically (never over an input, nor over a file without ``force``)."""
    from ._atomic import atomic_file
    from .meshes import _as_mesh

    mesh = _as_mesh(mesh, f"the {fmt.name} writer")
    module = _meshio_module(fmt)
    import meshio

    data = meshio.Mesh(
        np.asarray(mesh.vertices, dtype=np.float64),
        [("triangle", np.asarray(mesh.triangles, dtype=np.int64))],
    )
    suffix = (
        Path(path).suffix.lower()
        if Path(path).suffix.lower() in fmt.extensions
        else fmt.extensions[0]
    )
    with (
        atomic_file(path, inputs=inputs, force=force) as fh,
        tempfile.TemporaryDirectory(prefix="faceretarget-meshio-") as scratch,
    ):
        made = Path(scratch) / f"mesh{suffix}"
        _meshio_write(module, made, data, fmt, Path(path))
        with open(made, "rb") as src:
            shutil.copyfileobj(src, fh)


def _meshio_write(
    module: ModuleType, made: Path, data: meshio.Mesh, fmt: MeshioFormat, dest: Path
) -> None:
    """meshio's writer into scratch file ``made``; its failures become an OutputError."""
    from ..errors import OutputError

    with _quiet() as said:
        try:
            module.write(str(made), data, **fmt.write_options)
        except MemoryError:
            raise
        except Exception as exc:
            detail = (str(exc) or said.getvalue() or "").strip().splitlines()
            raise OutputError(
                f"{dest}: meshio could not write this mesh as {fmt.name} ({type(exc).__name__}"
                f"{': ' + detail[0][:200] if detail else ''}); nothing was written; save it as .obj, .ply or .vtu instead"
            ) from None
