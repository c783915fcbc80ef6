"""The fitted coating transfer: decomposition, bases, basis transfer, synthesis.

:class:`CoatingModel` holds everything that depends on the (source reference, target
reference) pair and the source bases; per-frame work is done in chunks of frames by
:meth:`CoatingModel.decompose` (source frame -> weights + fine-scale motion) and
:meth:`CoatingModel.synthesize` (weights + fine-scale motion -> target frame), so a
sequence of any length is processed with memory bounded by the chunk size.

Per frame (local coordinates, head motion removed)::

    S~_t = smooth(S_t)                      Taubin (sec. 3)
    c_t  = F(S~_t)^T M_S (S_t - S~_t)       coating (eq. 1)
    D_t  = c_t - c_0                        fine-scale motion (eq. 3)
    w_t  = NNLS(S~_t; b_1..b_K)             weights (eq. 6)
    T~_t = sum_i w_ti b'_i                  target smooth frame (eq. 8)
    T_t  = T~_t + M_T^-1 F(T~_t) (c'_0 + D_t)   (eq. 5 with eq. 16)

Eq. 16 rotates the source coating difference by the rotation ``R_v`` between the source
and target local frames; with coatings stored in local coordinates that rotation is
``F_T F_S^T`` applied implicitly: the same local coordinates are read in the target's
frame. Source and target share the tangent neighbours, so their tangents correspond.
"""
from __future__ import annotations

import numpy as np

from faceretarget.geometry.deformation_gradients import DeformationTransfer
from functools import cached_property

from faceretarget.geometry.mesh_ops import face_areas, unique_edges, vertex_adjacency

from .alignment import frame_chunks, to_local
from .bases import BasisSpace, blend, select_bases, selection_vertices
from .multiscale import MultiScale

__all__ = ["CoatingModel", "size_ratio"]


def size_ratio(source: np.ndarray, target: np.ndarray, triangles: np.ndarray) -> float:
    """sqrt of the surface-area ratio target / source (a linear size ratio)."""
    return float(np.sqrt(face_areas(target, triangles).sum() / face_areas(source, triangles).sum()))


class CoatingModel:
    """Coating transfer between a source and a target of one topology.

    Parameters
    ----------
    source_reference, target_reference : (V, 3)
    triangles : (T, 3)
    source_lines, target_lines : {name: vertex chain}
    stable : (V,) weights of the stable vertices (translation gauge)
    iterations, laplacian, screening, sigma : see the retargeter
    detail_scale : float or "auto" (the target/source size ratio, :func:`size_ratio`)
    """

    def __init__(self, source_reference, target_reference, triangles, *, source_lines, target_lines, stable, iterations, laplacian, screening, sigma, detail_scale):
        self.triangles = np.asarray(triangles, dtype=np.int64)
        self.source = MultiScale(source_reference, triangles, iterations=iterations, laplacian=laplacian, screening=screening)
        self.target = MultiScale(target_reference, triangles, iterations=iterations, laplacian=laplacian, screening=screening, neighbors=self.source.neighbors)
        self.source_lines = {k: np.asarray(v) for k, v in source_lines.items()}
        self.target_lines = {k: np.asarray(v) for k, v in target_lines.items()}
        self.stable = np.asarray(stable, dtype=np.float64)
        self.transfer = DeformationTransfer(self.target.smooth_reference, triangles, feature_lines=self.target_lines or None, sigma=sigma, gauge_weights=self.stable)
        self.ratio = size_ratio(self.source.smooth_reference, self.target.smooth_reference, triangles)
        self.detail_scale = self.ratio if detail_scale == "auto" else float(detail_scale)
        self.source_center = self.source.smooth_reference.mean(axis=0)
        self.target_center = self.target.smooth_reference.mean(axis=0)
        self.basis_frames: list[int] = []
        self.selection_rms: list[float] = []
        for factor in (self.target.factor, self.transfer.factor):  # factorize now (one-time setup)
            factor.solve(np.zeros(factor.n))
        self.adjacency  # noqa: B018 - build the edit-time topology now (one-time setup)

    @property
    def n_vertices(self) -> int:
        return self.source.n_vertices

    @cached_property
    def edges(self) -> np.ndarray:
        """(E, 2) unique mesh edges."""
        return unique_edges(self.triangles)

    @cached_property
    def adjacency(self):
        """(V, V) CSR 0/1 vertex adjacency."""
        return vertex_adjacency(self.triangles, self.n_vertices)

    # -- fitting -------------------------------------------------------------------------
    def fit_bases(self, vertices, motion_of, *, epsilon: float, max_bases: int, height: float, chunk: int, max_frames: int) -> None:
        """Select source bases among the frames ``vertices (F, V, 3)`` and transfer them (sec. 4.1-4.2).

        ``motion_of(frame_ids, frames) -> (n, 4, 4)`` gives the head motion to remove.
        Candidates are at most ``max_frames`` evenly spaced frames (all of them for shorter
        sequences): neighbouring frames of a 30-60 fps capture are near duplicates, and
        every candidate must be smoothed. Only candidate frames are read.
        """
        ids = selection_vertices(self.n_vertices)
        n_frames = vertices.shape[0]
        candidates = np.unique(np.linspace(0, n_frames - 1, min(n_frames, int(max_frames))).round().astype(np.int64))
        samples = np.empty((candidates.size, 3 * ids.size))
        for sl in frame_chunks(candidates.size, chunk):
            picked = candidates[sl]
            frames = np.asarray(vertices[picked])
            smooth = self.source.smooth(to_local(motion_of(picked, frames), frames))
            samples[sl] = (smooth[:, ids] - self.source_center).reshape(smooth.shape[0], -1)
        reference = (self.source.smooth_reference[ids] - self.source_center).ravel()
        chosen, history = select_bases(samples, reference, epsilon=epsilon, max_bases=max_bases, height=height)
        frames = [int(candidates[i]) for i in chosen]
        self.basis_frames = frames
        self.selection_rms = history
        bases = [self.source.smooth_reference[None]]
        if frames:
            picked = np.asarray(frames)
            raw = np.asarray(vertices[np.sort(picked)])[np.argsort(np.argsort(picked))]
            bases.append(self.source.smooth(to_local(motion_of(picked, raw), raw)))
        self.set_source_bases(np.concatenate(bases))

    def set_source_bases(self, bases: np.ndarray) -> None:
        """Use ``bases (K, V, 3)`` (smooth source meshes, the reference first) and transfer them."""
        self.source_bases = np.asarray(bases, dtype=np.float64)
        self.space = BasisSpace(self.source_bases, self.source_center, adjoint=self.source.adjoint)
        self._source_flat = (self.source_bases - self.source_center).reshape(self.source_bases.shape[0], -1)
        self.target_bases = self.transfer_bases(self.source_bases)
        self._target_flat = (self.target_bases - self.target_center).reshape(self.target_bases.shape[0], -1)

    def transfer_bases(self, bases: np.ndarray) -> np.ndarray:
        """Feature-preserving deformation transfer of smooth source meshes (eq. 9-11)."""
        ref = self.source.smooth_reference
        means = self.transfer.component_means(bases - ref) * self.ratio
        return self.transfer.transfer(ref, bases, source_feature_lines=self.source_lines or None, mean_displacement=means)

    # -- per frame -------------------------------------------------------------------------
    def decompose(self, local: np.ndarray):
        """Source frames ``(C, V, 3)`` (head motion removed) -> ``(weights (C, K), D (C, V, 3))``.

        The weights are those of the Taubin-smoothed frames (eq. 6), computed exactly from
        the raw frames through the adjoint filter; the smooth mesh the coating is taken
        against is the blend of the bases, ``S~_t = sum_i w_ti b_i`` (eq. 6 itself), so the
        small residual of eq. 7 stays in the coating (and is transferred) instead of being
        dropped, and frames are not smoothed one by one.
        """
        weights = self.space.weights_of_raw(local)
        smooth = (weights @ self._source_flat).reshape(local.shape) + self.source_center
        coating = self.source.coating(local, smooth)
        return weights, coating - self.source.reference_coating

    def smooth_target(self, weights: np.ndarray, bases: np.ndarray | None = None) -> np.ndarray:
        """Target smooth frames ``T~_t`` (eq. 8) -> ``(C, V, 3)``."""
        if bases is None or bases is self.target_bases:
            w = np.asarray(weights, dtype=np.float64)
            return (w @ self._target_flat).reshape(w.shape[0], self.n_vertices, 3) + self.target_center
        return blend(bases, self.target_center, weights)

    def synthesize(self, weights: np.ndarray, details: np.ndarray, bases: np.ndarray | None = None) -> np.ndarray:
        """Target frames (local coordinates) from weights and fine-scale motion (eq. 5)."""
        smooth = self.smooth_target(weights, bases)
        coating = self.target.reference_coating + self.detail_scale * np.asarray(details, dtype=np.float64)
        return self.target.reconstruct(smooth, coating)
