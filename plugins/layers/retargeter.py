"""The ``layers`` retargeter: Kholgade, Matthews & Sheikh 2011, parameter-parallel facial layers.

fit: assemble the actor's bases (``Source.actor_layers`` over the markers, plus
``Source.actor_layers_2d`` over 2D tracks when given), the character's
(``TargetRig.layers``), the lip-closure bias and, when the character has blendshapes and
landmarks paired with the markers, the residual transfer (``residual.py``). retarget: a
whole-shot test of whether there is head motion at all, the alignment (Procrustes, then
model-based), layer weights and simplex coefficients by the biased, smoothed bilinear
problem (Eq. 7), then the character by the same composition (Eq. 5) plus the residual.
See ``model.py``, ``solver.py``, ``compose.py`` and ``docs/methods/layers.md`` for the
equations as read from the paper and where (and why) the defaults depart from it.
"""

from __future__ import annotations

from collections.abc import Iterable, Iterator
from concurrent.futures import ThreadPoolExecutor
from dataclasses import fields
from functools import partial

import numpy as np

from faceretarget import manifest
from faceretarget._threads import blas_single_threaded, single_threaded_blas
from faceretarget._validate import short_repr
from faceretarget.errors import (
    CapabilityError,
    ConfigError,
    FaceRetargetError,
    ShapeError,
    TopologyMismatchError,
)
from faceretarget.model import Animation, Source, TargetRig
from faceretarget.retargeter import Retargeter
from faceretarget.validation import Interval, check_value, validate_params

from . import compose
from .model import build_actor, build_character
from .residual import build_residual, solve_residual
from .solver import (
    Extraction,
    Observations,
    extract,
    fit_block,
    observe,
    reconstruct,
    resolve_lip_bias,
)

__all__ = ["LayersRetargeter"]


def _lip_markers(value):
    """``lip_markers`` as a pair: what its declared constraint (None or an array) cannot say."""
    if value is None:
        return None
    message = (
        "lip_markers: expected None or a pair (upper, lower) of marker/track names or 3D marker indices, "
        f"got {short_repr(value)}"
    )
    if not isinstance(value, (list, tuple, np.ndarray)) or (
        isinstance(value, np.ndarray) and value.ndim != 1
    ):
        raise ConfigError(message)
    items = list(value)
    if len(items) != 2:
        raise ConfigError(message)
    out = []
    for item in items:
        if isinstance(item, str):
            out.append(str(item))
        elif isinstance(item, (bool, np.bool_)) or not isinstance(
            item, (int, float, np.integer, np.floating)
        ):
            raise ConfigError(message)
        else:
            out.append(check_value(item, [Interval(int)], "lip_markers", "layers"))
    return tuple(out)


#: The head-motion significance test looks at about this many frames spread over the shot.
GATE_FRAMES = 200
#: A size ratio within this fraction of a power of ten is a change of units (m, cm, mm).
UNIT_TOLERANCE = 0.25
#: Frames solved at a time while another thread writes the solved frames' vertices
#: (``LayersRetargeter._solve_into``): each block costs ~2 ms of set-up, and the last one is
#: written after the solve has ended.
SOLVE_BLOCK = 128


def _motion_map(residual, actor_reference, character_neutral):
    """(q (3, 3), k) turning the actor's head motion into the character's, or None; and a note.

    The paper (sec. 5) applies the actor's rotation and translation to the character as
    they are, which assumes one frame and one unit. We keep that when the character is
    about the actor's size and posed alike, and otherwise convert: ``k`` scales the
    translation (the power of ten nearest the size ratio when within 25% of it: a change
    of units, metres vs centimetres; else the ratio itself: a character of another size)
    and ``q`` turns the rotation into the character's frame when the faces are posed more
    than 10 degrees apart. The size ratio and the posing come from the similarity fit of
    the landmarks paired with the markers (the residual's). Without paired landmarks only a
    change of units is corrected: the power of ten nearest the ratio of the RMS radii of
    the character's neutral and the markers.
    """
    ref = np.asarray(actor_reference, dtype=np.float64)
    q = np.eye(3)
    if residual is not None:
        ratio = residual.scale
        q = residual.transfer / residual.scale
        source = "landmark similarity"
    else:
        neutral = np.asarray(character_neutral, dtype=np.float64)
        size_a = float(np.sqrt(np.mean(np.sum((ref - ref.mean(axis=0)) ** 2, axis=1))))
        size_c = float(np.sqrt(np.mean(np.sum((neutral - neutral.mean(axis=0)) ** 2, axis=1))))
        if not (size_a > 0 and size_c > 0 and np.isfinite(size_c / size_a)):
            return None, "as the actor's"
        ratio = size_c / size_a
        source = "size ratio"
    power = 10.0 ** np.round(np.log10(ratio))
    # the landmark fit measures the size ratio; the radii only the units (the markers
    # cover less than the character's mesh, so their ratio is not a size ratio)
    k = power if (residual is None or abs(ratio / power - 1.0) < UNIT_TOLERANCE) else ratio
    if k == 1.0 and np.allclose(q, np.eye(3)):
        return None, f"as the actor's ({source} {ratio:.4g}: same units)"
    return (
        (q, float(k)),
        f"translation x {k:.6g} ({source} {ratio:.4g}){', rotation into the character frame' if not np.allclose(q, np.eye(3)) else ''}",
    )


class LayersRetargeter(Retargeter):
    """Deconstruct the actor into emotion/speech/blink layers and rebuild the character in parallel."""

    #: Capabilities and summary: registry.toml (Retargeter.packaged_manifest), by this name.
    name = "layers"
    #: Types, ranges and choices of the parameters, with their meanings: registry.toml.
    parameter_constraints = manifest.constraints("layers")

    def __init__(
        self,
        *,
        smoothing: float = 0.02,
        lip_sigma: float = 0.02,
        gamma_max: float = 0.9,
        lip_markers=None,
        speech_layer: str = "speech",
        closed_viseme=None,
        mouth_region=None,
        composition: str = "additive",
        head_motion: str = "auto",
        head_motion_refinement: int = 1,
        rigid_points: str = "stable",
        residual: str = "auto",
        project_blendshapes: bool = False,
        max_iter: int = 100,
        tol: float = 1e-8,
    ):
        self.smoothing = smoothing
        self.lip_sigma = lip_sigma
        self.gamma_max = gamma_max
        self.lip_markers = lip_markers
        self.speech_layer = speech_layer
        self.closed_viseme = closed_viseme
        self.mouth_region = mouth_region
        self.composition = composition
        self.head_motion = head_motion
        self.head_motion_refinement = head_motion_refinement
        self.rigid_points = rigid_points
        self.residual = residual
        self.project_blendshapes = project_blendshapes
        self.max_iter = max_iter
        self.tol = tol

    # -- parameters ------------------------------------------------------------------
    def _params(self) -> dict:
        """Every constructor parameter, checked against its declared constraints (registry.toml;
        a ParameterError naming it and the valid values), ``lip_markers`` also as a pair."""
        params = validate_params(self)
        params["lip_markers"] = _lip_markers(params["lip_markers"])
        return params

    def _param(self, name: str):
        """One parameter, checked again at retarget time (set_params may change it after fit)."""
        return check_value(getattr(self, name), self.parameter_constraints[name], name, "layers")

    # -- fit -------------------------------------------------------------------------
    def _fit(self, source: Source, target: TargetRig) -> None:
        params = self._params()
        if params["project_blendshapes"] and target.blendshapes is None:
            raise CapabilityError(
                "project_blendshapes=True needs a TargetRig with blendshapes; this one has none"
            )
        layers3d = source.actor_layers
        ref3d = np.asarray(source.marker_reference(), dtype=np.float64)
        names3d = source.landmarks.names if source.kind == "mesh" else source.performance.names
        layers2d = source.actor_layers_2d
        ref2d = names2d = None
        if layers2d is not None:
            ref2d = np.asarray(source.tracks2d.reference, dtype=np.float64)
            names2d = source.tracks2d.names
        actor = build_actor(layers3d, ref3d, layers2d, ref2d, names3d, names2d or ())
        residual, why = None, "off (residual='none')"
        if params["residual"] != "none":
            residual, why = build_residual(
                ref3d, names3d, target.neutral, target.landmarks, target.blendshapes
            )
            if residual is None:
                if params["residual"] == "blendshapes":
                    raise CapabilityError(
                        f"layers: residual='blendshapes' needs a TargetRig with blendshapes and landmarks "
                        f"paired with the source's markers; {why}"
                    )
                why = f"off: {why}"
        character = build_character(
            target.layers,
            target.neutral.vertices,
            layers3d,
            extra=None if residual is None else target.blendshapes.deltas,
        )
        speech = params["speech_layer"]
        poses3 = np.asarray(layers3d.layers[speech], float) if speech in layers3d.layers else None
        poses2 = (
            np.asarray(layers2d.layers[speech], float)
            if (layers2d is not None and speech in layers2d.layers)
            else None
        )
        lip = resolve_lip_bias(
            actor,
            poses3,
            poses2,
            lip_markers=params["lip_markers"],
            speech_layer=speech,
            closed_viseme=params["closed_viseme"],
            mouth_region=params["mouth_region"],
            lip_sigma=params["lip_sigma"],
            masks3d=np.asarray(layers3d.masks),
            masks2d=None if layers2d is None else np.asarray(layers2d.masks),
        )
        self.actor_ = actor
        self.character_ = character
        self.lip_ = lip
        self.residual_ = residual
        self.motion_map_, self.motion_note_ = _motion_map(residual, ref3d, target.neutral.vertices)
        self.residual_note_ = why or (
            f"blendshapes: {residual.n_shapes} shapes through {len(residual.marker_ids)} landmarks, "
            f"scale {residual.scale:.6g}"
        )
        self.projection_ = (
            compose.build_projection(character, target.blendshapes)
            if params["project_blendshapes"]
            else None
        )
        self.rig_ = target.blendshapes if params["project_blendshapes"] else None
        self.triangles_ = np.asarray(target.neutral.triangles)
        # a mesh source can be streamed as raw vertices: keep how to sample its markers
        self.source_landmarks_ = source.landmarks if source.kind == "mesh" else None
        self.source_triangles_ = (
            np.asarray(source.performance.triangles) if source.kind == "mesh" else None
        )
        self.source_vertex_count_ = source.performance.n_vertices if source.kind == "mesh" else None
        # streaming cannot see a whole shot: it follows the significance test on the fit source
        self.stream_head_motion_ = True
        if params["head_motion"] == "auto" and source.head_motion is None and source.n_frames:
            self.stream_head_motion_ = self._detect_head_motion(source.marker_positions())[0]

    # -- retarget --------------------------------------------------------------------
    def _settings(self) -> dict:
        """The retarget-time parameters, checked again (set_params may change them after fit)."""
        p = {
            name: self._param(name)
            for name in (
                "rigid_points",
                "smoothing",
                "gamma_max",
                "max_iter",
                "tol",
                "composition",
                "head_motion_refinement",
            )
        }
        return dict(
            rigid_points=p["rigid_points"],
            smoothing=p["smoothing"],
            gamma_max=p["gamma_max"],
            max_iter=p["max_iter"],
            tol=p["tol"],
            additive=p["composition"] == "additive",
            passes=1 + p["head_motion_refinement"],
        )

    def _solve(self, markers, tracks, head_motion, states=None, frame_offset=0, settings=None):
        """(observations, extraction, residual weights or None, states) of a block of frames.

        ``states``: (per-pass layer states, residual state) of the frame before the block.
        See ``solver.fit_block`` and ``residual.solve_residual``.
        """
        settings = self._settings() if settings is None else settings
        layer_states, residual_state = (None, None) if states is None else states
        residual = getattr(self, "residual_", None)
        obs, params, layer_states = fit_block(
            self.actor_,
            self.lip_,
            markers,
            tracks,
            head_motion,
            states=layer_states,
            frame_offset=frame_offset,
            keep_local=residual is not None,
            **settings,
        )
        weights = None
        if residual is not None:
            recon, _ = reconstruct(self.actor_, params)
            weights, residual_state = solve_residual(
                residual, obs.local3 - recon, settings["smoothing"], residual_state
            )
        return obs, params, weights, (layer_states, residual_state)

    def _observe(self, markers, tracks, head_motion, frame_offset=0):
        """Pass 0 only: alignment to the neutral (the paper's Eq. 6)."""
        rigid_points = self._param("rigid_points")
        return observe(
            self.actor_,
            self.lip_,
            markers,
            tracks,
            head_motion,
            rigid_points=rigid_points,
            frame_offset=frame_offset,
        )

    def _extract(self, obs, state=None, start=None, rigid=None):
        """One solve of Eq. 7 over the observed block (``rigid``: data modulo the alignment's motions)."""
        st = self._settings()
        return extract(
            self.actor_,
            self.lip_,
            obs,
            smoothing=st["smoothing"],
            gamma_max=st["gamma_max"],
            max_iter=st["max_iter"],
            tol=st["tol"],
            state=state,
            additive=st["additive"],
            start=start,
            rigid=rigid,
        )

    def _inputs(self, source: Source):
        """(markers, tracks, head motion, note) of a source; head motion: known (F, 4, 4), None
        (estimate) or "none" (identity: head_motion='none', or 'auto' and the whole-shot
        significance test finds no head motion)."""
        if not isinstance(source, Source):
            raise ShapeError(f"layers: expected a faceretarget.Source, got {type(source).__name__}")
        markers = source.marker_positions()
        if markers.shape[1] != self.actor_.n3:
            raise TopologyMismatchError(
                f"layers: this source has {markers.shape[1]} markers but the model was fitted on {self.actor_.n3}"
            )
        tracks = None
        if self.actor_.n2:
            if source.tracks2d is None:
                raise CapabilityError(
                    f"layers: the model was fitted with {self.actor_.n2} 2D tracks; this source has no tracks2d"
                )
            tracks = source.tracks2d.positions
        mode = self._param("head_motion")
        if mode == "none":
            return markers, tracks, "none", "none (head_motion='none')"
        if mode == "auto" and source.head_motion is not None:
            return markers, tracks, source.head_motion, "known (Source.head_motion)"
        if mode == "auto":
            detected, evidence = self._detect_head_motion(markers)
            note = f"{'estimated' if detected else 'none'} (significance test: evidence {evidence:.3g})"
            return markers, tracks, (None if detected else "none"), note
        return markers, tracks, None, "estimated (head_motion='procrustes')"

    def _character_motion(self, motion: np.ndarray) -> np.ndarray:
        """The actor's head motion ``(F, 4, 4)`` as the character's (units and frame; see ``_motion_map``)."""
        if self.motion_map_ is None:
            return motion
        q, k = self.motion_map_
        out = np.array(motion, dtype=np.float64)
        out[:, :3, :3] = q @ motion[:, :3, :3] @ q.T
        out[:, :3, 3] = k * motion[:, :3, 3] @ q.T
        return out

    def _detect_head_motion(self, markers) -> tuple[bool, float]:
        """Whether the markers hold significant rigid head motion beyond what the actor's
        poses explain (``faceretarget.geometry.head_motion``, whole-shot significance test)."""
        from faceretarget.geometry.head_motion import estimate_head_motion

        actor = self.actor_
        basis = (
            actor.basis_t[: 3 * actor.n3] * actor.scale3d
        )  # (3 N3, K): every pose's displacement
        # the neutral poses (zero displacement) and repeated poses add nothing to the span
        norms = np.linalg.norm(basis, axis=0)
        keep = norms > 1e-9 * max(float(norms.max()), np.finfo(float).tiny)
        basis = np.unique(basis[:, keep], axis=1)
        x = np.asarray(markers, dtype=np.float64)
        if x.shape[0] == 0:
            return False, 0.0
        # the evidence is a sum over frames: ~GATE_FRAMES frames spread over the shot tell as much
        x = x[:: max(1, -(-x.shape[0] // GATE_FRAMES))]
        try:
            _, info = estimate_head_motion(actor.reference3d, x, basis=basis, return_info=True)
        except (FaceRetargetError, np.linalg.LinAlgError):
            # the test cannot be made (too few markers, a degenerate basis): estimate per frame
            return True, float("nan")
        return bool(info.detected), float(info.evidence)

    @blas_single_threaded
    def _retarget(self, source: Source) -> Animation:
        markers, tracks, known, note = self._inputs(source)
        if self.projection_ is None:
            out = np.empty((markers.shape[0], self.character_.n_vertices, 3))
            obs, params, residual = self._solve_into(markers, tracks, known, out)
        else:
            obs, params, residual, _ = self._solve(markers, tracks, known)
        common = dict(
            head_motion=self._character_motion(obs.head_motion),
            fps=source.fps,
            extras=self._extras(params, obs, residual),
            provenance={"diagnostics": self._diagnostics(params, note)},
        )
        if self.projection_ is None:
            return Animation(vertices=out, triangles=self.triangles_, **common)
        beta = compose.region_coefficients(
            params.weights, params.coefficients, self.actor_.layer_of
        )
        weights = compose.project(self.projection_, beta, extra=residual)
        return Animation(weights=weights, rig=self.rig_, **common)

    def _solve_into(self, markers, tracks, head_motion, out):
        """:meth:`_solve` of every frame, :data:`SOLVE_BLOCK` frames at a time, while one
        other thread writes each solved block's character vertices (Eq. 5) into ``out (F, V,
        3)``: the extraction is a chain from frame to frame on one core, the vertices of the
        frames solved so far are the other core's work (and its first writes fault the new
        result's pages in). What that thread has not started when the last block is solved
        is written here. The same as one solve of all frames, then
        :func:`.compose.world_vertices`, to rounding (a product over a block's frames may round
        apart from one over all of them: 3.6e-15 in the 2D alignment, the vertices bitwise on
        ``benchmarks/bench_layers.py``'s problem). Returns (observations with ``head_motion`` and
        ``alignment2d`` only, extraction, residual weights or None)."""
        pieces: list = []
        queued: list = []
        with ThreadPoolExecutor(1) as writer:
            try:
                self._solve_blocks(markers, tracks, head_motion, out, writer, pieces, queued)
            except BaseException:
                for future, _ in queued:  # nothing more to write
                    future.cancel()
                raise
            for future, write in reversed(queued):  # not started yet: written here
                if not future.cancel():
                    break
                write()
            for future, _ in queued:
                if not future.cancelled():
                    future.result()
        obs = [p[0] for p in pieces]
        kept: dict = dict.fromkeys(f.name for f in fields(Observations))
        kept["head_motion"] = np.concatenate([o.head_motion for o in obs])
        if obs[0].alignment2d is not None:
            kept["alignment2d"] = np.concatenate([o.alignment2d for o in obs])
        params = Extraction(
            *(np.concatenate([getattr(p[1], f.name) for p in pieces]) for f in fields(Extraction))
        )
        residual = None if pieces[0][2] is None else np.concatenate([p[2] for p in pieces])
        return Observations(**kept), params, residual

    def _solve_blocks(self, markers, tracks, head_motion, out, writer, pieces, queued) -> None:
        """The loop of :meth:`_solve_into`: each block solved, its writing handed to ``writer``
        (appended to ``queued`` with the call), its results appended to ``pieces``."""
        states = None
        for start in range(0, markers.shape[0], SOLVE_BLOCK):
            rows = slice(start, start + SOLVE_BLOCK)
            obs, params, residual, states = self._solve(
                markers[rows],
                None if tracks is None else tracks[rows],
                head_motion[rows] if isinstance(head_motion, np.ndarray) else head_motion,
                states=states,
                frame_offset=start,
            )
            beta = compose.region_coefficients(
                params.weights, params.coefficients, self.actor_.layer_of
            )
            write = partial(
                compose.world_vertices,
                self.character_,
                beta,
                self._character_motion(obs.head_motion),
                extra=residual,
                out=out[rows],
                workers=1,
            )
            queued.append((writer.submit(write), write))
            pieces.append((obs, params, residual))

    def deconstruct(self, source: Source) -> dict:
        """The actor side only: layered parameters and how well they explain the markers (Fig. 8).

        Returns a dict with ``layer_weights (F, m, J)`` (w_jl, row = region), ``coefficients
        {layer: (F, K_j)}``, ``layer_names``, ``region_names``,
        ``head_motion (F, 4, 4)``, ``lip_gamma (F,)``, ``objective (F,)``,
        ``reconstruction (F, N, 3)`` (the 3D markers Eq. 4 predicts, world coordinates) and
        ``rms_error (F,)`` (RMS distance to the observed markers, marker units).
        """
        self._check_fitted()
        markers, tracks, known, _ = self._inputs(source)
        obs, params, residual, _ = self._solve(markers, tracks, known)
        local, _ = reconstruct(self.actor_, params)  # Eq. 4 inside the brackets
        rot, trans = obs.head_motion[:, :3, :3], obs.head_motion[:, :3, 3]
        world = np.einsum("fij,fpj->fpi", rot, local) + trans[:, None, :]
        dist2 = np.sum((world - np.asarray(markers, dtype=np.float64)) ** 2, axis=-1)
        out = self._extras(params, obs, residual)
        out.update(
            head_motion=obs.head_motion,
            reconstruction=world,
            rms_error=np.sqrt(np.nanmean(dist2, axis=1)),
        )
        return out

    def _extras(self, params, obs=None, residual=None) -> dict:
        actor = self.actor_
        offsets = actor.offsets
        beta = compose.region_coefficients(params.weights, params.coefficients, actor.layer_of)
        out = {
            "layer_weights": params.weights,
            "layer_names": actor.layer_names,
            "region_names": actor.region_names,
            "coefficients": {
                n: params.coefficients[:, offsets[j] : offsets[j + 1]]
                for j, n in enumerate(actor.layer_names)
            },
            "weighted_coefficients": {
                n: beta[:, :, offsets[j] : offsets[j + 1]] for j, n in enumerate(actor.layer_names)
            },
            "lip_gamma": params.gamma,
            "objective": params.objective,
        }
        if obs is not None and obs.alignment2d is not None:
            out["alignment_2d"] = obs.alignment2d
        if residual is not None:
            out["residual_weights"] = residual
            out["residual_names"] = self.residual_.names
        return out

    def _diagnostics(self, params, head_motion_note: str = "") -> dict:
        lip = self.lip_
        return {
            "lip_markers": list(lip.names) if lip.enabled else None,
            "lip_bias": lip.note or "on",
            "mouth_region": self.actor_.region_names[lip.mouth] if lip.enabled else None,
            "mean_iterations": float(np.mean(params.iterations)),
            "max_iterations": int(np.max(params.iterations)),
            "residual": self.residual_note_,
            "head_motion": head_motion_note,
            "head_motion_units": self.motion_note_,
        }

    # -- streaming -------------------------------------------------------------------
    def stream(self, frames: Iterable) -> Iterator[np.ndarray]:
        """Retarget frame by frame (the model is first-order Markov); yields ``(V, 3)`` world vertices.

        Each item is ``markers (N, 3)`` (NaN = missing), a source mesh frame ``(V_src, 3)``
        when fitted on a mesh source (sampled at its landmarks), a pair ``(markers,
        tracks2d (N2, 2))``, or a dict with ``"markers"``, optional ``"tracks2d"`` and
        ``"head_motion" (4, 4)``. The result equals :meth:`retarget` on the same frames
        (up to rounding) when the batch source carries no known head motion. A stream cannot
        run the whole-shot head-motion test (``head_motion="auto"``): frames without a known
        head motion follow the test made at ``fit`` on the fit source (estimated per frame,
        or none).
        """
        self._check_fitted()
        return self._stream(iter(frames))

    def _stream(self, frames: Iterator) -> Iterator[np.ndarray]:
        states = None
        settings = self._settings()
        mode = self._param("head_motion")
        for index, item in enumerate(frames):
            markers, tracks, head = self._parse_frame(item, index)
            if mode == "none":
                known = "none"
            elif mode == "auto" and head is not None:
                known = head[None]
            elif mode == "auto" and not self.stream_head_motion_:
                known = "none"  # the fit source's significance test found none
            else:
                known = None
            with single_threaded_blas():
                obs, params, residual, states = self._solve(
                    markers[None],
                    None if tracks is None else tracks[None],
                    known,
                    states,
                    index,
                    settings,
                )
                beta = compose.region_coefficients(
                    params.weights, params.coefficients, self.actor_.layer_of
                )
                motion = self._character_motion(obs.head_motion)
                if self.projection_ is not None:
                    local = self.rig_.evaluate(
                        compose.project(self.projection_, beta, extra=residual)
                    )
                    rot, trans = motion[0, :3, :3], motion[0, :3, 3]
                    out = local[0] @ rot.T + trans
                else:
                    out = compose.world_vertices(self.character_, beta, motion, extra=residual)[0]
            yield out

    def _parse_frame(self, item, index: int):
        tracks = head = None
        if isinstance(item, dict):
            markers, tracks, head = (
                item.get("markers"),
                item.get("tracks2d"),
                item.get("head_motion"),
            )
        elif isinstance(item, tuple):
            if len(item) != 2:
                raise ShapeError(
                    f"stream: frame {index} is a tuple of {len(item)}; expected (markers, tracks2d)"
                )
            markers, tracks = item
        else:
            markers = item
        pts = np.asarray(markers, dtype=np.float64)
        if (
            self.source_landmarks_ is not None
            and pts.ndim == 2
            and pts.shape[0] == self.source_vertex_count_
            and pts.shape[0] != self.actor_.n3
        ):
            pts = self.source_landmarks_.positions(pts, self.source_triangles_)
        if pts.ndim != 2 or pts.shape != (self.actor_.n3, 3):
            raise ShapeError(
                f"stream: frame {index} has shape {pts.shape}; expected ({self.actor_.n3}, 3) markers"
            )
        if self.actor_.n2 and tracks is None:
            raise CapabilityError(
                f"stream: the model uses {self.actor_.n2} 2D tracks; pass (markers, tracks2d) pairs"
            )
        if tracks is not None:
            tracks = np.asarray(tracks, dtype=np.float64)
            if not self.actor_.n2:
                tracks = None
        if head is not None:
            head = np.asarray(head, dtype=np.float64)
            if head.shape != (4, 4):
                raise ShapeError(
                    f"stream: frame {index} head_motion must be (4, 4), got {head.shape}"
                )
        return pts, tracks, head
