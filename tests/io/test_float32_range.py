"""Formats that store float32 refuse values beyond its range instead of writing inf
(found by the random fuzz mode: a PLY converted to GLB crashed in the JSON header)."""

import numpy as np
import pytest

import faceretarget as fr
from faceretarget.errors import OutputError

HUGE = 1e306


def mesh():
    return fr.Mesh(
        np.array([[0.0, 0.0, 0.0], [1.0, 0.0, 0.0], [0.0, HUGE, 0.0]]), np.array([[0, 1, 2]])
    )


def sequence():
    frames = np.repeat(np.array(mesh().vertices)[None], 2, axis=0)
    return fr.MeshSequence(frames, mesh().triangles, fps=30.0)


def markers():
    positions = np.zeros((2, 3, 3))
    positions[1, 2, 0] = HUGE
    return fr.MarkerSequence(positions, names=["a", "b", "c"], fps=30.0)


@pytest.mark.parametrize(
    "make, ext",
    [
        (mesh, ".glb"),
        (mesh, ".stl"),
        (sequence, ".pc2"),
        (sequence, ".mdd"),
        (sequence, ".glb"),
        (markers, ".c3d"),
    ],
)
def test_float32_formats_refuse_values_out_of_range(make, ext, tmp_path):
    out = tmp_path / f"out{ext}"
    with pytest.raises(OutputError, match="beyond float32's range"):
        fr.save(make(), out)
    assert list(tmp_path.iterdir()) == [], "nothing may be left behind"


@pytest.mark.parametrize("ext", [".npz", ".obj", ".ply"])
def test_float64_formats_keep_them(ext, tmp_path):
    out = tmp_path / f"out{ext}"
    fr.save(mesh(), out)
    assert np.asarray(fr.load(out, kind="mesh").vertices).max() == HUGE
