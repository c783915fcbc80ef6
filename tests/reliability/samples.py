"""Small valid model objects of every data kind, and seed files written by the registered writers.

Imported as ``reliability.samples``. Everything is derived from the registry, so a format
added by a plugin gets seeds (and is fuzzed) without changes here.
"""

from __future__ import annotations

import functools
from pathlib import Path

import numpy as np

import faceretarget as fr
from faceretarget.errors import FaceRetargetError
from faceretarget.registry import registry

ARKIT = ["jawOpen", "mouthSmileLeft", "eyeBlinkRight"]


def grid_mesh(n: int = 3) -> fr.Mesh:
    """An ``n x n`` vertex grid in the z = 0 plane, two triangles per cell."""
    xs, ys = np.meshgrid(np.arange(n, dtype=float), np.arange(n, dtype=float))
    vertices = np.stack([xs.ravel(), ys.ravel(), 0.1 * xs.ravel() * ys.ravel()], axis=1)
    tris = []
    for i in range(n - 1):
        for j in range(n - 1):
            a, b, c, d = i * n + j, i * n + j + 1, (i + 1) * n + j, (i + 1) * n + j + 1
            tris += [[a, b, d], [a, d, c]]
    return fr.Mesh(vertices, np.array(tris), name="grid")


def sample(kind: str, *, frames: int = 4, n: int = 3):
    """A small valid object of ``kind`` (one of ``faceretarget.hookspecs.DATA_KINDS``)."""
    mesh = grid_mesh(n)
    rng = np.random.default_rng(7)
    v = np.asarray(mesh.vertices)
    if kind == "mesh":
        return mesh
    if kind == "mesh_sequence":
        return fr.MeshSequence(
            v[None] + 0.01 * rng.normal(size=(frames,) + v.shape), mesh.triangles, fps=24.0
        )
    rig = fr.BlendshapeRig(mesh, 0.1 * rng.normal(size=(len(ARKIT),) + v.shape), ARKIT)
    if kind == "rig":
        return rig
    if kind == "markers":
        n_markers = max(5, n)
        pos = rng.normal(size=(frames, n_markers, 3))
        pos[frames - 1, 1] = (
            np.nan
        )  # a missing sample (frame 0 stays complete: it is the reference)
        return fr.MarkerSequence(pos, names=[f"m{i}" for i in range(n_markers)], fps=60.0)
    if kind == "weights":
        return fr.WeightSequence(rng.uniform(0, 1, size=(frames, len(ARKIT))), ARKIT, fps=30.0)
    if kind == "animation":
        return fr.Animation(weights=rng.uniform(0, 1, size=(frames, len(ARKIT))), rig=rig, fps=30.0)
    raise ValueError(kind)


def readers():
    """Every registered (Reader, PluginInfo), as pytest ids -> records."""
    return list(registry().readers)


def writers():
    return list(registry().writers)


def _suffix(ext: str) -> str:
    return "" if ext == "/" else ext


def _try_read(reader, path: Path, kind_obj):
    """Options that let ``reader`` read ``path`` (None if it cannot)."""
    topology = kind_obj.triangles if hasattr(kind_obj, "triangles") else None
    candidates = [{}]
    if topology is not None:
        topology_mesh = kind_obj.reference if isinstance(kind_obj, fr.MeshSequence) else grid_mesh()
        candidates.append({"topology": topology_mesh})
    for options in candidates:
        try:
            reader.read(path, **options)
            return options
        except FaceRetargetError:
            continue
    return None


@functools.cache
def seed(reader_name: str, folder: str, n: int = 3):
    """A valid file for the reader called ``reader_name`` written by a registered writer
    (from a sample with an ``n x n`` vertex grid).

    Returns ``(path, options)`` such that ``reader.read(path, **options)`` succeeds, or
    None when no registered writer produces a file this reader accepts.
    """
    reader = next(r for r, _ in readers() if r.name == reader_name)
    root = Path(folder)
    root.mkdir(parents=True, exist_ok=True)
    for ext in reader.extensions:
        ranked = sorted(
            (w for w, _ in writers() if ext in w.extensions), key=lambda w: w.kind != reader.kind
        )
        for i, writer in enumerate(ranked):
            obj = sample(writer.kind, n=n, frames=4 if n <= 3 else 4 * n)
            path = root / f"seed_{reader_name}_{n}_{i}{_suffix(ext)}"
            try:
                writer.write(obj, path, force=True)
            except FaceRetargetError:
                continue
            options = _try_read(reader, path, obj)
            if options is not None:
                return path, options
    return None
