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

**No invented head motion** (:func:`estimate_motion`). A Procrustes fit always finds
*some* motion: the expressions move the stable vertices a little, and the fit takes
part of that for head motion (0.1-0.5 degrees on the synthetic, ICT and cross-rig cases
without head motion). The estimate is kept only when it is significant, by the test of
:mod:`faceretarget.geometry.head_motion` (evaluated chunk by chunk, without an
expression basis): with ``c0_f`` the stable vertices' squared displacement from the
reference and ``c1_f`` what remains once the fitted motion is removed, the motion is kept
if, over some ``window`` consecutive frames (one second), ``sum (c0 - c1) >
HEAD_MOTION_GATE * sum (c1 + floor)``; otherwise every frame gets exactly the identity.
Measured: sources without head motion 0.26-0.51 (synthetic, ICT, cross_rig), real head
motion 1,000-6,000 (the cases' 10 degrees), 4.5 for a 0.5-degree nod over four seconds,
5.5 for a one-degree turn of a second. A missed small motion is harmless here (the
transfer then carries it as deformation, rotation included); an invented one is not:
it makes the result depend on where the source and target sit in space.

**Source in the target's frame and units** (:class:`Placement`). Deformation gradients
are not invariant to a rotation of the source relative to the target (a rotated source
transfers rotated gradients), and detail magnitudes and head translations are in the
source's units. The local source frames are therefore mapped by the similarity
``x -> u R (x - c_s)`` that best aligns the source reference with the target reference
centred on its centroid ``c_t`` (Procrustes, all vertices; the transfer works in these
centred target coordinates, so a far-away target loses no float32 precision in the
smoothing), whose scale ``u`` is the Procrustes scale rounded
to a power of ten: a change of units (metres, centimetres, millimetres) is undone, while
a genuinely larger or smaller face (ratios 0.32-3.2) keeps the source's absolute detail
magnitudes (the paper's convention; ``detail_scale='auto'`` scales them by the face-size
ratio). The result, in the target's units, then does not change when either mesh is
scaled by a power of ten or moved rigidly (tested to 1e-6 relative). Head motion is
carried in world axes, its translation times ``u`` (a head turning in the source's world
turns the target the same way in the target's world, as the parallel-rig cases define it).
"""

from __future__ import annotations

import numpy as np

from faceretarget.geometry.mesh_ops import translated
from faceretarget.geometry.procrustes import apply as apply_transform
from faceretarget.geometry.procrustes import fit_rigid, to_matrix
from faceretarget.geometry.procrustes import remove as remove_transform

__all__ = [
    "ALIGN_POINTS",
    "HEAD_MOTION_GATE",
    "frame_chunks",
    "RigidFit",
    "stable_weights",
    "ResidualMotion",
    "stable_vertices",
    "estimate_motion",
    "Placement",
    "to_local",
    "to_world",
]

ALIGN_POINTS = 4000
#: Significance gate of the estimated head motion (see the module doc): 6x the largest
#: ratio measured on sources without head motion.
HEAD_MOTION_GATE = 3.0
#: Noise floor of the gate, a fraction of the face size (RMS radius of the reference).
HEAD_MOTION_NOISE_FLOOR = 1e-3


def frame_chunks(n_frames: int, chunk: int):
    """Consecutive ``slice`` objects of at most ``chunk`` frames."""
    step = max(1, int(chunk))
    for start in range(0, n_frames, step):
        yield slice(start, min(n_frames, start + step))


def to_local(motion: np.ndarray, points: np.ndarray) -> np.ndarray:
    """Undo ``motion (C, 4, 4)`` on world ``points (C, V, 3)``: ``R^T (x - t)`` (float64;
    :func:`faceretarget.geometry.procrustes.remove`)."""
    return remove_transform(motion, points)


def to_world(motion: np.ndarray, points: np.ndarray) -> np.ndarray:
    """Apply ``motion (C, 4, 4)`` to local ``points (C, V, 3)``: ``R x + t`` (float64;
    :func:`faceretarget.geometry.procrustes.apply`)."""
    return apply_transform(motion, points)


class RigidFit:
    """Procrustes fit of frames onto a reference, on a fixed (weighted) subset of vertices.

    reference : (V, 3); weights : (V,) or None (all vertices count). Calling it on a chunk
    of world frames ``(C, V, 3)`` returns their motions ``(C, 4, 4)`` (reference -> frame).
    """

    def __init__(self, reference: np.ndarray, weights: np.ndarray | None = None):
        ref = np.asarray(reference, dtype=np.float64)
        candidates = (
            np.arange(ref.shape[0]) if weights is None else np.flatnonzero(np.asarray(weights) > 0)
        )
        pick = np.unique(
            np.linspace(0, candidates.size - 1, min(ALIGN_POINTS, candidates.size))
            .round()
            .astype(np.int64)
        )
        self.ids = candidates[pick]
        self.reference = ref[self.ids]
        self.weights = None if weights is None else np.asarray(weights, dtype=np.float64)[self.ids]

    def __call__(self, frames: np.ndarray) -> np.ndarray:
        return self.reference_fit(frames[:, self.ids])

    def reference_fit(self, points: np.ndarray) -> np.ndarray:
        """Motions ``(C, 4, 4)`` of frames already restricted to ``self.ids`` (``(C, len(ids), 3)``)."""
        rot, trans, _ = fit_rigid(
            self.reference, np.asarray(points, dtype=np.float64), self.weights
        )
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


def stable_vertices(
    reference: np.ndarray,
    vertices,
    *,
    stable_fraction: float,
    chunk: int,
    motion: np.ndarray | None = None,
) -> np.ndarray:
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
        m = (
            fit.reference_fit(frames)
            if motion is None
            else np.asarray(motion[sl], dtype=np.float64)
        )
        residual.add(to_local(m, frames))
    weights = np.zeros(np.asarray(reference).shape[0])
    weights[ids] = stable_weights(residual.rms(), stable_fraction)
    return weights


def estimate_motion(
    reference: np.ndarray, vertices, stable: np.ndarray, *, chunk: int, window: int
) -> tuple[np.ndarray, float]:
    """Head motion ``(F, 4, 4)`` of world frames ``vertices (F, V, 3)`` and the gate's evidence.

    Each frame's motion is a Procrustes fit on the stable vertices (``stable``, from
    :func:`stable_vertices`); the frames are read ``chunk`` at a time (only the fitted
    vertices). The motion is kept only if it passes the significance gate over ``window``
    consecutive frames (see the module doc); otherwise it is exactly the identity.
    Returns ``(motion, evidence)``.
    """
    fit = RigidFit(reference, stable)
    ref = fit.reference
    w = np.ones(ref.shape[0]) if fit.weights is None else fit.weights
    n_frames = vertices.shape[0]
    motion = np.empty((n_frames, 4, 4))
    c0 = np.empty(n_frames)
    c1 = np.empty(n_frames)
    for sl in frame_chunks(n_frames, chunk):
        frames = np.asarray(vertices[sl][:, fit.ids], dtype=np.float64)
        m = fit.reference_fit(frames)
        motion[sl] = m
        c0[sl] = np.einsum("v,fvd->f", w, (frames - ref) ** 2)
        c1[sl] = np.einsum("v,fvd->f", w, (to_local(m, frames) - ref) ** 2)
    centre = (w @ ref) / w.sum()
    size = float(np.sqrt((w @ np.sum((ref - centre) ** 2, axis=1)) / w.sum()))
    floor = (HEAD_MOTION_NOISE_FLOOR * size) ** 2 * 3.0 * w.sum()
    span = max(1, min(int(window), n_frames))
    kernel = np.ones(span)
    gain = np.convolve(c0 - c1, kernel, mode="valid")
    left = np.convolve(c1 + floor, kernel, mode="valid")
    evidence = float(np.max(gain / np.maximum(left, np.finfo(float).tiny))) if n_frames else 0.0
    if not evidence > HEAD_MOTION_GATE:
        motion[:] = np.eye(4)
    return motion, evidence


class Placement:
    """The similarity bringing (head-motion-free) source frames into the transfer's coordinates:
    the target's frame and units, centred on the target reference's centroid.

    ``x -> u R (x - c_s)``: ``R`` and the centroids ``c_s``, ``c_t`` from the Procrustes fit
    of ``source_reference`` onto ``target_reference`` (same vertex order), ``u`` its scale
    rounded to a power of ten (see the module doc). Target points enter the transfer's
    coordinates by :meth:`to_model` (minus ``c_t``) and leave them by :meth:`to_target`.
    """

    def __init__(self, source_reference: np.ndarray, target_reference: np.ndarray):
        src = np.asarray(source_reference, dtype=np.float64)
        tgt = np.asarray(target_reference, dtype=np.float64)
        rot, _, scale = fit_rigid(src, tgt, scale=True)
        self.scale = float(scale)
        self.unit = float(10.0 ** np.round(np.log10(self.scale)))
        self.rotation = np.asarray(rot, dtype=np.float64)
        self.source_center = src.mean(axis=0)
        self.target_center = tgt.mean(axis=0)
        m = np.eye(4)
        m[:3, :3] = self.unit * self.rotation
        m[:3, 3] = -m[:3, :3] @ self.source_center
        self.matrix = m

    def to_model(self, points: np.ndarray) -> np.ndarray:
        """Target points (head motion removed) -> the transfer's coordinates."""
        return translated(points, -self.target_center)

    def to_target(self, points: np.ndarray) -> np.ndarray:
        """The transfer's coordinates -> target points (head motion removed)."""
        return translated(points, self.target_center)

    def model_transform(self, transform: np.ndarray) -> np.ndarray:
        """A 4x4 transform of target points (head motion removed) as one of the transfer's coordinates."""
        shift = np.eye(4)
        shift[:3, 3] = self.target_center
        back = np.eye(4)
        back[:3, 3] = -self.target_center
        return back @ np.asarray(transform, dtype=np.float64) @ shift

    def __call__(self, points: np.ndarray) -> np.ndarray:
        """Source points ``(..., V, 3)`` (head motion removed) in the transfer's coordinates."""
        p = np.asarray(points, dtype=np.float64)
        return p @ self.matrix[:3, :3].T + self.matrix[:3, 3]

    def local(self, motion: np.ndarray, frames: np.ndarray) -> np.ndarray:
        """World source frames ``(C, V, 3)`` with their head ``motion (C, 4, 4)`` removed, in the
        transfer's coordinates: one pass (the similarity and the inverse motion composed)."""
        m = np.asarray(motion, dtype=np.float64)
        inverse = np.zeros_like(m)
        rt = np.transpose(m[:, :3, :3], (0, 2, 1))
        inverse[:, :3, :3] = rt
        inverse[:, :3, 3] = -np.einsum("fij,fj->fi", rt, m[:, :3, 3])
        inverse[:, 3, 3] = 1.0
        return to_world(self.matrix @ inverse, frames)

    def target_motion(self, motion: np.ndarray) -> np.ndarray:
        """Source head motion ``(F, 4, 4)`` as applied to the target: world axes, translation
        in the target's units (times ``unit``)."""
        out = np.array(motion, dtype=np.float64)
        out[:, :3, 3] *= self.unit
        return out
