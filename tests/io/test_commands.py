"""`faceretarget convert`: conversions, refusals, one-line errors."""

from __future__ import annotations

import argparse
import os

import numpy as np
import pytest

import faceretarget as fr
from faceretarget.errors import OutputError
from faceretarget.io.commands import add_convert_arguments, convert, run_convert


def _run(*argv) -> int:
    parser = add_convert_arguments(argparse.ArgumentParser())
    return run_convert(parser.parse_args([str(a) for a in argv]))


def test_conversions(tmp_path, mesh, rig, seq, markers, weights, capsys):
    fr.save(mesh, tmp_path / "m.ply")
    assert _run(tmp_path / "m.ply", tmp_path / "m.obj") == 0
    assert "wrote" in capsys.readouterr().out
    np.testing.assert_array_equal(fr.load(tmp_path / "m.obj").vertices, mesh.vertices)
    fr.save(seq, tmp_path / "take.pc2")
    _run(
        tmp_path / "take.pc2", tmp_path / "take.glb", "--topology", tmp_path / "m.obj", "--fps", 24
    )
    anim = fr.load(tmp_path / "take.glb")
    assert anim.fps == 24 and anim.n_frames == seq.n_frames
    fr.save(rig, tmp_path / "rigdir")
    _run(tmp_path / "rigdir", tmp_path / "rig.glb")
    assert fr.load(tmp_path / "rig.glb").names == rig.names
    fr.save(markers, tmp_path / "k.c3d")
    _run(tmp_path / "k.c3d", tmp_path / "k.trc")
    assert fr.load(tmp_path / "k.trc").names == markers.names
    fr.save(weights, tmp_path / "w.npz")
    _run(tmp_path / "w.npz", tmp_path / "w.csv")
    np.testing.assert_array_equal(fr.load(tmp_path / "w.csv").weights, weights.weights)


def test_refusals(tmp_path, mesh):
    fr.save(mesh, tmp_path / "m.obj")
    with pytest.raises(OutputError, match="same file"):
        convert(tmp_path / "m.obj", tmp_path / "m.obj", force=True)
    os.symlink(tmp_path / "m.obj", tmp_path / "alias.obj")
    with pytest.raises(OutputError, match="same file"):
        convert(tmp_path / "m.obj", tmp_path / "alias.obj", force=True)
    convert(tmp_path / "m.obj", tmp_path / "m.ply")
    with pytest.raises(OutputError, match="already exists"):
        convert(tmp_path / "m.obj", tmp_path / "m.ply")
    _run(tmp_path / "m.obj", tmp_path / "m.ply", "--force")


@pytest.mark.parametrize(
    "ext",
    ["obj", "ply", "off", "stl", "glb", "gltf", "c3d", "trc", "csv", "npz", "npy", "pc2", "mdd"],
)
def test_cli_garbage_is_a_typed_one_line_error_and_no_output(tmp_path, capsys, ext):
    """The `faceretarget convert` command on random bytes: a typed error (not an
    'internal error'), one line, nothing written."""
    from faceretarget.cli import main

    bad = tmp_path / f"in.{ext}"
    bad.write_bytes(
        np.random.default_rng(len(ext)).integers(0, 256, 3000, dtype=np.uint8).tobytes()
    )
    out = tmp_path / "out.glb"
    code = main(["convert", str(bad), str(out)])
    err = capsys.readouterr().err.strip()
    assert code != 0 and err.startswith("faceretarget: error:") and str(bad) in err
    assert len(err.splitlines()) == 1
    assert not out.exists()
