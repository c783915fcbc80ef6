"""Rigid (and similarity) Procrustes alignment, batched over frames, NaN-aware.

Conventions: a transform maps *reference* (neutral) coordinates to frame
coordinates, ``x_frame ~= s * R @ x_ref + t``. Head motion is stored as 4x4
matrices ``[[s R, t], [0, 1]]`` (with s = 1 for rigid motion).
"""

from __future__ import annotations

import numpy as np

from ..errors import DegenerateGeometryError, ShapeError


def fit_rigid(
    reference: np.ndarray,
    frames: np.ndarray,
    weights: np.ndarray | None = None,
    *,
    scale: bool = False,
):
    """Best rigid (or similarity) transform from ``reference`` onto each frame (Kabsch / Umeyama).

    Parameters
    ----------
    reference : (N, D) float, D in {2, 3}
        Reference (neutral) points.
    frames : (F, N, D) or (N, D) float
        Target points; NaN rows are missing samples and get zero weight.
    weights : (N,) or (F, N) float, optional
        Non-negative point weights (e.g. to align on stable points only).
    scale : bool
        Also fit a uniform scale (similarity transform).

    Returns
    -------
    rotation : (F, D, D)   proper rotations (det = +1)
    translation : (F, D)
    scales : (F,)          ones unless ``scale``
    """
    ref = np.asarray(reference, dtype=np.float64)
    frm = np.asarray(frames, dtype=np.float64)
    single = frm.ndim == 2
    if single:
        frm = frm[None]
    if ref.ndim != 2 or frm.shape[1:] != ref.shape or ref.shape[1] not in (2, 3):
        raise ShapeError(
            f"fit_rigid: reference (N, D) and frames (F, N, D) must agree, got {ref.shape} and {frm.shape}"
        )
    n_frames, n_points, dim = frm.shape
    valid = ~np.any(np.isnan(frm), axis=-1)
    w = (
        np.ones((n_frames, n_points))
        if weights is None
        else np.broadcast_to(np.asarray(weights, dtype=np.float64), (n_frames, n_points))
    )
    w = np.where(valid, w, 0.0)
    total = w.sum(axis=1)
    if np.any(np.count_nonzero(w, axis=1) < dim):
        f = int(np.flatnonzero(np.count_nonzero(w, axis=1) < dim)[0])
        raise DegenerateGeometryError(
            f"fit_rigid: frame {f} has fewer than {dim} usable points; a rigid fit needs at least {dim}"
        )
    x = np.where(valid[..., None], frm, 0.0)
    wn = w / total[:, None]
    mu_ref = wn @ ref  # (F, D)
    mu_frm = np.matmul(wn[:, None, :], x)[:, 0]
    a = ref[None] - mu_ref[:, None]
    b = x - mu_frm[:, None]
    cov = np.matmul((b * wn[..., None]).transpose(0, 2, 1), a)  # frame x ref
    u, sig, vt = np.linalg.svd(cov)
    det = np.sign(np.linalg.det(u @ vt))
    det[det == 0] = 1.0
    fix = np.ones((n_frames, dim))
    fix[:, -1] = det
    rot = (u * fix[:, None, :]) @ vt
    if scale:
        var_ref = np.sum(wn * np.sum(a * a, axis=2), axis=1)
        s = np.einsum("fd,fd->f", sig, fix) / np.maximum(var_ref, np.finfo(float).tiny)
    else:
        s = np.ones(n_frames)
    trans = mu_frm - s[:, None] * np.matmul(rot, mu_ref[..., None])[..., 0]
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
    """Apply ``(F, D+1, D+1)`` transforms to ``points (F, P, D)`` or ``(P, D)`` (broadcast over frames)."""
    m = np.asarray(transforms, dtype=np.float64)
    dim = m.shape[-1] - 1
    p = np.asarray(points, dtype=np.float64)
    lin = m[:, :dim, :dim]
    return (
        np.matmul(p, lin.transpose(0, 2, 1)) + m[:, None, :dim, dim]
    )  # rows: p @ L^T (broadcasts (P, D))


def remove(
    transforms: np.ndarray, points: np.ndarray, reference: np.ndarray | None = None
) -> np.ndarray:
    """Undo ``(F, D+1, D+1)`` transforms on ``points (F, P, D)``: back to reference coordinates.

    With ``reference (P, D)`` returns the displacements from it instead (one pass, no
    temporary). 3D points go through a numba kernel (one 3x3 inverse a frame); a singular
    transform raises :class:`DegenerateGeometryError`.
    """
    m = np.asarray(transforms, dtype=np.float64)
    p = np.asarray(points, dtype=np.float64)
    if p.ndim == 3 and p.shape[2] == 3 and m.shape == (p.shape[0], 4, 4):
        from ._procrustes_kernels import remove_affine

        ref = (
            np.zeros((p.shape[1], 3))
            if reference is None
            else np.ascontiguousarray(reference, dtype=np.float64)
        )
        out = np.empty(p.shape)
        bad = remove_affine(np.ascontiguousarray(m), np.ascontiguousarray(p), ref, out)
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
