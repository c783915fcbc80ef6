"""Small synthetic parallel rigs for the spacetime tests (no files, nothing outside the repository)."""

from __future__ import annotations

from types import SimpleNamespace

import numpy as np
import pytest

import faceretarget as fr

#: Affine map from the toy target's coordinates to the toy source's (so the RBF warp, whose
#: linear polynomial reproduces affine maps exactly, makes the rigs exactly parallel).
AFFINE = np.array([[1.12, 0.05, 0.0], [-0.03, 0.93, 0.04], [0.02, 0.0, 1.05]])
OFFSET = np.array([0.4, -0.7, 0.2])


def grid_mesh(nx: int = 9, ny: int = 9, width: float = 14.0) -> fr.Mesh:
    """A curved face-sized (cm) grid."""
    x, y = np.meshgrid(
        np.linspace(-width / 2, width / 2, nx), np.linspace(-width / 2, width / 2, ny)
    )
    z = 4.0 - 0.04 * (x**2 + y**2)
    vertices = np.stack([x.ravel(), y.ravel(), z.ravel()], axis=1)
    ids = np.arange(nx * ny).reshape(ny, nx)
    a, b, c, d = (
        ids[:-1, :-1].ravel(),
        ids[:-1, 1:].ravel(),
        ids[1:, 1:].ravel(),
        ids[1:, :-1].ravel(),
    )
    triangles = np.concatenate([np.stack([a, b, c], 1), np.stack([a, c, d], 1)])
    return fr.Mesh(vertices, triangles)


def smooth_deltas(mesh: fr.Mesh, n_shapes: int, rng, support=None) -> np.ndarray:
    """(M, V, 3) smooth random blendshape deltas of about 1 cm (optionally only where ``support``)."""
    v = mesh.vertices
    out = np.zeros((n_shapes, len(v), 3))
    for j in range(n_shapes):
        for _ in range(2):
            centre = v[rng.integers(len(v))]
            bump = np.exp(-np.sum((v - centre) ** 2, axis=1) / (2 * 3.0**2))
            out[j] += bump[:, None] * rng.normal(0.0, 0.8, 3)
        if support is not None:
            out[j] *= support[j][:, None]
    return out


def smooth_weights(n_frames: int, n_shapes: int, rng, start_neutral: bool = False) -> np.ndarray:
    t = np.arange(n_frames)[:, None]
    w = 0.5 + 0.45 * np.sin(
        2 * np.pi * t / rng.uniform(15, 50, n_shapes) + rng.uniform(0, 2 * np.pi, n_shapes)
    )
    if start_neutral:
        w *= np.sin(np.pi * np.arange(n_frames) / max(n_frames - 1, 1))[:, None] ** 2
    return w


def rotation(angles: np.ndarray) -> np.ndarray:
    """(F, 3, 3) rotations from (F, 3) small angles (x, y, z)."""
    from scipy.spatial.transform import Rotation

    return Rotation.from_euler("xyz", angles).as_matrix()


def _make_toy(
    seed=0,
    n_frames=40,
    n_shapes=6,
    n_markers=24,
    head_motion=False,
    noise=0.0,
    expression=True,
    missing=0.0,
    weights=None,
    support=None,
    extra_source_shapes=0,
    extra_weights=None,
    fps=30.0,
):
    """A toy parallel-rig problem: a target grid rig, and source markers related to the target by
    :data:`AFFINE` (exactly parallel), optionally with head motion, noise and missing samples.

    ``extra_source_shapes`` adds source-only expressions the target cannot reproduce (driven
    by ``extra_weights`` if given).
    """
    rng = np.random.default_rng(seed)
    mesh = grid_mesh()
    deltas = smooth_deltas(mesh, n_shapes, rng, support)
    names = [f"shape{j}" for j in range(n_shapes)]
    rig = fr.BlendshapeRig(mesh, deltas, names)
    lm_ids = np.sort(rng.choice(mesh.n_vertices, n_markers, replace=False))
    marker_names = [f"m{i}" for i in range(n_markers)]
    target = fr.TargetRig(mesh, blendshapes=rig, landmarks=fr.Landmarks(lm_ids, names=marker_names))
    if weights is None:
        weights = (
            smooth_weights(n_frames, n_shapes, rng)
            if expression
            else np.zeros((n_frames, n_shapes))
        )
    n_frames = len(weights)
    src_neutral = mesh.vertices[lm_ids] @ AFFINE.T + OFFSET
    src_deltas = deltas[:, lm_ids] @ AFFINE.T
    local = src_neutral + np.einsum("fm,mnk->fnk", weights, src_deltas)
    if extra_source_shapes:
        extra = smooth_deltas(mesh, extra_source_shapes, rng)[:, lm_ids] @ AFFINE.T
        if extra_weights is None:
            extra_weights = smooth_weights(n_frames, extra_source_shapes, rng)
        local = local + np.einsum("fm,mnk->fnk", extra_weights, extra)
    motion = np.tile(np.eye(4), (n_frames, 1, 1))
    if head_motion:
        t = np.arange(n_frames)[:, None]
        angles = 0.15 * np.sin(
            2 * np.pi * t / np.array([37.0, 53.0, 71.0]) + np.array([0.3, 1.0, 2.0])
        )
        motion[:, :3, :3] = rotation(angles)
        motion[:, :3, 3] = np.stack(
            [np.sin(t[:, 0] / 9.0), 0.5 * np.cos(t[:, 0] / 7.0), 0.3 * np.sin(t[:, 0] / 5.0)], 1
        )
    world = np.einsum("fij,fnj->fni", motion[:, :3, :3], local) + motion[:, None, :3, 3]
    if noise:
        world = world + rng.normal(0.0, noise, world.shape)
    if missing:
        drop = rng.random(world.shape[:2]) < missing
        drop[0] = False  # keep the neutral-pose reference check simple
        world = np.where(drop[..., None], np.nan, world)
    source = fr.Source(fr.MarkerSequence(world, names=marker_names, reference=src_neutral, fps=fps))
    return SimpleNamespace(
        source=source,
        target=target,
        rig=rig,
        weights=weights,
        motion=motion,
        landmarks=lm_ids,
        src_neutral=src_neutral,
        src_deltas=src_deltas,
        world=world,
        affine=AFFINE,
    )


@pytest.fixture
def make_toy():
    """The toy problem builder (see :func:`_make_toy`)."""
    return _make_toy


@pytest.fixture(scope="session")
def ict_case():
    return fr.cases.ict(n_frames=60)


@pytest.fixture(scope="session")
def synthetic_case():
    return fr.cases.synthetic(resolution=800, n_frames=60)
