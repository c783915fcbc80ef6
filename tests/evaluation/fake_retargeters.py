"""Tiny hand-built parallel-rig case and fake retargeters for the evaluation tests.

Importable by name (``fake_retargeters``; conftest puts this folder on sys.path) so that
batch workers in other processes can unpickle the classes.
"""

from __future__ import annotations

import time
from types import SimpleNamespace

import numpy as np

from faceretarget import (
    Animation,
    BlendshapeRig,
    Capabilities,
    Landmarks,
    LayeredRig,
    Mesh,
    MeshSequence,
    Retargeter,
    Source,
    TargetRig,
)
from faceretarget.hookspecs import hookimpl

SHAPES = ("jawOpen", "eyeBlinkLeft", "browInnerUp", "wrinkle")


def grid(n: int = 9, width: float = 2.0, height: float = 2.4):
    """(n*n, 3) vertices on a bumped grid and its (2 (n-1)^2, 3) triangles."""
    xs, ys = np.meshgrid(
        np.linspace(-width / 2, width / 2, n), np.linspace(-height / 2, height / 2, n)
    )
    z = 0.3 * np.cos(xs) * np.cos(0.5 * ys)
    vertices = np.stack([xs.ravel(), ys.ravel(), z.ravel()], axis=1)
    idx = np.arange(n * n).reshape(n, n)
    a, b, c, d = (
        idx[:-1, :-1].ravel(),
        idx[:-1, 1:].ravel(),
        idx[1:, :-1].ravel(),
        idx[1:, 1:].ravel(),
    )
    triangles = np.concatenate([np.stack([a, b, d], 1), np.stack([a, d, c], 1)])
    return vertices, triangles


def rotation_y(angle):
    c, s = np.cos(angle), np.sin(angle)
    return np.array([[c, 0, s], [0, 1, 0], [-s, 0, c]])


def tiny_case(
    n: int = 9,
    n_frames: int = 12,
    name: str = "tiny",
    layers: bool = True,
    head_motion: bool = True,
):
    """A source and a target rig with the same topology and semantics, and the ground truth."""
    vertices, triangles = grid(n)
    rows = vertices[:, 1].reshape(n, n)[:, 0]
    row = lambda j: np.arange(n * j, n * (j + 1))  # noqa: E731
    x, y = vertices[:, 0], vertices[:, 1]
    deltas = np.zeros((len(SHAPES), len(vertices), 3))
    deltas[0, :, 1] = -0.3 * np.clip(-y, 0, None)  # jaw: lower half moves down
    deltas[1, :, 1] = -0.2 * np.exp(-((x + 0.5) ** 2 + (y - 0.5) ** 2) / 0.1)  # left lid down
    deltas[2, :, 1] = 0.15 * np.clip(y - 0.6, 0, None)  # brow up
    deltas[3, :, 2] = 0.02 * np.cos(9 * x) * np.cos(9 * y)  # fine wrinkle detail
    target_neutral = vertices * [1.0, 1.1, 1.0]
    source_neutral = vertices * [0.9, 1.0, 1.2]
    target_rig = BlendshapeRig(
        Mesh(target_neutral, triangles),
        deltas,
        SHAPES,
        bounds=np.tile([0.0, 1.0], (len(SHAPES), 1)),
    )
    source_rig = BlendshapeRig(Mesh(source_neutral, triangles), 1.2 * deltas, SHAPES)
    t = np.linspace(0, 1, n_frames)
    weights = np.stack(
        [
            np.sin(np.pi * t) ** 2,
            (np.sin(3 * np.pi * t) > 0.8).astype(float),
            0.5 * t,
            0.8 * np.sin(np.pi * t),
        ],
        1,
    )
    if head_motion:
        motion = np.tile(np.eye(4), (n_frames, 1, 1))
        for f in range(n_frames):
            motion[f, :3, :3] = rotation_y(0.2 * np.sin(2 * np.pi * t[f]))
            motion[f, :3, 3] = [0.1 * t[f], 0.0, 0.05]
    else:
        motion = None
    lm_ids = np.array(
        [row(1)[4], row(2)[3], row(2)[5], row(6)[2], row(7)[2], row(6)[6], row(7)[6], row(4)[4]]
    )
    lines = {
        "lip_upper": row(3)[2:7],
        "lip_lower": row(2)[2:7],
        "eye_left_upper": row(7)[1:4],
        "eye_left_lower": row(6)[1:4],
    }
    source_local = source_rig.evaluate(weights)
    world = (
        source_local
        if motion is None
        else np.einsum("fij,fvj->fvi", motion[:, :3, :3], source_local) + motion[:, None, :3, 3]
    )
    source = Source(
        MeshSequence(world, triangles, reference=source_neutral),
        head_motion=motion,
        landmarks=Landmarks(lm_ids),
        feature_lines=lines,
        rig=source_rig,
    )
    layered = None
    if layers:
        masks = np.stack([(y > 0).astype(float), (y <= 0).astype(float)])
        layered = LayeredRig(
            {"emotion": target_neutral[None] + deltas[:2]}, masks, region_names=["upper", "lower"]
        )
    target = TargetRig(
        target_rig.neutral,
        blendshapes=target_rig,
        layers=layered,
        landmarks=Landmarks(lm_ids),
        feature_lines=lines,
    )
    truth = Animation(weights=weights, rig=target_rig, head_motion=motion, fps=30.0)
    return SimpleNamespace(
        name=name,
        source=source,
        target=target,
        truth=truth,
        meta={"weights": weights, "rows": rows},
    )


def _local(source: Source) -> np.ndarray:
    v = np.asarray(source.performance.vertices, dtype=np.float64)
    if source.head_motion is None:
        return v
    rot, trans = source.head_motion[:, :3, :3], source.head_motion[:, None, :3, 3]
    return np.einsum("fji,fvj->fvi", rot, v - trans)


class OracleFake(Retargeter):
    """Exact: solves the source rig's weights and drives the target rig with them."""

    name = "fake_oracle"
    capabilities = Capabilities(
        sources=("mesh",), needs=("blendshapes", "source_rig"), outputs="weights"
    )

    def __init__(self, *, scale=1.0):
        self.scale = scale

    def _fit(self, source, target):
        self.rig_ = target.blendshapes

    def _retarget(self, source):
        rig = source.rig
        disp = (_local(source) - rig.neutral.vertices).reshape(source.n_frames, -1)
        w = np.linalg.lstsq(rig.delta_matrix, disp.T, rcond=None)[0].T * self.scale
        return Animation(weights=w, rig=self.rig_, head_motion=source.head_motion, fps=source.fps)


class TransferFake(Retargeter):
    """Copies source displacements onto the target neutral (same topology); optional delay."""

    name = "fake_transfer"
    capabilities = Capabilities(sources=("mesh",), outputs="vertices", same_topology=True)

    def __init__(self, *, gain=1.0, delay=0.0):
        self.gain = gain
        self.delay = delay

    def _fit(self, source, target):
        self.neutral_ = np.asarray(target.neutral.vertices)
        self.triangles_ = np.asarray(target.neutral.triangles)

    def _retarget(self, source):
        time.sleep(self.delay)
        disp = _local(source) - np.asarray(source.performance.reference.vertices)
        local = self.neutral_ + self.gain * disp
        m = source.head_motion
        world = (
            local
            if m is None
            else np.einsum("fij,fvj->fvi", m[:, :3, :3], local) + m[:, None, :3, 3]
        )
        return Animation(vertices=world, triangles=self.triangles_, fps=source.fps)


class NeutralFake(Retargeter):
    """Zero weights (the neutral every frame)."""

    name = "fake_neutral"
    capabilities = Capabilities(
        sources=("mesh", "markers"), needs=("blendshapes",), outputs="weights"
    )

    def __init__(self):
        pass

    def _fit(self, source, target):
        self.rig_ = target.blendshapes

    def _retarget(self, source):
        return Animation(
            weights=np.zeros((source.n_frames, self.rig_.n_shapes)),
            rig=self.rig_,
            head_motion=source.head_motion,
        )


class BrokenFake(Retargeter):
    """Raises in fit."""

    name = "fake_broken"
    capabilities = Capabilities(sources=("mesh",))

    def __init__(self):
        pass

    def _fit(self, source, target):
        raise RuntimeError("boom in fit")


class WrongShapeFake(Retargeter):
    """Returns one vertex too few."""

    name = "fake_wrongshape"
    capabilities = Capabilities(sources=("mesh",))

    def __init__(self):
        pass

    def _fit(self, source, target):
        self.neutral_ = np.asarray(target.neutral.vertices)

    def _retarget(self, source):
        return Animation(vertices=np.repeat(self.neutral_[None, :-1], source.n_frames, axis=0))


class ExamplesFake(Retargeter):
    """Needs example poses the tiny case does not have."""

    name = "fake_examples"
    capabilities = Capabilities(sources=("mesh",), needs=("examples",))

    def __init__(self):  # the registry needs an explicit (empty) keyword signature
        pass


class BadCheckFake(Retargeter):
    """Its applicability check itself raises."""

    name = "fake_badcheck"
    capabilities = Capabilities(sources=("mesh",))

    def __init__(self):
        pass

    @classmethod
    def why_not(cls, source, target):
        raise KeyError("why_not is broken")


ALL = [
    OracleFake,
    TransferFake,
    NeutralFake,
    BrokenFake,
    WrongShapeFake,
    ExamplesFake,
    BadCheckFake,
]


@hookimpl
def faceretarget_retargeters():
    return ALL


def fake_registry():
    """A registry with the built-ins and these fakes (as plugin 'fakes', distribution 'local')."""
    import sys

    from faceretarget.registry import Registry

    return Registry().load(extra=[("fakes", sys.modules[__name__])])


def write_fake_npz(animation, path, **options):
    """A test writer for ``.fnpz``: the vertices and the method name."""
    with open(path, "wb") as fh:
        np.savez(
            fh,
            vertices=np.asarray(animation.vertices),
            method=str(animation.provenance.get("method", "")),
        )


@hookimpl
def faceretarget_writers():
    from faceretarget.hookspecs import Writer

    return [Writer("fake_npz", "animation", (".fnpz",), write_fake_npz, "test writer")]


# -- presets (paper reproductions) for the tests of compare(..., presets=...) -------------
def _frames_preset(cases, res):
    """Records each of the comparison's cases ("first", "second") and this process's id."""
    import os

    for name in ("first", "second"):
        frames = len(cases(name).truth.vertices)
        res.table.append({"case": name, "frames": frames, "pid": os.getpid()})
    res.agrees, res.evidence = True, "agrees: the cases arrived"


def _sleeper_preset(cases, res):
    time.sleep(600)


def _crash_preset(cases, res):
    import os

    os._exit(3)


def fake_presets():
    from faceretarget.hookspecs import Preset

    def make(name, run):
        return Preset(name, name, "no paper", "a test preset", run, claim="c", setting="s")

    return [
        make("fake_frames", _frames_preset),
        make("fake_sleeper", _sleeper_preset),
        make("fake_crash", _crash_preset),
    ]


@hookimpl
def faceretarget_presets():
    return fake_presets()
