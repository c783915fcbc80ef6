"""Residual transfer (ours, not in the paper): what the actor's layers do not span, carried spatially.

The layered model transfers *content*: the part of the actor's expression its simplices
span. Whatever they do not span (an eyebrow raised alone, a jaw slid sideways, a puffed
cheek: animation is rarely a mix of a few hand-picked extremes) is the actor's residual
``r_A(t) = x_local(t) - (x_mu + layered(t))`` at the 3D markers, and the paper drops it
("motions outside the simplex extremes are truncated", sec. 7). When the character has
blendshapes and landmarks paired with the markers, we carry the residual to the
character the way a spatial retargeter would, and add it to the layered output::

    r_C(t) = s R r_A(t)                      (one similarity fitted to the neutral landmarks;
                                             R only when the faces are posed > 10 degrees apart)
    w(t)   = argmin_w  |D_L w - r_C(t)|^2 / (P u^2) + rho |w|^2 + lambda |w - w(t-1)|^2
    x_C(t) = R(t) (x_muC + layered_C(t) + D w(t)) + t(t)

``D`` are the character's blendshape deltas, ``D_L`` at its P paired landmarks, ``u`` their
RMS size (so the data term is unit-free like the layers' own), ``rho`` a small ridge
(``RIDGE`` x the mean diagonal of the normalised Gram) and ``lambda`` the layers'
``smoothing`` (the same first-order Markov pull, so streaming equals batch). The residual
weights are not bounded: the residual is a correction, positive or negative.

Measured on ``cases.cross_rig`` (300 frames, RMS error in % of face height): the layers
alone 0.31, with the residual 0.145, the per-frame blendshape fit of the whole motion
(``spacetime_noconst``) 0.24: the layers carry most of the motion without the spatial
transfer's errors (the same-named shapes moving differently), the spatial transfer only
the small remainder.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from faceretarget.geometry.procrustes import fit_rigid

__all__ = ["RESIDUAL_MODES", "ResidualModel", "build_residual", "pair_markers", "solve_residual"]

RESIDUAL_MODES = ("auto", "blendshapes", "none")
#: Ridge of the residual fit, relative to the mean diagonal of the normalised Gram matrix.
RIDGE = 1e-3
#: With the similarity's rotation below this angle (degrees) only its scale is used (the
#: faces are shaped differently, not posed differently; FIDELITY_NOTES: scale alone is better).
ROTATION_DEGREES = 10.0


@dataclass
class ResidualModel:
    """The fitted residual transfer.

    marker_ids : (P,) source marker of each paired target landmark
    transfer : (3, 3) ``s R`` (source displacements -> character displacements)
    deltas_at : (M, P, 3) character deltas at the paired landmarks
    gram : (M, M) ``D_L^T D_L / (P u^2)``; ridge : rho; unit : u
    names : (M,) blendshape names; scale, angle : the similarity's scale and rotation (degrees)
    target_centroid : (3,) centroid of the paired landmarks on the character's neutral
    """

    marker_ids: np.ndarray
    transfer: np.ndarray
    deltas_at: np.ndarray
    gram: np.ndarray
    ridge: float
    unit: float
    names: tuple
    scale: float
    angle: float
    target_centroid: np.ndarray

    @property
    def n_shapes(self) -> int:
        return int(self.gram.shape[0])


def pair_markers(source_names, target_names) -> np.ndarray | None:
    """Source marker index of each target landmark, or None when they do not pair.

    Paired by name (every target name among the source names), else by order when the
    counts agree and no name is shared (default names on one side).
    """
    src, tgt = list(source_names), list(target_names)
    if src == tgt:
        return np.arange(len(tgt), dtype=np.int64)
    position = {name: i for i, name in enumerate(src)}
    found = [n for n in tgt if n in position]
    if len(found) == len(tgt):
        return np.array([position[n] for n in tgt], dtype=np.int64)
    if not found and len(src) == len(tgt):
        return np.arange(len(tgt), dtype=np.int64)
    return None


def build_residual(
    source_reference: np.ndarray, source_names, target_neutral, target_landmarks, blendshapes
) -> tuple[ResidualModel | None, str]:
    """The residual transfer from the source's neutral markers to the character, or (None, why not)."""
    if blendshapes is None:
        return None, "the target has no blendshapes"
    if target_landmarks is None:
        return None, "the target has no landmarks paired with the markers"
    ids = pair_markers(source_names, target_landmarks.names)
    if ids is None:
        return None, "the target's landmark names do not pair with the source's markers"
    if len(ids) < 4:
        return None, f"only {len(ids)} paired landmarks"
    points = np.asarray(
        target_landmarks.positions(target_neutral.vertices, target_neutral.triangles),
        dtype=np.float64,
    )
    src = np.asarray(source_reference, dtype=np.float64)[ids]
    rot, _, scale = fit_rigid(src, points, scale=True)
    angle = float(np.degrees(np.arccos(np.clip((np.trace(rot) - 1.0) / 2.0, -1.0, 1.0))))
    transfer = float(scale) * (rot if angle > ROTATION_DEGREES else np.eye(3))
    deltas = np.asarray(blendshapes.deltas, dtype=np.float64)
    deltas_at = (
        np.asarray(
            target_landmarks.positions(
                deltas + target_neutral.vertices[None], target_neutral.triangles
            ),
            dtype=np.float64,
        )
        - points[None]
    )
    flat = deltas_at.reshape(len(deltas), -1)
    unit = float(np.sqrt(np.mean(np.sum(deltas_at**2, axis=-1))))
    if not np.isfinite(unit) or unit <= 0.0:
        return None, "the target's blendshapes do not move its landmarks"
    gram = flat @ flat.T / (len(ids) * unit**2)
    ridge = RIDGE * float(np.trace(gram)) / len(gram)
    model = ResidualModel(
        marker_ids=ids,
        transfer=transfer,
        deltas_at=deltas_at,
        gram=gram,
        ridge=ridge,
        unit=unit,
        names=tuple(blendshapes.names),
        scale=float(scale),
        angle=angle,
        target_centroid=points.mean(axis=0),
    )
    return model, ""


def solve_residual(model: ResidualModel, residual: np.ndarray, smoothing: float, state=None):
    """Residual weights ``(F, M)`` for the actor residual ``(F, N3, 3)`` (NaN = missing marker).

    First-order recursive: frame t is pulled towards frame t-1 (``state``: the weights of
    the frame before the block, or None at the start of a sequence). Returns (weights,
    state after the block).
    """
    r = np.asarray(residual, dtype=np.float64)[:, model.marker_ids] @ model.transfer.T  # (F, P, 3)
    n_frames, n_points = r.shape[0], r.shape[1]
    missing = np.isnan(r[..., 0])
    r = np.where(missing[..., None], 0.0, r)
    norm = 1.0 / (n_points * model.unit**2)
    flat = model.deltas_at.reshape(model.n_shapes, -1)
    rhs = (r.reshape(n_frames, -1) @ flat.T) * norm  # (F, M)
    eye = np.eye(model.n_shapes)
    lam = float(smoothing)
    base = model.gram + model.ridge * eye
    inv_first = np.linalg.inv(base)
    inv = np.linalg.inv(base + lam * eye) if lam > 0 else inv_first
    out = np.empty((n_frames, model.n_shapes))
    prev = state
    for t in range(n_frames):
        if missing[t].any():
            keep = ~missing[t]
            sub = model.deltas_at[:, keep].reshape(model.n_shapes, -1)
            gram = sub @ sub.T * norm + model.ridge * eye
            b = rhs[t] + (lam * prev if prev is not None else 0.0)
            out[t] = np.linalg.solve(gram + (lam * eye if prev is not None else 0.0), b)
        elif prev is None:
            out[t] = inv_first @ rhs[t]
        else:
            out[t] = inv @ (rhs[t] + lam * prev)
        prev = out[t]
    return out, (None if n_frames == 0 else out[-1].copy())
