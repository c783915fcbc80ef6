"""Small model objects shared by the I/O tests (built in code; nothing read from disk)."""

from __future__ import annotations

import numpy as np
import pytest

from faceretarget.io._atomic import clear_inputs
from faceretarget.model import (
    Animation,
    BlendshapeRig,
    MarkerSequence,
    Mesh,
    MeshSequence,
    WeightSequence,
)


@pytest.fixture(autouse=True)
def _forget_inputs():
    """Each test starts with no recorded inputs (the record is process-wide by design)."""
    clear_inputs()
    yield
    clear_inputs()


def grid_mesh(n: int = 4, seed: int = 0) -> Mesh:
    """An (n x n)-vertex open patch with irrational-looking coordinates (float64 exactness matters)."""
    rng = np.random.default_rng(seed)
    u, v = np.meshgrid(np.arange(n, dtype=float), np.arange(n, dtype=float), indexing="ij")
    verts = (
        np.stack([u.ravel(), v.ravel(), np.sin(u.ravel() * 0.7) * np.cos(v.ravel())], axis=1) / 3.0
    )
    verts += rng.normal(0, 1e-3, verts.shape)
    tris = []
    for i in range(n - 1):
        for j in range(n - 1):
            a, b, c, d = i * n + j, (i + 1) * n + j, (i + 1) * n + j + 1, i * n + j + 1
            tris += [[a, b, c], [a, c, d]]
    return Mesh(verts, np.array(tris), name="patch")


@pytest.fixture
def mesh() -> Mesh:
    return grid_mesh()


@pytest.fixture
def rig(mesh) -> BlendshapeRig:
    rng = np.random.default_rng(1)
    return BlendshapeRig(
        mesh,
        rng.normal(0, 0.05, (3, mesh.n_vertices, 3)),
        ["jawOpen", "eyeBlink_L", "brow/up"],
        bounds=[[0, 1], [0, 1], [-1, 1]],
    )


@pytest.fixture
def seq(mesh) -> MeshSequence:
    rng = np.random.default_rng(2)
    return MeshSequence(
        mesh.vertices[None] + rng.normal(0, 0.01, (6, mesh.n_vertices, 3)), mesh.triangles, fps=24.0
    )


@pytest.fixture
def animation(rig) -> Animation:
    rng = np.random.default_rng(3)
    n = 7
    angles = np.linspace(0, 0.3, n)
    head = np.tile(np.eye(4), (n, 1, 1))
    head[:, 0, 0] = head[:, 1, 1] = np.cos(angles)
    head[:, 0, 1], head[:, 1, 0] = -np.sin(angles), np.sin(angles)
    head[:, :3, 3] = rng.normal(0, 0.1, (n, 3))
    return Animation(
        weights=rng.random((n, rig.n_shapes)),
        rig=rig,
        head_motion=head,
        fps=30.0,
        provenance={
            "method": "test",
            "parameters": {"alpha": np.float64(0.5)},
            "timings": [1.5, 2],
        },
    )


@pytest.fixture
def markers() -> MarkerSequence:
    rng = np.random.default_rng(4)
    pos = rng.normal(0, 30, (12, 4, 3))
    pos[0, 2] = np.nan  # missing in the first frame: the reference comes from frame 1
    pos[5:8, 1] = np.nan
    return MarkerSequence(
        pos,
        names=["LBrow", "RBrow", "Chin", "Nose tip"],
        fps=120.0,
        reference=np.where(np.isnan(pos[0]), pos[1], pos[0]),
    )


@pytest.fixture
def weights() -> WeightSequence:
    rng = np.random.default_rng(5)
    return WeightSequence(
        rng.random((75, 4)),
        ["eyeBlinkLeft", "EyeBlinkRight", "jawOpen", "mouth, with comma"],
        fps=60.0,
    )
