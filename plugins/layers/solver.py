"""Parameter extraction (Kholgade et al. 2011, sec. 4): head motion, then W(t), alpha(t).

Head motion (sec. 4, first paragraph). The paper aligns the 3D markers and the 2D
tracks each to their neutral by Procrustes (3D rigid; 2D similarity, since image tracks
also change scale as the head moves in depth), then, Eq. 6::

    x_hat(t) = R(t)^-1 (x_A(t) - t(t)) - x_muA

That alignment takes expression for motion (the paper's own limitation: "excessive
non-rigid motion can dominate the alignment"): a jaw opening tilts the head, a blink or an
open mouth moves and scales the eye and lip tracks. :func:`fit_block` starts from it
(weighted by rigidity, ``1 / (eps^2 + m_p^2)`` with ``m_p`` the RMS displacement of point p
over the actor's poses; ``rigid_points="all"``: plain) and then, per round, solves Eq. 7
with the data measured modulo the alignment's small motions (the projection below) and
re-aligns every frame to the layered model's reconstruction of it (model-based alignment;
``head_motion_refinement`` rounds, 0 = the paper). A known ``Source.head_motion`` (or
"none") replaces the 3D estimate; the 2D similarity is always estimated.

Projection: with ``Jr (C, r)`` the derivative of ``x_hat`` (normalised units) with respect
to the r motion parameters at the neutral (3D: 3 rotations, 3 translations; 2D: rotation,
scale, 2 translations), the data term becomes ``|P (x_hat - f)|^2`` with ``P = I - Jr
(Jr^T Jr)^-1 Jr^T`` restricted to the observed coordinates: the joint least squares of Eq. 4
over (alignment, layers) with the alignment's small motions eliminated. It enters the
reduced form as a rank-r correction (``_kernels``), and makes the round's solution
independent of the starting alignment to first order.

Per-frame problem (Eq. 7, reconstructed). With ``gamma = exp(-d^2 / (2 sigma^2))``::

    min_{W, alpha}  |x_hat - sum_j sum_l w_jl M_Al B_Aj alpha_j|^2
                    + gamma / (1 - gamma) * (|W[mouth, :] - e_speech|^2 + |alpha_speech - alpha_mm|^2)
                    + lambda / (1 - gamma) * (|W - W(t-1)|_F^2 + |alpha - alpha(t-1)|^2)
    s.t. sum_j w_jl = 1, w_jl >= 0 (every region l);  sum_k alpha_jk = 1, alpha_jk >= 0 (every layer j)

(``composition="additive"``, the default: ``0 <= w_jl <= 1`` each instead of the sum.)
The bias vector ``(w21, w22, w23) = (0, 1, 0)`` in the paper is the mouth region's
row of W (emotion 0, speech 1, blink 0; the prose indexes w by region first there),
and ``alpha_mm`` the one-hot closed-lips viseme; with the additive composition the bias
keeps only its viseme part (the weights are left to the data). We minimise the equivalent
``(1 - gamma) * data + gamma * bias + lambda * smooth`` with ``gamma`` capped at
``gamma_max`` < 1 so the data never vanish. The data term is normalised (see
``model.py``): a mean over observed points in units of the RMS basis displacement.

Lip distance ``d``: the distance between the two lip points (3D markers or 2D tracks,
after alignment) *minus their distance in the closed-lips viseme pose*, clipped at 0,
so markers that sit on the lips' outer edges (never touching) still measure closure;
``sigma`` is ``lip_sigma`` times the widest lip opening among the speech poses.
A frame missing either lip point gets ``gamma = 0``.

Missing markers (NaN) drop their coordinates from that frame's data term (the Gram
tensor is downdated); the frame keeps its parameters from the rest of the face and the
smoothing term. Frames whose 3D markers are too few for the rigid fit (< 3) raise
:class:`~faceretarget.errors.DegenerateGeometryError` when head motion must be
estimated; 2D tracks with < 2 points in a frame are ignored for that frame.
"""

from __future__ import annotations

from dataclasses import dataclass, replace

import numpy as np

from faceretarget._validate import check_number, check_param, sum_finite
from faceretarget.errors import (
    ConfigError,
    DegenerateGeometryError,
    IndexRangeError,
    NonFiniteError,
    ShapeError,
    UnknownNameError,
)
from faceretarget.geometry.procrustes import fit_rigid, to_matrix

from .model import ActorModel

__all__ = [
    "LipBias",
    "Observations",
    "Extraction",
    "resolve_lip_bias",
    "observe",
    "extract",
    "uniform_state",
    "reconstruct",
    "fit_block",
    "fit_to_frames",
    "realign",
]

#: Lip pairs are found by name when names hold "lip" and one of these.
_UPPER_WORDS = ("upper", "top", "sup")
_LOWER_WORDS = ("lower", "bottom", "bot", "inf")
#: Relative floor of the closed distance in the lip-pair score (fraction of the widest opening).
_GAP_FLOOR = 0.05


@dataclass
class LipBias:
    """Where the lip-closure bias looks and what it pulls towards (-1 = bias off)."""

    part: int  # 3: the pair is among the 3D markers, 2: among the 2D tracks
    upper: int
    lower: int
    closed_gap: float
    sigma: float
    mouth: int
    speech: int
    closed: int
    names: tuple = ()
    note: str = ""

    @property
    def enabled(self) -> bool:
        return self.mouth >= 0 and self.speech >= 0 and self.closed >= 0 and self.sigma > 0


def _config_number(value, name: str, **limits):
    """``check_number`` raising :class:`ConfigError` (a bad parameter, named in the message)."""
    return check_param(check_number, value, name, **limits)


def _index(value, name: str) -> int:
    """A whole-number index parameter (its range is checked by the caller)."""
    if isinstance(value, (bool, np.bool_)) or not isinstance(
        value, (int, float, np.integer, np.floating)
    ):
        raise ConfigError(f"{name}: expected a name or a 0-based index, got {value!r}"[:200])
    return _config_number(value, name, integer=True)


def _disabled(note: str) -> LipBias:
    return LipBias(3, -1, -1, 0.0, 0.0, -1, -1, -1, (), note)


def _gaps(points: np.ndarray, upper: np.ndarray, lower: np.ndarray) -> np.ndarray:
    """Distances between paired points: ``points (S, P, D)`` -> ``(S, n_pairs)``."""
    return np.linalg.norm(points[:, upper] - points[:, lower], axis=-1)


def _pick_pair(names, speech_poses: np.ndarray, closed: int, lip_markers):
    """(upper, lower, score) of the lip pair in one point set, or None."""
    n = speech_poses.shape[1]
    if lip_markers is not None:
        ids = []
        for item in lip_markers:
            if isinstance(item, str):
                if item not in names:
                    return None
                ids.append(names.index(item))
            else:
                ids.append(_index(item, "lip_markers"))
        if any(i < 0 or i >= n for i in ids):
            raise IndexRangeError(
                f"lip_markers: indices {ids} out of range for {n} points (valid: 0..{n - 1})"
            )
        return ids[0], ids[1], np.inf
    low = [s.lower() for s in names]
    ups = [i for i, s in enumerate(low) if "lip" in s and any(w in s for w in _UPPER_WORDS)]
    los = [i for i, s in enumerate(low) if "lip" in s and any(w in s for w in _LOWER_WORDS)]
    if ups and los:
        upper, lower = np.repeat(ups, len(los)), np.tile(los, len(ups))
        bonus = np.inf  # named pairs win over the geometric guess
    else:
        upper, lower = np.triu_indices(n, 1)
        bonus = 0.0
    gaps = _gaps(speech_poses, upper, lower)
    opening = gaps.max(axis=0) - gaps[closed]
    floor = _GAP_FLOOR * max(float(opening.max()), 1e-300)
    score = opening / (gaps[closed] + floor)
    best = int(np.argmax(score))
    if opening[best] <= 0:
        return None
    return int(upper[best]), int(lower[best]), float(score[best]) + bonus


def resolve_lip_bias(
    actor: ActorModel,
    speech_poses3d,
    speech_poses2d,
    *,
    lip_markers,
    speech_layer,
    closed_viseme,
    mouth_region,
    lip_sigma,
    masks3d,
    masks2d,
) -> LipBias:
    """Choose the lip pair, closed viseme and mouth region of the bias (see module doc).

    ``speech_poses3d (K_s, N3, 3)`` / ``speech_poses2d (K_s, N2, 2)``: absolute speech poses.
    """
    lip_sigma = _config_number(lip_sigma, "lip_sigma", low=0)
    if lip_markers is not None and (
        not isinstance(lip_markers, (list, tuple, np.ndarray)) or len(lip_markers) != 2
    ):
        raise ConfigError(
            f"lip_markers must be a pair (upper, lower) of names or indices, got {lip_markers!r}"[
                :200
            ]
        )
    if speech_layer not in actor.layer_names:
        if closed_viseme is not None or lip_markers is not None:
            raise UnknownNameError(
                f"speech_layer {speech_layer!r} is not a layer of the actor ({', '.join(actor.layer_names)}); "
                "name the layer that holds the visemes"
            )
        return _disabled(f"no {speech_layer!r} layer: lip-closure bias off")
    if lip_sigma == 0:
        return _disabled("lip_sigma = 0: lip-closure bias off")
    speech = actor.layer_names.index(speech_layer)
    names = actor.pose_names[speech_layer]
    if closed_viseme is None:
        k_closed = 0
    elif isinstance(closed_viseme, str):
        if closed_viseme not in names:
            raise UnknownNameError(
                f"closed_viseme {closed_viseme!r} is not a pose of layer {speech_layer!r}: {', '.join(names)}"
            )
        k_closed = names.index(closed_viseme)
    else:
        k_closed = _index(closed_viseme, "closed_viseme")
        if not 0 <= k_closed < len(names):
            raise IndexRangeError(
                f"closed_viseme {closed_viseme} out of range for {len(names)} poses of {speech_layer!r} "
                f"(valid: 0..{len(names) - 1} or a pose name: {', '.join(names)})"
            )
    choices = []
    by_index = lip_markers is not None and not all(isinstance(v, str) for v in lip_markers)
    for part, poses, pnames, masks in (
        (3, speech_poses3d, actor.names3d, masks3d),
        (2, speech_poses2d, actor.names2d, masks2d),
    ):
        if poses is None or (by_index and part == 2):  # indices refer to the 3D markers
            continue
        found = _pick_pair(list(pnames), poses, k_closed, lip_markers)
        if found is not None:
            choices.append((found[2], part, found[0], found[1], poses, pnames, masks))
    if not choices:
        if lip_markers is not None:
            raise UnknownNameError(f"lip_markers {lip_markers!r}: no such markers or tracks")
        return _disabled("no lip pair opens across the speech poses: lip-closure bias off")
    _, part, up, lo, poses, pnames, masks = max(choices, key=lambda c: c[0])
    gaps = _gaps(poses, np.array([up]), np.array([lo]))[:, 0]
    closed_gap = float(gaps[k_closed])
    sigma = float(lip_sigma) * float(gaps.max() - closed_gap)
    if not (np.isfinite(sigma) and np.isfinite(sigma * sigma)):
        raise ConfigError(
            f"lip_sigma: {lip_sigma!r} is too large (sigma = lip_sigma * widest lip opening overflows); "
            "pass a fraction of the opening, e.g. 0.1"
        )
    if mouth_region is None:
        mouth = int(np.argmax(masks[:, up] + masks[:, lo]))
    elif isinstance(mouth_region, str):
        if mouth_region not in actor.region_names:
            raise UnknownNameError(
                f"mouth_region {mouth_region!r} is not a region: {', '.join(actor.region_names)}"
            )
        mouth = actor.region_names.index(mouth_region)
    else:
        mouth = _index(mouth_region, "mouth_region")
        if not 0 <= mouth < actor.n_regions:
            raise IndexRangeError(
                f"mouth_region {mouth_region} out of range for {actor.n_regions} regions "
                f"(valid: 0..{actor.n_regions - 1} or a region name: {', '.join(actor.region_names)})"
            )
    label = (pnames[up], pnames[lo]) if len(pnames) > max(up, lo) else (str(up), str(lo))
    return LipBias(
        part,
        up,
        lo,
        closed_gap,
        sigma,
        mouth,
        speech,
        actor.pose_index(speech_layer, k_closed),
        label,
        "",
    )


@dataclass
class Observations:
    """One block of frames reduced to what the solver needs.

    g : (F, m, K), xx : (F,)  data projections and squared norms (normalised units)
    missing : (F, C) bool, any_missing : (F,) bool, n_valid : (F,) observed points
    gap : (F,) lip distance (NaN when a lip point is missing or the bias is off)
    head_motion : (F, 4, 4) 3D head motion (neutral -> world)
    alignment2d : (F, 3, 3) 2D similarity of the tracks (neutral -> image; identity
        where a frame's tracks are unusable), or None without tracks
    xhat : (F, C) aligned, normalised data (Eq. 6; zero where missing), when asked for
    qraw : (F, r) ``jac^T x_hat`` for the projected data term of an alignment pass
    local3 : (F, N3, 3) the aligned 3D markers (NaN where missing), when asked for
    """

    g: np.ndarray
    xx: np.ndarray
    missing: np.ndarray
    any_missing: np.ndarray
    n_valid: np.ndarray
    gap: np.ndarray
    head_motion: np.ndarray
    alignment2d: np.ndarray | None = None
    xhat: np.ndarray | None = None
    qraw: np.ndarray | None = None
    local3: np.ndarray | None = None


def _check_points(arr, n: int, dim: int, what: str) -> np.ndarray:
    a = np.asarray(arr, dtype=np.float64)
    if a.ndim != 3 or a.shape[1:] != (n, dim):
        raise ShapeError(f"{what}: expected (F, {n}, {dim}) points, got {tuple(a.shape)}")
    if sum_finite(a):  # nothing missing
        return a
    if np.isinf(a).any():
        raise NonFiniteError(f"{what}: infinite coordinates; mark missing samples with NaN")
    partial = np.isnan(a).any(axis=-1) & ~np.isnan(a).all(axis=-1)
    if partial.any():
        f, p = (int(i) for i in np.argwhere(partial)[0])
        raise NonFiniteError(
            f"{what}: point {p} at frame {f} has some coordinates NaN; a missing sample is NaN in all"
        )
    return a


def fit_to_frames(
    reference: np.ndarray,
    frames: np.ndarray,
    weights=None,
    *,
    scale: bool = False,
    min_points: int = 0,
) -> np.ndarray:
    """Rigid (or similarity) Procrustes of a reference onto each frame, as ``(F, D + 1, D + 1)``
    transforms ``[[s R, t], [0, 1]]`` with ``frame ~ s R ref + t``: the shared fit
    :func:`faceretarget.geometry.procrustes.fit_rigid`.

    ``reference (N, D)`` for all frames or ``(F, N, D)`` per frame (the model's
    reconstruction of each frame); ``frames (F, N, D)`` with NaN rows missing; ``weights
    (N,)`` or None. The identity for frames with fewer than ``min_points`` points.
    """
    rot, trans, s = fit_rigid(reference, frames, weights, scale=scale, min_points=min_points)
    return to_matrix(rot, trans, s)


def _to_local(points: np.ndarray, transforms: np.ndarray) -> np.ndarray:
    """Points ``(F, P, D)`` back through transforms ``[[s R, t], [0, 1]]``: ``R^T (x - t) / s``."""
    dim = points.shape[-1]
    lin = transforms[:, :dim, :dim]
    scale2 = np.einsum("fij,fij->f", lin, lin) / dim  # s^2
    return np.matmul(points - transforms[:, None, :dim, dim], lin) / scale2[:, None, None]


def observe(
    actor: ActorModel,
    lip: LipBias,
    markers,
    tracks=None,
    head_motion=None,
    *,
    rigid_points: str = "stable",
    frame_offset: int = 0,
    keep_xhat: bool = False,
    reference3d=None,
    reference2d=None,
    checked: bool = False,
    rigid=None,
) -> Observations:
    """Align one block of frames and project it on the actor's bases.

    markers : (F, N3, 3) float, NaN = missing; tracks : (F, N2, 2) or None
    head_motion : (F, 4, 4) known 3D head motion, None to estimate it, or the string
        ``"none"`` (the source has no head motion: identity)
    reference3d : (F, N3, 3), reference2d : (F, N2, 2), optional
        What each frame is aligned to instead of the neutral: the layered model's
        reconstruction of the frame from a previous pass (model-based alignment, which
        does not mistake the expression for head motion). The data ``x_hat`` stay relative
        to the neutral (Eq. 6).
    checked : the points were checked already (a later alignment pass)
    rigid : :class:`~.model.RigidProjection` when the alignment is estimated (fills ``qraw``)
    """
    from ._kernels import project as project_kernel

    x3 = markers if checked else _check_points(markers, actor.n3, 3, "markers")
    n_frames = x3.shape[0]
    valid3 = ~np.isnan(x3[..., 0])
    if rigid_points not in ("stable", "all"):
        raise ConfigError(f"rigid_points must be 'stable' or 'all', got {rigid_points!r}")
    if isinstance(head_motion, str) and head_motion == "none":
        motion = np.tile(np.eye(4), (n_frames, 1, 1))
        local3 = x3
    elif head_motion is None:
        counts = valid3.sum(axis=1)
        if np.any(counts < 3):
            f = int(np.flatnonzero(counts < 3)[0])
            raise DegenerateGeometryError(
                f"frame {f + frame_offset} has only {int(counts[f])} of {actor.n3} markers; the rigid head fit needs "
                "at least 3: fill the gap (interpolate) or drop the frame"
            )
        weights = actor.rigid_weights3d if rigid_points == "stable" else None
        motion = fit_to_frames(
            actor.reference3d if reference3d is None else reference3d, x3, weights
        )
        local3 = _to_local(x3, motion)  # R^T (x - t), Eq. 6
    else:
        motion = np.asarray(head_motion, dtype=np.float64)
        if motion.shape != (n_frames, 4, 4):
            raise ShapeError(f"head_motion: expected ({n_frames}, 4, 4), got {motion.shape}")
        rot, trans = motion[:, :3, :3], motion[:, :3, 3]
        local3 = np.matmul(x3 - trans[:, None, :], rot)
    blocks = [((local3 - actor.reference3d) / actor.scale3d).reshape(n_frames, -1)]
    missing = [np.repeat(~valid3, 3, axis=1)]
    n_valid = valid3.sum(axis=1)
    local2 = align2 = None
    if actor.n2:
        if tracks is None:
            raise ShapeError(
                f"the fitted model uses {actor.n2} 2D tracks; this input has none (pass tracks2d)"
            )
        x2 = tracks if checked else _check_points(tracks, actor.n2, 2, "tracks2d")
        if x2.shape[0] != n_frames:
            raise ShapeError(f"tracks2d: {x2.shape[0]} frames but the markers have {n_frames}")
        valid2 = ~np.isnan(x2[..., 0])
        usable = valid2.sum(axis=1) >= 2
        valid2 &= usable[:, None]
        w2 = actor.rigid_weights2d if rigid_points == "stable" else None
        align2 = fit_to_frames(
            actor.reference2d if reference2d is None else reference2d,
            x2,
            w2,
            scale=True,
            min_points=2,
        )
        local2 = np.where(valid2[..., None], _to_local(x2, align2), np.nan)
        blocks.append(((local2 - actor.reference2d) / actor.scale2d).reshape(n_frames, -1))
        missing.append(np.repeat(~valid2, 2, axis=1))
        n_valid = n_valid + valid2.sum(axis=1)
    xhat = np.concatenate(blocks, axis=1) if len(blocks) > 1 else blocks[0]
    miss = np.concatenate(missing, axis=1) if len(missing) > 1 else missing[0]
    xhat[miss] = 0.0
    g = np.empty((n_frames, actor.n_regions * actor.n_poses))
    xx = np.empty(n_frames)
    xhat = np.ascontiguousarray(xhat)
    project_kernel(xhat, actor.projector_t, g, xx)
    g = g.reshape(n_frames, actor.n_regions, actor.n_poses)
    qraw = None
    if rigid is not None:
        qraw = np.empty((n_frames, rigid.jac_t.shape[0]))
        project_kernel(xhat, rigid.jac_t, qraw, np.empty(n_frames))
    if lip.enabled:
        pts = local3 if lip.part == 3 else local2
        gap = np.linalg.norm(pts[:, lip.upper] - pts[:, lip.lower], axis=-1)
    else:
        gap = np.full(n_frames, np.nan)
    return Observations(
        g=np.ascontiguousarray(g),
        xx=xx,
        missing=np.ascontiguousarray(miss),
        any_missing=miss.any(axis=1),
        n_valid=n_valid.astype(np.float64),
        gap=gap,
        head_motion=motion,
        alignment2d=align2,
        xhat=xhat if keep_xhat else None,
        qraw=qraw,
        local3=np.where(valid3[..., None], local3, np.nan) if keep_xhat else None,
    )


def realign(
    actor: ActorModel,
    obs: Observations,
    markers,
    tracks,
    head_motion,
    reference3d,
    reference2d,
    *,
    rigid_points: str,
    keep_local: bool,
) -> Observations:
    """``obs`` with the alignment refitted to per-frame references (the model's reconstruction):
    the 3D head motion when it is estimated (``head_motion`` None), the 2D similarity when
    there are tracks; and the aligned 3D markers when ``keep_local``. Nothing is projected."""
    motion = obs.head_motion
    if head_motion is None:
        motion = fit_to_frames(
            reference3d, markers, actor.rigid_weights3d if rigid_points == "stable" else None
        )
    align2 = obs.alignment2d
    if actor.n2 and tracks is not None:
        align2 = fit_to_frames(
            reference2d,
            tracks,
            actor.rigid_weights2d if rigid_points == "stable" else None,
            scale=True,
            min_points=2,
        )
    local3 = _to_local(markers, motion) if keep_local else None  # NaN stays NaN
    return replace(obs, head_motion=motion, alignment2d=align2, local3=local3, xhat=None)


@dataclass
class Extraction:
    """Per-frame layered parameters.

    weights : (F, m, J) mask weights ``w_jl`` (row l sums to 1 over layers j; in [0, 1]
        each when the composition is additive)
    coefficients : (F, K) stacked simplex coefficients (each layer's block sums to 1)
    gamma : (F,) lip-closure bias factor used; objective : (F,); iterations : (F,)
    """

    weights: np.ndarray
    coefficients: np.ndarray
    gamma: np.ndarray
    objective: np.ndarray
    iterations: np.ndarray


def uniform_state(actor: ActorModel, additive: bool = False) -> tuple[np.ndarray, np.ndarray]:
    """The deterministic start of a sequence: uniform alphas; every layer 1/J in each
    region (convex) or 1 (additive)."""
    w = np.full((actor.n_regions, actor.n_layers), 1.0 if additive else 1.0 / actor.n_layers)
    sizes = np.bincount(actor.layer_of, minlength=actor.n_layers)
    return w, 1.0 / sizes[actor.layer_of].astype(np.float64)


def bias_factor(lip: LipBias, gap: np.ndarray, gamma_max: float) -> np.ndarray:
    """``gamma(t) = exp(-d^2 / (2 sigma^2))`` with ``d = max(0, gap - closed gap)``, capped."""
    if not lip.enabled:
        return np.zeros_like(gap)
    d = np.maximum(gap - lip.closed_gap, 0.0)
    two_s2 = 2.0 * lip.sigma**2
    if two_s2 > 0.0:
        gamma = np.exp(-(d * d) / two_s2)
    else:  # sigma so small its square underflows: the limit (1 on closed lips, 0 otherwise)
        gamma = np.where(d > 0.0, 0.0, 1.0)
    return np.minimum(np.where(np.isnan(gap), 0.0, gamma), gamma_max)


def extract(
    actor: ActorModel,
    lip: LipBias,
    obs: Observations,
    *,
    smoothing: float,
    gamma_max: float,
    max_iter: int,
    tol: float,
    state=None,
    additive: bool = False,
    start=None,
    rigid=None,
) -> tuple[Extraction, tuple[np.ndarray, np.ndarray]]:
    """Solve Eq. 7 frame after frame; ``state`` = (W, alpha) of the frame before, if any.

    ``start`` = (weights (F, m, J), coefficients (F, K)): where each frame's solve starts
    (a previous alignment pass of the same frames); default: the previous frame's result.
    ``rigid``: (:class:`~.model.RigidProjection`, with ``obs.qraw``): the data term is
    measured modulo the alignment's small motions (the alignment is estimated).
    Returns the extraction and the state after the last frame (for streaming).
    """
    from ._kernels import solve_frames

    smoothing = _config_number(smoothing, "smoothing", low=0)
    gamma_max = _config_number(gamma_max, "gamma_max", low=0, high=1)
    if gamma_max >= 1.0:
        raise ConfigError(f"gamma_max: expected a finite number >= 0 and < 1, got {gamma_max!r}")
    max_iter = _config_number(
        max_iter, "max_iter", integer=True, low=1, high=np.iinfo(np.int64).max
    )
    tol = _config_number(tol, "tol", low=0)
    n_frames = obs.g.shape[0]
    gamma = bias_factor(lip, obs.gap, gamma_max)
    smoothing = float(smoothing)
    if rigid is None:
        jac = np.empty((actor.basis_t.shape[0], 0))
        jtj, uraw, qraw = (
            np.empty((0, 0)),
            np.empty((0, actor.n_regions, actor.n_poses)),
            np.empty((n_frames, 0)),
        )
    else:
        jac, jtj, uraw, qraw = rigid.jac, rigid.jtj, rigid.uraw, obs.qraw
    c_d = (1.0 - gamma) / np.maximum(obs.n_valid, 1.0)
    c_s = np.full(n_frames, smoothing)
    has_prev = state is not None
    w0, a0 = state if has_prev else uniform_state(actor, additive)
    m, J, K = actor.n_regions, actor.n_layers, actor.n_poses
    out_w = np.empty((n_frames, m, J))
    out_a = np.empty((n_frames, K))
    out_obj = np.empty(n_frames)
    out_it = np.empty(n_frames, dtype=np.int64)
    if start is None:
        start_w, start_a, use_start = np.empty((1, m, J)), np.empty((1, K)), False
    else:
        start_w, start_a, use_start = (
            np.ascontiguousarray(start[0]),
            np.ascontiguousarray(start[1]),
            True,
        )
    solve_frames(
        np.ascontiguousarray(actor.gram),  # C order: the kernel copies it flat (_copy)
        actor.pair_used,
        actor.basis_t,
        actor.coord_masks,
        obs.g,
        obs.xx,
        obs.missing,
        obs.any_missing,
        c_d,
        gamma,
        c_s,
        actor.layer_of,
        J,
        lip.mouth,
        lip.speech,
        lip.closed,
        np.ascontiguousarray(w0, dtype=np.float64),
        np.ascontiguousarray(a0, dtype=np.float64),
        has_prev,
        bool(additive),
        start_w,
        start_a,
        use_start,
        jac,
        np.ascontiguousarray(jtj),
        np.ascontiguousarray(uraw),
        qraw,
        int(max_iter),
        float(tol),
        out_w,
        out_a,
        out_obj,
        out_it,
    )
    result = Extraction(out_w, out_a, gamma, out_obj, out_it)
    return result, (out_w[-1].copy(), out_a[-1].copy())


def reconstruct(actor: ActorModel, params: Extraction):
    """The actor's local (head motion removed) points Eq. 4 predicts: ``(F, N3, 3)`` and ``(F, N2, 2)`` or None."""
    beta = params.weights[:, :, actor.layer_of] * params.coefficients[:, None, :]
    flat = beta.reshape(beta.shape[0], -1) @ actor.projector_t  # (F, C), normalised units
    n3 = 3 * actor.n3
    local3 = flat[:, :n3].reshape(-1, actor.n3, 3) * actor.scale3d + actor.reference3d
    local2 = None
    if actor.n2:
        local2 = flat[:, n3:].reshape(-1, actor.n2, 2) * actor.scale2d + actor.reference2d
    return local3, local2


def fit_block(
    actor: ActorModel,
    lip: LipBias,
    markers,
    tracks,
    head_motion,
    *,
    passes: int,
    rigid_points: str,
    smoothing: float,
    gamma_max: float,
    max_iter: int,
    tol: float,
    additive: bool,
    states=None,
    frame_offset: int = 0,
    keep_local: bool = False,
):
    """Alignment and extraction of one block of frames: Eq. 6 and Eq. 7 (see the module doc).

    Nothing to estimate (known 3D head motion or "none", no 2D tracks), or ``passes =
    1``: the paper, Procrustes to the mean, then Eq. 7. Otherwise ``passes - 1`` rounds
    of: solve Eq. 7 with the data measured modulo the alignment's small motions (a
    Gauss-Newton step of the joint fit of Eq. 4 over the alignment and the layers, the
    alignment eliminated), then align every frame to the layered model's reconstruction
    of it. The first round starts from the paper's alignment, a later one from the
    previous round's parameters; the result is the last round's parameters with the
    alignment fitted to them. Each round is its own first-order Markov chain (smoothed
    towards the same round at the frame before), so a block of frames and the same
    frames one at a time agree.

    ``head_motion``: known (F, 4, 4), None (estimate) or "none" (identity). ``states``:
    per round, (W, alpha) of the frame before the block, or None. ``keep_local``: also
    return the aligned 3D markers (``obs.local3``). Returns (observations, extraction,
    states after the block).
    """
    estimate3 = head_motion is None
    rigid = actor.rigid_projection(estimate3, actor.n2 > 0) if passes > 1 else None
    requested = max(passes - 1, 1)
    n_rounds = requested if rigid is not None else 1
    states = [None] * requested if states is None else list(states)
    markers = _check_points(markers, actor.n3, 3, "markers")
    if tracks is not None and actor.n2:
        tracks = _check_points(tracks, actor.n2, 2, "tracks2d")
    common = dict(rigid_points=rigid_points, frame_offset=frame_offset, checked=True)
    obs = observe(
        actor,
        lip,
        markers,
        tracks,
        head_motion,
        keep_xhat=keep_local and rigid is None,
        rigid=rigid,
        **common,
    )
    out, start = [], None
    for k in range(n_rounds):
        params, last = extract(
            actor,
            lip,
            obs,
            smoothing=smoothing,
            gamma_max=gamma_max,
            max_iter=max_iter,
            tol=tol,
            state=states[k] if n_rounds == requested else states[-1],
            additive=additive,
            start=start,
            rigid=rigid,
        )
        out.append(last)
        if rigid is None:
            break
        start = (params.weights, params.coefficients)
        ref3, ref2 = reconstruct(actor, params)
        if k == n_rounds - 1:
            obs = realign(
                actor,
                obs,
                markers,
                tracks,
                head_motion,
                ref3,
                ref2,
                rigid_points=rigid_points,
                keep_local=keep_local,
            )
        else:
            obs = observe(
                actor,
                lip,
                markers,
                tracks,
                head_motion,
                reference3d=ref3 if estimate3 else None,
                reference2d=ref2,
                rigid=rigid,
                **common,
            )
    if (
        len(out) < requested
    ):  # (nothing to align in this block: every round continues from this one)
        out = [last] * (requested - len(out)) + out
    return obs, params, out
