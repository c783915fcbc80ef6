"""The ``layers`` retargeter: Kholgade, Matthews & Sheikh 2011, parameter-parallel facial layers.

fit: assemble the actor's bases (``Source.actor_layers`` over the markers, plus
``Source.actor_layers_2d`` over 2D tracks when given), the character's
(``TargetRig.layers``), and the lip-closure bias. retarget: per frame head motion by
Procrustes, layer weights and simplex coefficients by the biased, smoothed bilinear
problem (Eq. 7), then the character by the same composition (Eq. 5). See ``model.py``,
``solver.py`` and ``compose.py`` for the equations as read from the paper.
"""
from __future__ import annotations

from typing import Iterable, Iterator

import numpy as np

from faceretarget._validate import check_bool, check_choice, check_number, check_param, short_repr
from faceretarget.errors import CapabilityError, ConfigError, InputError, ShapeError, TopologyMismatchError
from faceretarget.model import Animation, Source, TargetRig
from faceretarget.retargeter import Capabilities, Retargeter

from . import compose
from .model import build_actor, build_character
from .solver import extract, observe, resolve_lip_bias

__all__ = ["LayersRetargeter"]

#: Upper bounds of the numeric parameters (far beyond any useful value; they keep the
#: solver's arithmetic finite and its run time bounded).
MAX_SMOOTHING = 1e6
MAX_LIP_SIGMA = 1e6
MAX_ITER = 10_000


def _number(value, name: str, **limits):
    """``check_number`` with the plugin's error type (ConfigError, message naming ``name``)."""
    return check_param(check_number, value, name, **limits)


def _choice(value, name: str, choices) -> str:
    return check_param(check_choice, value, name, choices)


def _name_or_index(value, name: str, what: str):
    """None, a name (str) or a whole-number index (range checked later, against the model)."""
    if value is None or isinstance(value, str):
        return value
    message = f"{name}: expected None, the name of a {what} or its 0-based index (a whole number), got {short_repr(value)}"
    if isinstance(value, (bool, np.bool_)) or not isinstance(value, (int, float, np.integer, np.floating)):
        raise ConfigError(message)
    try:
        return check_number(value, name, integer=True)
    except InputError:
        raise ConfigError(message) from None


def _lip_markers(value):
    if value is None:
        return None
    message = ("lip_markers: expected None or a pair (upper, lower) of marker/track names or 3D marker indices, "
               f"got {short_repr(value)}")
    if not isinstance(value, (list, tuple, np.ndarray)) or (isinstance(value, np.ndarray) and value.ndim != 1):
        raise ConfigError(message)
    items = list(value)
    if len(items) != 2:
        raise ConfigError(message)
    out = []
    for item in items:
        if isinstance(item, str):
            out.append(str(item))
        elif isinstance(item, (bool, np.bool_)) or not isinstance(item, (int, float, np.integer, np.floating)):
            raise ConfigError(message)
        else:
            out.append(_number(item, "lip_markers", integer=True))
    return tuple(out)


def _flag(value, name: str) -> bool:
    return check_param(check_bool, value, name)


class LayersRetargeter(Retargeter):
    """Deconstruct the actor into emotion/speech/blink layers and rebuild the character in parallel."""

    name = "layers"
    capabilities = Capabilities(
        sources=("markers", "mesh"),
        needs=("layers", "actor_layers"),
        outputs="vertices",
        stream=True,
        edit=False,
        same_topology=False,
    )
    summary = "Layered simplicial bases (emotion, speech, blink) with region mask weights, transferred parameter-parallel"
    parameter_docs = {
        "smoothing": "lambda of Eq. 7: pull of each frame's weights and coefficients towards the previous frame's",
        "lip_sigma": "sigma of the lip-closure bias, as a fraction of the widest lip opening among the speech poses (0: bias off)",
        "gamma_max": "cap on the bias factor gamma < 1, so the data term never vanishes on closed lips",
        "lip_markers": "(upper, lower) lip marker or 2D-track names, or 3D marker indices; default: by name ('lip' + upper/lower) or geometry",
        "speech_layer": "name of the layer holding the visemes (the bias target)",
        "closed_viseme": "closed-lips pose of the speech layer (name or index); default: its first pose",
        "mouth_region": "region the bias acts on (name or index); default: the region covering the lip markers",
        "head_motion": "'auto' (Source.head_motion if given, else Procrustes) or 'procrustes' (always estimate)",
        "rigid_points": "'stable' (weight the rigid fit to points the layers barely move) or 'all' (plain Procrustes)",
        "project_blendshapes": "also project every frame onto TargetRig.blendshapes by bounded least squares (output weights)",
        "max_iter": "maximum alternations (weights step + coefficients step) per frame",
        "tol": "relative decrease of the objective below which a frame has converged",
    }

    def __init__(
        self,
        *,
        smoothing: float = 0.02,
        lip_sigma: float = 0.1,
        gamma_max: float = 0.9,
        lip_markers=None,
        speech_layer: str = "speech",
        closed_viseme=None,
        mouth_region=None,
        head_motion: str = "auto",
        rigid_points: str = "stable",
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
        self.head_motion = head_motion
        self.rigid_points = rigid_points
        self.project_blendshapes = project_blendshapes
        self.max_iter = max_iter
        self.tol = tol

    # -- parameters ------------------------------------------------------------------
    def _params(self) -> dict:
        """Every constructor parameter, checked (ConfigError naming it and the valid values)."""
        speech = self.speech_layer
        if not isinstance(speech, str):
            raise ConfigError(f"speech_layer: expected the name (str) of the layer holding the visemes, got {short_repr(speech)}")
        return dict(
            smoothing=_number(self.smoothing, "smoothing", low=0, high=MAX_SMOOTHING),
            lip_sigma=_number(self.lip_sigma, "lip_sigma", low=0, high=MAX_LIP_SIGMA),
            gamma_max=self._gamma_max(),
            lip_markers=_lip_markers(self.lip_markers),
            speech_layer=speech,
            closed_viseme=_name_or_index(self.closed_viseme, "closed_viseme", "pose of the speech layer"),
            mouth_region=_name_or_index(self.mouth_region, "mouth_region", "region"),
            head_motion=_choice(self.head_motion, "head_motion", ("auto", "procrustes")),
            rigid_points=_choice(self.rigid_points, "rigid_points", ("stable", "all")),
            project_blendshapes=_flag(self.project_blendshapes, "project_blendshapes"),
            max_iter=_number(self.max_iter, "max_iter", integer=True, low=1, high=MAX_ITER),
            tol=_number(self.tol, "tol", low=0),
        )

    def _gamma_max(self) -> float:
        message = f"gamma_max: expected a finite number >= 0 and < 1, got {short_repr(self.gamma_max)}"
        try:
            value = check_number(self.gamma_max, "gamma_max", low=0, high=1)
        except InputError:
            raise ConfigError(message) from None
        if value >= 1.0:
            raise ConfigError(message)
        return value

    # -- fit -------------------------------------------------------------------------
    def _fit(self, source: Source, target: TargetRig) -> None:
        params = self._params()
        if params["project_blendshapes"] and target.blendshapes is None:
            raise CapabilityError("project_blendshapes=True needs a TargetRig with blendshapes; this one has none")
        layers3d = source.actor_layers
        ref3d = np.asarray(source.marker_reference(), dtype=np.float64)
        names3d = source.landmarks.names if source.kind == "mesh" else source.performance.names
        layers2d = source.actor_layers_2d
        ref2d = names2d = None
        if layers2d is not None:
            ref2d = np.asarray(source.tracks2d.reference, dtype=np.float64)
            names2d = source.tracks2d.names
        actor = build_actor(layers3d, ref3d, layers2d, ref2d, names3d, names2d or ())
        character = build_character(target.layers, target.neutral.vertices, layers3d)
        speech = params["speech_layer"]
        poses3 = np.asarray(layers3d.layers[speech], float) if speech in layers3d.layers else None
        poses2 = np.asarray(layers2d.layers[speech], float) if (layers2d is not None and speech in layers2d.layers) else None
        lip = resolve_lip_bias(
            actor, poses3, poses2,
            lip_markers=params["lip_markers"], speech_layer=speech, closed_viseme=params["closed_viseme"],
            mouth_region=params["mouth_region"], lip_sigma=params["lip_sigma"],
            masks3d=np.asarray(layers3d.masks), masks2d=None if layers2d is None else np.asarray(layers2d.masks),
        )
        self.actor_ = actor
        self.character_ = character
        self.lip_ = lip
        self.projection_ = compose.build_projection(character, target.blendshapes) if params["project_blendshapes"] else None
        self.rig_ = target.blendshapes if params["project_blendshapes"] else None
        self.triangles_ = np.asarray(target.neutral.triangles)
        # a mesh source can be streamed as raw vertices: keep how to sample its markers
        self.source_landmarks_ = source.landmarks if source.kind == "mesh" else None
        self.source_triangles_ = np.asarray(source.performance.triangles) if source.kind == "mesh" else None
        self.source_vertex_count_ = source.performance.n_vertices if source.kind == "mesh" else None

    # -- retarget --------------------------------------------------------------------
    def _observe(self, markers, tracks, head_motion, frame_offset=0):
        rigid_points = _choice(self.rigid_points, "rigid_points", ("stable", "all"))
        return observe(self.actor_, self.lip_, markers, tracks, head_motion, rigid_points=rigid_points,
                       frame_offset=frame_offset)

    def _extract(self, obs, state=None):
        # read at retarget time (as before), checked again in case set_params changed them after fit
        return extract(self.actor_, self.lip_, obs,
                       smoothing=_number(self.smoothing, "smoothing", low=0, high=MAX_SMOOTHING),
                       gamma_max=self._gamma_max(),
                       max_iter=_number(self.max_iter, "max_iter", integer=True, low=1, high=MAX_ITER),
                       tol=_number(self.tol, "tol", low=0), state=state)

    def _inputs(self, source: Source):
        """(markers, tracks, known head motion) of a source, checked against the fitted model."""
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
                raise CapabilityError(f"layers: the model was fitted with {self.actor_.n2} 2D tracks; this source has no tracks2d")
            tracks = source.tracks2d.positions
        head_motion = _choice(self.head_motion, "head_motion", ("auto", "procrustes"))
        known = source.head_motion if head_motion == "auto" else None
        return markers, tracks, known

    def _retarget(self, source: Source) -> Animation:
        obs = self._observe(*self._inputs(source))
        params, _ = self._extract(obs)
        beta = compose.region_coefficients(params.weights, params.coefficients, self.actor_.layer_of)
        extras = self._extras(params)
        common = dict(head_motion=obs.head_motion, fps=source.fps, extras=extras,
                      provenance={"diagnostics": self._diagnostics(params)})
        if self.projection_ is not None:
            weights = compose.project(self.projection_, beta)
            return Animation(weights=weights, rig=self.rig_, **common)
        vertices = compose.world_vertices(self.character_, beta, obs.head_motion)
        return Animation(vertices=vertices, triangles=self.triangles_, **common)

    def deconstruct(self, source: Source) -> dict:
        """The actor side only: layered parameters and how well they explain the markers (Fig. 8).

        Returns a dict with ``layer_weights (F, m, J)`` (w_jl, row = region), ``coefficients
        {layer: (F, K_j)}``, ``layer_names``, ``region_names``,
        ``head_motion (F, 4, 4)``, ``lip_gamma (F,)``, ``objective (F,)``,
        ``reconstruction (F, N, 3)`` (the 3D markers Eq. 4 predicts, world coordinates) and
        ``rms_error (F,)`` (RMS distance to the observed markers, marker units).
        """
        self._check_fitted()
        markers, tracks, known = self._inputs(source)
        obs = self._observe(markers, tracks, known)
        params, _ = self._extract(obs)
        actor = self.actor_
        beta = compose.region_coefficients(params.weights, params.coefficients, actor.layer_of)
        flat = beta.reshape(beta.shape[0], -1) @ actor.projector_t  # (F, C): Eq. 4 inside the brackets, normalised
        local = flat[:, : 3 * actor.n3].reshape(-1, actor.n3, 3) * actor.scale3d + actor.reference3d
        rot, trans = obs.head_motion[:, :3, :3], obs.head_motion[:, :3, 3]
        world = np.einsum("fij,fpj->fpi", rot, local) + trans[:, None, :]
        dist2 = np.sum((world - np.asarray(markers, dtype=np.float64)) ** 2, axis=-1)
        out = self._extras(params)
        out.update(head_motion=obs.head_motion, reconstruction=world,
                   rms_error=np.sqrt(np.nanmean(dist2, axis=1)))
        return out

    def _extras(self, params) -> dict:
        actor = self.actor_
        offsets = actor.offsets
        return {
            "layer_weights": params.weights,
            "layer_names": actor.layer_names,
            "region_names": actor.region_names,
            "coefficients": {n: params.coefficients[:, offsets[j]:offsets[j + 1]] for j, n in enumerate(actor.layer_names)},
            "lip_gamma": params.gamma,
            "objective": params.objective,
        }

    def _diagnostics(self, params) -> dict:
        lip = self.lip_
        return {
            "lip_markers": list(lip.names) if lip.enabled else None,
            "lip_bias": lip.note or "on",
            "mouth_region": self.actor_.region_names[lip.mouth] if lip.enabled else None,
            "mean_iterations": float(np.mean(params.iterations)),
            "max_iterations": int(np.max(params.iterations)),
        }

    # -- streaming -------------------------------------------------------------------
    def stream(self, frames: Iterable) -> Iterator[np.ndarray]:
        """Retarget frame by frame (the model is first-order Markov); yields ``(V, 3)`` world vertices.

        Each item is ``markers (N, 3)`` (NaN = missing), a source mesh frame ``(V_src, 3)``
        when fitted on a mesh source (sampled at its landmarks), a pair ``(markers,
        tracks2d (N2, 2))``, or a dict with ``"markers"``, optional ``"tracks2d"`` and
        ``"head_motion" (4, 4)``. The result equals :meth:`retarget` on the same frames
        (up to rounding) when the batch source carries no known head motion.
        """
        self._check_fitted()
        return self._stream(iter(frames))

    def _stream(self, frames: Iterator) -> Iterator[np.ndarray]:
        state = None
        for index, item in enumerate(frames):
            markers, tracks, head = self._parse_frame(item, index)
            obs = self._observe(markers[None], None if tracks is None else tracks[None], None if head is None else head[None], index)
            params, state = self._extract(obs, state)
            beta = compose.region_coefficients(params.weights, params.coefficients, self.actor_.layer_of)
            if self.projection_ is not None:
                local = self.rig_.evaluate(compose.project(self.projection_, beta))
                rot, trans = obs.head_motion[0, :3, :3], obs.head_motion[0, :3, 3]
                yield local[0] @ rot.T + trans
            else:
                yield compose.world_vertices(self.character_, beta, obs.head_motion)[0]

    def _parse_frame(self, item, index: int):
        tracks = head = None
        if isinstance(item, dict):
            markers, tracks, head = item.get("markers"), item.get("tracks2d"), item.get("head_motion")
        elif isinstance(item, tuple):
            if len(item) != 2:
                raise ShapeError(f"stream: frame {index} is a tuple of {len(item)}; expected (markers, tracks2d)")
            markers, tracks = item
        else:
            markers = item
        pts = np.asarray(markers, dtype=np.float64)
        if (self.source_landmarks_ is not None and pts.ndim == 2 and pts.shape[0] == self.source_vertex_count_
                and pts.shape[0] != self.actor_.n3):
            pts = self.source_landmarks_.positions(pts, self.source_triangles_)
        if pts.ndim != 2 or pts.shape != (self.actor_.n3, 3):
            raise ShapeError(f"stream: frame {index} has shape {pts.shape}; expected ({self.actor_.n3}, 3) markers")
        if self.actor_.n2 and tracks is None:
            raise CapabilityError(f"stream: the model uses {self.actor_.n2} 2D tracks; pass (markers, tracks2d) pairs")
        if tracks is not None:
            tracks = np.asarray(tracks, dtype=np.float64)
            if not self.actor_.n2:
                tracks = None
        if head is not None:
            head = np.asarray(head, dtype=np.float64)
            if head.shape != (4, 4):
                raise ShapeError(f"stream: frame {index} head_motion must be (4, 4), got {head.shape}")
        return pts, tracks, head
