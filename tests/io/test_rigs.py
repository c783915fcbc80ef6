"""Blendshape rigs: OBJ folders (neutral detection, rig.json), npz; exact round trips."""

from __future__ import annotations

import json

import numpy as np
import pytest

import faceretarget as fr
from faceretarget.errors import FileFormatError
from faceretarget.io.rigs import exact_positions
from faceretarget.model import BlendshapeRig


def _hand_made_folder(folder, mesh, names=("smile_L", "jawOpen", "frown")):
    """Shapes as absolute meshes, the way a DCC exports them (coordinates near and far from 0)."""
    folder.mkdir()
    rng = np.random.default_rng(7)
    fr.save(mesh, folder / "Neutral.obj")
    shapes = []
    for name in names:
        shape = mesh.vertices + rng.normal(0, 0.3, mesh.vertices.shape) * rng.random(
            (mesh.n_vertices, 1)
        )
        fr.save(mesh.with_vertices(shape), folder / f"{name}.obj")
        shapes.append(shape)
    return np.array(shapes)


def test_folder_rig_without_sidecar(tmp_path, mesh):
    shapes = _hand_made_folder(tmp_path / "rig", mesh, names=("shape10", "shape2", "jaw"))
    rig = fr.load(tmp_path / "rig")
    assert isinstance(rig, BlendshapeRig) and rig.names == (
        "jaw",
        "shape2",
        "shape10",
    )  # natural order
    np.testing.assert_array_equal(rig.neutral.vertices + rig.deltas[1], shapes[1])


def test_folder_rig_round_trip_is_exact(tmp_path, mesh):
    _hand_made_folder(tmp_path / "rig", mesh)
    once = fr.load(tmp_path / "rig")
    fr.save(once, tmp_path / "out")
    meta = json.loads((tmp_path / "out" / "rig.json").read_text())
    assert [s["name"] for s in meta["shapes"]] == list(once.names)
    twice = fr.load(tmp_path / "out")
    assert twice.names == once.names
    np.testing.assert_array_equal(
        twice.deltas, once.deltas
    )  # bit-exact deltas through absolute OBJs
    np.testing.assert_array_equal(twice.neutral.vertices, once.neutral.vertices)


def test_rig_json_keeps_unsafe_names_and_bounds(tmp_path, rig):
    fr.save(rig, tmp_path / "out")
    assert (tmp_path / "out" / "brow_up.obj").exists()
    back = fr.load(tmp_path / "out")
    assert back.names == rig.names
    np.testing.assert_array_equal(back.bounds, rig.bounds)
    np.testing.assert_allclose(back.deltas, rig.deltas, atol=1e-15)


def test_npz_rig_round_trip(tmp_path, rig):
    fr.save(rig, tmp_path / "r.npz")
    back = fr.load(tmp_path / "r.npz")
    np.testing.assert_array_equal(back.deltas, rig.deltas)
    assert back.names == rig.names and back.neutral.name == rig.neutral.name


def test_exact_positions_reproduce_deltas_bit_for_bit():
    rng = np.random.default_rng(0)
    neutral = rng.normal(0, 10, (2000, 3)) * 10.0 ** rng.integers(-8, 3, (2000, 1))
    shape = rng.normal(0, 10, (2000, 3))
    delta = shape - neutral  # what a reader computes from two files
    np.testing.assert_array_equal(exact_positions(neutral, delta) - neutral, delta)


def test_folder_rig_errors(tmp_path, mesh):
    _hand_made_folder(tmp_path / "rig", mesh)
    fr.save(mesh, tmp_path / "rig" / "base.obj")
    with pytest.raises(FileFormatError, match="cannot tell which file is the neutral"):
        fr.load(tmp_path / "rig", kind="rig")
    assert fr.load(tmp_path / "rig", kind="rig", neutral="base").n_shapes == 4
    (tmp_path / "rig" / "base.obj").unlink()
    (tmp_path / "rig" / "odd.obj").write_text("v 0 0 0\nv 1 0 0\nv 0 1 0\nf 1 2 3\n")
    with pytest.raises(FileFormatError, match="odd.obj.*'odd' has a different topology"):
        fr.load(tmp_path / "rig")
    (tmp_path / "rig" / "odd.obj").unlink()
    (tmp_path / "rig" / "rig.json").write_text(
        json.dumps({"neutral": "Neutral.obj", "shapes": [{"name": "x", "file": "../x.obj"}]})
    )
    with pytest.raises(FileFormatError, match="plain names"):
        fr.load(tmp_path / "rig")
