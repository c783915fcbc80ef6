"""The plugin I/O contract (docs/plugins.md, "Readers and writers").

A plugin defined here (registered programmatically, nothing installed) adds readers and
writers for ``.obj`` (which the core reads) and ``.pts``. Checked:

- ``save`` hands every writer a temporary path and moves it into place: a plugin writer
  cannot replace an existing file without ``force`` or an input, and one that writes
  the destination itself is refused with its output discarded;
- readers decline files (``accepts`` or ``FormatMismatchError``) and the next is tried;
- ``priority`` decides between a plugin's reader and the built-in for one extension;
- ``faceretarget formats`` shows which reader is shadowed by which;
- the atomic writer is public in ``faceretarget.io``.
"""

import subprocess
import sys
import textwrap
import types
from pathlib import Path

import numpy as np
import pytest

import faceretarget as fr
import faceretarget.io as fio
from faceretarget import Reader, Writer, hookimpl
from faceretarget import registry as registry_module
from faceretarget.errors import FormatMismatchError, OutputError, PluginOutputError
from faceretarget.model import Mesh

TRI = Mesh([[0.0, 0, 0], [1, 0, 0], [0, 1, 0]], [[0, 1, 2]])


def _read_pts(path, **options):
    text = Path(path).read_text()
    if not text.startswith("PTS\n"):
        raise FormatMismatchError(f"{path}: not a PTS file")
    return Mesh(np.loadtxt(text.splitlines()[1:], ndmin=2), [[0, 1, 2]])


def _write_pts(obj, path, **options):
    calls.append(Path(path))
    with open(path, "w") as fh:  # a plain open(): the contract makes it atomic
        fh.write("PTS\n" + "\n".join(" ".join(map(repr, v)) for v in obj.vertices.tolist()) + "\n")


def _write_pts_to_destination(obj, path, **options):
    """A rogue writer: writes the final name (and an input) itself, bypassing its temporary."""
    for name in ("out.rogue", "in.pts"):
        target = Path(path).parent / name
        if name == "out.rogue" or target.exists():
            target.write_text("PTS\n0 0 0\n")
    Path(path).write_text("PTS\n0 0 0\n")


calls: list[Path] = []
seen: list[str] = []


def _obj_plugin_reader(path, **options):
    seen.append("plugin")
    return Mesh(TRI.vertices * 2, TRI.triangles)


def _plugin(priority=0, accepts=None):
    module = types.ModuleType("contractplug")
    module.faceretarget_readers = hookimpl(
        lambda: [
            Reader("pts", "mesh", (".pts",), _read_pts, "points with a PTS header"),
            Reader(
                "pts-loose",
                "mesh",
                (".pts",),
                lambda path, **o: Mesh(np.zeros((3, 3)), [[0, 1, 2]]),
                "fallback",
                priority=-5,
            ),
            Reader(
                "obj-plugin",
                "mesh",
                (".obj",),
                _obj_plugin_reader,
                "the plugin's OBJ",
                priority=priority,
                accepts=accepts,
            ),
        ]
    )
    module.faceretarget_writers = hookimpl(
        lambda: [
            Writer("pts", "mesh", (".pts",), _write_pts, "points with a PTS header"),
            Writer(
                "rogue",
                "mesh",
                (".rogue",),
                _write_pts_to_destination,
                "writes its destination itself",
            ),
        ]
    )
    return module


@pytest.fixture
def use_plugin(monkeypatch):
    def install(**kwargs):
        reg = registry_module.Registry().load(extra=[("contractplug", _plugin(**kwargs))])
        monkeypatch.setattr(registry_module, "_REGISTRY", reg)
        calls.clear()
        seen.clear()
        return reg

    return install


def test_a_plugin_writer_gets_a_temporary_path_and_never_overwrites_without_force(
    tmp_path, use_plugin
):
    use_plugin()
    dest = tmp_path / "a.pts"
    fr.save(TRI, dest)
    assert (
        calls and calls[0] != dest and calls[0].parent == dest.parent and calls[0].suffix == ".pts"
    )
    assert not calls[0].exists()  # moved into place
    assert dest.read_text().startswith("PTS\n0.0 0.0 0.0\n")
    before = dest.read_bytes()
    with pytest.raises(OutputError, match="already exists"):
        fr.save(Mesh(TRI.vertices + 1, TRI.triangles), dest)
    assert dest.read_bytes() == before
    fr.save(Mesh(TRI.vertices + 1, TRI.triangles), dest, force=True)
    assert dest.read_bytes() != before
    assert sorted(p.name for p in tmp_path.iterdir()) == ["a.pts"]  # no temporaries left


def test_a_plugin_writer_cannot_write_over_an_input(tmp_path, use_plugin):
    use_plugin()
    src = tmp_path / "in.pts"
    fr.save(TRI, src)
    fr.load(src)  # now an input of this process
    before = src.read_bytes()
    with pytest.raises(OutputError, match="input"):
        fr.save(Mesh(TRI.vertices + 1, TRI.triangles), src, force=True)
    assert src.read_bytes() == before
    other = tmp_path / "listed.pts"
    fr.save(TRI, other)
    with pytest.raises(OutputError, match="input"):
        fr.save(TRI, other, force=True, inputs=[other])


def test_a_writer_that_writes_its_destination_itself_is_refused(tmp_path, use_plugin):
    use_plugin()
    with pytest.raises(PluginOutputError, match="instead of the temporary path"):
        fr.save(TRI, tmp_path / "out.rogue")
    assert [
        p.name for p in tmp_path.iterdir() if p.name.startswith(".")
    ] == []  # its temporary discarded
    (tmp_path / "out.rogue").unlink()
    src = tmp_path / "in.pts"  # an input it overwrites behind the core's back is caught too
    fr.save(TRI, src)
    fr.load(src)
    with pytest.raises(PluginOutputError, match="in.pts"):
        fr.save(TRI, tmp_path / "out.rogue")


def test_readers_decline_and_the_next_is_tried(tmp_path, use_plugin):
    use_plugin()
    good = tmp_path / "good.pts"
    good.write_text("PTS\n0 0 0\n1 0 0\n0 1 0\n")
    np.testing.assert_array_equal(fr.load(good).vertices, TRI.vertices)
    loose = tmp_path / "loose.pts"
    loose.write_text("0 0 0\n")  # the 'pts' reader declines it: the lower-priority one reads it
    assert fr.load(loose).vertices.sum() == 0


def test_builtin_reader_wins_a_tie_and_a_higher_priority_plugin_wins(tmp_path, use_plugin):
    fio.save(TRI, tmp_path / "m.obj")
    use_plugin(priority=0)
    np.testing.assert_array_equal(fr.load(tmp_path / "m.obj").vertices, TRI.vertices)
    assert seen == []  # shadowed by the built-in
    use_plugin(priority=10)
    np.testing.assert_array_equal(fr.load(tmp_path / "m.obj").vertices, TRI.vertices * 2)
    assert seen == ["plugin"]
    use_plugin(priority=10, accepts=lambda path: False)  # it declines: the built-in reads it
    np.testing.assert_array_equal(fr.load(tmp_path / "m.obj").vertices, TRI.vertices)
    assert seen == []


def test_formats_shows_which_reader_is_shadowed(use_plugin):
    use_plugin(priority=0)
    rows = {(r["direction"], r["name"]): r for r in fio.formats()}
    assert rows[("read", "obj-plugin")]["shadowed_by"] == {".obj": "obj"}
    assert rows[("read", "obj")]["shadows"] == {".obj": ["obj-plugin"]}
    assert "shadowed by obj (.obj)" in fio.shadow_note(rows[("read", "obj-plugin")])
    use_plugin(priority=10)
    rows = {(r["direction"], r["name"]): r for r in fio.formats()}
    assert rows[("read", "obj")]["shadowed_by"] == {".obj": "obj-plugin"}
    assert rows[("read", "pts-loose")]["shadowed_by"] == {".pts": "pts"}


def test_faceretarget_formats_prints_the_shadowing(tmp_path):
    """The command line, with the plugin on an entry point of a distribution made in tmp_path."""
    site = tmp_path / "site"
    pkg = site / "contractplug_dist"
    pkg.mkdir(parents=True)
    (pkg / "__init__.py").write_text(
        textwrap.dedent("""
        import faceretarget
        from faceretarget import Reader

        def _read(path, **options):
            raise faceretarget.errors.FormatMismatchError(f"{path}: not mine")

        @faceretarget.hookimpl
        def faceretarget_readers():
            return [Reader("obj-shadowed", "mesh", (".obj",), _read, "a plugin OBJ reader")]
    """)
    )
    info = site / "contractplug_dist-0.1.dist-info"
    info.mkdir()
    (info / "METADATA").write_text("Metadata-Version: 2.1\nName: contractplug-dist\nVersion: 0.1\n")
    (info / "entry_points.txt").write_text("[faceretarget]\ncontractplug = contractplug_dist\n")
    import os

    env = dict(
        os.environ,
        PYTHONPATH=os.pathsep.join(filter(None, [str(site), os.environ.get("PYTHONPATH")])),
    )
    env.pop("FACERETARGET_DISABLE_PLUGINS", None)
    out = subprocess.run(
        [sys.executable, "-m", "faceretarget.cli", "formats"],
        capture_output=True,
        text=True,
        env=env,
    )
    assert out.returncode == 0, out.stderr
    lines = out.stdout.splitlines()
    at = next(i for i, line in enumerate(lines) if line.split()[:1] == ["obj-shadowed"])
    assert "contractplug-dist 0.1" in lines[at]
    assert "shadowed by obj (.obj)" in lines[at + 1]
    assert any("wins over obj-shadowed (.obj)" in line for line in lines)


def test_the_atomic_writer_is_public(tmp_path):
    dest = tmp_path / "x.bin"
    with fio.atomic_path(dest) as tmp:
        assert tmp != dest and tmp.parent == dest.parent
        tmp.write_bytes(b"data")
    assert dest.read_bytes() == b"data"
    with pytest.raises(OutputError, match="already exists"), fio.atomic_path(dest) as tmp:
        tmp.write_bytes(b"other")
    with pytest.raises(RuntimeError), fio.atomic_path(dest, force=True) as tmp:
        tmp.write_bytes(b"half")
        raise RuntimeError("the writer failed")
    assert dest.read_bytes() == b"data" and sorted(p.name for p in tmp_path.iterdir()) == ["x.bin"]
    for name in (
        "atomic_path",
        "atomic_file",
        "atomic_dir",
        "write_bytes",
        "note_input",
        "is_input",
    ):
        assert name in fio.__all__ and (getattr(fio, name).__doc__ or "").strip()
