"""Rigid head motion of a mesh performance: estimate, remove, re-apply.

The source vertices are in world coordinates (head motion included). Xu et al. work on
the "rigidly aligned source sequence" (sec. 4.1); we estimate each frame's rigid motion
by Procrustes against the source reference, in two passes over the frames: the first
on every vertex (:func:`stable_vertices`), the second, folded into the pass that then
uses the frames, on the most *stable* vertices only (the fraction ``stable_fraction``
with the smallest residual motion after the first pass: forehead, nose bridge), so
expressions (a jaw drop) bias the estimate less. The same stable vertices fix the
translation gauge of deformation transfer. When the source carries its known head
motion (``Source.head_motion``), it is used instead of the estimate.

The motion is re-applied to the retargeted target frames, so rigid motion is carried
exactly and never turned into expression. Rigid fits use at most ``ALIGN_POINTS``
evenly spaced vertices: plenty for six parameters.
"""
from __future__ import annotations

import numpy as np

from faceretarget.geometry.procrustes import fit_rigid, to_matrix

__all__ = ["ALIGN_POINTS", "frame_chunks", "RigidFit", "stable_weights", "ResidualMotion", "stable_vertices", "to_local", "to_world"]

ALIGN_POINTS = 4000


def frame_chunks(n_frames: int, chunk: int):
    """Consecutive ``slice`` objects of at most ``chunk`` frames."""
    step = max(1, int(chunk))
    for start in range(0, n_frames, step):
        yield slice(start, min(n_frames, start + step))


def _rigid(motion, points, inverse):
    from ._kernels import rigid

    p = np.asarray(points)
    if p.dtype not in (np.float32, np.float64):
        p = p.astype(np.float64)
    p = np.ascontiguousarray(p)
    out = np.empty(p.shape, dtype=np.float64)
    rigid(p, np.ascontiguousarray(motion, dtype=np.float64), out, inverse)
    return out


def to_local(motion: np.ndarray, points: np.ndarray) -> np.ndarray:
    """Undo ``motion (C, 4, 4)`` on world ``points (C, V, 3)``: ``R^T (x - t)`` (float64)."""
    return _rigid(motion, points, True)


def to_world(motion: np.ndarray, points: np.ndarray) -> np.ndarray:
    """Apply ``motion (C, 4, 4)`` to local ``points (C, V, 3)``: ``R x + t``."""
    return _rigid(motion, points, False)


class RigidFit:
    """Procrustes fit of frames onto a reference, on a fixed (weighted) subset of vertices.

    reference : (V, 3); weights : (V,) or None (all vertices count). Calling it on a chunk
    of world frames ``(C, V, 3)`` returns their motions ``(C, 4, 4)`` (reference -> frame).
    """

    def __init__(self, reference: np.ndarray, weights: np.ndarray | None = None):
        ref = np.asarray(reference, dtype=np.float64)
        candidates = np.arange(ref.shape[0]) if weights is None else np.flatnonzero(np.asarray(weights) > 0)
        pick = np.unique(np.linspace(0, candidates.size - 1, min(ALIGN_POINTS, candidates.size)).round().astype(np.int64))
        self.ids = candidates[pick]
        self.reference = ref[self.ids]
        self.weights = None if weights is None else np.asarray(weights, dtype=np.float64)[self.ids]

    def __call__(self, frames: np.ndarray) -> np.ndarray:
        return self.reference_fit(frames[:, self.ids])

    def reference_fit(self, points: np.ndarray) -> np.ndarray:
        """Motions ``(C, 4, 4)`` of frames already restricted to ``self.ids`` (``(C, len(ids), 3)``)."""
        rot, trans, _ = fit_rigid(self.reference, np.asarray(points, dtype=np.float64), self.weights)
        return to_matrix(rot, trans)


class ResidualMotion:
    """Accumulates each vertex's squared displacement from the reference once motion is removed."""

    def __init__(self, reference: np.ndarray):
        self.reference = np.asarray(reference, dtype=np.float64)
        self.total = np.zeros(self.reference.shape[0])
        self.count = 0

    def add(self, local: np.ndarray) -> None:
        self.total += np.sum((local - self.reference) ** 2, axis=(0, 2))
        self.count += local.shape[0]

    def rms(self) -> np.ndarray:
        return np.sqrt(self.total / max(1, self.count))


def stable_weights(residual: np.ndarray, fraction: float) -> np.ndarray:
    """(V,) 0/1 weights of the ``fraction`` of vertices with the smallest residual motion.

    All vertices when the residual is (numerically) the same everywhere (a static or
    purely rigid performance).
    """
    r = np.asarray(residual, dtype=np.float64)
    if r.max() <= 1e-12 * max(1.0, r.max()) or r.max() - r.min() <= 1e-9 * max(r.max(), 1e-300):
        return np.ones_like(r)
    cut = np.quantile(r, min(max(float(fraction), 0.05), 1.0))
    w = (r <= cut).astype(np.float64)
    return w if w.sum() >= 3 else np.ones_like(r)


def stable_vertices(reference: np.ndarray, vertices, *, stable_fraction: float, chunk: int, motion: np.ndarray | None = None) -> np.ndarray:
    """First pass: the stable-vertex weights ``(V,)`` (non-zero on stable vertices of an even
    subsample of at most ``ALIGN_POINTS``).

    Each frame's motion is fitted on the subsample (or taken from the known ``motion``),
    and the residual motion of the subsample's vertices decides which are stable.
    ``vertices : (F, V, 3)`` world frames, possibly memory-mapped (read ``chunk`` at a time).
    """
    fit = RigidFit(reference)
    ids = fit.ids
    residual = ResidualMotion(np.asarray(reference, dtype=np.float64)[ids])
    for sl in frame_chunks(vertices.shape[0], chunk):
        frames = np.asarray(vertices[sl][:, ids])
        m = fit.reference_fit(frames) if motion is None else np.asarray(motion[sl], dtype=np.float64)
        residual.add(to_local(m, frames))
    weights = np.zeros(np.asarray(reference).shape[0])
    weights[ids] = stable_weights(residual.rms(), stable_fraction)
    return weights
