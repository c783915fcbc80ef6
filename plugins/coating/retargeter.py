"""The ``coating`` retargeter (Xu et al. 2014) and the ``deformation_transfer`` baseline.

Both take a dense mesh performance, remove its rigid head motion (the known
``Source.head_motion``, or a Procrustes estimate on stable vertices kept only when it is
significant), bring the local frames into the target's frame and units (a similarity
whose scale is a power of ten, see :mod:`.alignment`), transfer the local deformation
onto the target in the source's topology (the target is resampled first if its topology
differs) and re-apply the head motion (translation in the target's units). The result
therefore does not depend on the units or the placement of either mesh. Frames are
processed in chunks of ``chunk_frames``; :meth:`CoatingRetargeter.iter_retarget` and
:meth:`CoatingRetargeter.retarget_to` stream sequences too long for memory.
"""

from __future__ import annotations

import time
from collections.abc import Iterator
from pathlib import Path
from typing import ClassVar

import numpy as np

from faceretarget import manifest
from faceretarget._threads import touched_meanwhile
from faceretarget.errors import InputError, OutputError, TopologyMismatchError
from faceretarget.geometry.deformation_gradients import (
    DeformationTransfer,
    check_triangles,
    gradient_columns,
    reference_inverse,
)
from faceretarget.model import Animation, FrameSource, MeshSequence, Source, TargetRig
from faceretarget.retargeter import Retargeter
from faceretarget.validation import Options, check_value, validate_params

from .alignment import Placement, estimate_motion, frame_chunks, stable_vertices, to_world
from .topology import OutputMap, common_topology, describe, same_topology

__all__ = ["CoatingRetargeter", "DeformationTransferRetargeter"]


class _MeshTransfer(Retargeter):
    """Shared plumbing: parameter checks, topology, head motion, chunked output."""

    @classmethod
    def why_not(cls, source: Source, target: TargetRig | None) -> str | None:
        """None if ``fit(source, target)`` can run, else what is missing.

        Besides the declared needs: a target whose triangles differ from the source's is
        resampled in the source's topology, which needs landmarks on both.
        """
        reason = super().why_not(source, target)
        if reason or target is None or not isinstance(source.performance, MeshSequence):
            return reason
        src_mesh, tgt_mesh = source.performance.reference, target.neutral
        if not same_topology(src_mesh, tgt_mesh) and (
            source.landmarks is None or target.landmarks is None
        ):
            lacking = " and ".join(
                x
                for x, has in (
                    ("the Source", source.landmarks is not None),
                    ("the TargetRig", target.landmarks is not None),
                )
                if not has
            )
            return (
                f"{cls.name}: the target mesh ({tgt_mesh.n_vertices} vertices) has a different topology from the source "
                f"({src_mesh.n_vertices} vertices); resampling it needs landmarks on both (corresponding points, same order), "
                f"and {lacking} has none: pass Source(..., landmarks=...) and TargetRig(..., landmarks=...)"
            )
        return None

    def _check_params(self) -> None:
        """Every constructor parameter against its declared constraints (registry.toml; the edit
        weights too, so a bad one fails at fit, not at the first edit): a
        :class:`~faceretarget.errors.ParameterError` naming it, its valid values and the value."""
        validate_params(self)

    def _prepare(self, source: Source, target: TargetRig):
        """Common topology and the stable vertices of the fit source (one pass over its frames)."""
        perf = source.performance
        check_triangles(perf.reference.vertices, perf.triangles, f"{self.name} (source reference)")
        check_triangles(
            target.neutral.vertices, target.neutral.triangles, f"{self.name} (target neutral)"
        )
        topo = common_topology(source, target, what=self.name)
        ref = np.asarray(perf.reference.vertices, dtype=np.float64)
        stable = stable_vertices(
            ref,
            perf.vertices,
            stable_fraction=self.stable_fraction,
            chunk=int(self.chunk_frames),
            motion=source.head_motion,
        )
        self.topology_ = topo
        self.source_triangles_ = np.asarray(perf.triangles)
        self.source_reference_ = ref
        self.stable_ = stable
        self.placement_ = Placement(ref, topo.target_reference)
        self.output_ = OutputMap(self.placement_, topo.back)
        return topo, stable

    def _check_source(self, source: Source) -> None:
        perf = source.performance
        if not isinstance(perf, MeshSequence):
            raise InputError(f"{self.name}: expected a mesh-sequence source, got {source.kind}")
        if perf.n_vertices != self.source_reference_.shape[0] or not np.array_equal(
            perf.triangles, self.source_triangles_
        ):
            raise TopologyMismatchError(
                f"{self.name}: this source has {perf.n_vertices} vertices / {perf.triangles.shape[0]} triangles but the retargeter "
                f"was fitted on {self.source_reference_.shape[0]} / {self.source_triangles_.shape[0]}; fit on a source of this topology"
            )

    def _source_motion(self, source: Source) -> tuple[np.ndarray, dict]:
        """Head motion ``(F, 4, 4)`` of the source (source world) and how it was found: the
        known one, or the stable-vertex Procrustes fit, kept only when significant (exactly
        the identity otherwise; one pass over the stable vertices of every frame)."""
        self._check_source(source)
        if source.head_motion is not None:
            return np.asarray(source.head_motion, dtype=np.float64), {"head_motion": "given"}
        window = max(1, int(round(float(source.fps or 30.0))))
        motion, evidence = estimate_motion(
            self.source_reference_,
            source.performance.vertices,
            self.stable_,
            chunk=int(self.chunk_frames),
            window=window,
        )
        detected = not np.array_equal(motion, np.broadcast_to(np.eye(4), motion.shape))
        return motion, {
            "head_motion": "estimated" if detected else "none detected",
            "head_motion_evidence": evidence,
        }

    def _local_chunks(self, source: Source, motion: np.ndarray):
        """One pass over the source: ``(slice, target head motion (n, 4, 4), local frames in the
        target's frame (n, V, 3))``; ``motion`` from :meth:`_source_motion`."""
        perf = source.performance
        target_motion = self.placement_.target_motion(motion)
        for sl in frame_chunks(perf.n_frames, int(self.chunk_frames)):
            yield (
                sl,
                target_motion[sl],
                self.placement_.local(motion[sl], np.asarray(perf.vertices[sl])),
            )

    def iter_retarget(self, source: Source) -> Iterator[tuple[slice, np.ndarray]]:
        """Retarget chunk by chunk: yields ``(frames slice, target vertices (n, V_t, 3))``.

        Memory stays bounded by ``chunk_frames`` whatever the sequence length (the
        source may be memory-mapped); nothing is kept between chunks.
        """
        self._check_fitted()
        self._check_source(source)
        return ((item[0], item[2]) for item in self._chunks(source))

    def _animation(
        self,
        vertices,
        source: Source,
        motion: np.ndarray,
        diagnostics: dict,
        extras: dict | None = None,
    ) -> Animation:
        return Animation(
            vertices=vertices,
            head_motion=motion,
            triangles=self.target_.neutral.triangles,
            fps=source.fps,
            provenance={"diagnostics": diagnostics},
            extras=extras,
        )


class CoatingRetargeter(_MeshTransfer):
    """Controllable high-fidelity facial performance transfer (Xu et al. 2014)."""

    #: Capabilities and summary: registry.toml (Retargeter.packaged_manifest), by this name.
    name: ClassVar[str] = "coating"
    #: Types, ranges and choices of the parameters, with their meanings: registry.toml.
    parameter_constraints: ClassVar[dict] = manifest.constraints("coating")

    def __init__(
        self,
        *,
        iterations: int = 40,
        epsilon: float = 0.001,
        max_bases: int = 60,
        max_selection_frames: int = 250,
        sigma: float = 100.0,
        laplacian: str = "uniform",
        screening: float = 0.1,
        detail_scale: float | str = 1.0,
        stable_fraction: float = 0.5,
        chunk_frames: int = 32,
        cache_details: bool = True,
        lambda_b: float = 1.0,
        lambda_w: float = 1.0,
        lambda_c: float = 1000.0,
        edit_window: float = 1.0,
        detail_threshold: float = 0.23,
        lambda_key: float = 1.0,
        lambda_gradient: float = 0.1,
        lambda_boundary: float = 1.0,
    ):
        self.iterations = iterations
        self.epsilon = epsilon
        self.max_bases = max_bases
        self.max_selection_frames = max_selection_frames
        self.sigma = sigma
        self.laplacian = laplacian
        self.screening = screening
        self.detail_scale = detail_scale
        self.stable_fraction = stable_fraction
        self.chunk_frames = chunk_frames
        self.cache_details = cache_details
        self.lambda_b = lambda_b
        self.lambda_w = lambda_w
        self.lambda_c = lambda_c
        self.edit_window = edit_window
        self.detail_threshold = detail_threshold
        self.lambda_key = lambda_key
        self.lambda_gradient = lambda_gradient
        self.lambda_boundary = lambda_boundary

    # -- fit -------------------------------------------------------------------------------
    @classmethod
    def why_not(cls, source: Source, target: TargetRig | None) -> str | None:
        """None if ``fit(source, target)`` can run, else what is missing: the declared needs,
        landmarks on both sides for a target of another topology, and a source feature line
        of the same name for every target line."""
        reason = super().why_not(source, target)
        if reason or target is None:
            return reason
        missing = sorted(set(target.feature_lines) - set(source.feature_lines))
        if missing:
            return (
                f"coating: target feature line(s) {missing} have no source line of the same name (source has {sorted(source.feature_lines)}); "
                "name the lines alike on both sides (e.g. eye_L, eye_R, mouth_inner)"
            )
        return None

    def _edit_weights(self, lambda_b, lambda_w, lambda_c) -> tuple[float, float, float]:
        """The large-scale edit's term weights (an edit call's own, else the parameters), each
        checked against the parameter's constraints."""
        return tuple(
            check_value(value, self.parameter_constraints[name], name, "coating.edit")
            for name, value in (
                ("lambda_b", lambda_b),
                ("lambda_w", lambda_w),
                ("lambda_c", lambda_c),
            )
        )

    def _fit(self, source: Source, target: TargetRig) -> None:
        from .model import CoatingModel

        self._check_params()
        start = time.perf_counter()
        topo, stable = self._prepare(source, target)
        prepare = time.perf_counter() - start
        start = time.perf_counter()
        model = CoatingModel(
            self.placement_(self.source_reference_),
            self.placement_.to_model(topo.target_reference),
            self.source_triangles_,
            source_lines=dict(source.feature_lines),
            target_lines=topo.target_lines,
            stable=stable,
            iterations=int(self.iterations),
            laplacian=self.laplacian,
            screening=float(self.screening),
            sigma=float(self.sigma),
            detail_scale=self.detail_scale
            if isinstance(self.detail_scale, str)
            else float(self.detail_scale),
        )
        setup = time.perf_counter() - start
        start = time.perf_counter()
        perf = source.performance
        motion, info = self._source_motion(source)
        placement = self.placement_
        model.fit_bases(
            perf.vertices,
            lambda ids, frames: placement.local(motion[ids], frames),
            epsilon=float(self.epsilon),
            max_bases=int(self.max_bases),
            chunk=int(self.chunk_frames),
            max_frames=int(self.max_selection_frames),
        )
        self.model_ = model
        self.n_bases_ = model.n_bases
        self.basis_frames_ = list(model.basis_frames)
        self.fit_head_motion_ = info
        self.timings_ = {
            "stable_pass_s": prepare,
            "setup_s": setup,
            "bases_s": time.perf_counter() - start,
        }

    # -- retarget --------------------------------------------------------------------------
    def _diagnostics(self, motion_info: dict) -> dict:
        return {
            "n_bases": self.n_bases_,
            "basis_frames": self.basis_frames_,
            "selection_rms": list(self.model_.selection_rms),
            "sigma": self.model_.sigma,
            "line_sigmas": dict(self.model_.line_sigmas),
            "line_proportion": self.model_.line_proportion,
            "unit_scale": self.placement_.unit,
            **motion_info,
            "same_topology": self.topology_.same,
            "correspondence": describe(self.topology_.report),
            "fit_timings_s": dict(self.timings_),
        }

    def _chunks(self, source: Source, source_motion: np.ndarray | None = None):
        self._check_fitted()
        self._check_source(source)
        model = self.model_
        if source_motion is None:
            source_motion = self._source_motion(source)[0]
        for sl, motion, local in self._local_chunks(source, source_motion):
            weights, details = model.decompose(local)
            out = to_world(motion, self.output_(model.synthesize(weights, details)))
            yield sl, motion, out, weights, details

    def _track(self, source, source_motion, motion, weights, details):
        from .track import CoatingTrack

        return CoatingTrack(
            model=self.model_,
            performance=source.performance,
            source_motion=source_motion,
            placement=self.placement_,
            motion=motion,
            source_weights=weights,
            weights=weights.copy(),
            bases=self.model_.target_bases,
            details=details,
            back=self.output_,
            target_vertex=self.topology_.target_vertex,
            chunk=int(self.chunk_frames),
        )

    def _retarget(self, source: Source) -> Animation:
        n_frames = source.n_frames
        n_target = self.target_.neutral.n_vertices
        out, touched = touched_meanwhile((n_frames, n_target, 3))  # while the first chunk runs
        motion = np.empty((n_frames, 4, 4))
        weights = np.empty((n_frames, self.n_bases_))
        details = (
            np.empty((n_frames, self.model_.n_vertices, 3), dtype=np.float32)
            if self.cache_details
            else None
        )
        source_motion, info = self._source_motion(source)
        for sl, m, frames, w, d in self._chunks(source, source_motion):
            touched()
            out[sl] = frames
            motion[sl] = m
            weights[sl] = w
            if details is not None:
                details[sl] = d
        track = self._track(source, source_motion, motion, weights, details)
        return self._animation(
            out, source, motion, self._diagnostics(info), {"coating": track, "weights": weights}
        )

    def retarget_to(self, source: Source, path) -> Animation:
        """Retarget into a ``.npy`` file written chunk by chunk (float32, ``(F, V_t, 3)``).

        For sequences too long for memory: the source may be memory-mapped and only one
        chunk of frames is in memory at a time. Returns an :class:`Animation` whose
        vertices are the memory-mapped file (opened read-only).
        """
        self._check_fitted()
        path = Path(path)
        if path.suffix != ".npy":
            raise OutputError(f"coating.retarget_to: the output must be a .npy file, got {path}")
        if not path.parent.is_dir():
            raise OutputError(
                f"coating.retarget_to: folder {path.parent} does not exist; create it first"
            )
        perf = source.performance
        source_file = getattr(getattr(perf.vertices, "base", None), "filename", None) or getattr(
            perf.vertices, "filename", None
        )
        if source_file is not None and Path(source_file).resolve() == path.resolve():
            raise OutputError(
                f"coating.retarget_to: {path} is the source's own file; write elsewhere"
            )
        self._check_source(source)
        start = time.perf_counter()
        tmp = path.with_name(path.name + ".part")
        out = np.lib.format.open_memmap(
            tmp,
            mode="w+",
            dtype=np.float32,
            shape=(source.n_frames, self.target_.neutral.n_vertices, 3),
        )
        motion = np.empty((source.n_frames, 4, 4))
        weights = np.empty((source.n_frames, self.n_bases_))
        source_motion, info = self._source_motion(source)
        for sl, m, frames, w, _d in self._chunks(source, source_motion):
            out[sl] = frames
            motion[sl] = m
            weights[sl] = w
        out.flush()
        del out
        tmp.replace(path)
        seconds = time.perf_counter() - start
        vertices = np.load(path, mmap_mode="r")
        track = self._track(source, source_motion, motion, weights, None)
        diagnostics = self._diagnostics(info)
        diagnostics["written_to"] = str(path)
        return self._stamp(
            self._animation(
                vertices, source, motion, diagnostics, {"coating": track, "weights": weights}
            ),
            seconds,
            source,
        )

    # -- editing ---------------------------------------------------------------------------
    def edit(
        self,
        animation: Animation,
        *,
        points=None,
        distances=None,
        fixed=None,
        window=None,
        mode: str = "both",
        detail=None,
        lambda_b: float | None = None,
        lambda_w: float | None = None,
        lambda_c: float | None = None,
    ) -> Animation:
        """Spacetime editing of a coating result; returns a new :class:`Animation`.

        Large-scale editing (sec. 4.3), constraints on the output vertices (world
        coordinates, target vertex ids):

        points : iterable of ``(frame, vertex, (x, y, z))``
            Move ``vertex`` to the position at ``frame`` (eq. 14).
        distances : iterable of ``(frame, vertex_a, vertex_b, distance)``
            Set the distance between two vertices, along their current direction (eq. 15).
        fixed : iterable of ``(frame, vertex_ids)``
            Keep these vertices where they are at ``frame`` (use with the others for local
            control).
        window : ``(first, last)`` frames, optional
            Temporal window in which weights may change; their change is zero just outside
            it (default: ``edit_window`` seconds either side of the edited frames).
        mode : "both" | "bases" | "weights"
            Update the blendshape bases (the edit reaches every similar expression in the
            sequence, fig. 4b), the weights (only frames in the window change, fig. 4d),
            or alternate both (fig. 4c).
        lambda_b, lambda_w, lambda_c : float, optional
            Override the retargeter's term weights for this edit.

        Fine-scale editing (sec. 5.2): ``detail=`` a :class:`~faceretarget.plugins.coating.details.DetailEdit`
        (or a dict of its fields): select wrinkles by vertex set or by distance to a
        curve at a key frame, scale / remove / copy-paste them or deform them to a drawn
        curve, and propagate the change through the detail's active frame range.
        """
        from .details import DetailEdit, apply_detail_edit
        from .editing import _MODES, apply_large_scale

        self._check_fitted()
        track = animation.extras.get("coating") if isinstance(animation, Animation) else None
        if track is None or getattr(track, "model", None) is not self.model_:
            raise InputError(
                "coating.edit: the animation was not produced by this fitted coating retargeter (its extras['coating'] is missing or from another fit); retarget first"
            )
        large = any(x is not None for x in (points, distances, fixed))
        if detail is not None and large:
            raise InputError(
                "coating.edit: give either large-scale constraints (points / distances / fixed) or detail=, not both in one call"
            )
        if detail is None and not large:
            raise InputError(
                "coating.edit: nothing to edit; give points=, distances=, fixed= or detail="
            )
        if detail is not None:
            spec = detail if isinstance(detail, DetailEdit) else DetailEdit(**dict(detail))
            new_track, changed, diagnostics = apply_detail_edit(self, track, animation, spec)
        else:
            mode = check_value(mode, [Options(_MODES)], "mode", "coating.edit")
            lambdas = self._edit_weights(
                self.lambda_b if lambda_b is None else lambda_b,
                self.lambda_w if lambda_w is None else lambda_w,
                self.lambda_c if lambda_c is None else lambda_c,
            )
            new_track, changed, diagnostics = apply_large_scale(
                self,
                track,
                animation,
                points=points,
                distances=distances,
                fixed=fixed,
                window=window,
                mode=mode,
                lambdas=lambdas,
            )
        diagnostics["changed_frames"] = int(changed.size)
        prov = dict(animation.provenance)
        prov["diagnostics"] = dict(prov.get("diagnostics", {}), last_edit=diagnostics)
        prov.setdefault("edits", [])
        prov["edits"] = list(prov["edits"]) + [diagnostics.get("kind", "edit")]
        extras = dict(animation.extras)
        extras["coating"] = new_track
        extras["weights"] = new_track.weights
        return animation.replace(
            vertices=_edited_frames(animation, new_track, changed), provenance=prov, extras=extras
        )


def _edited_frames(animation: Animation, track, changed: np.ndarray) -> FrameSource:
    """The edited result's vertices, lazily: frames in ``changed`` re-synthesized from
    ``track`` when read (a chunk at a time), the others those of ``animation``; so ``edit()``
    returns once the edit is solved, and reading a few frames costs only those."""
    moved = np.zeros(animation.n_frames, dtype=bool)
    moved[changed] = True
    return FrameSource(
        _EditedFrames(animation, track, moved),
        animation.n_frames,
        animation.n_vertices,
        chunk=track.chunk,
    )


class _EditedFrames:
    """``(ids) -> (n, V, 3)`` of an edited result (a class, not a closure: results pickle)."""

    def __init__(self, animation: Animation, track, moved: np.ndarray):
        self.animation, self.track, self.moved = animation, track, moved

    def __call__(self, ids: np.ndarray) -> np.ndarray:
        out = np.array(self.animation.frames(ids), dtype=np.float64)
        hit = np.flatnonzero(self.moved[ids])
        if hit.size:
            out[hit] = self.track.world_frames(ids[hit])
        return out


class DeformationTransferRetargeter(_MeshTransfer):
    """Plain per-frame deformation transfer (Sumner & Popovic 2004), the baseline of Xu et al."""

    #: Capabilities and summary: registry.toml (Retargeter.packaged_manifest), by this name.
    name: ClassVar[str] = "deformation_transfer"
    parameter_constraints: ClassVar[dict] = manifest.constraints("deformation_transfer")

    def __init__(self, *, stable_fraction: float = 0.5, chunk_frames: int = 32):
        self.stable_fraction = stable_fraction
        self.chunk_frames = chunk_frames

    def _fit(self, source: Source, target: TargetRig) -> None:
        from .model import size_ratio

        self._check_params()
        topo, stable = self._prepare(source, target)
        start = time.perf_counter()
        self.transfer_ = DeformationTransfer(
            self.placement_.to_model(topo.target_reference),
            self.source_triangles_,
            gauge_weights=stable,
        )
        self.transfer_.factor.solve(
            np.zeros(self.transfer_.free.size)
        )  # factorize now (one-time setup)
        self.aligned_reference_ = self.placement_(self.source_reference_)
        self.inverse_ = reference_inverse(self.aligned_reference_, self.source_triangles_)
        self.ratio_ = size_ratio(
            self.aligned_reference_, topo.target_reference, self.source_triangles_
        )
        self.timings_ = {"setup_s": time.perf_counter() - start}

    def _chunks(self, source: Source, source_motion: np.ndarray | None = None):
        self._check_fitted()
        self._check_source(source)
        ref = self.aligned_reference_
        if source_motion is None:
            source_motion = self._source_motion(source)[0]
        for sl, motion, local in self._local_chunks(source, source_motion):
            means = self.transfer_.component_means(local - ref) * self.ratio_
            columns = gradient_columns(self.inverse_, local, self.source_triangles_)
            rhs = self.transfer_.rhs_columns(columns)
            out = self.transfer_.solve_rhs(rhs, means, overwrite_rhs=True)
            yield sl, motion, to_world(motion, self.output_(out))

    def _retarget(self, source: Source) -> Animation:
        out = np.empty((source.n_frames, self.target_.neutral.n_vertices, 3))
        motion = np.empty((source.n_frames, 4, 4))
        source_motion, info = self._source_motion(source)
        for sl, m, frames in self._chunks(source, source_motion):
            out[sl] = frames
            motion[sl] = m
        diagnostics = {
            "same_topology": self.topology_.same,
            "unit_scale": self.placement_.unit,
            **info,
            "fit_timings_s": dict(self.timings_),
        }
        return self._animation(out, source, motion, diagnostics)
