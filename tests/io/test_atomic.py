"""Atomic writes: inputs never overwritten, existing outputs need force, no partial files."""

from __future__ import annotations

import os
import signal
import subprocess
import sys
import textwrap
import time

import numpy as np
import pytest

import faceretarget as fr
from faceretarget.errors import OutputError
from faceretarget.io._atomic import atomic_file, note_input, temp_owner


def test_refuses_to_write_over_an_input_even_with_force(tmp_path, mesh):
    path = tmp_path / "m.obj"
    fr.save(mesh, path)
    fr.load(path)  # now an input of this process
    with pytest.raises(OutputError, match="input"):
        fr.save(mesh, path, force=True)
    link = tmp_path / "link.obj"
    os.link(path, link)  # the same file under another name
    with pytest.raises(OutputError, match="input"):
        fr.save(mesh, link, force=True)
    sym = tmp_path / "sym.obj"
    sym.symlink_to(path)
    with pytest.raises(OutputError, match="input"):
        fr.save(mesh, sym, force=True)


def test_inputs_argument_and_existing_outputs(tmp_path, mesh):
    out = tmp_path / "out.ply"
    other = tmp_path / "declared.ply"
    fr.save(mesh, other)
    with pytest.raises(OutputError, match="input"):
        fr.save(mesh, other, force=True, inputs=[other])
    fr.save(mesh, out)
    before = out.read_bytes()
    with pytest.raises(OutputError, match="already exists.*force"):
        fr.save(mesh.with_vertices(mesh.vertices * 2), out)
    assert out.read_bytes() == before
    fr.save(mesh.with_vertices(mesh.vertices * 2), out, force=True)
    np.testing.assert_array_equal(fr.load(out).vertices, mesh.vertices * 2)


def test_missing_folder_and_folder_in_place_of_file(tmp_path, mesh):
    with pytest.raises(OutputError, match="does not exist"):
        fr.save(mesh, tmp_path / "nowhere" / "m.obj")
    (tmp_path / "dir.obj").mkdir()
    with pytest.raises(OutputError, match="is a folder"):
        fr.save(mesh, tmp_path / "dir.obj", force=True)


def test_an_error_while_writing_leaves_nothing(tmp_path):
    target = tmp_path / "x.bin"
    target.write_bytes(b"old")
    with pytest.raises(RuntimeError), atomic_file(target, force=True) as fh:
        fh.write(b"new partial")
        raise RuntimeError("disk on fire")
    assert target.read_bytes() == b"old"
    assert sorted(p.name for p in tmp_path.iterdir()) == ["x.bin"]


def test_folder_outputs_replace_only_their_own_kind_of_content(tmp_path, seq):
    out = tmp_path / "frames"
    fr.save(seq, out)
    assert sorted(p.name for p in out.iterdir())[-1] == "sequence.json"
    fr.save(seq, out, force=True)  # OBJ frames + sidecar: replaceable
    (out / "notes.txt").write_text("mine")
    with pytest.raises(OutputError, match="other content"):
        fr.save(seq, out, force=True)
    assert (out / "notes.txt").read_text() == "mine"
    fr.load(out / "frame_00000.obj")
    with pytest.raises(OutputError, match="input"):
        fr.save(seq, out, force=True)


def test_sigkill_mid_write_leaves_the_previous_output_intact(tmp_path):
    """A writer killed while writing: the destination keeps its old content and the
    stale temporary file is cleaned up by the next write."""
    target = tmp_path / "out.bin"
    target.write_bytes(b"previous")
    ready = tmp_path / "ready"
    script = textwrap.dedent(f"""
        import time
        from faceretarget.io._atomic import atomic_file
        with atomic_file({str(target)!r}, force=True) as fh:
            fh.write(b"x" * 1000000)
            fh.flush()
            open({str(ready)!r}, "w").close()
            time.sleep(60)
    """)
    proc = subprocess.Popen([sys.executable, "-c", script])
    try:
        for _ in range(600):
            if ready.exists():
                break
            time.sleep(0.05)
        assert ready.exists(), "the writer never started"
        os.kill(proc.pid, signal.SIGKILL)
        proc.wait(timeout=30)
    finally:
        if proc.poll() is None:
            proc.kill()
    assert target.read_bytes() == b"previous"
    leftovers = [p for p in tmp_path.iterdir() if temp_owner(p.name)]
    assert len(leftovers) == 1  # the killed writer's temporary, never the destination
    with atomic_file(target, force=True) as fh:
        fh.write(b"next")
    assert target.read_bytes() == b"next"
    assert not [p for p in tmp_path.iterdir() if temp_owner(p.name)]


def test_note_input_covers_files_of_a_folder(tmp_path, seq):
    fr.save(seq, tmp_path / "take")
    note_input(tmp_path / "take")
    with pytest.raises(OutputError, match="input"):
        fr.save(seq.frame(0), tmp_path / "take" / "frame_00000.obj", force=True)


def test_folder_replacement_without_atomic_exchange_restores_after_a_crash(
    tmp_path, seq, monkeypatch
):
    """Where no atomic exchange exists the old folder is moved aside; if the writer dies
    before the new one is in place, the next write puts the old folder back first."""
    from faceretarget.io import _atomic

    out = tmp_path / "frames"
    fr.save(seq, out)
    before = sorted(p.name for p in out.iterdir())
    fr.save(seq, out, force=True)  # the atomic exchange path
    assert (
        sorted(p.name for p in tmp_path.iterdir()) == ["frames"]
        and sorted(p.name for p in out.iterdir()) == before
    )
    monkeypatch.setattr(_atomic, "_exchange", lambda a, b: False)
    real_replace = os.replace

    def die_after_moving_aside(src, dst):
        real_replace(src, dst)
        if str(dst).endswith(".frold"):
            raise KeyboardInterrupt  # the process "dies" between the two renames

    monkeypatch.setattr(_atomic.os, "replace", die_after_moving_aside)
    with pytest.raises(KeyboardInterrupt):
        fr.save(seq, out, force=True)
    monkeypatch.setattr(_atomic.os, "replace", real_replace)
    assert not out.exists()
    backup = next(p for p in tmp_path.iterdir() if p.name.endswith(".frold"))
    pid_dead = backup.name.replace(str(os.getpid()), "999999999")  # as if left by a dead process
    backup.rename(tmp_path / pid_dead)
    _atomic._remove_stale(out)
    assert sorted(p.name for p in out.iterdir()) == before


@pytest.mark.parametrize(
    "scheme", [".out.npz.{pid}.0123abcd.frtmp.npz", ".out.npz.frbatch-{pid}-89abcdef.npz"]
)
@pytest.mark.parametrize("pid", [10**25, 2**63, 0])
def test_a_temporary_name_with_an_impossible_pid_is_a_leftover_not_a_crash(pid, scheme, tmp_path):
    """Found by the long fuzz mode (issue 15): a pid beyond C long in a temporary's name
    made ``leftovers`` raise OverflowError from os.kill; pid 0 probed our own group."""
    from faceretarget.io import _atomic

    stale = tmp_path / scheme.format(pid=pid)
    stale.write_bytes(b"x")
    user = tmp_path / "out.npz"
    user.write_bytes(b"mine")
    assert _atomic.leftovers(tmp_path) == [stale]
    assert _atomic.remove_leftovers(user) == [stale]
    assert not stale.exists() and user.read_bytes() == b"mine"
