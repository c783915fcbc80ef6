"""Rigid head motion from facial markers, robust to expressions and to rig mismatch.

``estimate_head_motion(reference, markers, basis=...)`` returns per-frame transforms
``(F, 4, 4)`` mapping the neutral ``reference`` into each frame (``x ~= R n + t``).

Plain Procrustes against the neutral (:func:`faceretarget.geometry.procrustes.fit_rigid`)
turns expression into head motion: a jaw opening tilts the head. Fitting the head motion
jointly with an expression basis removes what the basis explains, but on a different rig
(or the target's shapes warped onto the source) what the basis does *not* explain still
leaks into the rigid motion: measured on real rig pairs, 1.4-2.2 degrees of rotation were
invented for sources without any head motion. Three things keep that out:

1. **Rigidity weights.** Marker ``i`` gets ``w_i = 1 / (eps^2 + m_i^2)``, where ``m_i`` is
   the RMS displacement of the marker over the basis' shapes and ``eps =
   config.HEAD_MOTION_RIGIDITY * face size`` (RMS radius of the reference): markers the
   expressions hardly move (nose bridge, inner eye corners, temples) carry the rigid fit,
   lips and jaw hardly count. Without a basis all markers weigh the same.
2. **Joint weighted fit.** In the head frame the local markers ``l_i = R^T (x_i - t)`` are
   fitted by the expressions, ``c = argmin sum_i w_i |l_i - n_i - B_i c|^2 + ridge |c|^2``
   (the tiny ridge keeps duplicate shapes solvable), and the head motion is the one whose
   residual ``r_i = l_i - n_i - B_i c`` exerts no net weighted force ``sum_i w_i r_i`` and no
   net weighted torque ``sum_i w_i (n_i - m) x r_i`` about the weighted centre ``m`` of the
   neutral. That is Gauss-Newton's fixed point for ``sum_i w_i |r_i|^2`` with the Jacobian
   taken at the neutral (the exact least-squares optimum takes the lever arms at ``l_i``;
   the two coincide when the expressions explain the markers, and differed by at most
   0.02 degrees on the ICT and cross-rig cases). With the Jacobian fixed, each step is one
   ``(6, 3N)`` gain matrix per pattern of missing markers applied to every frame (through
   per-frame moments, in a numba kernel), so there is no Python loop over frames. Rigid
   directions that the expressions can mimic on the visible markers (few markers left)
   are not updated (see ``config.HEAD_MOTION_IDENTIFIABLE``); such frames start from a
   weighted Procrustes fit instead of the identity.
3. **Significance gate (whole shot).** With ``c0_f`` the weighted residual of frame ``f``
   when only the expressions may move (identity head motion) and ``c1_f`` the residual
   with the fitted head motion, the rigid motion is kept only if, for some ``window``
   consecutive frames ``W`` (default ``config.HEAD_MOTION_WINDOW``; the whole shot if
   shorter)::

       sum_{f in W} (c0_f - c1_f)  >  config.HEAD_MOTION_SIGNIFICANCE * sum_{f in W} (c1_f + floor_f)

   where ``floor_f = (config.HEAD_MOTION_NOISE_FLOOR * face size)^2 * 3 * sum_i w_i`` over
   the frame's visible markers (a marker-noise floor). In words: somewhere in the shot the
   head motion must explain more of the markers' motion, beyond what the expressions
   explain, than ``HEAD_MOTION_SIGNIFICANCE`` times what remains unexplained (rig
   mismatch, noise). If so, every frame keeps its fitted motion; otherwise every frame
   gets exactly the identity. ``c0_f - c1_f`` is evaluated as the quadratic form of the
   expression-eliminated rigid normal matrix at the fitted motion (exact for small
   motions, where the decision is made).

Missing samples are NaN (a marker with any NaN coordinate is missing in that frame).
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Literal, overload

import numpy as np
import numpy.typing as npt

from .. import config
from .._threads import blas_single_threaded
from .._validate import sum_finite
from ..errors import DegenerateGeometryError, InputError, NonFiniteError, NumericalError, ShapeError
from . import procrustes

__all__ = [
    "estimate_head_motion",
    "HeadMotionModel",
    "rigidity_weights",
    "HeadMotionInfo",
    "DEFAULT_MAX_ITER",
    "DEFAULT_TOL",
]

#: Gauss-Newton steps at most (typically 5-10 converge to ``DEFAULT_TOL``).
DEFAULT_MAX_ITER = 60
#: Convergence: largest rotation update (radians) and translation update (times the face
#: size) of any frame.
DEFAULT_TOL = 1e-10
#: Frames gathered at once where per-frame matrices are needed (missing markers).
_CHUNK = 256
#: Frames per block of the marker-sized scratch (gate residuals, moments): memory bounded
#: by the block, and the block stays in cache.
_RESIDUAL_CHUNK = 1024


@dataclass(frozen=True)
class HeadMotionInfo:
    """What :func:`estimate_head_motion` decided, for diagnostics.

    Attributes
    ----------
    detected : bool
        The rigid motion passed the significance gate (False: identity was returned).
    evidence : float
        The largest ``sum_f (c0_f - c1_f) / sum_f (c1_f + floor_f)`` over ``window``
        consecutive frames, compared with ``significance``.
    marker_weights : (N,) float
        The rigidity weights used (mean 1 over the weighted markers).
    iterations : int
        Gauss-Newton steps taken.
    unidentifiable_frames : (K,) int
        Frames where some rigid direction could not be separated from the expressions on
        the visible markers (left at their weighted-Procrustes value).
    local : (F, N, 3) float or None
        Only when asked (``HeadMotionModel.estimate(keep_local=True)``): the markers with
        the returned motion removed, minus the reference (what ``procrustes.remove(motion,
        markers, reference)`` gives, bit for bit; the gate computes them anyway). None when
        a sample is missing or a marker has weight 0.
    """

    detected: bool
    evidence: float
    marker_weights: np.ndarray
    iterations: int
    unidentifiable_frames: np.ndarray
    local: np.ndarray | None = None


def rigidity_weights(
    reference: npt.ArrayLike, basis: npt.ArrayLike | None = None, *, eps: float | None = None
) -> np.ndarray:
    """``(N,)`` marker weights ``1 / (eps^2 + m_i^2)``, normalized to mean 1.

    ``m_i`` is the RMS displacement of marker ``i`` over the columns of ``basis (3N, M)``
    (x-y-z interleaved per marker); ``eps`` is in face sizes (RMS radius of ``reference``),
    default ``config.HEAD_MOTION_RIGIDITY``. Without a basis: all ones.
    """
    ref = _reference(reference)
    n = ref.shape[0]
    if basis is None:
        return np.ones(n)
    b = _basis(basis, n)
    eps = config.HEAD_MOTION_RIGIDITY if eps is None else float(eps)
    if not eps > 0 or not np.isfinite(eps):
        raise InputError(
            f"rigidity_weights: eps must be a positive number of face sizes, got {eps!r}"
        )
    size = _face_size(ref)
    motion2 = (
        np.mean(np.sum(b.reshape(n, 3, -1) ** 2, axis=1), axis=1) if b.shape[1] else np.zeros(n)
    )
    w = 1.0 / ((eps * size) ** 2 + motion2)
    return w / w.mean()


@overload
def estimate_head_motion(
    reference: npt.ArrayLike,
    markers: npt.ArrayLike,
    *,
    basis: npt.ArrayLike | None = None,
    marker_weights: npt.ArrayLike | None = None,
    ridge: float | None = None,
    significance: float | None = config.HEAD_MOTION_SIGNIFICANCE,
    window: int = config.HEAD_MOTION_WINDOW,
    max_iter: int = DEFAULT_MAX_ITER,
    tol: float = DEFAULT_TOL,
    return_info: Literal[False] = False,
) -> np.ndarray: ...
@overload
def estimate_head_motion(
    reference: npt.ArrayLike,
    markers: npt.ArrayLike,
    *,
    basis: npt.ArrayLike | None = None,
    marker_weights: npt.ArrayLike | None = None,
    ridge: float | None = None,
    significance: float | None = config.HEAD_MOTION_SIGNIFICANCE,
    window: int = config.HEAD_MOTION_WINDOW,
    max_iter: int = DEFAULT_MAX_ITER,
    tol: float = DEFAULT_TOL,
    return_info: Literal[True],
) -> tuple[np.ndarray, HeadMotionInfo]: ...
def estimate_head_motion(
    reference: npt.ArrayLike,
    markers: npt.ArrayLike,
    *,
    basis: npt.ArrayLike | None = None,
    marker_weights: npt.ArrayLike | None = None,
    ridge: float | None = None,
    significance: float | None = config.HEAD_MOTION_SIGNIFICANCE,
    window: int = config.HEAD_MOTION_WINDOW,
    max_iter: int = DEFAULT_MAX_ITER,
    tol: float = DEFAULT_TOL,
    return_info: bool = False,
) -> np.ndarray | tuple[np.ndarray, HeadMotionInfo]:
    """Rigid head motion ``(F, 4, 4)`` of ``markers`` relative to ``reference`` (see the module doc).

    One call of ``HeadMotionModel(reference, basis=..., marker_weights=..., ridge=...)
    .estimate(markers, ...)``; keep a :class:`HeadMotionModel` to estimate many shots of the
    same neutral and basis without redoing what depends on them alone.

    Parameters
    ----------
    reference : (N, 3) float
        Neutral marker positions (finite).
    markers : (F, N, 3) float
        Marker positions per frame; NaN = missing sample.
    basis : (3N, M) float, optional
        Expression displacements at the markers (x-y-z interleaved per marker, one column
        per shape), in the reference's frame and units. Gives the rigidity weights and is
        fitted jointly with the head motion. Without it: weighted Procrustes (all weights
        equal unless ``marker_weights``) with the same significance gate.
    marker_weights : (N,) float >= 0, optional
        Multiplies the rigidity weights (0 excludes a marker).
    ridge : float, optional
        Tikhonov term on the expression coefficients; default ``config.RIDGE_EPS`` times the
        mean diagonal of the weighted Gram matrix.
    significance : float or None
        Threshold of the significance gate; None returns the fitted motion unconditionally.
    window : int
        Frames over which the gate sums (the largest ratio over any ``window`` consecutive
        frames counts, so a short head turn in a long still shot is kept); give about one
        second of frames.
    max_iter, tol : Gauss-Newton limits (see :data:`DEFAULT_MAX_ITER`, :data:`DEFAULT_TOL`).
    return_info : bool
        Also return a :class:`HeadMotionInfo`.

    Returns
    -------
    motion : (F, 4, 4) float64, ``[[R, t], [0, 1]]``; exactly the identity in every frame when
        the gate finds no significant head motion.
    info : HeadMotionInfo, only with ``return_info``.
    """
    model = HeadMotionModel(reference, basis=basis, marker_weights=marker_weights, ridge=ridge)
    return model.estimate(
        markers,
        significance=significance,
        window=window,
        max_iter=max_iter,
        tol=tol,
        return_info=return_info,
    )


@dataclass(frozen=True)
class _Pattern:
    """What the Gauss-Newton steps and the gate need of one pattern of visible markers
    (see :func:`_gains`; ``projection`` only for a single shared pattern with a basis)."""

    rows: np.ndarray  # (P, N, 18): the gains' (6, 3) block of each marker, flattened
    schur: np.ndarray  # (P, 6, 6)
    ainv: np.ndarray | None  # (P, M, M)
    weak: np.ndarray  # (P,) bool
    sums: np.ndarray  # (P, 6, 3)
    offsets: np.ndarray  # (P, 6)
    projection: np.ndarray | None  # (3N, M): W B K with A^-1 = K K^T (see _projection)


class HeadMotionModel:
    """:func:`estimate_head_motion` for one neutral and expression basis, reusable.

    Everything that depends on the reference, the basis and the marker weights alone (the
    rigidity weights, the Gauss-Newton gains and the gate's expression projection of the
    complete marker set) is computed once; :meth:`estimate` then costs only what the
    frames need. The parameters are those of :func:`estimate_head_motion`; the arrays are
    copied (later changes to the caller's arrays do not reach the model).
    """

    #: Patterns of visible markers whose gains are kept (the complete set, usually).
    MAX_PATTERNS_KEPT = 4

    def __init__(
        self,
        reference: npt.ArrayLike,
        *,
        basis: npt.ArrayLike | None = None,
        marker_weights: npt.ArrayLike | None = None,
        ridge: float | None = None,
    ) -> None:
        ref = _reference(reference).copy()
        n = ref.shape[0]
        b = None if basis is None else _basis(basis, n).copy()
        if b is not None and b.shape[1] == 0:
            b = None
        w = rigidity_weights(ref, b)
        if marker_weights is not None:
            extra = np.asarray(marker_weights, dtype=np.float64)
            if extra.shape != (n,):
                raise ShapeError(
                    f"estimate_head_motion: marker_weights must be ({n},), got shape {extra.shape}"
                )
            if not np.isfinite(extra).all() or (extra < 0).any():
                raise InputError("estimate_head_motion: marker_weights must be finite and >= 0")
            w = w * extra
            if not w.any():
                raise DegenerateGeometryError("estimate_head_motion: every marker has weight 0")
            w = w / w[w > 0].mean()
        self.reference = ref
        self.basis = b
        self.marker_weights = w
        self.ridge = ridge
        self.size = _face_size(ref)
        self.centre = (w @ ref) / w.sum()
        # rigid generator at the neutral, rotation scaled by the face size (unknowns theta*size, t)
        self._gen = _generator((ref - self.centre) / self.size)  # (3N, 6)
        self._patterns: dict[bytes, _Pattern] = {}

    def _pattern(self, patterns: np.ndarray) -> _Pattern:
        """The gains etc. of ``patterns (P, N)``; a single pattern is kept for later calls."""
        key = patterns.tobytes() if patterns.shape[0] == 1 else b""
        if key and key in self._patterns:
            return self._patterns[key]
        w, ref = self.marker_weights, self.reference
        gains, schur, ainv, weak = _gains(patterns, w, self._gen, self.basis, self.ridge)
        blocks = gains.reshape(gains.shape[0], 6, -1, 3)  # (P, 6, N, 3)
        rows = np.ascontiguousarray(blocks.transpose(0, 2, 1, 3)).reshape(gains.shape[0], -1, 18)
        projection = None
        if key and self.basis is not None and ainv is not None:
            projection = _projection(self.basis, np.repeat(patterns[0] * w, 3), ainv[0])
        out = _Pattern(
            rows,
            schur,
            ainv,
            weak,
            blocks.sum(axis=2),
            np.einsum("pkia,ia->pk", blocks, ref),
            projection,
        )
        if key:
            if len(self._patterns) >= self.MAX_PATTERNS_KEPT:
                self._patterns.clear()
            self._patterns[key] = out
        return out

    @blas_single_threaded  # many small products per chunk of frames (faceretarget._threads)
    def estimate(
        self,
        markers: npt.ArrayLike,
        *,
        significance: float | None = config.HEAD_MOTION_SIGNIFICANCE,
        window: int = config.HEAD_MOTION_WINDOW,
        max_iter: int = DEFAULT_MAX_ITER,
        tol: float = DEFAULT_TOL,
        return_info: bool = False,
        keep_local: bool = False,
    ) -> np.ndarray | tuple[np.ndarray, HeadMotionInfo]:
        """Head motion of ``markers (F, N, 3)`` (NaN = missing): see :func:`estimate_head_motion`.

        ``keep_local`` (with ``return_info``): also return the head-frame displacements in
        ``info.local`` (see :class:`HeadMotionInfo`)."""
        ref, w = self.reference, self.marker_weights
        n = ref.shape[0]
        x = np.asarray(markers, dtype=np.float64)
        if x.ndim != 3 or x.shape[1:] != (n, 3):
            raise ShapeError(
                f"estimate_head_motion: markers must be (F, {n}, 3) like the reference, got {x.shape}"
            )
        if (
            isinstance(window, (bool, np.bool_))
            or not isinstance(window, (int, np.integer))
            or window < 1
        ):
            raise InputError(
                f"estimate_head_motion: window must be a whole number of frames >= 1, got {window!r}"
            )
        n_frames = x.shape[0]
        if n_frames == 0:
            out = np.zeros((0, 4, 4))
            return (
                (out, HeadMotionInfo(False, 0.0, w.copy(), 0, np.zeros(0, dtype=np.intp)))
                if return_info
                else out
            )
        shared = sum_finite(x)  # common case: nothing missing, one pattern
        if shared:
            valid = np.broadcast_to(w > 0, (n_frames, n))
            x0 = x
        else:
            if np.isinf(x).any():
                raise NonFiniteError(
                    "estimate_head_motion: markers contain infinite values; mark missing samples with NaN"
                )
            valid = ~np.isnan(x).any(axis=2) & (w > 0)
            x0 = np.where(valid[..., None], x, 0.0)
        counts = valid[:1].sum(axis=1) if shared else valid.sum(axis=1)
        if counts.min() < 3:
            f = int(np.argmax(counts < 3))
            raise DegenerateGeometryError(
                f"estimate_head_motion: frame {f} has {int(counts[f])} usable markers; a rigid fit needs at least 3"
            )
        size, centre = self.size, self.centre

        if shared or (valid[:1].all() and (n_frames == 1 or valid.all())):
            patterns, which = valid[:1].copy(), np.zeros(n_frames, dtype=np.intp)
        else:
            patterns, which = np.unique(valid, axis=0, return_inverse=True)
            which = which.reshape(-1)
        pat = self._pattern(patterns)

        rot = np.tile(np.eye(3), (n_frames, 1, 1))
        trans = np.zeros((n_frames, 3))
        weak_frames = np.flatnonzero(pat.weak[which])
        if weak_frames.size:  # start where the expressions cannot tell: weighted Procrustes
            r0, t0, _ = procrustes.fit_rigid(ref, x[weak_frames], weights=w)
            rot[weak_frames], trans[weak_frames] = r0, t0
        moments = _moments(pat.rows, which, x0)
        warm = np.ones(n_frames, dtype=np.bool_)
        warm[weak_frames] = False  # those keep their Procrustes start
        iterations, done, coords = _gauss_newton(
            moments, pat.sums, pat.offsets, which, centre, size, rot, trans, max_iter, tol, warm
        )
        if not done.all():  # far from the identity (e.g. > 150 degrees): restart from Procrustes
            again = np.flatnonzero(~done)
            sub_rot, sub_trans, _ = procrustes.fit_rigid(ref, x[again], weights=w)
            more, done_again, coords[again] = _gauss_newton(
                moments[again],
                pat.sums,
                pat.offsets,
                which[again],
                centre,
                size,
                sub_rot,
                sub_trans,
                max_iter,
                tol,
            )
            rot[again], trans[again] = sub_rot, sub_trans
            iterations += more
            if not done_again.all():
                raise NumericalError(
                    f"estimate_head_motion: Gauss-Newton did not converge in frame {int(again[np.argmin(done_again)])}; "
                    "check the reference and the markers (same order, same units)"
                )

        out = np.zeros((n_frames, 4, 4))  # the fitted motion; the identity if the gate says so
        out[:, 3, 3] = 1.0
        out[:, :3, :3] = rot
        out[:, :3, 3] = trans
        keep = keep_local and bool(valid[:1].all() if shared else valid.all())
        evidence, local = _evidence(
            x0, valid, ref, w, self.basis, out, coords, size, pat, which, window, keep
        )
        detected = significance is None or evidence > significance
        if not detected:
            if local is not None:
                local = x - ref
            out[:, :3, :3] = np.eye(3)
            out[:, :3, 3] = 0.0
        if return_info:
            info = HeadMotionInfo(
                bool(detected), float(evidence), w.copy(), int(iterations), weak_frames, local
            )
            return out, info
        return out


def _evidence(
    x0: np.ndarray,
    valid: np.ndarray,
    ref: np.ndarray,
    w: np.ndarray,
    basis: np.ndarray | None,
    motion: np.ndarray,
    z: np.ndarray,
    size: float,
    pattern: _Pattern,
    which: np.ndarray,
    window: int,
    keep: bool = False,
) -> tuple[float, np.ndarray | None]:
    """The gate's statistic: the largest ``sum_f (c0_f - c1_f) / sum_f (c1_f + floor_f)`` over
    ``window`` consecutive frames (the whole shot if shorter), and with ``keep`` (every
    sample valid) the local residuals ``(F, N, 3)`` it was computed from (else None).

    ``c0_f - c1_f`` (what the head motion explains beyond the expressions) is the quadratic
    form of the expression-eliminated rigid normal matrix (Schur complement) at the fitted
    motion's rigid coordinates ``z (F, 6)`` (the kernel's ``coords``); the remaining residual
    ``c1_f`` is computed exactly, removing ``motion (F, 4, 4)`` from the markers.
    """
    schur, ainv = pattern.schur, pattern.ainv
    n_frames = z.shape[0]
    if schur.shape[0] == 1:
        gain = np.einsum("fk,fk->f", z @ schur[0], z)
    else:
        gain = np.einsum("fk,fkl,fl->f", z, schur[which], z)
    floor = (config.HEAD_MOTION_NOISE_FLOOR * size) ** 2
    rest = np.empty(n_frames)
    shared = schur.shape[0] == 1  # one pattern of visible markers: weights shared by all frames
    if shared:
        wd = np.repeat(valid[0] * w, 3)
        unused = wd == 0
    kept = procrustes.remove(motion, x0, ref) if keep else None
    for start in range(0, n_frames, _RESIDUAL_CHUNK):  # scratch bounded by the chunk, not the shot
        sl = slice(start, start + _RESIDUAL_CHUNK)
        local = kept[sl] if kept is not None else procrustes.remove(motion[sl], x0[sl], ref)
        if shared:
            y = local.reshape(len(local), -1)
            if unused.any():  # never with keep (every sample valid): y is a view of kept
                y[:, unused] = 0.0
            rest[sl] = (
                _unexplained(y, wd, basis, ainv, which[sl], pattern.projection) + floor * wd.sum()
            )
        else:
            y = np.where(valid[sl, :, None], local, 0.0).reshape(len(local), -1)
            wd_sl = np.repeat(valid[sl] * w, 3, axis=1)
            rest[sl] = _unexplained(y, wd_sl, basis, ainv, which[sl]) + floor * wd_sl.sum(axis=1)
    span = min(max(int(window), 1), n_frames)
    gains = np.concatenate([[0.0], np.cumsum(np.maximum(gain, 0.0))])
    rests = np.concatenate([[0.0], np.cumsum(rest)])
    statistic = float(np.max((gains[span:] - gains[:-span]) / (rests[span:] - rests[:-span])))
    return statistic, kept


# ---------------------------------------------------------------------------------------
# pieces
# ---------------------------------------------------------------------------------------
def _reference(reference: npt.ArrayLike) -> np.ndarray:
    ref = np.asarray(reference, dtype=np.float64)
    if ref.ndim != 2 or ref.shape[1] != 3 or ref.shape[0] < 3:
        raise ShapeError(
            f"estimate_head_motion: reference must be (N, 3) with N >= 3, got {ref.shape}"
        )
    if not np.isfinite(ref).all():
        raise NonFiniteError(
            "estimate_head_motion: the reference contains NaN or infinity; give a complete neutral"
        )
    return ref


def _basis(basis: npt.ArrayLike, n: int) -> np.ndarray:
    b = np.asarray(basis, dtype=np.float64)
    if b.ndim != 2 or b.shape[0] != 3 * n:
        raise ShapeError(
            f"estimate_head_motion: basis must be (3N, M) = ({3 * n}, M), got {b.shape}"
        )
    if not np.isfinite(b).all():
        raise NonFiniteError("estimate_head_motion: the expression basis contains NaN or infinity")
    return b


def _face_size(ref: np.ndarray) -> float:
    size = float(np.sqrt(np.mean(np.sum((ref - ref.mean(axis=0)) ** 2, axis=1))))
    if not size > 0:
        raise DegenerateGeometryError("estimate_head_motion: the reference markers all coincide")
    return size


def _generator(q: np.ndarray) -> np.ndarray:
    """``(3N, 6)``: d/d(theta, t) of ``theta x q_i + t`` (x-y-z interleaved per marker)."""
    g = np.zeros((q.shape[0], 3, 6))
    g[:, 0, 1], g[:, 0, 2] = q[:, 2], -q[:, 1]
    g[:, 1, 0], g[:, 1, 2] = -q[:, 2], q[:, 0]
    g[:, 2, 0], g[:, 2, 1] = q[:, 1], -q[:, 0]
    g[:, :, 3:] = np.eye(3)
    return g.reshape(-1, 6)


def _gains(
    patterns: np.ndarray,
    w: np.ndarray,
    gen: np.ndarray,
    basis: np.ndarray | None,
    ridge: float | None,
) -> tuple[np.ndarray, np.ndarray, np.ndarray | None, np.ndarray]:
    """Per pattern of visible markers: the Gauss-Newton gain ``(P, 6, 3N)``, the rigid normal
    matrix after eliminating the expressions ``(P, 6, 6)``, the inverse expression Gram matrix
    ``A^-1 (P, M, M)`` (None without a basis) and whether a rigid direction is unidentifiable ``(P,)``.

    The rigid normal matrix after eliminating the expressions (Schur complement) is
    ``S = G^T W G - C A^-1 C^T`` with ``A = B^T W B + ridge I``, ``C = G^T W B``; relative to
    ``R = G^T W G`` its generalized eigenvalues are the fractions of each rigid direction
    the expressions cannot mimic. Directions below ``config.HEAD_MOTION_IDENTIFIABLE`` are
    dropped from the pseudo-inverse. All pattern products are single matrix products over
    the patterns (no loop).
    """
    n_pat, n = patterns.shape
    wd = np.repeat(patterns * w, 3, axis=1)  # (P, 3N)
    normal = (wd @ (gen[:, :, None] * gen[:, None, :]).reshape(3 * n, 36)).reshape(
        n_pat, 6, 6
    )  # G^T W G
    ainv = None
    if basis is None:
        schur = normal
        corrected = gen.T[None] * wd[:, None, :]  # (P, 6, 3N) = G^T W
    else:
        m = basis.shape[1]
        full = basis.T @ (basis * np.repeat(w, 3)[:, None])
        scale = np.trace(full) / m
        if scale <= 0:
            scale = 1.0
        ridge_value = config.RIDGE_EPS * scale if ridge is None else float(ridge)
        dropped = (~patterns) & (w > 0)
        if dropped.any():  # subtract the missing markers' Gram matrices
            per_marker = basis.reshape(n, 3, m)
            grams = np.matmul(per_marker.transpose(0, 2, 1), per_marker).reshape(
                n, m * m
            )  # (N, M*M)
            gram = full[None] - ((dropped * w) @ grams).reshape(n_pat, m, m)
        else:
            gram = np.repeat(full[None], n_pat, axis=0)
        gram += ridge_value * np.eye(m)
        coupling = (wd @ (gen[:, :, None] * basis[:, None, :]).reshape(3 * n, 6 * m)).reshape(
            n_pat, 6, m
        )  # G^T W B
        try:
            ainv = np.linalg.inv(gram)  # A^-1, also used by the gate
        except np.linalg.LinAlgError:
            raise NumericalError(
                "estimate_head_motion: the expression basis' Gram matrix is singular; give a positive ridge"
            ) from None
        h = np.matmul(ainv, coupling.transpose(0, 2, 1))  # (P, M, 6) = A^-1 C^T
        schur = normal - np.matmul(coupling, h)
        # G^T W - C A^-1 B^T W = (G - B H)^T W, with B H for all patterns in one product
        bh = (basis @ h.transpose(1, 0, 2).reshape(m, 6 * n_pat)).reshape(3 * n, n_pat, 6)
        corrected = (gen[:, None, :] - bh).transpose(1, 2, 0) * wd[:, None, :]
    # generalized eigenproblem S v = mu R v through R = L L^T
    try:
        chol = np.linalg.cholesky(normal)
    except np.linalg.LinAlgError:
        raise DegenerateGeometryError(
            "estimate_head_motion: the visible markers of some frame are collinear; a rigid fit needs 3 markers spread over the face"
        ) from None
    linv = np.linalg.inv(chol)
    sym = linv @ schur @ linv.transpose(0, 2, 1)
    sym = 0.5 * (sym + sym.transpose(0, 2, 1))
    mu, vec = np.linalg.eigh(sym)
    keep = mu >= config.HEAD_MOTION_IDENTIFIABLE
    inv_mu = np.where(keep, 1.0 / np.where(keep, mu, 1.0), 0.0)
    half = linv.transpose(0, 2, 1) @ vec  # (P, 6, 6)
    pinv = (half * inv_mu[:, None, :]) @ half.transpose(0, 2, 1)
    gains = np.matmul(pinv, corrected)  # (P, 6, 3N)
    # numpy's stubs type all(axis=1) as a scalar or an array; of (P, 6) it is a (P,) array
    return gains, schur, ainv, ~keep.all(axis=1)  # type: ignore[return-value]


def _moments(rows: np.ndarray, which: np.ndarray, x0: np.ndarray) -> np.ndarray:
    """What the gains need of the markers, once: the gain applied to the local residual
    ``y = R^T (x - t) - n`` is ``sum_ab P[b, k, a] R[b, a] - s[k] . (R^T t) - g[k]`` with
    ``P = sum_i x_i K_i^T`` (per frame), ``s = sum_i K_i``, ``g = sum_i K_i n_i`` (per pattern,
    in :class:`_Pattern`); ``K_i`` is the ``(6, 3)`` block of marker ``i``, row ``i`` of
    ``rows (P, N, 18)`` per pattern. Returns ``P (F, 3, 18)`` (b, then k-a flattened)."""
    n_frames, n = x0.shape[0], x0.shape[1]
    moments = np.empty((n_frames, 3, 18))
    if rows.shape[0] == 1:
        for start in range(0, n_frames, _RESIDUAL_CHUNK):  # a chunk of transposed markers at a time
            sl = slice(start, start + _RESIDUAL_CHUNK)
            xt = np.ascontiguousarray(x0[sl].transpose(0, 2, 1)).reshape(-1, n)  # (3f, N)
            np.matmul(xt, rows[0], out=moments[sl].reshape(-1, 18))
    else:
        for start in range(0, n_frames, _CHUNK):  # bounded memory for the gathered gains
            sl = slice(start, start + _CHUNK)
            moments[sl] = np.matmul(x0[sl].transpose(0, 2, 1), rows[which[sl]])
    return moments


def _gauss_newton(
    moments: np.ndarray,
    sums: np.ndarray,
    offsets: np.ndarray,
    which: np.ndarray,
    centre: np.ndarray,
    size: float,
    rot: np.ndarray,
    trans: np.ndarray,
    max_iter: int,
    tol: float,
    warm: npt.ArrayLike | None = None,
) -> tuple[int, np.ndarray, np.ndarray]:
    """Gauss-Newton steps on ``rot (F, 3, 3)`` / ``trans (F, 3)`` in place (numba kernel, one
    frame at a time until it converges; frames where ``warm (F,)`` is set start from the
    previous frame's result); returns (most steps taken, converged (F,), the converged
    frames' rigid coordinates ``z (F, 6)`` for the gate, see :func:`_evidence`)."""
    from ._head_motion_kernels import gauss_newton

    steps = np.empty(rot.shape[0], dtype=np.int64)
    coords = np.zeros((rot.shape[0], 6))
    warm = (
        np.zeros(rot.shape[0], dtype=np.bool_)
        if warm is None
        else np.ascontiguousarray(warm, dtype=np.bool_)
    )
    gauss_newton(
        np.ascontiguousarray(moments),
        np.ascontiguousarray(sums),
        np.ascontiguousarray(offsets),
        np.ascontiguousarray(which, dtype=np.int64),
        np.ascontiguousarray(centre, dtype=np.float64),
        float(size),
        rot,
        trans,
        int(max_iter),
        float(tol),
        steps,
        warm,
        coords,
    )
    done = steps >= 0
    return int(np.where(done, steps, max_iter).max(initial=0)), done, coords


def _projection(basis: np.ndarray, wd: np.ndarray, ainv: np.ndarray) -> np.ndarray:
    """``W B K (3N, M)`` with ``A^-1 = K K^T``: ``u^T A^-1 u = |K^T u|^2`` for ``u = B^T W y``,
    so a frame's explained energy is ``|y W B K|^2``, one product for all frames."""
    return (basis * wd[:, None]) @ np.linalg.cholesky(ainv)


def _unexplained(
    y: np.ndarray,
    wd: np.ndarray,
    basis: np.ndarray | None,
    ainv: np.ndarray | None,
    which: np.ndarray,
    projection: np.ndarray | None = None,
) -> np.ndarray:
    """Weighted residual energy per frame after the best expression fit: ``y^T W y - u^T A^-1 u``
    with ``u = B^T W y`` (``wd``: ``(3N,)`` shared or ``(F, 3N)`` per-frame weights;
    ``projection``: the pattern's :func:`_projection`, given with shared weights and a basis)."""
    if projection is not None and wd.ndim == 1:
        # shared weights: one product, u^T A^-1 u = |y W B K|^2
        proj = y @ projection
        return np.maximum(np.square(y) @ wd - np.einsum("fk,fk->f", proj, proj), 0.0)
    yw = y * wd
    total = np.einsum("fr,fr->f", yw, y)
    if basis is None:
        return total
    assert ainv is not None  # _gains gives A^-1 with a basis
    u = yw @ basis  # (F, M)
    if ainv.shape[0] == 1:
        explained = np.einsum("fk,fk->f", u @ ainv[0], u)
    else:
        explained = np.empty(len(u))
        for start in range(0, len(u), _CHUNK):  # bounded memory for the gathered inverses
            sl = slice(start, start + _CHUNK)
            explained[sl] = np.einsum("fk,fkl,fl->f", u[sl], ainv[which[sl]], u[sl])
    return np.maximum(total - explained, 0.0)
