"""Landmark displacement transfer in the spirit of Noh & Neumann 2001 (Expression Cloning).

1. Fit an RBF warp (phi(r) = r with a linear polynomial) from the source's neutral
   landmarks to the target's; its Jacobian at each landmark rescales and reorients the
   source displacements to the target's proportions.
2. Per frame: remove the rigid head motion (``faceretarget.geometry.head_motion``: weighted
   to the stillest landmarks, identity unless significant), take each
   landmark's displacement from the neutral, map it through the local Jacobian, and
   interpolate the displacements over every target vertex with a second RBF centred on
   the target landmarks; add to the target neutral; re-apply the head motion.

The interpolation is linear in the displacements, so it is precomputed once as a
``(V, N)`` matrix; a frame costs one matrix product.
"""

from __future__ import annotations

import numpy as np

import faceretarget as fr
from faceretarget.errors import DegenerateGeometryError, ShapeError
from faceretarget.geometry import procrustes
from faceretarget.geometry.head_motion import estimate_head_motion
from faceretarget.geometry.rbf import fit_rbf
from faceretarget.validation import validate_params


class DisplacementRetargeter(fr.Retargeter):
    """Direct landmark displacement transfer through an RBF warp (Noh & Neumann 2001)."""

    name = "displacement"
    summary = "landmark displacements warped by an RBF and interpolated over the target (Noh & Neumann 2001)"
    paper = "Noh & Neumann 2001, Expression Cloning, SIGGRAPH"
    capabilities = fr.Capabilities(
        sources=("markers", "mesh"), needs=("landmarks", "source_landmarks"), outputs="vertices"
    )
    # what `faceretarget info displacement` shows, and what fit() checks (faceretarget.validation);
    # faceretarget.toml beside this package says the same for `faceretarget list`, which reads
    # it without importing this module (the registry checks that the two agree)
    parameter_docs = {
        "jacobian": "rescale displacements by the warp's local Jacobian (True) or copy them unchanged (False)",
        "head_motion": "remove the source's rigid head motion before transfer and re-apply it after",
    }
    parameter_constraints = {"jacobian": ["boolean"], "head_motion": ["boolean"]}

    def __init__(self, *, jacobian=True, head_motion=True):
        self.jacobian = jacobian
        self.head_motion = head_motion

    def _fit(self, source, target):
        # parameters are checked here, not in __init__ (the estimator contract): a bad one is a
        # faceretarget.errors.ParameterError naming this method, the parameter and the valid values
        params = validate_params(self)
        self.jacobian_ = params["jacobian"]
        self.head_motion_ = params["head_motion"]
        src = np.asarray(source.marker_reference(), dtype=np.float64)
        tgt = target.landmarks.positions(target.neutral.vertices, target.neutral.triangles)
        if src.shape != tgt.shape:
            raise ShapeError(
                f"displacement: the source has {len(src)} landmarks but the target has {len(tgt)}; they must correspond one to one"
            )
        if len(src) < 4:
            raise DegenerateGeometryError(
                "displacement: at least 4 landmarks are needed for the RBF warp"
            )
        warp = fit_rbf(src, tgt, kernel="linear")
        self.jacobians_ = (
            _jacobians(warp, src)
            if self.jacobian_
            else np.repeat(np.eye(3)[None], len(src), axis=0)
        )
        self.source_reference_ = src
        self.interpolation_ = _interpolation_matrix(tgt, np.asarray(target.neutral.vertices))
        self.target_neutral_ = np.array(target.neutral.vertices)
        self.triangles_ = np.array(target.neutral.triangles)
        # head translations travel in world distance, converted between length units: the
        # power of ten nearest the faces' size ratio (metres -> centimetres: 100)
        ratio = _size(tgt) / _size(src)
        self.unit_ratio_ = float(10.0 ** np.round(np.log10(ratio)))

    def _retarget(self, source):
        markers = np.asarray(source.marker_positions(), dtype=np.float64)
        if markers.shape[1] != len(self.source_reference_):
            raise ShapeError(
                f"displacement: fitted for {len(self.source_reference_)} landmarks, got {markers.shape[1]}"
            )
        motion = None
        if self.head_motion_:
            if source.head_motion is not None:
                motion = np.asarray(source.head_motion)
            else:
                # rigidity-weighted and kept only where significant: no invented head motion
                motion = estimate_head_motion(self.source_reference_, markers)
            markers = procrustes.remove(motion, markers)
        disp = markers - self.source_reference_  # (F, N, 3); NaN where missing
        disp = np.einsum("nij,fnj->fni", self.jacobians_, disp)
        missing = np.isnan(disp).any(axis=-1)
        disp = np.where(
            missing[..., None], 0.0, disp
        )  # a missing marker contributes no displacement
        vertices = self.target_neutral_ + np.einsum("vn,fnd->fvd", self.interpolation_, disp)
        if motion is not None:
            motion = motion.copy()
            motion[:, :3, 3] *= self.unit_ratio_  # in the target's unit
            vertices = procrustes.apply(motion, vertices)
        return fr.Animation(
            vertices=vertices, head_motion=motion, triangles=self.triangles_, fps=source.fps
        )


def _size(points: np.ndarray) -> float:
    """RMS distance of ``points (N, 3)`` from their centroid."""
    return float(np.sqrt(np.mean(np.sum((points - points.mean(axis=0)) ** 2, axis=1))))


def _jacobians(warp, points: np.ndarray, step: float | None = None) -> np.ndarray:
    """(N, 3, 3) Jacobians of ``warp`` at ``points`` by central differences."""
    h = step or 1e-4 * float(np.linalg.norm(np.ptp(points, axis=0)))
    out = np.empty((len(points), 3, 3))
    for axis in range(3):
        e = np.zeros(3)
        e[axis] = h
        out[:, :, axis] = (warp(points + e) - warp(points - e)) / (2 * h)
    return out


def _interpolation_matrix(centers: np.ndarray, points: np.ndarray) -> np.ndarray:
    """(P, N) matrix mapping values at ``centers`` to RBF-interpolated values at ``points``."""
    rbf = fit_rbf(centers, np.eye(len(centers)), kernel="linear")
    return rbf(points)
