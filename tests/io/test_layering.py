"""IO is layered: a format table filled by the hooks, dispatch above it, the registry above both.

- no ``faceretarget.io`` module imports ``faceretarget.registry`` (checked in a fresh
  interpreter, and in the source for imports inside functions): only the dispatcher's
  :func:`faceretarget.io.dispatch.table` reaches it, at call time;
- the built-in formats are registered by :mod:`faceretarget.io.builtin` through the same
  hooks as a plugin's, and the dispatcher knows none of them: which kind an ambiguous file
  holds comes from the sniffers the readers declare (``Reader.sniff``), and "this file
  is actually X" from their magic bytes (``Reader.magic``), a plugin's exactly as a built-in's;
- the records are checked at registration (messages name the plugin and the hook);
- ``faceretarget formats`` shows the priority of built-ins that have one.
"""

from __future__ import annotations

import ast
import dataclasses
import re
import subprocess
import sys
import textwrap
import types
from pathlib import Path

import numpy as np
import pytest

import faceretarget as fr
import faceretarget.registry as registry_module
from faceretarget import Reader, hookimpl
from faceretarget.errors import FileFormatError, FormatMismatchError, PluginLoadError
from faceretarget.io import builtin, dispatch
from faceretarget.io.formats import FormatTable
from faceretarget.model import MarkerSequence, Mesh, WeightSequence

IO_DIR = Path(dispatch.__file__).parent
IO_MODULES = sorted(p.stem for p in IO_DIR.glob("*.py") if p.stem != "__init__")

#: io modules that may name the registry, and why
MAY_IMPORT_REGISTRY = {
    "dispatch": "table(): the one way io reaches the registry, at call time",
    "commands": "`cases export` lists the retargeters that apply to a case (a command, above the registry)",
}


def test_no_io_module_imports_the_registry():
    modules = ["faceretarget.io"] + [f"faceretarget.io.{m}" for m in IO_MODULES]
    code = textwrap.dedent(f"""
        import importlib, sys
        for name in {modules!r}:
            importlib.import_module(name)
            if "faceretarget.registry" in sys.modules:
                print("IMPORTED-BY", name)
                break
    """)
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=120)
    assert out.returncode == 0, out.stderr
    assert "IMPORTED-BY" not in out.stdout, (
        f"importing {out.stdout.split()[-1]} imports faceretarget.registry"
    )


def _registry_imports(path: Path) -> list[int]:
    """Lines of ``path`` importing faceretarget.registry (at any depth: lazy imports too)."""
    lines = []
    for node in ast.walk(ast.parse(path.read_text(encoding="utf-8"))):
        if isinstance(node, ast.ImportFrom):
            names = [node.module or ""] + [f"{node.module or ''}.{a.name}" for a in node.names]
            if any(n.split(".")[-1] == "registry" or n.endswith(".registry") for n in names if n):
                lines.append(node.lineno)
        elif isinstance(node, ast.Import) and any(a.name.endswith(".registry") for a in node.names):
            lines.append(node.lineno)
    return lines


def test_only_the_dispatcher_reaches_the_registry():
    offenders = {
        m: _registry_imports(IO_DIR / f"{m}.py")
        for m in ["__init__", *IO_MODULES]
        if m not in MAY_IMPORT_REGISTRY
    }
    assert not {m: ln for m, ln in offenders.items() if ln}, (
        "io modules importing the registry (use dispatch.table())"
    )
    assert _registry_imports(IO_DIR / "dispatch.py"), (
        "the dispatcher gets its table from the registry"
    )


def test_the_builtin_formats_are_a_plugin_like_any_other():
    import importlib.metadata as md

    (ep,) = [ep for ep in md.entry_points(group="faceretarget") if ep.name == "builtin_io"]
    assert ep.value == "faceretarget.io.builtin"
    reg = registry_module.registry()
    assert {r.name for r, info in reg.readers if info.name == "builtin_io"} == {
        r.name for r in builtin.builtin_readers()
    }
    import faceretarget.io as fio

    assert not hasattr(fio, "faceretarget_readers") and not hasattr(fio, "faceretarget_writers")


# ---------------------------------------------------------------------------------------
# the dispatcher chooses by what the records declare
# ---------------------------------------------------------------------------------------
def _builtin_table(change) -> FormatTable:
    """The registry's table with every built-in reader passed through ``change``."""
    reg = registry_module.registry()
    readers = [(change(r) if info.builtin else r, info) for r, info in reg.readers]
    return FormatTable(readers, reg.writers)


def test_ambiguous_files_are_told_apart_by_the_readers_sniffers(
    tmp_path, monkeypatch, markers, weights
):
    fr.save(weights, tmp_path / "w.csv")
    fr.save(markers, tmp_path / "k.csv")
    assert isinstance(fr.load(tmp_path / "w.csv"), WeightSequence)
    assert isinstance(fr.load(tmp_path / "k.csv"), MarkerSequence)
    # the same table with the sniffers taken off the records: the dispatcher has no other way to tell
    blind = _builtin_table(lambda r: dataclasses.replace(r, sniff=None))
    monkeypatch.setattr(dispatch, "table_source", lambda: blind)
    assert isinstance(
        fr.load(tmp_path / "k.csv"), MarkerSequence
    )  # the first kind registered for .csv
    with pytest.raises(FileFormatError, match="not a marker layout"):
        fr.load(tmp_path / "w.csv")
    assert isinstance(fr.load(tmp_path / "w.csv", kind="weights"), WeightSequence)


def test_a_shared_sniffer_is_asked_once_per_file(tmp_path, monkeypatch, rig):
    fr.save(rig, tmp_path / "r.npz")
    calls = []
    real = builtin.SNIFF_NPZ

    def counting(path):
        calls.append(path)
        return real(path)

    table = _builtin_table(
        lambda r: dataclasses.replace(r, sniff=counting) if r.sniff is real else r
    )
    monkeypatch.setattr(dispatch, "table_source", lambda: table)
    assert fr.load(tmp_path / "r.npz", format=None, kind=None).n_shapes == rig.n_shapes
    assert len(calls) == 1


ZZ_MAGIC = b"ZZMESH1\n"


def _zz_plugin(**extra):
    """A plugin reading '.zz' files as meshes or as markers, by their first line."""

    def sniff(path):
        first = Path(path).read_bytes()[:16]
        return {ZZ_MAGIC: "mesh", b"ZZMARK1\n": "markers"}.get(first[:8])

    def read_mesh(path, **options):
        return Mesh(np.eye(3), [[0, 1, 2]])

    def read_markers(path, **options):
        return MarkerSequence(np.zeros((2, 1, 3)), names=["a"])

    module = types.ModuleType("zzplug")
    module.faceretarget_readers = hookimpl(
        lambda: [
            Reader(
                "zz-markers",
                "markers",
                (".zz",),
                read_markers,
                "zz markers",
                sniff=sniff,
                magic=(b"ZZMARK1\n",),
            ),
            Reader(
                "zz-mesh",
                "mesh",
                (".zz",),
                read_mesh,
                "zz mesh",
                sniff=sniff,
                magic=(ZZ_MAGIC,),
                **extra,
            ),
        ]
    )
    return module


@pytest.fixture
def zz(monkeypatch):
    def install(**extra):
        reg = registry_module.Registry().load(extra=[("zzplug", _zz_plugin(**extra))])
        monkeypatch.setattr(registry_module, "_REGISTRY", reg)
        return reg

    return install


def test_a_plugins_sniffer_chooses_among_its_readers(tmp_path, zz):
    zz()
    (tmp_path / "m.zz").write_bytes(ZZ_MAGIC + b"...")
    (tmp_path / "k.zz").write_bytes(b"ZZMARK1\n...")
    (tmp_path / "x.zz").write_bytes(b"neither")
    assert isinstance(fr.load(tmp_path / "m.zz"), Mesh)
    assert isinstance(fr.load(tmp_path / "k.zz"), MarkerSequence)
    assert isinstance(
        fr.load(tmp_path / "x.zz"), MarkerSequence
    )  # cannot tell: the first registered kind


def test_magic_bytes_name_a_misnamed_file(tmp_path, zz):
    zz()
    (tmp_path / "m.bin").write_bytes(ZZ_MAGIC + b"...")
    with pytest.raises(
        FileFormatError,
        match=r"no reader for '\.bin' files \(it looks like a zz-mesh file \(zz mesh; \.zz, format='zz-mesh'\)\)",
    ):
        fr.load(tmp_path / "m.bin")
    assert isinstance(fr.load(tmp_path / "m.bin", format="zz-mesh"), Mesh)
    # the built-ins declare theirs the same way: a glTF binary named .obj is no OBJ
    fr.save(Mesh(np.eye(3), [[0, 1, 2]]), tmp_path / "t.glb")
    (tmp_path / "t.dat").write_bytes((tmp_path / "t.glb").read_bytes())
    with pytest.raises(FileFormatError, match=r"it looks like a gltf-\w+ file \(.*\.glb/\.gltf"):
        fr.load(tmp_path / "t.dat")


def test_when_every_reader_declines_the_magic_names_the_file(tmp_path, zz):
    zz(accepts=lambda path: False)
    reg = registry_module.registry()
    assert any(r.name == "zz-mesh" for r, _ in reg.readers)
    fr.save(Mesh(np.eye(3), [[0, 1, 2]]), tmp_path / "t.ply")
    (tmp_path / "p.zz").write_bytes((tmp_path / "t.ply").read_bytes())
    # a PLY file named .zz, read as a mesh: the only mesh reader declines; the built-in PLY magic names it
    with pytest.raises(
        FormatMismatchError,
        match=r"this looks like a ply file .*every reader for it declined it: zz-mesh",
    ):
        fr.load(tmp_path / "p.zz", kind="mesh")


@pytest.mark.parametrize(
    "field, value, message",
    [
        (
            "sniff",
            "npz",
            r"plugin 'badplug' \(local -\), hook faceretarget_readers: 'bad': sniff must be a callable",
        ),
        (
            "magic",
            b"PK",
            r"plugin 'badplug' \(local -\), hook faceretarget_readers: 'bad': magic must be a tuple of non-empty byte strings",
        ),
        ("magic", ("PK",), r"magic must be a tuple of non-empty byte strings"),
        ("magic", (b"",), r"magic must be a tuple of non-empty byte strings"),
    ],
)
def test_records_are_checked_at_registration(field, value, message):
    module = types.ModuleType("badplug")
    record = Reader("bad", "mesh", (".bad",), lambda path, **o: None, "bad", **{field: value})
    module.faceretarget_readers = hookimpl(lambda: [record])
    reg = registry_module.Registry().load(extra=[("badplug", module)])
    (failure,) = [f for f in reg.failures if f.name == "badplug"]
    assert re.search(message, failure.error), failure.error
    with pytest.raises(PluginLoadError):  # a built-in with the same fault is fatal
        registry_module.Registry()._register(
            module, registry_module.PluginInfo("x", "faceretarget", "0", builtin=True), fatal=True
        )


# ---------------------------------------------------------------------------------------
# what the reviews asked for
# ---------------------------------------------------------------------------------------
def test_formats_shows_the_priority_of_builtins_that_have_one(capsys):
    from faceretarget.cli import main

    assert main(["formats"]) == 0
    lines = {
        ln.split()[0]: ln
        for ln in capsys.readouterr().out.splitlines()
        if ln.startswith("  ") and ln.split()
    }
    assert lines["vtk"].endswith("[priority -1]") and lines["gmsh"].endswith("[priority -1]")
    assert "priority" not in lines["obj"]


@pytest.mark.parametrize(
    "name, content, message",
    [
        (
            "photo.vtk",
            b"\x89PNG\r\n\x1a\n" + bytes(64),
            "this looks like a PNG image, not a VTK legacy file",
        ),
        (
            "grid.vtu",
            b'<?xml version="1.0"?>\n<svg xmlns="x"></svg>\n',
            "this looks like an SVG image, not a VTK XML file",
        ),
        (
            "mesh.msh",
            b"# vtk DataFile Version 4.2\nx\nASCII\nDATASET POLYDATA\n",
            "this looks like a VTK legacy file, not a Gmsh mesh; if that is what it is, give it the .vtk extension",
        ),
        (
            "mesh.vtk",
            b"$MeshFormat\n4.1 0 8\n$EndMeshFormat\n",
            "this looks like a Gmsh mesh, not a VTK legacy file; if that is what it is, give it the .msh extension",
        ),
    ],
)
def test_meshio_extensions_name_what_a_file_really_is(tmp_path, name, content, message):
    pytest.importorskip("meshio")
    (tmp_path / name).write_bytes(content)
    with pytest.raises(FileFormatError, match=message.replace(".", r"\.").replace("(", r"\(")):
        fr.load(tmp_path / name)
