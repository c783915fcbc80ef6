"""The fitted coating transfer: decomposition, bases, basis transfer, synthesis.

:class:`CoatingModel` holds everything that depends on the (source reference, target
reference) pair and the source bases; per-frame work is done in chunks of frames by
:meth:`CoatingModel.decompose` (source frame -> weights + fine-scale motion) and
:meth:`CoatingModel.synthesize` (weights + fine-scale motion -> target frame), so a
sequence of any length is processed with memory bounded by the chunk size.

Per frame (local coordinates in the target's frame and units, head motion removed)::

    w_t  = NNLS(G S_t; b_1..b_K)            weights of the Taubin-smoothed frame (eq. 6)
    B_t  = sum_i w_ti b_i                   the frame's smooth mesh as the bases see it
    D_t  = F(B_t)^T M_S (S_t - G S_t) - c_0     fine-scale motion: the wrinkles (eq. 1, 3)
    E_t  = F(B_t)^T M_S (G S_t - B_t)       residual of eq. 7 (what the bases miss)
    T~_t = sum_i w_ti b'_i                  target smooth frame (eq. 8)
    T_t  = T~_t + M_T^-1 F(T~_t) (c'_0 + D_t + E_t)   (eq. 5 with eq. 16)

The transfer needs only the sum ``D_t + E_t = F(B_t)^T M_S (S_t - B_t) - c_0``, which
costs no smoothing of the frame (:meth:`CoatingModel.decompose`); the two layers are
separated (one Taubin smoothing a frame, :meth:`CoatingModel.wrinkles`) only where a
detail edit reads the wrinkles, so detail edits and their active ranges act on ``D_t``
and the basis-fit residual ``E_t`` is carried unchanged.

Eq. 16 rotates the source coating difference by the rotation ``R_v`` between the source
and target local frames; with coatings stored in local coordinates that rotation is
``F_T F_S^T`` applied implicitly: the same local coordinates are read in the target's
frame. Source and target share the tangent neighbours, so their tangents correspond.
"""

from __future__ import annotations

from functools import cached_property

import numpy as np
import scipy.sparse as sp

from faceretarget import config
from faceretarget.geometry.deformation_gradients import DeformationTransfer
from faceretarget.geometry.factorized import SPDFactor, factorize
from faceretarget.geometry.local_frames import frame_neighbors
from faceretarget.geometry.mesh_ops import face_areas, unique_edges, vertex_adjacency
from faceretarget.geometry.smoothing import SmoothedDisplacements

from .alignment import frame_chunks
from .bases import BasisSpace, blend, blend_flat, select_bases, selection_vertices
from .multiscale import MultiScale, filter_pair

__all__ = [
    "CoatingModel",
    "size_ratio",
    "face_size",
    "line_logs",
    "line_proportion",
    "weight_lines",
    "LINE_PROPORTION_SCALE",
    "canonical_axes",
]

#: Feature-line weight, per line: ``sigma_l = sigma * exp(-(d_l / LINE_PROPORTION_SCALE)^2)``
#: with ``d_l`` the log-ratio of the target's to the source's length of line ``l``, relative
#: to the face-size ratio (:func:`line_logs`). 0.1: lines within ~5% of the source's
#: proportions keep most of the weight (synthetic human 0.55-0.83, ICT 0.85-0.93), lines
#: 40-70% larger (the stylized target's eyes and mouth) none, and so does a line of another
#: shape (a closed eye's slit against an open eye's rim: cases.cross_topology, d = 0.3-1.0).
LINE_PROPORTION_SCALE = 0.1
#: The candidates' displacements are held (float32, coordinate-major) when they fit in this
#: many bytes and smoothed through their column space (``SmoothedDisplacements``: rank-many
#: rows instead of every frame's three; its float64 rows take at most as much again); above
#: it (e.g. 250 candidates at 160K vertices) every candidate is smoothed chunk by chunk and
#: the chosen frames are smoothed again. At 80K vertices and 130 candidates: 126 MB.
CANDIDATE_CACHE_BYTES = 256 * 2**20


def size_ratio(source: np.ndarray, target: np.ndarray, triangles: np.ndarray) -> float:
    """sqrt of the surface-area ratio target / source (a linear size ratio)."""
    return float(np.sqrt(face_areas(target, triangles).sum() / face_areas(source, triangles).sum()))


def face_size(vertices: np.ndarray, triangles: np.ndarray) -> float:
    """Square root of the surface area: a size that does not depend on the mesh's orientation
    (0.97-1.2 times the y-extent of the synthetic and ICT faces)."""
    return float(np.sqrt(face_areas(vertices, triangles).sum()))


def line_logs(
    source: np.ndarray,
    target: np.ndarray,
    triangles: np.ndarray,
    source_lines: dict,
    target_lines: dict,
) -> dict[str, float]:
    """``{line: log(L_target / (L_source * r))}``: how much each target feature line differs in
    proportion from the source's line of the same name (``L`` the chain lengths, ``r`` the
    face-size ratio :func:`size_ratio`); lines without a usable counterpart are left out."""
    r = size_ratio(source, target, triangles)
    logs = {}
    for name, chain in target_lines.items():
        if name not in source_lines:
            continue
        t_chain, s_chain = np.asarray(chain), np.asarray(source_lines[name])
        if t_chain.size < 2 or s_chain.size < 2:
            continue
        lt = np.linalg.norm(np.diff(target[t_chain], axis=0), axis=1).sum()
        ls = np.linalg.norm(np.diff(source[s_chain], axis=0), axis=1).sum()
        if lt > 0 and ls > 0:
            logs[name] = float(np.log(lt / (ls * r)))
    return logs


def line_proportion(
    source: np.ndarray,
    target: np.ndarray,
    triangles: np.ndarray,
    source_lines: dict,
    target_lines: dict,
) -> float:
    """RMS over the lines of :func:`line_logs`: how much the target's feature lines differ in
    proportion from the source's, overall; 0 without lines."""
    logs = list(line_logs(source, target, triangles, source_lines, target_lines).values())
    return float(np.sqrt(np.mean(np.square(logs)))) if logs else 0.0


def weight_lines(transfer: DeformationTransfer, sigmas: dict) -> None:
    """Give each feature line of ``transfer`` (built with ``sigma=1``) its own weight: the line
    term becomes ``sum_l sigma_l sum_(segments of l) |(e0 - D e0_ref) / |e0_ref||^2``.

    The rows of the line operator and of the segments' reference directions are scaled by
    ``sqrt(sigma_l)`` (so the right-hand side ``F^T t`` gets ``sigma_l`` too) and the normal
    matrix is re-assembled; the factorization is lazy, so it is done once, on this matrix.
    """
    if transfer.line_operator is None or transfer.sigma != 1.0:
        return
    per_segment = np.concatenate(
        [
            np.full(max(len(chain) - 1, 0), float(sigmas.get(name, 0.0)))
            for name, chain in transfer.chains.items()
        ]
    )
    root = np.sqrt(per_segment)
    transfer.line_operator = (sp.diags(root) @ transfer.line_operator).tocsr()
    transfer._line_ref = transfer._line_ref * root[:, None]
    normal = (
        transfer.reduced_operator.T @ transfer.reduced_operator
        + transfer.line_operator.T @ transfer.line_operator
    ).tocsr()
    transfer.normal_matrix = normal
    transfer.factor = SPDFactor(
        normal[transfer.free][:, transfer.free], what="deformation-transfer normal equations"
    )


def canonical_axes(points: np.ndarray) -> np.ndarray:
    """(3, 3) rotation (columns: axes) fixed to the shape of ``points (V, 3)``, so that
    ``(points - mean) @ axes`` does not depend on how the mesh was rotated.

    Principal axes; the two most skewed get the sign of their third moment (a face's
    height and depth axes: chin/forehead, nose), the third completes a right-handed frame
    and comes first (the left-right axis of a symmetric face, which the sign test cannot
    orient), then the remaining two by decreasing spread.
    """
    p = np.asarray(points, dtype=np.float64)
    x = p - p.mean(axis=0)
    _, vecs = np.linalg.eigh(x.T @ x)
    vecs = vecs[:, ::-1]  # decreasing spread
    proj = x @ vecs
    spread = np.mean(proj**2, axis=0)
    skew = (
        np.mean(proj**3, axis=0)
        / np.maximum(spread, 1e-24 * max(float(spread.sum()), 1e-300)) ** 1.5
    )
    first = int(np.argmin(np.abs(skew)))
    rest = [i for i in range(3) if i != first]
    axes = [vecs[:, i] * (1.0 if skew[i] >= 0 else -1.0) for i in rest]
    lead = np.cross(axes[0], axes[1])
    return np.stack([lead, axes[0], axes[1]], axis=1)


class CoatingModel:
    """Coating transfer between a source and a target of one topology.

    Parameters
    ----------
    source_reference, target_reference : (V, 3), the source already in the target's frame
        and units (:class:`~.alignment.Placement`)
    triangles : (T, 3)
    source_lines, target_lines : {name: vertex chain}
    stable : (V,) weights of the stable vertices (translation gauge)
    iterations, laplacian, screening, sigma : see the retargeter (``sigma`` is scaled by the
        lines' proportions, :data:`LINE_PROPORTION_SCALE`; the weight used is ``self.sigma``)
    detail_scale : float or "auto" (the target/source size ratio, :func:`size_ratio`)
    """

    def __init__(
        self,
        source_reference,
        target_reference,
        triangles,
        *,
        source_lines,
        target_lines,
        stable,
        iterations,
        laplacian,
        screening,
        sigma,
        detail_scale,
    ):
        self.triangles = np.asarray(triangles, dtype=np.int64)
        src = np.asarray(source_reference, dtype=np.float64)
        tgt = np.asarray(target_reference, dtype=np.float64)
        # tangent neighbours chosen in the target's own principal axes: the frames, and so
        # the result, do not depend on how either mesh is oriented in space
        canonical = (src - tgt.mean(axis=0)) @ canonical_axes(tgt)
        neighbors = frame_neighbors(canonical, self.triangles)
        # one topology: one smoothing filter and its adjoint, both references in one call
        smoother, adjoint = filter_pair(self.triangles, src.shape[0], iterations)
        smooth_src, smooth_tgt = smoother(np.stack([src, tgt]))
        self.source = MultiScale(
            src,
            triangles,
            iterations=iterations,
            laplacian=laplacian,
            screening=screening,
            neighbors=neighbors,
            shared=(smoother, adjoint, smooth_src),
        )
        self.target = MultiScale(
            tgt,
            triangles,
            iterations=iterations,
            laplacian=laplacian,
            screening=screening,
            neighbors=neighbors,
            shared=(smoother, adjoint, smooth_tgt),
        )
        self.source_lines = {k: np.asarray(v) for k, v in source_lines.items()}
        self.target_lines = {k: np.asarray(v) for k, v in target_lines.items()}
        self.stable = np.asarray(stable, dtype=np.float64)
        logs = line_logs(src, tgt, self.triangles, self.source_lines, self.target_lines)
        self.line_proportion = (
            float(np.sqrt(np.mean(np.square(list(logs.values()))))) if logs else 0.0
        )
        # one weight per line: a line whose proportions (or shape) differ from the source's
        # gets no line term, without taking it from the lines that match
        self.line_sigmas = {
            name: float(sigma) * float(np.exp(-((d / LINE_PROPORTION_SCALE) ** 2)))
            for name, d in logs.items()
        }
        self.sigma = max(self.line_sigmas.values(), default=0.0)
        self.transfer = DeformationTransfer(
            self.target.smooth_reference,
            triangles,
            feature_lines=self.target_lines or None,
            sigma=1.0,
            gauge_weights=self.stable,
        )
        weight_lines(self.transfer, self.line_sigmas)
        self.ratio = size_ratio(
            self.source.smooth_reference, self.target.smooth_reference, triangles
        )
        self.detail_scale = self.ratio if detail_scale == "auto" else float(detail_scale)
        self.source_center = self.source.smooth_reference.mean(axis=0)
        self.target_center = self.target.smooth_reference.mean(axis=0)
        self.basis_frames: list[int] = []
        self.selection_rms: list[float] = []
        self.smoothing_rank: int | None = None
        factorize((self.target.factor, self.transfer.factor))  # now: one-time setup
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
    def fit_bases(
        self, vertices, local_of, *, epsilon: float, max_bases: int, chunk: int, max_frames: int
    ) -> None:
        """Select source bases among the frames ``vertices (F, V, 3)`` and transfer them (sec. 4.1-4.2).

        ``local_of(frame_ids, frames) -> (n, V, 3)`` removes the head motion and brings the
        frames into the target's frame. Candidates are at most ``max_frames`` evenly spaced
        frames (all of them for shorter sequences): neighbouring frames of a 30-60 fps
        capture are near duplicates. Only candidate frames are read. The stopping error is
        relative to :func:`face_size` of the source. ``smoothing_rank`` records the rows
        smoothed through :class:`SmoothedDisplacements` (None: every candidate smoothed).
        """
        height = face_size(self.source.reference, self.triangles)
        ids = selection_vertices(self.n_vertices)
        n_frames = vertices.shape[0]
        candidates = np.unique(
            np.linspace(0, n_frames - 1, min(n_frames, int(max_frames))).round().astype(np.int64)
        )
        # displacements from the reference are smoothed (G S = G R + G (S - R)): in float32
        # they keep ~7 digits of the motion, where absolute positions kept ~7 of the face
        ref = self.source.reference
        offset = self.source.smooth_reference - self.source_center
        # frames read a step: their float64 copies stay below glibc's fresh-page size
        step = min(chunk, config.scratch_items(24 * self.n_vertices))
        if candidates.size * self.n_vertices * 3 * 4 <= CANDIDATE_CACHE_BYTES:
            # all candidates at once, through their column space
            moved = np.empty((candidates.size, 3, self.n_vertices), dtype=np.float32)
            for sl in frame_chunks(candidates.size, step):
                picked = candidates[sl]
                local = local_of(picked, np.asarray(vertices[picked]))
                # the difference in float64, rounded once into the float32 store (no temporary)
                np.subtract(local, ref, out=moved[sl].transpose(0, 2, 1), casting="same_kind")
                del local
            smoothed = SmoothedDisplacements(self.source.smoother, moved, chunk=chunk)
            samples = (smoothed.at(ids) + offset[ids]).reshape(candidates.size, -1)
        else:
            smoothed = None
            samples = np.empty((candidates.size, 3 * ids.size))
            for sl in frame_chunks(candidates.size, step):
                picked = candidates[sl]
                smooth = self.source.smooth(local_of(picked, np.asarray(vertices[picked])) - ref)
                samples[sl] = (smooth[:, ids] + offset[ids]).reshape(smooth.shape[0], -1)
                del smooth
        reference = (self.source.smooth_reference[ids] - self.source_center).ravel()
        chosen, history = select_bases(
            samples, reference, epsilon=epsilon, max_bases=max_bases, height=height
        )
        frames = [int(candidates[i]) for i in chosen]
        self.basis_frames = frames
        self.selection_rms = history
        self.smoothing_rank = None if smoothed is None else smoothed.rank
        # the bases centred on the source's centre, the reference first, then the frames
        centred = np.empty((1 + len(frames), self.n_vertices, 3))
        centred[0] = offset
        adjoint_bases = None
        if frames and smoothed is not None:
            smoothed.frames(chosen, out=centred[1:])
            centred[1:] += offset
            # G^T (b - c) of every basis from G^T of (reference - c) and of the displacements'
            # smoothed column basis (fewer columns than the bases; linear, so exact)
            lifted = smoothed.filtered(self.source.adjoint, chosen, offset[None])
            lifted[1:] += lifted[0]
            adjoint_bases = lifted
        elif frames:
            picked = np.asarray(frames)
            raw = np.asarray(vertices[np.sort(picked)])[np.argsort(np.argsort(picked))]
            centred[1:] = self.source.smooth(local_of(picked, raw) - ref)
            centred[1:] += offset
        del smoothed
        self._use_bases(centred, adjoint_bases)

    def set_source_bases(self, bases: np.ndarray, adjoint_bases: np.ndarray | None = None) -> None:
        """Use ``bases (K, V, 3)`` (smooth source meshes, the reference first) and transfer them;
        ``adjoint_bases``: ``G^T (bases - center)`` when known (else computed here)."""
        self._use_bases(np.asarray(bases, dtype=np.float64) - self.source_center, adjoint_bases)

    def _use_bases(self, centred: np.ndarray, adjoint_bases: np.ndarray | None) -> None:
        """:meth:`set_source_bases` of the bases minus the source centre, ``centred (K, V, 3)``
        (kept as they are: the basis space's matrix)."""
        self.space = BasisSpace(
            centred,
            self.source_center,
            adjoint=self.source.adjoint,
            adjoint_bases=adjoint_bases,
            centred=True,
        )
        self._source_flat = self.space.matrix.T  # (K, 3V) rows of bases - center
        # deformation gradients and mean displacements do not see the translation
        self.target_bases = self._transfer(
            self.source.smooth_reference - self.source_center, centred
        )

    @property
    def source_bases(self) -> np.ndarray:
        """(K, V, 3) the source bases (smooth source meshes, the reference first); a new array."""
        k = self._source_flat.shape[0]
        return self._source_flat.reshape(k, self.n_vertices, 3) + self.source_center

    @property
    def n_bases(self) -> int:
        return int(self._source_flat.shape[0])

    def transfer_bases(self, bases: np.ndarray) -> np.ndarray:
        """Feature-preserving deformation transfer of smooth source meshes (eq. 9-11)."""
        return self._transfer(self.source.smooth_reference, np.asarray(bases, dtype=np.float64))

    def _transfer(self, reference: np.ndarray, bases: np.ndarray) -> np.ndarray:
        """:meth:`transfer_bases` of ``bases`` from ``reference`` (both moved alike or not)."""
        means = self.transfer.component_means(bases, reference=reference) * self.ratio
        return self.transfer.transfer(
            reference,
            bases,
            source_feature_lines=self.source_lines or None,
            mean_displacement=means,
        )

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
        smooth = self.source_smooth(weights)
        coating = self.source.coating(local, smooth)
        coating -= self.source.reference_coating
        return weights, coating

    def source_smooth(self, weights: np.ndarray) -> np.ndarray:
        """The source frames' smooth meshes as the bases see them, ``B_t`` -> ``(C, V, 3)``."""
        return blend_flat(weights, self._source_flat, self.source_center)

    def wrinkles(self, local: np.ndarray, weights: np.ndarray) -> np.ndarray:
        """The fine layer ``D_t = F(B_t)^T M (S_t - G S_t) - c_0`` of source frames ``local (C, V, 3)``
        with weights ``(C, K)``: the coating against the Taubin-smoothed frame (eq. 1, 3), in the
        frames of ``B_t`` like :meth:`decompose` (which returns ``D_t + E_t``). One smoothing a frame."""
        smooth = self.source_smooth(weights)
        frames = self.source.frames(smooth)
        return (
            self.source.coating(local, self.source.smooth(local), frames)
            - self.source.reference_coating
        )

    def smooth_target(self, weights: np.ndarray, bases: np.ndarray | None = None) -> np.ndarray:
        """Target smooth frames ``T~_t`` (eq. 8) -> ``(C, V, 3)``."""
        return blend(self.target_bases if bases is None else bases, self.target_center, weights)

    def synthesize(
        self, weights: np.ndarray, details: np.ndarray, bases: np.ndarray | None = None
    ) -> np.ndarray:
        """Target frames (local coordinates) from weights and fine-scale motion (eq. 5)."""
        smooth = self.smooth_target(weights, bases)
        coating = np.multiply(details, self.detail_scale, dtype=np.float64)  # one pass from float32
        coating += self.target.reference_coating
        return self.target.reconstruct(smooth, coating, overwrite_coating=True)
