"""The editable state of a coating result, stored in ``Animation.extras["coating"]``.

A :class:`CoatingTrack` holds what edits change (target bases, target weights, fine
detail layers) and what they read (source weights, head motion, the source's
transferred detail ``D_t + E_t``, cached in float32 when the result was computed in
memory, otherwise recomputed from the source frames on demand). It never changes after
construction: an edit builds a new track with :meth:`CoatingTrack.replace`.

Detail edits read the *wrinkles* ``D_t`` alone (:meth:`CoatingTrack.wrinkles`, the
coating against the Taubin-smoothed source frame, computed for the frames asked); the
synthesis uses the whole transferred detail (:meth:`CoatingTrack.fine_motion`), in which
the basis-fit residual ``E_t`` of eq. 7 is carried unchanged by detail edits.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from dataclasses import replace as dc_replace

import numpy as np

from .alignment import frame_chunks, to_world

__all__ = ["DetailLayer", "CoatingTrack"]


@dataclass(frozen=True)
class DetailLayer:
    """A fine-detail edit: ``D'_t[vertices] += delta[t - start]`` for ``start <= t < stop``."""

    start: int
    stop: int
    vertices: np.ndarray
    delta: np.ndarray  # (stop - start, P, 3) local coating coordinates


@dataclass(frozen=True)
class CoatingTrack:
    model: object
    performance: object
    source_motion: np.ndarray  # (F, 4, 4) head motion of the source frames (source world)
    placement: object  # :class:`~.alignment.Placement`: source local frames -> target frame
    motion: np.ndarray  # (F, 4, 4) head motion applied to the output (target world)
    source_weights: np.ndarray
    weights: np.ndarray
    bases: np.ndarray
    details: np.ndarray | None
    back: object
    target_vertex: np.ndarray
    chunk: int
    layers: tuple = field(default_factory=tuple)

    @property
    def n_frames(self) -> int:
        return int(self.weights.shape[0])

    def replace(self, **changes) -> CoatingTrack:
        return dc_replace(self, **changes)

    def _index(self, frames) -> np.ndarray:
        if isinstance(frames, slice):
            return np.arange(self.n_frames)[frames]
        return np.asarray(frames, dtype=np.int64).ravel()

    def _source_frames(self, idx: np.ndarray, compute) -> np.ndarray:
        """``compute(local source frames (n, V, 3), frame ids) -> (n, ...)`` over ``idx``, chunk by
        chunk, the frames read in increasing order."""
        out = None
        order = np.argsort(idx)
        for sl in frame_chunks(idx.size, self.chunk):
            sel = idx[order[sl]]
            local = self.placement.local(
                self.source_motion[sel], np.asarray(self.performance.vertices[sel])
            )
            block = compute(local, sel)
            if out is None:
                out = np.empty((idx.size,) + block.shape[1:])
            out[order[sl]] = block
        return out

    def fine_motion(self, frames, vertices=None) -> np.ndarray:
        """Target fine-scale motion ``D'_t + E_t`` (local coordinates) of ``frames`` -> ``(n, V, 3)``:
        the transferred detail with the detail edits' layers, as synthesized.

        ``vertices`` (ids of the common topology) restricts the result to ``(n, P, 3)``.
        """
        idx = self._index(frames)
        cols = (
            np.arange(self.model.n_vertices)
            if vertices is None
            else np.asarray(vertices, dtype=np.int64)
        )
        if self.details is not None:
            out = np.asarray(
                self.details[np.ix_(idx, cols)] if vertices is not None else self.details[idx],
                dtype=np.float64,
            )
        elif idx.size:
            out = self._source_frames(
                idx, lambda local, sel: self.model.decompose(local)[1][:, cols]
            )
        else:
            out = np.empty((0, cols.size, 3))
        return self._with_layers(out, idx, cols)

    def wrinkles(self, frames, vertices=None) -> np.ndarray:
        """The wrinkle layer ``D'_t`` (local coordinates) of ``frames`` -> ``(n, V, 3)`` (or ``(n, P, 3)``
        for ``vertices``): the source's coating against its Taubin-smoothed frames, with the
        detail edits' layers; without the basis-fit residual ``E_t``. One smoothing a frame."""
        idx = self._index(frames)
        cols = (
            np.arange(self.model.n_vertices)
            if vertices is None
            else np.asarray(vertices, dtype=np.int64)
        )
        if idx.size:
            out = self._source_frames(
                idx,
                lambda local, sel: self.model.wrinkles(local, self.source_weights[sel])[:, cols],
            )
        else:
            out = np.empty((0, cols.size, 3))
        return self._with_layers(out, idx, cols)

    def _with_layers(self, out: np.ndarray, idx: np.ndarray, cols: np.ndarray) -> np.ndarray:
        position = np.full(self.model.n_vertices, -1, dtype=np.int64)
        position[cols] = np.arange(cols.size)
        for layer in self.layers:
            hit = (idx >= layer.start) & (idx < layer.stop)
            where = position[layer.vertices]
            inside = where >= 0
            if hit.any() and inside.any():
                rows = np.flatnonzero(hit)
                out[rows[:, None], where[inside][None, :]] += layer.delta[idx[rows] - layer.start][
                    :, inside
                ]
        return out

    def local_frames(self, frames) -> np.ndarray:
        """Target frames ``(n, V, 3)`` in the common topology, head motion removed."""
        idx = self._index(frames)
        return self.model.synthesize(self.weights[idx], self.fine_motion(idx), self.bases)

    def world_frames(self, frames, out: np.ndarray | None = None) -> np.ndarray:
        """Target frames as output (head motion applied, target topology), chunk by chunk.

        Returns ``(n, V_t, 3)``; with ``out`` (e.g. a whole animation's vertices) frame
        ``idx[k]`` is written to ``out[idx[k]]`` instead and ``out`` is returned.
        """
        idx = self._index(frames)
        result = np.empty((idx.size, self.target_vertex.size, 3)) if out is None else out
        for sl in frame_chunks(idx.size, self.chunk):
            sel = idx[sl]
            block = to_world(self.motion[sel], self.back(self.local_frames(sel)))
            if out is None:
                result[sl] = block
            else:
                result[sel] = block
        return result
