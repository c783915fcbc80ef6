"""Rigid (and similarity) Procrustes alignment, batched over frames, NaN-aware.

Conventions: a transform maps *reference* (neutral) coordinates to frame
coordinates, ``x_frame ~= s * R @ x_ref + t``. Head motion is stored as 4x4
matrices ``[[s R, t], [0, 1]]`` (with s = 1 for rigid motion).
"""

from __future__ import annotations

import numpy as np
import numpy.typing as npt

from .._validate import readonly
from ..errors import DegenerateGeometryError, ShapeError


def fit_rigid(
    reference: np.ndarray,
    frames: np.ndarray,
    weights: np.ndarray | None = None,
    *,
    scale: bool = False,
    min_points: int | None = None,
) -> tuple[np.ndarray, np.ndarray, np.ndarray | np.floating]:
    """Best rigid (or similarity) transform from ``reference`` onto each frame (Kabsch / Umeyama).

    Parameters
    ----------
    reference : (N, D) or (F, N, D) float, D in {2, 3}
        Reference (neutral) points, one for all frames or one a frame (e.g. a model's
        reconstruction of each frame).
    frames : (F, N, D) or (N, D) float
        Target points; a row with a NaN is a missing sample and gets zero weight.
    weights : (N,) or (F, N) float, optional
        Non-negative point weights (e.g. to align on stable points only).
    scale : bool
        Also fit a uniform scale (similarity transform).
    min_points : int, optional
        None: a frame with fewer than D present points of non-zero weight raises
        :class:`DegenerateGeometryError`. A number: such a frame (fewer than ``min_points``,
        or no weight) gets the identity instead.

    Returns
    -------
    rotation : (F, D, D)   proper rotations (det = +1)
    translation : (F, D)
    scales : (F,)          ones unless ``scale``

    (For ``frames (N, D)``: one rotation, translation and scale.) One numba kernel (``_procrustes_kernels.kabsch``), frame by frame: a frame gives the
    same numbers alone as inside a batch.
    """
    from ._procrustes_kernels import kabsch

    frm = np.asarray(frames, dtype=np.float64)
    single = frm.ndim == 2
    if single:
        frm = frm[None]
    ref = np.asarray(reference, dtype=np.float64)
    per_frame = ref.ndim == 3
    if (
        frm.ndim != 3
        or frm.shape[2] not in (2, 3)
        or ref.shape[-2:] != frm.shape[1:]
        or ref.ndim not in (2, 3)
        or (per_frame and ref.shape[0] != frm.shape[0])
    ):
        raise ShapeError(
            "fit_rigid: reference (N, D) or (F, N, D) and frames (F, N, D) must agree, "
            f"got {ref.shape} and {frm.shape}"
        )
    n_frames, n_points, dim = frm.shape
    if weights is None:
        w = np.ones((1, n_points))
    else:
        w = np.asarray(weights, dtype=np.float64)
        if w.shape not in ((n_points,), (1, n_points), (n_frames, n_points)):
            raise ShapeError(
                f"fit_rigid: weights must be ({n_points},) or ({n_frames}, {n_points}), got {w.shape}"
            )
        w = w.reshape(-1, n_points)
    rot = np.empty((n_frames, dim, dim))
    trans = np.empty((n_frames, dim))
    s = np.empty(n_frames)
    skipped = kabsch(  # read-only inputs: one compiled specialization
        readonly(np.ascontiguousarray(ref if per_frame else ref[None])),
        readonly(np.ascontiguousarray(frm)),
        readonly(np.ascontiguousarray(w)),
        bool(scale),
        dim if min_points is None else int(min_points),
        rot,
        trans,
        s,
    )
    if min_points is None and skipped >= 0:
        raise DegenerateGeometryError(
            f"fit_rigid: frame {skipped} has fewer than {dim} usable points; a rigid fit needs at least {dim}"
        )
    if single:
        return rot[0], trans[0], s[0]
    return rot, trans, s


def to_matrix(
    rotation: np.ndarray, translation: np.ndarray, scales: np.ndarray | None = None
) -> np.ndarray:
    """(F, D+1, D+1) homogeneous matrices from ``rotation (F, D, D)``, ``translation (F, D)``."""
    rot = np.asarray(rotation, dtype=np.float64)
    n_frames, dim = rot.shape[0], rot.shape[1]
    out = np.zeros((n_frames, dim + 1, dim + 1))
    s = np.ones(n_frames) if scales is None else np.asarray(scales, dtype=np.float64)
    out[:, :dim, :dim] = rot * s[:, None, None]
    out[:, :dim, dim] = translation
    out[:, dim, dim] = 1.0
    return out


def apply(transforms: np.ndarray, points: np.ndarray) -> np.ndarray:
    """Apply ``(F, D+1, D+1)`` transforms to ``points (F, P, D)`` or ``(P, D)`` (broadcast over frames).

    3D points go through a numba kernel (``_procrustes_kernels.transform_points``) and may be
    float32; the result is float64.
    """
    m = np.asarray(transforms, dtype=np.float64)
    dim = m.shape[-1] - 1
    p = _points(points)
    if dim == 3 and m.ndim == 3 and p.ndim in (2, 3) and p.shape[-1] == 3:
        from ._procrustes_kernels import transform_points

        frames = p if p.ndim == 3 else np.broadcast_to(p, (m.shape[0], *p.shape))
        if frames.shape[0] == m.shape[0]:
            frames = np.ascontiguousarray(frames)
            out = np.empty(frames.shape)
            transform_points(
                readonly(np.ascontiguousarray(m)), readonly(frames), _NO_REFERENCE, False, out
            )
            return out
    lin = m[:, :dim, :dim]
    return (
        np.matmul(p, lin.transpose(0, 2, 1)) + m[:, None, :dim, dim]
    )  # rows: p @ L^T (broadcasts (P, D))


def remove(
    transforms: np.ndarray, points: np.ndarray, reference: np.ndarray | None = None
) -> np.ndarray:
    """Undo ``(F, D+1, D+1)`` transforms on ``points (F, P, D)``: back to reference coordinates.

    With ``reference (P, D)`` returns the displacements from it instead (one pass, no
    temporary). 3D points go through a numba kernel (one 3x3 inverse a frame; points may be
    float32, the result is float64); a singular transform raises
    :class:`DegenerateGeometryError`.
    """
    m = np.asarray(transforms, dtype=np.float64)
    p = _points(points)
    if p.ndim == 3 and p.shape[2] == 3 and m.shape == (p.shape[0], 4, 4):
        from ._procrustes_kernels import transform_points

        ref = (
            _NO_REFERENCE
            if reference is None
            else np.ascontiguousarray(reference, dtype=np.float64)
        )
        if ref.shape not in ((0, 3), p.shape[1:]):
            raise ShapeError(f"remove: reference must be {p.shape[1:]}, got {ref.shape}")
        out = np.empty(p.shape)
        bad = transform_points(
            readonly(np.ascontiguousarray(m)),
            readonly(np.ascontiguousarray(p)),
            readonly(ref),
            True,
            out,
        )
        if bad >= 0:
            raise DegenerateGeometryError(
                f"remove: the transform of frame {bad} is singular (or NaN); give invertible head motion"
            )
        return out
    try:
        out = apply(np.linalg.inv(m), p)
    except np.linalg.LinAlgError:
        raise DegenerateGeometryError(
            "remove: a transform is singular; give invertible head motion"
        ) from None
    return out if reference is None else out - reference


#: ``transform_points``' reference when there is none (no rows: nothing subtracted).
_NO_REFERENCE = readonly(np.zeros((0, 3)))


def _points(points: npt.ArrayLike) -> np.ndarray:
    """``points`` as a float32 or float64 array (float32 is kept: the kernels read it as is)."""
    p = np.asarray(points)
    return p if p.dtype in (np.float32, np.float64) else p.astype(np.float64)
