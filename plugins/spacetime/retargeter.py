"""Spacetime expression cloning for blendshapes (Seol et al. 2012) and its per-frame baselines.

``spacetime`` (mode ``"movement"``): the source's marker *velocities* are matched by the
target's blendshape weights over the whole sequence, with boundary values at the first
and last frames and at user-constrained frames, a PCA prior on the target's expression
space, an optional Sobolev position term, and spacetime editing (:meth:`edit`).

The per-frame baselines of the paper's comparisons (fig. 7, 9, 11) are the modes
``"noconst"``, ``"rangepf"`` and ``"priorpf"``, also registered as ``spacetime_noconst``,
``spacetime_rangepf`` and ``spacetime_priorpf``; ``spacetime_paper`` is the method with the paper's settings. These
four are plain subclasses that change only defaults (their ``mode``, the paper's settings
:data:`PAPER`, and the paper's ``alpha = 0.5`` for ``spacetime_priorpf``).
"""

from __future__ import annotations

from collections.abc import Mapping
from typing import ClassVar

import numpy as np

from faceretarget import manifest, naming
from faceretarget._threads import blas_single_threaded
from faceretarget._validate import as_array, short_repr
from faceretarget.errors import (
    CapabilityError,
    ConfigError,
    IndexRangeError,
    InputError,
    NonFiniteError,
    ShapeError,
    TopologyMismatchError,
    UnknownNameError,
)
from faceretarget.model import Animation, Source, TargetRig
from faceretarget.retargeter import Retargeter
from faceretarget.validation import Interval, check_value, validate_params

from . import calibration
from .examples import adapt_basis, example_weights
from .prior import fit_prior
from .solver import (
    BoundedStats,
    System,
    energy_terms,
    solve_bounded,
    solve_movement,
    solve_movement_bounded,
    solve_per_frame,
)


class SpacetimeRetargeter(Retargeter):
    """Spacetime expression cloning for blendshapes (Seol et al. 2012).

    Parameters
    ----------
    mode : "movement" | "noconst" | "rangepf" | "priorpf"
        Movement matching (the method), or a per-frame baseline: unconstrained least
        squares, bounded least squares in ``[lower, upper]``, least squares with the prior.
    alpha : float >= 0
        Prior weight (Eq. 4) in the paper's units: a face whose neutral markers have an RMS
        radius of ``calibration.FACE_SIZE_REF`` = 60 (a human face in millimetres), captured at
        ``calibration.FPS_REF`` = 30 frames per second. With ``scale_alpha`` the weight used is
        ``alpha * (face size / 60)**2 * (30 / fps)**2`` in movement matching and
        ``alpha * (face size / 60)**2`` in per-frame solves (boundary values, "Prior PF"), so one
        value means the same balance in any length unit and frame rate. 0 disables the prior.
    scale_alpha : bool
        Rescale ``alpha`` with the face size (RMS radius of the source's neutral markers) and
        the frame rate (the velocity term shrinks with the square of the frame rate).
    beta : float >= 0
        Sobolev position weight (sec. 7.1); 0 = pure movement matching.
    marker_weights : None | (N,) | (F, N) | {marker name: weight}
        Per-marker (or per-frame per-marker) weights of the Sobolev term; None = all 1, a
        mapping gives 0 to unlisted markers.
    prior_shapes : None | sequence of shape names or indices
        Blendshapes whose PCA forms the prior (fig. 13). None: all of them, or none when
        ``prior_animations`` is given.
    prior_animations : None | (K, M) weights | (K, V, 3) target vertices
        Target animation frames (local, no head motion) added to the prior's PCA samples.
    prior_center : "neutral" | "mean"
        Centre of the prior's PCA: the neutral (default; a face at rest has zero prior energy
        even when shapes are linearly dependent at the markers) or the sample mean (Eq. 3 as
        printed).
    boundary : "per_frame" | "neutral" | "none" | (2, M) weights
        Boundary values at the first and last frame: the per-frame solution there (with the
        prior), neutral (zero weights, the paper's capture protocol), none (needs ``beta > 0``),
        or given weights.
    constraints : None | {frame: (M,) weights or {shape name: weight}}
        User-constrained frames (extra boundary conditions, sec. 6).
    remove_head_motion : bool
        Estimate the rigid head motion (``geometry.head_motion``: a joint fit with the shapes,
        weighted to the markers expressions move least, kept only where significant; the paper
        uses Procrustes, sec. 3.1), remove it before and re-apply it to the target after, its
        translation in the target's unit. A ``Source.head_motion`` is always used when given.
    head_motion_refinement : int, 0 <= n <= 100
        Extra Gauss-Newton steps of the unweighted joint fit (``calibration.refine_head_motion``)
        after the estimate, when head motion was detected. 0 (default): the estimator
        (``geometry.head_motion``: rigidity-weighted joint fit with the shapes, converged, plus a
        significance gate) needs none; unweighted steps let rig mismatch back into the head
        (largest rotation error with 10 degrees of head motion: transferred-expression ICT
        pair 0.47 degrees without, 0.93 with 3 steps; ``cases.cross_rig`` 0.20 / 0.26).
    rbf_kernel : "linear" | "multiquadric" | "gaussian" | "thin_plate"
        RBF kernel of scale-proportion matching (sec. 3.2; the paper's is ``"linear"``, r).
    lower, upper : float
        Weight range of "Range PF" and of the in-range diagnostic.
    """

    name: ClassVar[str] = "spacetime"
    #: Types, ranges and choices of the parameters, with their meanings: registry.toml.
    parameter_constraints: ClassVar[dict] = manifest.constraints("spacetime")

    def __init__(
        self,
        *,
        mode="movement",
        alpha=0.01,
        scale_alpha=True,
        beta=1.0,
        marker_weights=None,
        prior_shapes=None,
        prior_animations=None,
        prior_center="neutral",
        boundary="auto",
        constraints=None,
        remove_head_motion=True,
        head_motion_refinement=0,
        rbf_kernel="linear",
        lower=-0.5,
        upper=1.5,
        bounds="rig",
        sparsity=0.0,
        transfer="similarity",
        samples="auto",
        max_samples=1000,
        example_weight=0.3,
    ):
        self.mode = mode
        self.alpha = alpha
        self.scale_alpha = scale_alpha
        self.beta = beta
        self.marker_weights = marker_weights
        self.prior_shapes = prior_shapes
        self.prior_animations = prior_animations
        self.prior_center = prior_center
        self.boundary = boundary
        self.constraints = constraints
        self.remove_head_motion = remove_head_motion
        self.head_motion_refinement = head_motion_refinement
        self.rbf_kernel = rbf_kernel
        self.lower = lower
        self.upper = upper
        self.bounds = bounds
        self.sparsity = sparsity
        self.transfer = transfer
        self.samples = samples
        self.max_samples = max_samples
        self.example_weight = example_weight

    # ------------------------------------------------------------------------------------
    # fit
    # ------------------------------------------------------------------------------------
    @blas_single_threaded  # small products only; and the bounded solve's float32 w-step would
    # turn the last-bit differences of threaded BLAS into ~1e-8 differences of the weights
    def _fit(self, source: Source, target: TargetRig) -> None:
        self._check_params()
        params = self.params_
        rig = target.blendshapes
        landmarks = target.landmarks
        source_names = _marker_names(source)
        pairs = calibration.pair_markers(source_names, landmarks.names)
        source_neutral = np.asarray(source.marker_reference(), dtype=np.float64)
        if source_neutral.ndim != 2 or source_neutral.shape[1] != 3:
            raise ShapeError(
                f"spacetime: needs 3D markers (N, 3); this source's markers are {source_neutral.shape[1:]}"
            )
        source_neutral = source_neutral[pairs]
        if not np.isfinite(source_neutral).all():
            raise NonFiniteError(
                "spacetime: the source's neutral markers contain NaN; give a complete reference pose"
            )
        tris = rig.neutral.triangles
        target_neutral = landmarks.positions(rig.neutral.vertices, tris)
        calibration.check_spread(source_neutral, "source neutral markers")
        calibration.check_spread(target_neutral, "target landmarks")
        self.dense_ = self._dense_pairs(source, rig, target_neutral, source_neutral)
        if self.dense_ is None:
            points, point_deltas = target_neutral, landmarks.positions(rig.deltas, tris)
        else:
            ids = self.dense_.target_ids
            points, point_deltas = rig.neutral.vertices[ids], rig.deltas[:, ids]
        self.transfer_ = calibration.fit_transfer(
            target_neutral, source_neutral, params["transfer"], self.rbf_kernel
        )
        self.frame_ = calibration.similarity_matrix(target_neutral, source_neutral)
        neutral = self.transfer_.points(points)
        deltas = self.transfer_.deltas(points, point_deltas)
        n_points, n_shapes = len(points), rig.n_shapes
        basis = deltas.reshape(n_shapes, -1).T  # (3P, M), x-y-z interleaved per point
        self.resolved_bounds_ = self._resolve_bounds(rig)
        self.examples_used_ = ()
        if params["example_weight"] > 0:
            basis = self._adapt_to_examples(source, target, basis, pairs, points)
        samples = self._prior_samples(rig, landmarks, neutral, basis)
        names = [source_names[i] for i in pairs]
        if self.dense_ is not None and self.marker_weights is not None:
            raise ConfigError(
                "spacetime: marker_weights weight the landmarks, but this mesh source is fitted through dense "
                "correspondence; give samples='landmarks' to use marker_weights"
            )
        marker_weights, frame_weights = self._marker_weights(n_points, names)
        self.landmark_names_ = tuple(landmarks.names)
        self.n_markers_ = len(pairs)
        self.n_points_ = n_points
        self.source_neutral_ = source_neutral
        self.basis_ = basis
        self.marker_basis_ = (
            basis
            if self.dense_ is None
            else (
                self.transfer_.deltas(target_neutral, landmarks.positions(rig.deltas, tris))
                .reshape(n_shapes, -1)
                .T
            )
        )
        self.prior_ = fit_prior(samples, basis, neutral.ravel(), self.prior_center)
        self.face_size_ = calibration.face_size(source_neutral)
        self.marker_weights_ = marker_weights
        self.frame_weights_ = frame_weights
        self.rig_ = rig
        self.bounds_ = self.resolved_bounds_
        self.systems_ = {}
        self.head_models_ = {}
        self.system_ = self._system(source.fps if self.mode == "movement" else None)
        self.alpha_effective_ = self.system_.alpha

    def _adapt_to_examples(
        self, source: Source, target: TargetRig, basis, pairs, points
    ) -> np.ndarray:
        """The basis corrected by the example pose pairs both sides have (see ``examples.py``)."""
        if source.examples is None or target.examples is None:
            return basis
        common = [n for n in target.example_names if n in source.example_names]
        if not common:
            return basis
        rig = target.blendshapes
        t_idx = [target.example_names.index(n) for n in common]
        s_idx = [source.example_names.index(n) for n in common]
        bounds = self.resolved_bounds_
        weights = example_weights(
            rig.deltas, target.examples[t_idx] - rig.neutral.vertices, *(bounds or (None, None))
        )
        if self.dense_ is not None:
            corr = self.dense_.source
            source_pts = (
                corr.apply(source.examples[s_idx])
                - corr.apply(source.performance.reference.vertices)[None]
            )
        elif source.kind == "mesh":
            ref = source.performance.reference.vertices
            tris = source.performance.triangles
            source_pts = (
                source.landmarks.positions(source.examples[s_idx], tris)
                - source.landmarks.positions(ref, tris)[None]
            )[:, pairs]
        else:
            if source.examples.shape[1] != len(source.performance.names):
                return basis
            source_pts = (
                source.examples[s_idx][:, pairs]
                - np.asarray(source.marker_reference())[pairs][None]
            )
        if not np.isfinite(source_pts).all():
            return basis
        self.examples_used_ = tuple(common)
        return adapt_basis(
            basis, weights, source_pts.reshape(len(common), -1), self.params_["example_weight"]
        )

    def _dense_pairs(self, source: Source, rig, target_landmarks, source_landmarks):
        """Dense target-source pairs for a mesh source (``samples``), or None for landmarks only."""
        how = self.params_["samples"]
        if how == "landmarks" or self.mode != "movement" and how == "auto":
            return None
        if source.kind != "mesh":
            if how == "dense":
                raise CapabilityError(
                    f"spacetime: samples='dense' needs a mesh-sequence source; this source is {source.kind}; "
                    "use samples='auto' or 'landmarks'"
                )
            return None
        from faceretarget.correspond.dense import dense_pairs

        reference = source.performance.reference
        return dense_pairs(
            rig.neutral,
            target_landmarks,
            reference,
            source_landmarks,
            max_points=self.params_["max_samples"],
        )

    def _resolve_bounds(self, rig):
        """(lower (M,), upper (M,)) weight bounds of the whole-sequence solve, or None (paper)."""
        value = self.bounds
        m = rig.n_shapes
        if value is None:
            return None
        if isinstance(value, str):
            if rig.bounds is not None:
                b = np.asarray(rig.bounds, dtype=np.float64)
                return b[:, 0].copy(), b[:, 1].copy()
            if naming.conventionally_bounded(rig.names):
                return np.zeros(m), np.ones(m)
            return None
        arr = _float_array(value, "bounds", f"'rig', None, (lower, upper) or an ({m}, 2) array")
        if arr.shape == (2,):
            arr = np.broadcast_to(arr, (m, 2))
        if arr.shape != (m, 2) or np.isnan(arr).any() or np.any(arr[:, 0] > arr[:, 1]):
            raise ShapeError(
                f"spacetime: bounds must be 'rig', None, (lower, upper) or an ({m}, 2) array with lower <= upper, got {short_repr(value)}"
            )
        return arr[:, 0].copy(), arr[:, 1].copy()

    def _system(self, fps: float | None) -> System:
        """The energy's matrices (cached): for movement matching of a performance at ``fps``,
        or for per-frame solves (``fps=None``: no time axis, so no frame-rate rescaling)."""
        if fps not in self.systems_:
            params = self.params_
            alpha, beta = params["alpha"], params["beta"]
            if params["scale_alpha"]:
                alpha *= (self.face_size_ / calibration.FACE_SIZE_REF) ** 2
                if fps is not None:
                    alpha *= (calibration.FPS_REF / fps) ** 2
                    beta *= (calibration.FPS_REF / fps) ** 2
            # the prior is per frame, the data terms sum over points: same balance with any count
            alpha *= self.n_points_ / self.n_markers_
            prior = self.prior_
            system = System(
                self.basis_,
                alpha * prior.matrix,
                alpha * prior.vector,
                beta,
                self.marker_weights_,
                alpha=alpha,
            )
            # per-shape L1 weight relative to the shape's own position term: an isolated shape
            # held still is shrunk by `sparsity` (whatever its size)
            system.l1 = params["sparsity"] * beta * np.diag(system.gram).copy()
            self.systems_[fps] = system
        return self.systems_[fps]

    def _check_params(self) -> None:
        """Check every constructor parameter that does not need the data (raised from ``fit``).

        The checked values (plain ``float``/``int``/``bool``/``str``) are kept in ``params_``
        and used by ``fit``/``retarget``/``edit``; array-valued parameters are checked where
        their shapes are known. Types, ranges and choices are declared in registry.toml
        (``parameter_constraints``); what they cannot say (several parameters together, the
        boundary array's numbers) is checked here.
        """
        p = validate_params(self)  # a ParameterError (a ConfigError) naming a bad one
        mode, beta, lower, upper = p["mode"], p["beta"], p["lower"], p["upper"]
        if not lower < upper:
            raise ConfigError(
                f"spacetime: lower/upper: need lower < upper (the weight range of 'rangepf'), got lower={lower!r}, upper={upper!r}"
            )
        if p["sparsity"] > 0 and mode == "movement" and beta == 0:
            raise ConfigError(
                "spacetime: sparsity > 0 weighs the L1 term against the position term, which beta=0 turns off; "
                "give beta > 0 or sparsity=0"
            )
        if isinstance(self.boundary, str):
            if self.boundary == "none" and mode == "movement" and beta == 0:
                raise ConfigError(
                    "spacetime: boundary='none' leaves movement matching without any position anchor; "
                    "give beta > 0 (Sobolev term), or use boundary='per_frame' / 'neutral'"
                )
        else:
            _float_array(
                self.boundary,
                "boundary",
                "one of 'per_frame', 'neutral', 'none' or a (2, M) array of weights",
            )
        keep = (
            "mode",
            "alpha",
            "beta",
            "scale_alpha",
            "lower",
            "upper",
            "remove_head_motion",
            "head_motion_refinement",
            "transfer",
            "samples",
            "max_samples",
            "sparsity",
            "example_weight",
        )
        self.params_ = {k: p[k] for k in keep}

    def _prior_samples(self, rig, landmarks, neutral, basis) -> np.ndarray:
        """(K, 3N) absolute (warped) marker positions of the prior's training faces."""
        chosen = self.prior_shapes
        if chosen is None:
            chosen = [] if self.prior_animations is not None else range(rig.n_shapes)
        elif isinstance(chosen, (str, bytes, Mapping)) or not _iterable(chosen):
            raise ConfigError(
                f"spacetime: prior_shapes: expected None or a sequence of blendshape names or indices, got {short_repr(chosen)}"
            )
        index = np.array([self._shape_index(rig, c) for c in chosen], dtype=np.intp)
        samples = [neutral.ravel()[None] + basis.T[index]]
        if self.prior_animations is not None:
            anim = _float_array(
                self.prior_animations,
                "prior_animations",
                f"None, (K, {rig.n_shapes}) weights or (K, {rig.neutral.n_vertices}, 3) target vertices",
            )
            if anim.ndim in (2, 3) and not np.isfinite(anim).all():
                raise NonFiniteError(
                    "spacetime: prior_animations contain NaN or infinity; give finite weights or vertices"
                )
            if anim.ndim == 2 and anim.shape[1] == rig.n_shapes:
                samples.append(neutral.ravel()[None] + anim @ basis.T)
            elif anim.ndim == 3 and anim.shape[1:] == (rig.neutral.n_vertices, 3):
                if self.dense_ is None:
                    points = landmarks.positions(anim, rig.neutral.triangles)
                else:
                    points = anim[:, self.dense_.target_ids]
                samples.append(self.transfer_.points(points.reshape(-1, 3)).reshape(len(anim), -1))
            else:
                raise ShapeError(
                    f"spacetime: prior_animations must be (K, {rig.n_shapes}) weights or (K, {rig.neutral.n_vertices}, 3) "
                    f"target vertices, got {anim.shape}"
                )
        return np.concatenate(samples, axis=0)

    @staticmethod
    def _shape_index(rig, key) -> int:
        if isinstance(key, (int, np.integer)) and not isinstance(key, (bool, np.bool_)):
            if not -rig.n_shapes <= key < rig.n_shapes:
                raise IndexRangeError(
                    f"spacetime: prior_shapes: shape index {key} out of range for {rig.n_shapes} shapes "
                    f"(valid {-rig.n_shapes}..{rig.n_shapes - 1})"
                )
            return int(key) % rig.n_shapes
        if not isinstance(key, str):
            raise ConfigError(
                f"spacetime: prior_shapes: entries must be blendshape names (str) or indices (int), got {short_repr(key)}"
            )
        try:
            return rig.index(key)
        except UnknownNameError as exc:
            raise UnknownNameError(f"spacetime: prior_shapes: {exc}") from None

    def _marker_weights(self, n_markers: int, names: list[str]):
        """(N,) constant Sobolev weights, and (F, N) per-frame weights or None."""
        mw = self.marker_weights
        if mw is None:
            return np.ones(n_markers), None
        if isinstance(mw, Mapping):
            unknown = [k for k in mw if k not in names]
            if unknown:
                raise TopologyMismatchError(
                    f"spacetime: marker_weights name unknown markers: {', '.join(map(str, unknown[:8]))}"
                )
            weight = [Interval(float, 0, None)]
            out = np.array(
                [
                    check_value(mw.get(n, 0.0), weight, f"marker_weights[{n!r}]", "spacetime")
                    for n in names
                ],
                dtype=np.float64,
            )
            frame = None
        else:
            arr = _float_array(
                mw,
                "marker_weights",
                f"None, ({n_markers},) or (F, {n_markers}) weights, or {{marker name: weight}}",
            )
            if arr.ndim == 1 and arr.shape[0] == n_markers:
                out, frame = arr, None
            elif arr.ndim == 2 and arr.shape[1] == n_markers:
                out, frame = np.ones(n_markers), arr
            else:
                raise ShapeError(
                    f"spacetime: marker_weights must be ({n_markers},) or (F, {n_markers}), got {arr.shape}"
                )
        check = out if frame is None else frame
        if not np.isfinite(check).all() or (check < 0).any():
            raise ConfigError(
                "spacetime: marker_weights must be finite and >= 0 (0 = marker ignored by the Sobolev term)"
            )
        return out, frame

    # ------------------------------------------------------------------------------------
    # retarget
    # ------------------------------------------------------------------------------------
    @blas_single_threaded
    def _retarget(self, source: Source) -> Animation:
        markers, reference = self._source_markers(source)
        n_frames = markers.shape[0]
        frame_weights = self.frame_weights_
        if frame_weights is not None and frame_weights.shape[0] != n_frames:
            raise ShapeError(
                f"spacetime: marker_weights has {frame_weights.shape[0]} frames but the source has {n_frames}"
            )
        known, known_weights = self._known_frames(n_frames)
        params = self.params_
        local = None  # (F, N, 3) marker deltas, head motion removed, if the estimate gives them
        if source.head_motion is not None:
            # a copy: the result's head motion must not be the caller's array
            motion, how = np.array(source.head_motion, dtype=np.float64), "given"
        elif params["remove_head_motion"]:
            # joint fit with the shapes at the markers, weighted to the markers expressions move
            # least, and gated: exactly the identity unless the head motion is significant
            motion, found = self._head_model(reference).estimate(
                markers,
                window=max(1, round(source.fps)),
                return_info=True,
                keep_local=self.dense_ is None,  # the marker deltas, computed by the gate
            )
            how = "estimated" if found.detected else "none detected"
            local = found.local
        else:
            motion, how = None, "none"
        system = self._system(source.fps if self.mode == "movement" else None)
        if how == "estimated" and params["head_motion_refinement"]:
            fitted, local = None, None
            for _ in range(params["head_motion_refinement"]):
                motion, fitted = calibration.refine_head_motion(
                    reference, markers, motion, fitted, self.marker_basis_, system.ridge
                )
        deltas = (
            local if local is not None else self._local_deltas(source, motion, markers, reference)
        )
        del markers  # (F, N, 3), not needed past here: the solve's scratch takes its place
        stats = BoundedStats()
        terms: dict = {}  # filled by the structured solve, else computed below
        weights = self._solve(system, deltas, known, known_weights, stats, terms)
        if not terms:
            terms = energy_terms(system, deltas, weights)
        inside = (weights >= params["lower"]) & (weights <= params["upper"])
        lo, hi = self.bounds_ if self.bounds_ is not None else (-np.inf, np.inf)
        diagnostics = {
            "fraction_outside_bounds": 0.0
            if self.bounds_ is None
            else float(np.mean((weights < lo - 1e-9) | (weights > hi + 1e-9))),
            "bounds": None if self.bounds_ is None else [float(np.min(lo)), float(np.max(hi))],
            "admm_iterations": stats.iterations,
            "admm_converged": stats.converged,
            "samples": "landmarks" if self.dense_ is None else "dense",
            "n_points": self.n_points_,
            "transfer": self.transfer_.how,
            "transfer_scale": self.transfer_.scale,
            "transfer_rotation_degrees": self.transfer_.angle,
            "examples": list(self.examples_used_),
            "velocity_error": float(terms["velocity"].sum()),
            "position_error": float(terms["position"].sum()),
            "fraction_in_range": np.count_nonzero(inside) / inside.size,
            "alpha_effective": system.alpha,
            "prior_decay_frames": system.decay_frames(),
            "face_size": self.face_size_,
            "head_motion": how,
            "solver": "per_frame"
            if self.mode != "movement"
            else (
                "structured"
                if not np.isnan(deltas).any() and frame_weights is None
                else "block_tridiagonal"
            ),
        }
        extras = {}
        if self.mode == "movement":
            extras["spacetime"] = {
                "deltas": deltas,
                "known_frames": np.flatnonzero(known),
                "fingerprint": self._fingerprint(),
            }
        return Animation(
            weights=weights,
            rig=self.rig_,
            head_motion=calibration.motion_to_target(motion, self.frame_),
            fps=source.fps,
            provenance={"diagnostics": diagnostics},
            extras=extras,
        )

    def _head_model(self, reference: np.ndarray):
        """The head-motion estimator for this source neutral and the marker basis, kept for
        the next shot of the same neutral (its gains depend on nothing else)."""
        from faceretarget.geometry.head_motion import HeadMotionModel

        models = self.__dict__.setdefault("head_models_", {})  # absent from older pickles
        key = reference.tobytes()
        model = models.get(key)
        if model is None:
            if len(models) >= HEAD_MODELS_KEPT:
                models.clear()
            model = models[key] = HeadMotionModel(reference, basis=self.marker_basis_)
        return model

    def _local_deltas(self, source: Source, motion, markers, reference) -> np.ndarray:
        """(F, P, 3) source displacements from the neutral at the fitted points, head motion removed."""
        if self.dense_ is None:
            return calibration.to_local(motion, markers, reference)
        if source.kind != "mesh":
            raise CapabilityError(
                "spacetime: this retargeter was fitted to a mesh source (dense samples); retarget a mesh source, or fit with samples='landmarks'"
            )
        perf = source.performance
        corr = self.dense_.source
        if perf.n_vertices != corr.n_vertices:
            raise TopologyMismatchError(
                f"spacetime: fitted to a source mesh of {corr.n_vertices} vertices, got {perf.n_vertices}; fit again on this source"
            )
        points = corr.apply(perf.vertices)
        return calibration.to_local(motion, points, corr.apply(perf.reference.vertices))

    def _source_markers(self, source: Source):
        """(F, N, 3) markers and (N, 3) neutral in the order of the target's landmarks."""
        positions = np.asarray(source.marker_positions(), dtype=np.float64)
        reference = np.asarray(source.marker_reference(), dtype=np.float64)
        if positions.ndim != 3 or positions.shape[2] != 3:
            raise ShapeError(f"spacetime: needs 3D markers (F, N, 3), got {positions.shape}")
        pairs = calibration.pair_markers(_marker_names(source), self.landmark_names_)
        if np.array_equal(pairs, np.arange(positions.shape[1])):
            return positions, reference  # already in order: no (F, N, 3) copy
        return np.take(positions, pairs, axis=1), reference[pairs]

    def _constraint_weights(self, value, frame) -> np.ndarray:
        rig = self.rig_
        name = f"constraints[{frame!r}]"
        if isinstance(value, Mapping):
            out = np.zeros(rig.n_shapes)
            for k, v in value.items():
                try:
                    index = rig.index(str(k))
                except UnknownNameError as exc:
                    raise UnknownNameError(f"spacetime: {name}: {exc}") from None
                out[index] = check_value(v, [Interval(float)], f"{name}[{k!r}]", "spacetime")
        else:
            out = _float_array(value, name, f"({rig.n_shapes},) weights or {{shape name: weight}}")
            if out.shape != (rig.n_shapes,):
                raise ShapeError(
                    f"spacetime: {name}: constraint weights must be ({rig.n_shapes},) or {{shape name: weight}}, got {out.shape}"
                )
        if not np.isfinite(out).all():
            raise NonFiniteError(f"spacetime: {name}: constraint weights contain NaN or infinity")
        return out

    def _known_frames(self, n_frames: int):
        """Boundary and user-constrained frames: (F,) bool and (F, M) weights (NaN = to fill)."""
        m = self.rig_.n_shapes
        known = np.zeros(n_frames, dtype=bool)
        values = np.full((n_frames, m), np.nan)
        if self.mode == "movement":
            ends = [0, n_frames - 1]
            if isinstance(self.boundary, str):
                boundary = self.boundary
                if boundary == "auto":
                    boundary = "none" if self.params_["beta"] > 0 else "per_frame"
                if boundary != "none":
                    known[ends] = True
                    if boundary == "neutral":
                        values[ends] = 0.0
            else:
                given = _float_array(
                    self.boundary,
                    "boundary",
                    f"one of 'per_frame', 'neutral', 'none' or a (2, {m}) array of weights",
                )
                if given.shape != (2, m) or not np.isfinite(given).all():
                    raise ShapeError(
                        f"spacetime: boundary weights must be a finite (2, {m}) array [first, last], got {given.shape}"
                    )
                known[ends] = True
                values[0], values[-1] = given[0], given[1]
        for frame, value in (self.constraints or {}).items():
            f = _frame_index(frame, n_frames, "constraints frame")
            known[f] = True
            values[f] = self._constraint_weights(value, frame)
        return known, values

    def _solve(
        self,
        system: System,
        deltas: np.ndarray,
        known: np.ndarray,
        values: np.ndarray,
        stats: BoundedStats | None = None,
        terms: dict | None = None,
    ) -> np.ndarray:
        """Weights (F, M) for local marker deltas (F, N, 3); fills per-frame boundary values
        (``terms``: see :func:`solver.solve_movement`)."""
        if self.mode == "movement":
            todo = known & np.isnan(values[:, 0])
            if todo.any():
                values = values.copy()
                if self.bounds_ is None:
                    values[todo] = solve_per_frame(self._system(None), deltas[todo], use_prior=True)
                else:
                    values[todo] = solve_bounded(
                        self._system(None), deltas[todo], *self.bounds_, use_prior=True
                    )
            return self._solve_movement(
                system, deltas, known, values, self.frame_weights_, stats, terms
            )
        if self.mode == "rangepf":
            weights = solve_bounded(system, deltas, self.params_["lower"], self.params_["upper"])
        else:
            weights = solve_per_frame(system, deltas, use_prior=self.mode == "priorpf")
        weights[known] = values[known]
        return weights

    def _solve_movement(
        self, system, deltas, known, values, frame_weights, stats=None, terms=None
    ) -> np.ndarray:
        """Movement matching, bounded (ADMM) when the retargeter has bounds or an L1 term."""
        if self.bounds_ is None and not np.any(system.l1):
            return solve_movement(system, deltas, known, values, frame_weights, terms)
        m = system.n_shapes
        lo, hi = (
            self.bounds_ if self.bounds_ is not None else (np.full(m, -np.inf), np.full(m, np.inf))
        )
        return solve_movement_bounded(
            system, deltas, known, values, lo, hi, system.l1, frame_weights, stats
        )

    def _fingerprint(self) -> list[float]:
        """Numbers identifying the fitted calibration (kept in the Animation; survive saving)."""
        b = self.basis_
        params = self.params_
        return [
            float(b.shape[0]),
            float(b.shape[1]),
            float(b.sum()),
            float(np.abs(b).sum()),
            params["alpha"],
            float(params["scale_alpha"]),
            params["beta"],
        ]

    # ------------------------------------------------------------------------------------
    # spacetime editing (sec. 6)
    # ------------------------------------------------------------------------------------
    @blas_single_threaded
    def edit(self, animation: Animation, *, frame=None, weights=None, window=None) -> Animation:
        """Spacetime edit: new weights at ``frame`` become a boundary condition (sec. 6).

        Parameters
        ----------
        animation : Animation
            A result of this (fitted) retargeter's :meth:`retarget` or :meth:`edit`.
        frame : int or sequence of int
            Edited frame(s) (negative counts from the end).
        weights : (M,) or (K, M) array, or {shape name: weight}
            New weights; a mapping changes only the named shapes of the current weights.
        window : (a, b), optional
            Range of propagation (inclusive). The current weights at ``a`` and ``b`` stay fixed
            and only frames strictly inside are re-solved; frames outside are untouched.
            Default: the whole sequence, with all earlier boundary and edited frames fixed.

        Returns a new Animation (the input is not modified); its edited frames are kept as
        constraints by later edits.
        """
        self._check_fitted()
        if self.mode != "movement":
            raise CapabilityError(
                f"spacetime: edit needs mode='movement' (this retargeter uses mode={self.mode!r})"
            )
        if frame is None or weights is None:
            raise InputError(
                "spacetime.edit: give frame= (the edited frame) and weights= (its new weights)"
            )
        state = animation.extras.get("spacetime") if isinstance(animation, Animation) else None
        if state is None or animation.weights is None:
            raise InputError(
                "spacetime.edit: the animation must come from spacetime's retarget() or edit()"
            )
        mine = np.asarray(self._fingerprint())
        theirs = np.asarray(state.get("fingerprint", ()), dtype=np.float64).ravel()
        if theirs.shape != mine.shape or not np.allclose(theirs, mine, rtol=1e-12, atol=0.0):
            raise InputError(
                "spacetime.edit: this animation was produced by a spacetime retargeter fitted to another rig or calibration"
            )
        current = np.array(animation.weights, dtype=np.float64)
        n_frames, m = current.shape
        frames = [_frame_index(f, n_frames) for f in np.atleast_1d(np.asarray(frame, dtype=object))]
        new_values = self._edit_values(weights, current, frames)
        if window is None:
            start, stop = 0, n_frames - 1
        else:
            if len(window) != 2:
                raise ShapeError(
                    f"spacetime.edit: window must be (first, last) frames, got {window!r}"
                )
            start, stop = (_frame_index(w, n_frames) for w in window)
            if start > stop:
                raise InputError(f"spacetime.edit: window start {start} is after its end {stop}")
            outside = [f for f in frames if not start <= f <= stop]
            if outside:
                raise IndexRangeError(
                    f"spacetime.edit: edited frame(s) {outside} lie outside the window [{start}, {stop}]"
                )
        known = np.zeros(n_frames, dtype=bool)
        known[state["known_frames"]] = True
        if window is not None:
            known[[start, stop]] = True
        values = current.copy()
        for f, v in zip(frames, new_values):
            known[f] = True
            values[f] = v
        span = slice(start, stop + 1)
        frame_weights = None if self.frame_weights_ is None else self.frame_weights_[span]
        result = current.copy()
        result[span] = self._solve_movement(
            self._system(animation.fps),
            state["deltas"][span],
            known[span],
            values[span],
            frame_weights,
        )
        new_state = dict(state, known_frames=np.union1d(state["known_frames"], frames))
        provenance = dict(animation.provenance)
        provenance["edits"] = list(provenance.get("edits", [])) + [
            {"frames": frames, "window": [start, stop]}
        ]
        return animation.replace(
            weights=result,
            extras=dict(animation.extras, spacetime=new_state),
            provenance=provenance,
        )

    def _edit_values(self, weights, current: np.ndarray, frames: list[int]) -> np.ndarray:
        m = current.shape[1]
        if isinstance(weights, Mapping):
            out = current[frames].copy()
            for k, v in weights.items():
                out[:, self.rig_.index(str(k))] = float(v)
        else:
            out = np.asarray(weights, dtype=np.float64)
            if out.shape == (m,):
                out = np.broadcast_to(out, (len(frames), m)).copy()
            if out.shape != (len(frames), m):
                raise ShapeError(
                    f"spacetime.edit: weights must be ({m},) or ({len(frames)}, {m}), got {out.shape}"
                )
        if not np.isfinite(out).all():
            raise NonFiniteError("spacetime.edit: weights contain NaN or infinity")
        return out


def _marker_names(source: Source) -> tuple[str, ...]:
    """Names of the source's markers (or of its landmarks, for a mesh sequence)."""
    if source.kind == "markers":
        return tuple(source.performance.names)
    if source.landmarks is None:
        raise CapabilityError(
            "spacetime needs a mesh-sequence source with landmarks (Source(..., landmarks=...)) to sample markers"
        )
    return tuple(source.landmarks.names)


def _frame_index(frame, n_frames: int, what: str = "frame") -> int:
    try:
        f = int(frame)
        whole = bool(f == frame)
    except (TypeError, ValueError, OverflowError):
        raise IndexRangeError(
            f"spacetime: {what} {short_repr(frame)} is not an integer frame index"
        ) from None
    if not whole or not -n_frames <= f < n_frames:
        raise IndexRangeError(
            f"spacetime: {what} {short_repr(frame)} out of range for {n_frames} frames (valid {-n_frames}..{n_frames - 1})"
        )
    return f % n_frames


def _iterable(value) -> bool:
    try:
        iter(value)
    except TypeError:
        return False
    return True


def _float_array(value, name: str, valid: str) -> np.ndarray:
    """``value`` as a float64 array (any shape); a :class:`ShapeError` naming ``name`` and what is
    valid for input that is not real numbers (text, complex, dates, ragged lists, mappings)."""
    arr = as_array(value, f"spacetime: {name}")
    if arr.dtype.kind in "biuf":
        return np.asarray(arr, dtype=np.float64)
    if arr.dtype.kind == "O":
        try:
            return arr.astype(np.float64)
        except (TypeError, ValueError, OverflowError):
            pass
    raise ShapeError(f"spacetime: {name}: expected {valid}, got {short_repr(value)}")


#: Head-motion estimators kept per retargeter (one per source neutral seen).
HEAD_MODELS_KEPT = 4

#: The paper's own choices, where the default differs (see docs/methods/spacetime.md for why and
#: the measured effect of each): no weight bounds in the whole-sequence solve, no position
#: or L1 term, boundary values from per-frame solves, scale-proportion matching by the RBF
#: warp on the landmarks only. The variants below spell these defaults out in their
#: signatures (registry.toml repeats them; the registry checks that both agree).
PAPER = dict(
    bounds=None,
    beta=0.0,
    sparsity=0.0,
    boundary="per_frame",
    transfer="rbf",
    samples="landmarks",
    example_weight=0.0,
)


def _arguments(local_vars: dict) -> dict:
    """A variant's constructor arguments (its ``locals()``) for ``SpacetimeRetargeter.__init__``."""
    return {k: v for k, v in local_vars.items() if k not in ("self", "__class__")}


class SpacetimePaper(SpacetimeRetargeter):
    """Seol et al. 2012 as published: :class:`SpacetimeRetargeter` with the defaults :data:`PAPER`."""

    name: ClassVar[str] = "spacetime_paper"

    def __init__(
        self,
        *,
        mode="movement",
        alpha=0.01,
        scale_alpha=True,
        beta=0.0,
        marker_weights=None,
        prior_shapes=None,
        prior_animations=None,
        prior_center="neutral",
        boundary="per_frame",
        constraints=None,
        remove_head_motion=True,
        head_motion_refinement=0,
        rbf_kernel="linear",
        lower=-0.5,
        upper=1.5,
        bounds=None,
        sparsity=0.0,
        transfer="rbf",
        samples="landmarks",
        max_samples=1000,
        example_weight=0.0,
    ):
        super().__init__(**_arguments(locals()))


class SpacetimeNoconst(SpacetimeRetargeter):
    """The paper's baseline "No Const": ``mode="noconst"`` with the defaults :data:`PAPER`."""

    name: ClassVar[str] = "spacetime_noconst"

    def __init__(
        self,
        *,
        mode="noconst",
        alpha=0.01,
        scale_alpha=True,
        beta=0.0,
        marker_weights=None,
        prior_shapes=None,
        prior_animations=None,
        prior_center="neutral",
        boundary="per_frame",
        constraints=None,
        remove_head_motion=True,
        head_motion_refinement=0,
        rbf_kernel="linear",
        lower=-0.5,
        upper=1.5,
        bounds=None,
        sparsity=0.0,
        transfer="rbf",
        samples="landmarks",
        max_samples=1000,
        example_weight=0.0,
    ):
        super().__init__(**_arguments(locals()))


class SpacetimeRangepf(SpacetimeRetargeter):
    """The paper's baseline "Range PF": ``mode="rangepf"`` with the defaults :data:`PAPER`."""

    name: ClassVar[str] = "spacetime_rangepf"

    def __init__(
        self,
        *,
        mode="rangepf",
        alpha=0.01,
        scale_alpha=True,
        beta=0.0,
        marker_weights=None,
        prior_shapes=None,
        prior_animations=None,
        prior_center="neutral",
        boundary="per_frame",
        constraints=None,
        remove_head_motion=True,
        head_motion_refinement=0,
        rbf_kernel="linear",
        lower=-0.5,
        upper=1.5,
        bounds=None,
        sparsity=0.0,
        transfer="rbf",
        samples="landmarks",
        max_samples=1000,
        example_weight=0.0,
    ):
        super().__init__(**_arguments(locals()))


class SpacetimePriorpf(SpacetimeRetargeter):
    """The paper's baseline "Prior PF": ``mode="priorpf"``, ``alpha=0.5`` and the defaults :data:`PAPER`."""

    name: ClassVar[str] = "spacetime_priorpf"

    def __init__(
        self,
        *,
        mode="priorpf",
        alpha=0.5,
        scale_alpha=True,
        beta=0.0,
        marker_weights=None,
        prior_shapes=None,
        prior_animations=None,
        prior_center="neutral",
        boundary="per_frame",
        constraints=None,
        remove_head_motion=True,
        head_motion_refinement=0,
        rbf_kernel="linear",
        lower=-0.5,
        upper=1.5,
        bounds=None,
        sparsity=0.0,
        transfer="rbf",
        samples="landmarks",
        max_samples=1000,
        example_weight=0.0,
    ):
        super().__init__(**_arguments(locals()))


RETARGETERS = [
    SpacetimeRetargeter,
    SpacetimePaper,
    SpacetimeNoconst,
    SpacetimeRangepf,
    SpacetimePriorpf,
]
