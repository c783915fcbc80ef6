"""Mesh formats read and written through meshio (faceretarget.io.meshio_formats).

Checked: every writable format round-trips a mesh exactly through ``faceretarget.io``
save/load; the read-only one (Nastran) reads files made elsewhere; quads and
polygons are fan-triangulated exactly as the native OBJ reader does; the native readers
keep precedence (a meshio record for ``.obj`` loses to the built-in OBJ reader); meshio
is not imported by ``import faceretarget``, ``faceretarget list`` or ``formats``; a file
with no surface cells is a typed error saying what it holds and what to do; the writers
go through the atomic, input-safe writer; ``faceretarget formats`` says "via meshio".
"""

import subprocess
import sys
import types

import numpy as np
import pytest

import faceretarget.io as fio
from faceretarget import cli, hookimpl
from faceretarget import registry as registry_module
from faceretarget.errors import (
    FaceRetargetError,
    FaceRetargetWarning,
    FileFormatError,
    OutputError,
)
from faceretarget.io import builtin
from faceretarget.io import meshio_formats as mf
from faceretarget.model import Mesh

meshio = pytest.importorskip("meshio")

WRITABLE = [(f.name, ext) for f in mf.FORMATS if f.writable for ext in f.extensions]
READ_ONLY = [f.name for f in mf.FORMATS if not f.writable]


def _native_readers():
    return [r for r in builtin.builtin_readers() if r.priority == 0]


# ---------------------------------------------------------------------------------------
# the format table
# ---------------------------------------------------------------------------------------
def test_the_table_names_meshio_formats_the_native_readers_do_not_claim():
    from meshio._helpers import extension_to_filetypes

    native = {e for r in _native_readers() for e in r.extensions}
    for fmt in mf.FORMATS:
        for ext in fmt.extensions:
            assert fmt.module in extension_to_filetypes.get(ext, []) or ext == ".msh", (
                fmt.name,
                ext,
            )
            assert ext not in native, f"{ext} is read natively; meshio must not claim it"
    assert "gmsh" in extension_to_filetypes[".msh"]


def test_meshio_records_rank_below_the_native_ones():
    rows = [r for r in fio.formats() if r["description"].endswith("via meshio")]
    assert {r["name"] for r in rows if r["direction"] == "read"} == {f.name for f in mf.FORMATS}
    assert {r["name"] for r in rows if r["direction"] == "write"} == {
        f.name for f in mf.FORMATS if f.writable
    }
    assert all(r["priority"] < 0 and r["kind"] == "mesh" for r in rows)
    assert not any(r["shadowed_by"] or r["shadows"] for r in rows)


# ---------------------------------------------------------------------------------------
# round trips
# ---------------------------------------------------------------------------------------
@pytest.mark.parametrize("name, ext", WRITABLE, ids=[f"{n}{e}" for n, e in WRITABLE])
def test_round_trip_through_save_and_load_is_exact(name, ext, mesh, tmp_path):
    path = tmp_path / f"patch{ext}"
    assert fio.save(mesh, path) == path
    back = fio.load(path)
    assert isinstance(back, Mesh)
    np.testing.assert_array_equal(back.vertices, mesh.vertices)  # float64, bit for bit
    np.testing.assert_array_equal(back.triangles, mesh.triangles)
    assert back.name == "patch"
    again = fio.load(path, kind="mesh", format=name)
    np.testing.assert_array_equal(again.vertices, mesh.vertices)
    assert sorted(p.name for p in tmp_path.iterdir()) == [path.name]  # no temporaries left


@pytest.mark.parametrize("name, ext", WRITABLE, ids=[f"{n}{e}" for n, e in WRITABLE])
def test_files_written_are_what_meshio_reads(name, ext, mesh, tmp_path):
    path = tmp_path / f"patch{ext}"
    fio.save(mesh, path)
    theirs = meshio.read(
        path, file_format=mf.FORMATS[[f.name for f in mf.FORMATS].index(name)].module
    )
    assert [c.type for c in theirs.cells] == ["triangle"]
    np.testing.assert_array_equal(theirs.cells[0].data, mesh.triangles)


def test_convert_reads_vtu_and_writes_gmsh(mesh, tmp_path, capsys):
    src, out = tmp_path / "in.vtu", tmp_path / "out.msh"
    fio.save(mesh, src)
    assert cli.main(["convert", str(src), str(out)]) == 0
    np.testing.assert_array_equal(fio.load(out).vertices, mesh.vertices)


def test_read_only_formats_have_no_writer(mesh, tmp_path):
    assert READ_ONLY == ["nastran"]  # meshio 5.3.5's Nastran writer fails on float64 coordinates
    with pytest.raises(FileFormatError, match="no writer for '.bdf'"):
        fio.save(mesh, tmp_path / "m.bdf")


def test_nastran_written_by_meshio_is_read(tmp_path):
    points = np.array([[0.0, 0, 0], [1, 0, 0], [1, 1, 0], [0, 1, 0]])
    path = tmp_path / "plate.bdf"
    meshio.write(path, meshio.Mesh(points, [("triangle", np.array([[0, 1, 2], [0, 2, 3]]))]))
    mesh = fio.load(path)
    np.testing.assert_array_equal(mesh.vertices, points)
    np.testing.assert_array_equal(mesh.triangles, [[0, 1, 2], [0, 2, 3]])


def test_quads_and_polygons_are_fan_triangulated_like_obj(tmp_path):
    points = np.array(
        [
            [0.0, 0, 0],
            [1, 0, 0],
            [2, 0, 0],
            [2, 1, 0],
            [1, 1, 0],
            [0, 1, 0],
            [1, 2, 0],
            [0.5, 2.5, 0],
        ]
    )
    quads = np.array([[0, 1, 4, 5], [1, 2, 3, 4]])
    pentagon = np.array([[5, 4, 3, 6, 7]])
    vtk = tmp_path / "faces.vtk"
    meshio.write(vtk, meshio.Mesh(points, [("quad", quads), ("polygon", pentagon)]), binary=False)
    obj = tmp_path / "faces.obj"
    lines = [f"v {x!r} {y!r} {z!r}" for x, y, z in points.tolist()]
    lines += [
        "f " + " ".join(str(i + 1) for i in face) for face in [*quads.tolist(), *pentagon.tolist()]
    ]
    obj.write_text("\n".join(lines) + "\n")
    ours, native = fio.load(vtk), fio.load(obj)
    np.testing.assert_array_equal(ours.vertices, native.vertices)
    np.testing.assert_array_equal(ours.triangles, native.triangles)
    assert ours.triangles.tolist()[:2] == [[0, 1, 4], [0, 4, 5]]


def test_points_of_a_2d_mesh_get_z_zero(tmp_path):
    path = tmp_path / "flat.vtu"
    meshio.write(
        path,
        meshio.Mesh(np.array([[0.0, 0], [1, 0], [0, 1]]), [("triangle", np.array([[0, 1, 2]]))]),
    )
    np.testing.assert_array_equal(fio.load(path).vertices, [[0, 0, 0], [1, 0, 0], [0, 1, 0]])


# ---------------------------------------------------------------------------------------
# files without a surface, damaged files
# ---------------------------------------------------------------------------------------
def test_a_volume_only_file_is_a_typed_error_saying_what_it_holds(tmp_path):
    path = tmp_path / "solid.vtu"
    meshio.write(
        path,
        meshio.Mesh(
            np.eye(4, 3),
            [("tetra", np.array([[0, 1, 2, 3]])), ("line", np.array([[0, 1], [1, 2]]))],
        ),
    )
    with pytest.raises(FileFormatError) as info:
        fio.load(path)
    message = str(info.value)
    assert isinstance(info.value, FaceRetargetError)
    assert message.startswith(str(path))
    assert "1 tetra, 2 line cells" in message and "no surface" in message
    assert "Extract Surface" in message  # what to do


def test_a_point_cloud_is_refused(tmp_path):
    path = tmp_path / "cloud.msh"
    meshio.write(
        path, meshio.Mesh(np.eye(3), [("vertex", np.array([[0], [1], [2]]))]), file_format="gmsh"
    )
    with pytest.raises(FileFormatError, match="3 vertex cells, no surface"):
        fio.load(path)


def test_surface_cells_are_kept_and_volume_cells_skipped_with_a_warning(tmp_path):
    path = tmp_path / "mixed.vtk"
    points = np.array([[0.0, 0, 0], [1, 0, 0], [0, 1, 0], [0, 0, 1]])
    meshio.write(
        path,
        meshio.Mesh(
            points, [("tetra", np.array([[0, 1, 2, 3]])), ("triangle", np.array([[0, 2, 1]]))]
        ),
    )
    with pytest.warns(FaceRetargetWarning, match="skipped 1 tetra cells"):
        mesh = fio.load(path)
    np.testing.assert_array_equal(mesh.vertices, points)  # every point kept, in file order
    np.testing.assert_array_equal(mesh.triangles, [[0, 2, 1]])


def test_a_damaged_file_is_a_typed_error_naming_it_not_an_exit(tmp_path):
    path = tmp_path / "photo.msh"
    path.write_bytes(b"\x89PNG\r\n\x1a\n" + bytes(200))
    with pytest.raises(
        FileFormatError, match="photo.msh: this looks like a PNG image, not a Gmsh mesh"
    ):
        fio.load(path)  # meshio.read() itself would sys.exit(1)
    photo = (
        tmp_path / "photo.inp"
    )  # an extension without an expected content: meshio's own error, and what it looks like
    photo.write_bytes(b"\x89PNG\r\n\x1a\n" + bytes(200))
    with pytest.raises(
        FileFormatError, match="photo.inp: not a readable abaqus file.*looks like a PNG image"
    ):
        fio.load(photo)
    empty = tmp_path / "empty.vtk"
    empty.write_bytes(b"")
    with pytest.raises(FileFormatError, match="empty.vtk"):
        fio.load(empty)


def test_the_memory_budget_is_checked_before_parsing(mesh, tmp_path, monkeypatch):
    from faceretarget.errors import ResourceLimitError

    path = tmp_path / "m.mesh"
    fio.save(mesh, path)
    monkeypatch.setenv("FACERETARGET_MEMORY_BUDGET", "512")
    with pytest.raises(ResourceLimitError, match="FACERETARGET_MEMORY_BUDGET"):
        fio.load(path)


# ---------------------------------------------------------------------------------------
# writing: atomic, never over an input or an existing file without force
# ---------------------------------------------------------------------------------------
def test_writers_never_overwrite_without_force(mesh, tmp_path):
    path = tmp_path / "m.vtu"
    fio.save(mesh, path)
    before = path.read_bytes()
    moved = Mesh(mesh.vertices + 1, mesh.triangles)
    with pytest.raises(OutputError, match="already exists"):
        fio.save(moved, path)
    assert path.read_bytes() == before
    writer = next(w for w in builtin.builtin_writers() if w.name == "vtu")
    with pytest.raises(OutputError, match="already exists"):
        writer.write(moved, path)  # called directly, without save(): still atomic and checked
    assert path.read_bytes() == before
    fio.save(moved, path, force=True)
    np.testing.assert_array_equal(fio.load(path).vertices, moved.vertices)
    assert sorted(p.name for p in tmp_path.iterdir()) == ["m.vtu"]


def test_writers_never_replace_an_input(mesh, tmp_path):
    path = tmp_path / "in.msh"
    fio.save(mesh, path)
    fio.load(path)
    with pytest.raises(OutputError, match="input"):
        fio.save(mesh, path, force=True)


def test_a_failing_meshio_writer_is_an_output_error_and_writes_nothing(mesh, tmp_path, monkeypatch):
    def broken(*args, **kwargs):
        raise AssertionError("field too wide")

    monkeypatch.setattr(meshio.vtk, "write", broken)
    with pytest.raises(
        OutputError, match="meshio could not write this mesh as vtk.*AssertionError: field too wide"
    ):
        fio.save(mesh, tmp_path / "m.vtk")
    assert list(tmp_path.iterdir()) == []


# ---------------------------------------------------------------------------------------
# precedence: the native readers win
# ---------------------------------------------------------------------------------------
def _meshio_obj_plugin():
    """A plugin registering meshio's OBJ reader/writer with the meshio records' priority."""
    fmt = mf.MeshioFormat("meshio-obj", "obj", (".obj",), "OBJ through meshio")
    module = types.ModuleType("meshioobj")
    module.faceretarget_readers = hookimpl(lambda: [mf.reader_record(fmt)])
    module.faceretarget_writers = hookimpl(lambda: [mf.writer_record(fmt)])
    return module


def test_a_native_format_goes_to_the_native_reader_though_meshio_reads_it(tmp_path, monkeypatch):
    reg = registry_module.Registry().load(extra=[("meshioobj", _meshio_obj_plugin())])
    monkeypatch.setattr(registry_module, "_REGISTRY", reg)

    def meshio_used(*args, **kwargs):
        raise AssertionError("meshio read a file a native reader claims")

    monkeypatch.setattr(mf, "_meshio_read", meshio_used)
    monkeypatch.setattr(mf, "write_mesh", meshio_used)
    path = tmp_path / "tri.obj"
    path.write_text("v 0 0 0\nv 1 0 0\nv 0 1 0\nf 1 2 3\n")
    assert fio.load(path).n_triangles == 1
    fio.save(Mesh([[0.0, 0, 0], [1, 0, 0], [0, 1, 0]], [[0, 1, 2]]), tmp_path / "out.obj")
    rows = {(r["direction"], r["name"]): r for r in fio.formats()}
    assert rows[("read", "meshio-obj")]["shadowed_by"] == {".obj": "obj"}
    assert rows[("write", "meshio-obj")]["shadowed_by"] == {".obj": "obj"}


# ---------------------------------------------------------------------------------------
# meshio is imported lazily
# ---------------------------------------------------------------------------------------
LAZY = """
import sys
import faceretarget, faceretarget.io
from faceretarget import cli
assert "meshio" not in sys.modules, "import faceretarget imported meshio"
for argv in (["list"], ["formats"]):
    assert cli.main(argv) == 0
    assert "meshio" not in sys.modules, f"faceretarget {argv[0]} imported meshio"
path = sys.argv[1]
open(path, "w").write("v 0 0 0\\nv 1 0 0\\nv 0 1 0\\nf 1 2 3\\n")
faceretarget.io.load(path)
assert "meshio" not in sys.modules, "reading an OBJ imported meshio"
faceretarget.io.save(faceretarget.io.load(path), path[:-4] + ".vtu")
assert "meshio" in sys.modules
print("lazy ok")
"""


def test_meshio_is_imported_only_when_one_of_its_formats_is_used(tmp_path):
    done = subprocess.run(
        [sys.executable, "-c", LAZY, str(tmp_path / "t.obj")],
        capture_output=True,
        text=True,
        timeout=300,
        cwd=tmp_path,
    )
    assert done.returncode == 0, done.stderr[-2000:]
    assert "lazy ok" in done.stdout


def test_faceretarget_formats_says_which_formats_come_from_meshio(capsys):
    assert cli.main(["formats"]) == 0
    out = capsys.readouterr().out
    for name in ("vtk", "vtu", "gmsh", "medit", "abaqus"):
        line = next(ln for ln in out.splitlines() if ln.split()[:1] == [name])
        assert line.rstrip().endswith("via meshio [priority -1]"), (
            line
        )  # below the native formats, and says so
