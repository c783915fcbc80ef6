"""Evaluation cases with known answers: parallel rigs driven by the same weights.

A :class:`Case` holds a :class:`~faceretarget.model.Source`, a
:class:`~faceretarget.model.TargetRig` and the ground-truth
:class:`~faceretarget.model.Animation` (the target rig driven by the source's
true weights, with the same rigid head motion), so that::

    case = faceretarget.cases.synthetic()
    anim = faceretarget.get(name).fit(case.source, case.target).retarget(case.source)
    error = anim.vertices - case.truth.vertices

Four generators:

- :func:`synthetic`: procedural parallel rigs on a face-like open surface with eye and
  mouth holes, defined over a shared (u, v) parameter domain so every blendshape means
  the same thing on source and target (see ``_shape_fields``); any resolution.
- :func:`ict`: real parallel rigs from the ICT-FaceKit face region (committed fixture
  ``data/ict_face_fixture.npz``, MIT licence in ``data/ICT-FaceKit-LICENSE.txt``).
- :func:`cross_rig`: a pair of *different* rigs built from the ICT data like a real
  production pair (a remeshed source in metres, ~2K vertices; the ICT-topology target in
  centimetres; same-named shapes whose deltas differ), driven by sparse held weight curves
  with blinks and speech bursts (committed fixture ``data/ict_cross_rig_fixture.npz``).
- :func:`cross_topology`: a source of another topology like a scanned head: eyes closed
  with the lid holes filled, a mouth bag, the forehead cut lower and a skirt beyond the
  outline (2,357 vertices), onto the open-eye ICT face; the same generic shapes on both
  (committed fixture ``data/ict_cross_topology_fixture.npz``). ``wrinkles=True``: a denser
  (once-subdivided, 9,313-vertex) source, and wrinkles carried to the truth through the
  case's exact correspondence.

All carry every rig part a built-in method may need (dense source mesh sequence with
landmarks = marker layout, feature lines, example pose pairs, actor layers over the
markers; target blendshapes, layered poses with region masks, landmarks, feature lines,
examples). For :func:`synthetic` and :func:`ict` the frame weights are generated from the
layered model of :mod:`faceretarget.recipes` (per frame a convex emotion mix + a convex
viseme mix + a blink), so the layered description is exact; :func:`cross_rig` gives its
own animation-like curves, which the layers only approximate.
"""

from __future__ import annotations

import copy
import functools
from collections.abc import Callable, Iterable, Mapping, Sequence
from dataclasses import dataclass, field
from importlib import resources
from typing import TYPE_CHECKING, Any, NamedTuple

import numpy as np
import numpy.typing as npt

from . import recipes
from ._validate import as_fps
from .correspond.topology import boundary_loops
from .errors import InputError, UnknownNameError
from .model import (
    Animation,
    BlendshapeRig,
    Landmarks,
    LayeredRig,
    MarkerSequence,
    Mesh,
    MeshSequence,
    Source,
    TargetRig,
    apply_head_motion,
)

if TYPE_CHECKING:
    import scipy.sparse as sp
    from scipy.spatial import cKDTree

__all__ = [
    "Case",
    "synthetic",
    "ict",
    "cross_rig",
    "cross_topology",
    "face_surface",
    "CASES",
    "get_case",
    "MARKER_LAYOUT",
    "EMOTION_LAYER",
    "SPEECH_LAYER",
    "BLINK_LAYER",
    "EXAMPLES",
]

#: Poses of the three layers (names of recipes in :mod:`faceretarget.recipes`).
EMOTION_LAYER = ("neutral", "happiness", "sadness", "anger", "surprise", "disgust")
SPEECH_LAYER = ("MBP", "AA", "E", "O", "U", "FV", "L", "WQ", "CH")
BLINK_LAYER = ("open", "closed")
#: The 7 example pose pairs: (name, recipe table, recipe name).
EXAMPLES = (
    ("neutral", "emotion", "neutral"),
    ("happiness", "emotion", "happiness"),
    ("sadness", "emotion", "sadness"),
    ("surprise", "emotion", "surprise"),
    ("jaw_open", "viseme", "AA"),
    ("pucker", "viseme", "WQ"),
    ("blink", "blink", "closed"),
)
#: Region masks: names, and the softness of their borders as a fraction of face height.
REGION_NAMES = ("upper_face", "eyes", "mouth_jaw")
_MASK_SOFTNESS = 0.02
#: Head motion amplitudes: rotation (degrees) and translation (fraction of face height).
_HEAD_ROTATION_DEG = 10.0
_HEAD_TRANSLATION = 0.05


@dataclass(frozen=True)
class Case:
    """An evaluation case.

    Attributes
    ----------
    name : str
    source : Source
    target : TargetRig
    truth : Animation or None
        The right answer (target vertices with head motion), if known.
    meta : dict
        ``weights`` (F, M) true weights, ``weight_names``, ``layer_coefficients``
        {layer: (F, K) convex coefficients}, ``layer_recipes`` {layer: (K, M) weights of
        each pose}, so ``weights = sum_layer coefficients @ recipes`` (:func:`cross_rig`:
        ``layer_coefficients`` is None, its curves are not layered); ``head_motion``
        (F, 4, 4) (also inside the source vertices and the truth; ``source.head_motion``
        is None so methods estimate it); ``face_height`` (target, mesh units),
        ``source_face_height``, ``unmapped_recipe_names``, ``seed``; :func:`synthetic`
        adds ``source_uv`` / ``target_uv`` (vertex parameters), ``boundary_loops``,
        ``target_kind``, ``wrinkles``; :func:`ict` adds ``expressions``; :func:`cross_rig`
        adds ``source_kind``, ``unit_scale``, ``source_correspondence``, ``perturbation``.
    """

    name: str
    source: Source
    target: TargetRig
    truth: Animation | None
    meta: dict = field(default_factory=dict)

    def __repr__(self) -> str:
        return f"Case({self.name!r}: {self.source!r} -> {self.target!r})"


# =======================================================================================
# Shared pieces: weight curves, head motion, layers, masks
# =======================================================================================
def _sigmoid(x: npt.ArrayLike) -> np.ndarray:
    """The logistic function 1 / (1 + exp(-x)), overflow-free (scipy.special costs 0.6 s to import)."""
    return 0.5 * (1.0 + np.tanh(0.5 * np.asarray(x, dtype=np.float64)))


def _interpolate_keys(key_frames: np.ndarray, key_values: np.ndarray, n_frames: int) -> np.ndarray:
    """Smoothstep interpolation of ``key_values (K, D)`` at increasing ``key_frames`` -> (F, D).

    Each frame is a convex combination of two consecutive keys, so convex keys give
    convex frames.
    """
    frames = np.arange(n_frames, dtype=np.float64)
    k = np.clip(np.searchsorted(key_frames, frames, side="right") - 1, 0, len(key_frames) - 2)
    span = key_frames[k + 1] - key_frames[k]
    s = np.clip((frames - key_frames[k]) / span, 0.0, 1.0)
    s = s * s * (3.0 - 2.0 * s)
    return (1.0 - s)[:, None] * key_values[k] + s[:, None] * key_values[k + 1]


def _cycling_choice(rng: np.random.Generator, choices: int, count: int) -> np.ndarray:
    """``count`` picks from ``range(choices)`` cycling through random permutations (all appear)."""
    reps = -(-count // choices)
    return np.concatenate([rng.permutation(choices) for _ in range(reps)])[:count]


def _layer_curves(
    rng: np.random.Generator, n_frames: int, fps: float, n_emotions: int, n_visemes: int
) -> dict[str, np.ndarray]:
    """Layer coefficients: emotion (F, Ke) and speech (F, Ks) convex, blink (F, 2) convex."""
    # emotion: a key every 0.8-1.6 s, starting neutral; each key mixes one emotion with neutral
    times = [0.0]
    while times[-1] < n_frames:
        times.append(times[-1] + rng.uniform(0.8, 1.6) * fps)
    n_keys = len(times)
    picks = 1 + _cycling_choice(rng, n_emotions - 1, n_keys)
    keys = np.zeros((n_keys, n_emotions))
    keys[0, 0] = 1.0
    for i in range(1, n_keys):
        s = rng.uniform(0.55, 1.0) if rng.random() > 0.15 else 0.0
        keys[i, 0] = 1.0 - s
        keys[i, picks[i]] += s
    emotion = _interpolate_keys(np.asarray(times), keys, n_frames)

    # speech: words of 2-5 visemes (3-6 frames each) between closed-lips pauses
    t = float(rng.integers(4, 9))
    key_t, key_v = [0.0], [0]
    n_spoken = 0
    pool = _cycling_choice(rng, n_visemes - 1, 4 * n_frames) + 1
    while t < n_frames:
        for _ in range(int(rng.integers(2, 6))):
            t += rng.uniform(3.0, 6.0) * fps / 30.0
            key_t.append(t)
            key_v.append(int(pool[n_spoken]))
            n_spoken += 1
        t += rng.uniform(4.0, 12.0) * fps / 30.0
        key_t.append(t)
        key_v.append(0)
        t += rng.uniform(2.0, 8.0) * fps / 30.0
    key_t.append(max(t, n_frames) + 1.0)
    key_v.append(0)
    skeys = np.zeros((len(key_v), n_visemes))
    amp = rng.uniform(0.7, 1.0, len(key_v))
    skeys[np.arange(len(key_v)), key_v] = amp
    skeys[:, 0] += 1.0 - amp
    speech = _interpolate_keys(np.asarray(key_t), skeys, n_frames)

    # blink: a 9-frame (at 30 fps) close-hold-open pulse every 1.5-3.5 s
    blink = np.zeros(n_frames)
    frames = np.arange(n_frames, dtype=np.float64)
    start = rng.uniform(0.3, 1.2) * fps
    unit = fps / 30.0
    while start < n_frames:
        depth = rng.uniform(0.85, 1.0)
        x = (frames - start) / unit
        closing = np.clip(x / 3.0, 0.0, 1.0)
        opening = np.clip((x - 4.0) / 5.0, 0.0, 1.0)
        pulse = np.where(
            x < 4.0,
            closing * closing * (3 - 2 * closing),
            1.0 - opening * opening * (3 - 2 * opening),
        )
        blink = np.maximum(blink, depth * np.where((x >= 0) & (x <= 9.0), pulse, 0.0))
        start += rng.uniform(1.5, 3.5) * fps
    blinks = np.stack([1.0 - blink, blink], axis=1)
    return {"emotion": emotion, "speech": speech, "blink": blinks}


def _layer_recipe_matrices(names: Sequence[str]) -> tuple[dict[str, np.ndarray], list[str]]:
    """Recipe weight vectors of the three layers on a rig with shapes ``names``; unmapped names."""
    tables = {
        "emotion": (recipes.EMOTIONS, EMOTION_LAYER),
        "speech": (recipes.VISEMES, SPEECH_LAYER),
        "blink": (recipes.BLINKS, BLINK_LAYER),
    }
    unmapped: list[str] = []
    out = {}
    for layer, (table, poses) in tables.items():
        out[layer] = recipes.resolve_all(table, names, names=poses, on_unmapped="ignore")
        for p in poses:
            unmapped += [n for n in recipes.unmapped_names(table[p], names) if n not in unmapped]
    return out, unmapped


def _example_weights(names: Sequence[str]) -> np.ndarray:
    tables = {"emotion": recipes.EMOTIONS, "viseme": recipes.VISEMES, "blink": recipes.BLINKS}
    return np.stack(
        [recipes.resolve(tables[t][r], names, on_unmapped="ignore") for _, t, r in EXAMPLES]
    )


def _head_motion(
    rng: np.random.Generator,
    n_frames: int,
    fps: float,
    pivot: np.ndarray,
    height: float,
    enabled: bool,
) -> np.ndarray:
    """(F, 4, 4) smooth rigid motion about ``pivot`` (the neck), identity at frame 0."""
    out = np.tile(np.eye(4), (n_frames, 1, 1))
    if not enabled:
        return out
    t = np.arange(n_frames) / fps

    def smooth_curve(amplitude: float) -> np.ndarray:
        freqs = rng.uniform(0.08, 0.6, 3)
        phases = rng.uniform(0.0, 2 * np.pi, 3)
        amps = rng.uniform(0.4, 1.0, 3)
        c = (amps[:, None] * np.sin(2 * np.pi * freqs[:, None] * t[None] + phases[:, None])).sum(
            axis=0
        )
        c -= c[0]
        return amplitude * c / max(np.abs(c).max(), 1e-12)

    angles = np.deg2rad(
        [smooth_curve(_HEAD_ROTATION_DEG * f) for f in (0.6, 1.0, 0.4)]
    )  # pitch, yaw, roll
    trans = np.stack(
        [smooth_curve(_HEAD_TRANSLATION * height * f) for f in (1.0, 0.6, 0.8)], axis=1
    )
    cx, sx = np.cos(angles[0]), np.sin(angles[0])
    cy, sy = np.cos(angles[1]), np.sin(angles[1])
    cz, sz = np.cos(angles[2]), np.sin(angles[2])
    one, zero = np.ones(n_frames), np.zeros(n_frames)
    rx = np.stack([one, zero, zero, zero, cx, -sx, zero, sx, cx], 1).reshape(-1, 3, 3)
    ry = np.stack([cy, zero, sy, zero, one, zero, -sy, zero, cy], 1).reshape(-1, 3, 3)
    rz = np.stack([cz, -sz, zero, sz, cz, zero, zero, zero, one], 1).reshape(-1, 3, 3)
    rot = rz @ ry @ rx
    out[:, :3, :3] = rot
    out[:, :3, 3] = pivot - rot @ pivot + trans
    return out


def _region_masks(
    height_coord: np.ndarray, upper_cut: float, lower_cut: float, softness: float
) -> np.ndarray:
    """(3, P) smooth nonnegative masks summing to 1: above ``upper_cut``, between, below ``lower_cut``."""
    upper = _sigmoid((height_coord - upper_cut) / softness)
    lower = _sigmoid((lower_cut - height_coord) / softness)
    middle = np.clip(1.0 - upper - lower, 0.0, None)
    masks = np.stack([upper, middle, lower])
    return masks / masks.sum(axis=0, keepdims=True)


class _Side(NamedTuple):
    """One face of a parallel-rig pair: its rig, landmarks, feature lines and region masks (3, V)."""

    rig: BlendshapeRig
    landmarks: Landmarks
    feature_lines: dict
    masks: np.ndarray


def _assemble(
    name: str,
    src: _Side,
    tgt: _Side,
    *,
    n_frames: int,
    fps: float,
    seed: int,
    head_motion: bool,
    pivot: np.ndarray,
    meta: dict,
    weights: np.ndarray | None = None,
    source_kind: str = "mesh",
    unit_scale: float = 1.0,
) -> Case:
    """Build the Source, TargetRig and truth from two parallel rigs (shared by the generators).

    ``weights`` (F, M): the weight curves to use (default: generated from the layered
    model). ``source_kind``: "mesh" (a MeshSequence with ``src.landmarks``) or "markers"
    (a MarkerSequence of the landmark positions, named like them). ``unit_scale``: target
    units per source unit; the truth's head motion is the source's with its translation
    scaled by it (the same motion seen in the target's units).
    """
    source_rig, target_rig = src.rig, tgt.rig
    rng = np.random.default_rng(seed)
    names = source_rig.names
    layer_w, unmapped = _layer_recipe_matrices(names)
    if weights is None:
        coeffs = _layer_curves(rng, n_frames, fps, len(EMOTION_LAYER), len(SPEECH_LAYER))
        weights = sum(coeffs[k] @ layer_w[k] for k in ("emotion", "speech", "blink"))
    else:
        coeffs = None
    source_height = source_rig.neutral.height
    motion = _head_motion(rng, n_frames, fps, pivot, source_height, head_motion)
    target_motion = motion
    if unit_scale != 1.0:
        target_motion = motion.copy()
        target_motion[:, :3, 3] *= unit_scale

    source_neutral = source_rig.neutral
    ex_w = _example_weights(names)
    ex_names = [e[0] for e in EXAMPLES]
    src_tri = source_neutral.triangles

    def at_landmarks(points: np.ndarray) -> np.ndarray:
        """(..., V, 3) source points -> (..., N, 3) at the source landmarks."""
        return src.landmarks.positions(points, src_tri)

    if source_kind == "markers":  # the rig sampled at the markers, not the whole mesh
        lm_deltas = at_landmarks(source_rig.deltas)
        local = at_landmarks(source_neutral.vertices) + (
            weights @ lm_deltas.reshape(len(lm_deltas), -1)
        ).reshape(len(weights), -1, 3)
    else:
        local = source_rig.evaluate(weights)
    # identity motion leaves the points bit-identical: skip the (F, V, 3) product
    world = apply_head_motion(motion, local) if head_motion else local

    def poses(rig: BlendshapeRig, on_landmarks: bool = False) -> dict[str, np.ndarray]:
        out = {}
        for layer, w in layer_w.items():
            p = rig.evaluate(w)
            out[layer] = at_landmarks(p) if on_landmarks else p
        return out

    pose_names = {
        "emotion": list(EMOTION_LAYER),
        "speech": list(SPEECH_LAYER),
        "blink": list(BLINK_LAYER),
    }
    landmark_masks = at_landmarks(src.masks[:, :, None])[:, :, 0]
    actor_layers = LayeredRig(
        poses(source_rig, True), landmark_masks, pose_names=pose_names, region_names=REGION_NAMES
    )
    performance: MarkerSequence | MeshSequence
    if source_kind == "markers":
        performance = MarkerSequence(
            world,
            names=src.landmarks.names,
            fps=fps,
            reference=at_landmarks(source_neutral.vertices),
        )
        parts: dict[str, Any] = dict(examples=at_landmarks(source_rig.evaluate(ex_w)))
    else:
        performance = MeshSequence(
            world,
            source_neutral.triangles,
            fps=fps,
            reference=source_neutral,
            name=f"{name} source",
        )
        parts = dict(
            landmarks=src.landmarks,
            feature_lines=src.feature_lines,
            examples=source_rig.evaluate(ex_w),
        )
    source = Source(
        performance,
        **parts,
        example_names=ex_names,
        rig=source_rig,
        actor_layers=actor_layers,
        name=f"{name} source",
    )
    target = TargetRig(
        target_rig.neutral,
        blendshapes=target_rig,
        layers=LayeredRig(
            poses(target_rig), tgt.masks, pose_names=pose_names, region_names=REGION_NAMES
        ),
        landmarks=tgt.landmarks,
        feature_lines=tgt.feature_lines,
        examples=target_rig.evaluate(_example_weights(target_rig.names)),
        example_names=ex_names,
        name=f"{name} target",
    )
    truth = Animation(
        weights=weights,
        rig=target_rig,
        head_motion=target_motion,
        fps=fps,
        provenance={"method": "ground truth"},
    )
    meta = dict(meta)
    meta.update(
        weights=weights,
        weight_names=tuple(names),
        layer_coefficients=coeffs,
        layer_recipes=layer_w,
        head_motion=motion,
        face_height=target_rig.neutral.height,
        source_face_height=source_height,
        unmapped_recipe_names=unmapped,
    )
    return Case(name, source, target, truth, meta)


# =======================================================================================
# Synthetic parallel rigs
# =======================================================================================
# The parameter domain: an ellipse |(u, v / 1.3)| <= 1 (u to the character's left = +x,
# v up), with elliptic holes for the eyes and the mouth.
_OUTER = (0.0, 0.0, 1.0, 1.3)
_EYE_C, _EYE_A, _EYE_B = (0.38, 0.30), 0.17, 0.065
_MOUTH_C, _MOUTH_A, _MOUTH_B = (0.0, -0.60), 0.32, 0.05
_HOLES = {
    "eye_L": (_EYE_C[0], _EYE_C[1], _EYE_A, _EYE_B),
    "eye_R": (-_EYE_C[0], _EYE_C[1], _EYE_A, _EYE_B),
    "mouth_inner": (_MOUTH_C[0], _MOUTH_C[1], _MOUTH_A, _MOUTH_B),
}
_OUTER_LIP = (_MOUTH_C[0], _MOUTH_C[1] - 0.005, 0.37, 0.13)
#: Wavelength of the wrinkle fields in parameter units (about 0.8 cm on the source face).
_WRINKLE_WAVELENGTH = 0.1

#: Face proportions (cm; y up, looking along +z). ``eye_zoom`` and ``mouth_widen``
#: magnify the parameter domain around the eyes / mouth (stylized faces).
_FACES = {
    "actor": dict(
        sx=8.0,
        sy=8.0,
        taper=0.08,
        depth=6.0,
        curve_u=0.55,
        curve_v=0.18,
        nose=2.2,
        brow=0.5,
        socket=0.8,
        lips=0.6,
        chin=0.6,
        cheek=0.5,
        snout=0.0,
        eye_zoom=0.0,
        mouth_widen=0.0,
    ),
    "human": dict(
        sx=8.9,
        sy=8.5,
        taper=0.02,
        depth=7.0,
        curve_u=0.6,
        curve_v=0.22,
        nose=2.7,
        brow=0.7,
        socket=1.0,
        lips=0.8,
        chin=0.9,
        cheek=0.7,
        snout=0.0,
        eye_zoom=0.08,
        mouth_widen=0.05,
    ),
    "stylized": dict(
        sx=9.6,
        sy=7.2,
        taper=-0.06,
        depth=5.0,
        curve_u=0.5,
        curve_v=0.15,
        nose=1.4,
        brow=0.3,
        socket=0.6,
        lips=0.5,
        chin=0.4,
        cheek=0.9,
        snout=3.2,
        eye_zoom=0.7,
        mouth_widen=0.35,
    ),
}


#: The 54-marker layout: name -> (u, v) on the parameter domain ("_L" = character's left, +u).
def _marker_layout() -> dict[str, tuple[float, float]]:
    out: dict[str, tuple[float, float]] = {
        "forehead_L": (0.35, 0.85),
        "forehead_C": (0.0, 0.92),
        "forehead_R": (-0.35, 0.85),
    }
    for side, sg in (("L", 1.0), ("R", -1.0)):
        for i, (u, v) in enumerate(((0.15, 0.50), (0.30, 0.53), (0.45, 0.52), (0.60, 0.47)), 1):
            out[f"brow_{side}_{i}"] = (sg * u, v)
    for side, sg in (("L", 1.0), ("R", -1.0)):
        cu, cv = sg * _EYE_C[0], _EYE_C[1]
        out[f"eye_{side}_inner"] = (cu - sg * _EYE_A, cv)
        out[f"eye_{side}_outer"] = (cu + sg * _EYE_A, cv)
        out[f"eye_{side}_upper"] = (cu, cv + _EYE_B)
        out[f"eye_{side}_lower"] = (cu, cv - _EYE_B)
    out.update(
        {
            "nose_bridge": (0.0, 0.2),
            "nose_tip": (0.0, -0.28),
            "nose_L": (0.13, -0.3),
            "nose_R": (-0.13, -0.3),
            "nose_base": (0.0, -0.42),
        }
    )
    for side, sg in (("L", 1.0), ("R", -1.0)):
        for i, (u, v) in enumerate(((0.45, 0.1), (0.7, 0.05), (0.5, -0.25), (0.75, -0.4)), 1):
            out[f"cheek_{side}_{i}"] = (sg * u, v)
    mc_u, mc_v = _MOUTH_C
    out["mouth_corner_L"] = (mc_u + _MOUTH_A, mc_v)
    out["mouth_corner_R"] = (mc_u - _MOUTH_A, mc_v)
    for i, u in enumerate((-0.2, -0.1, 0.0, 0.1, 0.2), 1):
        dv = _MOUTH_B * np.sqrt(1.0 - (u / _MOUTH_A) ** 2)
        out[f"lip_upper_{i}"] = (u, mc_v + dv)
        out[f"lip_lower_{i}"] = (u, mc_v - dv)
    out["chin"] = (0.0, -1.0)
    out["chin_lower"] = (0.0, -1.18)
    for side, sg in (("L", 1.0), ("R", -1.0)):
        for i, (u, v) in enumerate(((0.3, -1.0), (0.55, -0.85), (0.75, -0.6), (0.88, -0.3)), 1):
            out[f"jaw_{side}_{i}"] = (sg * u, v)
    return out


MARKER_LAYOUT = _marker_layout()


def _ellipse_loop(cu: float, cv: float, a: float, b: float, spacing: float) -> np.ndarray:
    """(n, 2) points on an ellipse at equal arc length ~``spacing``, counter-clockwise from angle 0."""
    t = np.linspace(0.0, 2 * np.pi, 4097)
    pts = np.stack([cu + a * np.cos(t), cv + b * np.sin(t)], axis=1)
    arc = np.concatenate([[0.0], np.cumsum(np.linalg.norm(np.diff(pts, axis=0), axis=1))])
    n = max(int(np.ceil(arc[-1] / spacing)), 12)
    s = np.arange(n) * arc[-1] / n
    tt = np.interp(s, arc, t)
    return np.stack([cu + a * np.cos(tt), cv + b * np.sin(tt)], axis=1)


def _ellipse_distance(
    p: np.ndarray, cu: float, cv: float, a: float, b: float
) -> tuple[np.ndarray, np.ndarray]:
    """Normalized radius q (q < 1 inside) and approximate signed distance (q - 1) / |grad q|."""
    du, dv = (p[:, 0] - cu) / a, (p[:, 1] - cv) / b
    q = np.sqrt(du * du + dv * dv)
    with np.errstate(divide="ignore", invalid="ignore"):
        grad = np.sqrt((du / a) ** 2 + (dv / b) ** 2) / q
        dist = (q - 1.0) / grad
    return q, np.where(np.isfinite(dist), dist, -np.inf)


def _uv_mesh(resolution: int) -> tuple[np.ndarray, np.ndarray, dict[str, np.ndarray]]:
    """Triangulated parameter domain with about ``resolution`` vertices.

    Returns ``uv (V, 2)``, ``triangles (T, 3)`` (counter-clockwise in uv) and the boundary
    loops ``{name: vertex ids}`` ("outline", "eye_L", "eye_R", "mouth_inner").
    """
    from scipy.spatial import Delaunay

    area = np.pi * (_OUTER[2] * _OUTER[3] - 2 * _EYE_A * _EYE_B - _MOUTH_A * _MOUTH_B)
    h = np.sqrt(2.0 * area / (np.sqrt(3.0) * max(int(resolution), 60)))
    loops = {"outline": _ellipse_loop(*_OUTER, h)}
    for k, e in _HOLES.items():
        loops[k] = _ellipse_loop(*e, 0.9 * h)
    # hexagonal lattice (equilateral triangles away from the boundaries)
    rows = np.arange(-_OUTER[3], _OUTER[3] + h, h * np.sqrt(3.0) / 2.0)
    cols = np.arange(-_OUTER[2] - h, _OUTER[2] + h, h)
    gu, gv = np.meshgrid(cols, rows)
    gu = gu + (np.arange(len(rows)) % 2)[:, None] * (h / 2.0)
    lattice = np.stack([gu.ravel(), gv.ravel()], axis=1)
    margin = 0.55 * h
    keep = _ellipse_distance(lattice, *_OUTER)[1] < -margin
    for e in _HOLES.values():
        q, d = _ellipse_distance(lattice, *e)
        keep &= (q > 1.0) & (d > margin)
    lattice = lattice[keep]
    starts, offset = {}, 0
    for k, pts in loops.items():
        starts[k] = np.arange(offset, offset + len(pts))
        offset += len(pts)
    uv = np.concatenate(list(loops.values()) + [lattice])
    tri = Delaunay(uv).simplices.astype(np.int64)
    centroid = uv[tri].mean(axis=1)
    inside = np.zeros(len(tri), dtype=bool)
    for e in _HOLES.values():
        inside |= _ellipse_distance(centroid, *e)[0] < 1.0
    tri = tri[~inside]
    a, b, c = uv[tri[:, 0]], uv[tri[:, 1]], uv[tri[:, 2]]
    signed = (b[:, 0] - a[:, 0]) * (c[:, 1] - a[:, 1]) - (b[:, 1] - a[:, 1]) * (c[:, 0] - a[:, 0])
    tri[signed < 0] = tri[signed < 0][:, [0, 2, 1]]
    tri = tri[np.abs(signed) > 1e-9 * h * h]
    used = np.zeros(len(uv), dtype=bool)
    used[tri] = True
    if not used.all():  # compact (a lattice point cut off by the holes)
        remap = np.cumsum(used) - 1
        tri = remap[tri]
        starts = {k: remap[v[used[v]]] for k, v in starts.items()}
        uv = uv[used]
    return uv, tri, starts


def _warp(uv: np.ndarray, face: dict) -> np.ndarray:
    """Parameter-space magnification around the eyes and widening of the mouth (stylized faces)."""
    u, v = uv[:, 0].copy(), uv[:, 1].copy()
    if face["eye_zoom"]:
        du_total = np.zeros_like(u)
        dv_total = np.zeros_like(v)
        for sg in (1.0, -1.0):
            du, dv = u - sg * _EYE_C[0], v - _EYE_C[1]
            g = face["eye_zoom"] * np.exp(-((du / 0.26) ** 2) - ((dv / 0.17) ** 2))
            du_total += du * g
            dv_total += dv * g
        u, v = u + du_total, v + dv_total
    if face["mouth_widen"]:
        u = u + face["mouth_widen"] * u * np.exp(
            -((u / 0.5) ** 2) - (((v - _MOUTH_C[1]) / 0.28) ** 2)
        )
    return np.stack([u, v], axis=1)


def _base_map(p: np.ndarray, face: dict) -> np.ndarray:
    """The smooth 'cage' of a face (no features): scales, taper and a curved depth."""
    u, v = p[:, 0], p[:, 1]
    x = face["sx"] * u * (1.0 + face["taper"] * v)
    y = face["sy"] * v
    z = face["depth"] * (1.0 - face["curve_u"] * u * u - face["curve_v"] * v * v)
    return np.stack([x, y, z], axis=1)


def _g(u: np.ndarray, v: np.ndarray, cu: float, cv: float, su: float, sv: float) -> np.ndarray:
    return np.exp(-(((u - cu) / su) ** 2) - (((v - cv) / sv) ** 2))


def _features(p: np.ndarray, face: dict) -> np.ndarray:
    """Depth offsets (cm) of the facial features at warped parameters ``p``."""
    u, v = p[:, 0], p[:, 1]
    z = face["nose"] * (_g(u, v, 0.0, -0.12, 0.11, 0.26) + 0.5 * _g(u, v, 0.0, -0.3, 0.16, 0.1))
    z += face["brow"] * np.exp(-(((v - 0.5) / 0.1) ** 2) - (u / 0.8) ** 4)
    z -= face["socket"] * (
        _g(u, v, _EYE_C[0], _EYE_C[1], 0.22, 0.14) + _g(u, v, -_EYE_C[0], _EYE_C[1], 0.22, 0.14)
    )
    z += face["lips"] * _g(u, v, 0.0, _MOUTH_C[1], 0.36, 0.12)
    z += face["chin"] * _g(u, v, 0.0, -1.05, 0.3, 0.15)
    z += face["cheek"] * (_g(np.abs(u), v, 0.5, -0.05, 0.2, 0.2))
    z += face["snout"] * _g(u, v, 0.0, -0.42, 0.45, 0.4)
    return z


def face_surface(uv: npt.ArrayLike, face: str = "actor") -> np.ndarray:
    """Points ``(P, 3)`` of a procedural face surface at parameter points ``uv (P, 2)``.

    ``face`` is "actor" (the synthetic source), "human" or "stylized" (the targets). The
    same ``uv`` on two faces are corresponding points, which gives the exact answer for
    cross-topology correspondence (``meta["source_uv"]`` / ``meta["target_uv"]`` of a
    synthetic case hold the vertices' parameters).
    """
    if face not in _FACES:
        raise UnknownNameError(
            f"face_surface: face must be one of {', '.join(_FACES)}, got {face!r}"
        )
    uv = np.asarray(uv, dtype=np.float64)
    if uv.ndim != 2 or uv.shape[1] != 2:
        raise InputError(f"face_surface: uv must be (P, 2), got {uv.shape}")
    return _embed(uv, _FACES[face])


def _embed(uv: np.ndarray, face: dict) -> np.ndarray:
    p = _warp(uv, face)
    x = _base_map(p, face)
    x[:, 2] += _features(p, face)
    return x


def _cage(uv: np.ndarray, face: dict) -> np.ndarray:
    """The smooth cage through the warp (features excluded): where tangential motion goes."""
    return _base_map(_warp(uv, face), face)


def _normals(uv: np.ndarray, face: dict, step: float = 1e-4) -> np.ndarray:
    """(P, 3) unit normals of the full surface at parameter points (central differences)."""
    eu, ev = np.array([step, 0.0]), np.array([0.0, step])
    xu = _embed(uv + eu, face) - _embed(uv - eu, face)
    xv = _embed(uv + ev, face) - _embed(uv - ev, face)
    n = np.cross(xu, xv)
    return n / np.linalg.norm(n, axis=1, keepdims=True)


def _segment_distance(
    u: np.ndarray, v: np.ndarray, a: Sequence[float], b: Sequence[float]
) -> tuple[np.ndarray, np.ndarray]:
    """Distance from points (u, v) to the segment a-b, and the position t in [0, 1] along it."""
    ab = np.subtract(b, a)
    t = np.clip(((u - a[0]) * ab[0] + (v - a[1]) * ab[1]) / (ab @ ab), 0.0, 1.0)
    return np.hypot(u - a[0] - t * ab[0], v - a[1] - t * ab[1]), t


def _shape_fields(
    uv: np.ndarray,
) -> dict[str, tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]]:
    """The expression recipes on the parameter domain.

    For every shape of :data:`recipes.RECIPE_SHAPES`: ``(du, dv, dn, wrinkle)``, each (P,):
    a tangential displacement in parameter units (carried to 3D through each face's
    smooth cage, so it scales with that face's features) and a normal offset plus a
    high-frequency wrinkle offset in source centimetres (scaled by the face's size).
    """
    u, v = uv[:, 0], uv[:, 1]
    zero = np.zeros_like(u)
    lam = _WRINKLE_WAVELENGTH
    mc_v = _MOUTH_C[1]
    lip = _g(u, v, 0.0, mc_v, 0.40, 0.13)
    upper = _sigmoid((v - mc_v) / 0.012)
    lower = 1.0 - upper
    mid = np.exp(-((u / 0.26) ** 4))
    out = {}

    width = 0.012 + 0.5 * np.maximum(np.abs(u) - 0.28, 0.0)
    jaw = _sigmoid((mc_v - v) / width) * np.exp(-((u / 0.85) ** 4))
    out["jawOpen"] = (zero, -0.24 * jaw, -0.4 * jaw * np.clip((mc_v - v) / 0.5, 0.0, 1.0), zero)
    out["mouthClose"] = (zero, 0.025 * lip * mid * (lower - upper), 0.05 * lip, zero)
    out["mouthFunnel"] = (-0.12 * u * lip, 0.05 * lip * mid * (upper - lower), 0.5 * lip, zero)
    out["mouthPucker"] = (-0.3 * u * lip, 0.015 * lip * mid * (lower - upper), 0.7 * lip, zero)
    out["mouthRollLower"] = (
        zero,
        0.025 * _g(u, v, 0.0, -0.68, 0.3, 0.07) * lower,
        -0.4 * _g(u, v, 0.0, -0.68, 0.3, 0.07) * lower,
        zero,
    )

    # forehead furrows (brow raise), glabella lines (brow lower), crow's feet, nasolabial fold
    furrows = np.sin(2 * np.pi * (v - 0.62) / lam)
    inner_brow = _g(np.abs(u), v, 0.16, 0.52, 0.2, 0.2)
    out["browInnerUp"] = (
        zero,
        0.07 * inner_brow + 0.03 * _g(u, v, 0.0, 0.8, 0.4, 0.3),
        zero,
        0.08 * _g(u, v, 0.0, 0.8, 0.35, 0.2) * furrows,
    )

    for side, sg in (("Left", 1.0), ("Right", -1.0)):
        su = sg * u  # mirrored coordinate: the recipe is written for the left side
        corner = _g(su, v, _MOUTH_A, mc_v, 0.18, 0.15)
        stretch = _g(su, v, 0.36, mc_v, 0.2, 0.16)
        pside = lip * _sigmoid(su / 0.1)
        fold_d, fold_t = _segment_distance(su, v, (0.14, -0.3), (0.42, -0.72))
        fold = -0.12 * np.exp(-((fold_d / 0.025) ** 2)) * np.sin(np.pi * fold_t) ** 0.5
        ec = (_EYE_C[0] + _EYE_A + 0.04, _EYE_C[1])
        r = np.hypot(su - ec[0], v - ec[1])
        crow = (
            np.exp(-(((r - 0.09) / 0.06) ** 2))
            * _sigmoid((su - ec[0] + 0.02) / 0.02)
            * np.sin(12.0 * np.arctan2(v - ec[1], su - ec[0]))
        )
        out[f"mouthSmile{side}"] = (
            sg * 0.08 * corner,
            0.07 * corner,
            -0.05 * corner + 0.3 * _g(su, v, 0.48, -0.3, 0.16, 0.15),
            fold + 0.03 * crow,
        )
        out[f"mouthFrown{side}"] = (sg * 0.02 * corner, -0.07 * corner, -0.05 * corner, zero)
        out[f"mouthStretch{side}"] = (sg * 0.07 * stretch, -0.025 * stretch, -0.1 * stretch, zero)
        out[f"mouthPress{side}"] = (zero, 0.02 * pside * mid * (lower - upper), -0.12 * pside, zero)
        uu = _g(su, v, 0.14, -0.52, 0.16, 0.09) * upper
        out[f"mouthUpperUp{side}"] = (zero, 0.055 * uu, 0.08 * uu, zero)

        x = (su - _EYE_C[0]) / _EYE_A
        # lid opening profile sqrt(1 - x^2), softened at the corners (finite slope there)
        s = (np.sqrt(np.clip(1.0 - x * x, 0.0, 1.0) + 0.15**2) - 0.15) / (
            np.sqrt(1.0 + 0.15**2) - 0.15
        )
        above = _sigmoid((v - _EYE_C[1]) / 0.01)
        up_fall = np.exp(-((np.maximum(v - (_EYE_C[1] + _EYE_B * s), 0.0) / 0.10) ** 2)) * above
        lo_fall = np.exp(-((np.maximum((_EYE_C[1] - _EYE_B * s) - v, 0.0) / 0.06) ** 2)) * (
            1.0 - above
        )
        lid = 2.0 * _EYE_B * s
        out[f"eyeBlink{side}"] = (
            zero,
            0.97 * lid * (-0.8 * up_fall + 0.2 * lo_fall),
            0.08 * up_fall * s,
            zero,
        )
        out[f"eyeWide{side}"] = (zero, lid * (0.25 * up_fall - 0.08 * lo_fall), zero, zero)

        outer_brow = _g(su, v, 0.55, 0.52, 0.2, 0.2)
        out[f"browOuterUp{side}"] = (
            zero,
            0.07 * outer_brow + 0.02 * _g(su, v, 0.5, 0.8, 0.3, 0.3),
            zero,
            0.07 * _g(su, v, 0.45, 0.8, 0.28, 0.2) * furrows,
        )
        down = _g(su, v, 0.33, 0.5, 0.25, 0.14)
        glabella = _g(su, v, 0.07, 0.45, 0.08, 0.1) * np.sin(2 * np.pi * u / (0.8 * lam))
        out[f"browDown{side}"] = (-sg * 0.035 * down, -0.05 * down, 0.12 * down, 0.06 * glabella)
        cheek = _g(su, v, 0.45, 0.12, 0.2, 0.12)
        out[f"cheekSquint{side}"] = (zero, 0.045 * cheek, 0.25 * cheek, 0.07 * crow)
        sneer = _g(su, v, 0.1, -0.22, 0.09, 0.12)
        bunny = _g(su, v, 0.07, 0.08, 0.07, 0.08) * np.sin(2 * np.pi * v / (0.6 * lam))
        out[f"noseSneer{side}"] = (
            zero,
            0.04 * sneer + 0.02 * _g(su, v, 0.05, 0.0, 0.1, 0.15),
            0.1 * sneer,
            0.05 * bunny,
        )
    return {k: out[k] for k in recipes.RECIPE_SHAPES}


def _synthetic_rig(
    uv: np.ndarray, triangles: np.ndarray, face: dict, wrinkles: bool, name: str
) -> BlendshapeRig:
    """The blendshape rig of one face over the parameter mesh ``uv``."""
    neutral = Mesh(_embed(uv, face), triangles, name=name, _trusted=True)
    normal = _normals(uv, face)
    rest = _cage(uv, face)
    scale = face["sy"] / _FACES["actor"]["sy"]
    fields = _shape_fields(uv)
    deltas = np.empty((len(fields), len(uv), 3))
    for i, (du, dv, dn, wr) in enumerate(fields.values()):
        deltas[i] = _cage(uv + np.stack([du, dv], axis=1), face) - rest
        deltas[i] += (scale * (dn + wr if wrinkles else dn))[:, None] * normal
    return BlendshapeRig(neutral, deltas, list(fields))


def _chain_near_curve(uv: np.ndarray, tree: cKDTree, curve: np.ndarray) -> np.ndarray:
    """Vertex chain following a closed parameter curve (nearest vertices, repeats removed)."""
    ids = tree.query(curve)[1]
    keep = np.ones(len(ids), dtype=bool)
    keep[1:] = ids[1:] != ids[:-1]
    ids = ids[keep]
    _, first = np.unique(ids, return_index=True)
    return ids[np.sort(first)]


def synthetic(
    seed: int = 0,
    resolution: int = 3000,
    target: str = "human",
    n_frames: int = 120,
    fps: float = 30.0,
    head_motion: bool = True,
    wrinkles: bool = True,
    target_resolution: int | None = None,
) -> Case:
    """A procedural parallel-rig case.

    Parameters
    ----------
    seed : int
        Seeds the weight curves and head motion (the geometry does not depend on it).
    resolution : int
        About this many source vertices (60 up to several 100K; built vectorized).
    target : "human" | "stylized"
        Other human proportions, or a stylized face (wider mouth, larger eyes, a snout).
    n_frames, fps : int, float
    head_motion : bool
        Smooth rigid head motion (about 10 degrees, 5% of face height) in the source
        vertices and the truth.
    wrinkles : bool
        Bake expression-driven wrinkle fields (forehead furrows, glabella lines, crow's
        feet, nasolabial folds, nose bunny lines) into both rigs' deltas.
    target_resolution : int, optional
        Triangulate the target separately with about this many vertices (a different
        topology); default: the source's triangulation.

    The face is y-up, looking along +z, about 21 cm tall (source). ``meta`` also holds
    ``source_uv`` / ``target_uv`` (the parameter coordinates of the vertices), which give
    the exact cross-topology correspondence.
    """
    if target not in ("human", "stylized"):
        raise UnknownNameError(f"synthetic: target must be 'human' or 'stylized', got {target!r}")
    _check_counts(n_frames=n_frames, resolution=resolution, target_resolution=target_resolution)
    from scipy.spatial import cKDTree

    uv, tri, loops = _uv_mesh(resolution)
    if target_resolution is None:
        t_uv, t_tri, t_loops = uv, tri, loops
    else:
        t_uv, t_tri, t_loops = _uv_mesh(target_resolution)
    src_face, tgt_face = _FACES["actor"], _FACES[target]
    source_rig = _synthetic_rig(uv, tri, src_face, wrinkles, "synthetic actor")
    target_rig = _synthetic_rig(t_uv, t_tri, tgt_face, wrinkles, f"synthetic {target}")

    marker_names = list(MARKER_LAYOUT)
    marker_uv = np.array([MARKER_LAYOUT[k] for k in marker_names])
    lip_curve = _ellipse_loop(*_OUTER_LIP, 0.01)
    sides = []
    for pts, lp in ((uv, loops), (t_uv, t_loops)):
        tree = cKDTree(pts)
        ids = tree.query(marker_uv)[1]
        # the target's markers sit nearest to the source marker vertices' parameters
        marker_uv = pts[ids]
        lines = {k: lp[k] for k in ("eye_L", "eye_R", "mouth_inner")}
        lines["mouth_outer"] = _chain_near_curve(pts, tree, lip_curve)
        sides.append((Landmarks(ids, names=marker_names), lines))
    (src_lm, src_lines), (tgt_lm, tgt_lines) = sides
    return _assemble(
        f"synthetic-{target}",
        _Side(source_rig, src_lm, src_lines, _uv_masks(uv)),
        _Side(target_rig, tgt_lm, tgt_lines, _uv_masks(t_uv)),
        n_frames=n_frames,
        fps=fps,
        seed=seed,
        head_motion=head_motion,
        pivot=np.array([0.0, -1.3 * src_face["sy"], -0.3 * src_face["depth"]]),
        meta={
            "seed": seed,
            "target_kind": target,
            "wrinkles": wrinkles,
            "source_uv": uv,
            "target_uv": t_uv,
            "boundary_loops": {"source": loops, "target": t_loops},
        },
    )


def _uv_masks(uv: np.ndarray) -> np.ndarray:
    """Region masks over the parameter domain: forehead/brows, eyes/nose, mouth/jaw."""
    return _region_masks(uv[:, 1], 0.42, -0.2, _MASK_SOFTNESS * 2 * _OUTER[3])


def _check_counts(**values: Any) -> None:
    for k, val in values.items():
        if val is None:
            continue
        if int(val) != val or val < 1:
            raise InputError(f"{k} must be a positive integer, got {val!r}")
    if values.get("resolution") is not None and values["resolution"] < 60:
        raise InputError(f"resolution must be at least 60 vertices, got {values['resolution']}")
    if values.get("target_resolution") is not None and values["target_resolution"] < 60:
        raise InputError(
            f"target_resolution must be at least 60 vertices, got {values['target_resolution']}"
        )


# =======================================================================================
# ICT-FaceKit parallel rigs
# =======================================================================================
_ICT_FIXTURE = "ict_face_fixture.npz"
#: Identity coefficients (on the 10 identity modes) of the default source and target.
ICT_SOURCE_IDENTITY = (1.2, -0.8, 0.6, 0.0, -0.5, 0.3, 0.0, 0.4, -0.3, 0.0)
ICT_TARGET_IDENTITY = (-1.5, 1.4, -0.9, 1.0, 0.8, -0.6, 0.7, -0.4, 0.5, -0.5)
#: Names of the 68 Multi-PIE landmarks ("_L" = character's left, +x).
ICT_LANDMARK_NAMES = tuple(
    [f"jaw_{i:02d}" for i in range(17)]
    + [f"brow_R_{i}" for i in range(1, 6)]
    + [f"brow_L_{i}" for i in range(1, 6)]
    + [f"nose_bridge_{i}" for i in range(1, 5)]
    + [f"nose_base_{i}" for i in range(1, 6)]
    + [f"eye_R_{i}" for i in range(1, 7)]
    + [f"eye_L_{i}" for i in range(1, 7)]
    + [f"lip_outer_{i:02d}" for i in range(1, 13)]
    + [f"lip_inner_{i}" for i in range(1, 9)]
)


def _load_ict_fixture() -> dict[str, np.ndarray]:
    path = resources.files("faceretarget") / "data" / _ICT_FIXTURE
    with resources.as_file(path) as p, np.load(p) as data:
        out = {k: data[k] for k in data.files}
    deltas = (
        out.pop("expression_deltas_q").astype(np.float64)
        * out.pop("expression_scales")[:, None, None]
    )
    ident = (
        out.pop("identity_deltas_q").astype(np.float64) * out.pop("identity_scales")[:, None, None]
    )
    out["expression_deltas"], out["identity_deltas"] = deltas, ident
    return out


def _ict_identity(
    data: dict,
    coeffs: npt.ArrayLike | None,
    default: npt.ArrayLike | None,
    what: str,
    case: str = "ict",
) -> np.ndarray:
    """(V, 3) ICT face ``neutral + sum_k c_k identity_k`` for coefficients ``coeffs`` (or ``default``)."""
    n_modes = data["identity_deltas"].shape[0]
    c = np.asarray(default if coeffs is None else coeffs, dtype=np.float64)
    if c.ndim != 1 or c.shape[0] > n_modes or not np.isfinite(c).all():
        raise InputError(
            f"{case}: {what} must be up to {n_modes} finite identity coefficients, got shape {c.shape}"
        )
    return data["neutral"].astype(np.float64) + np.tensordot(
        c, data["identity_deltas"][: c.shape[0]], axes=1
    )


@functools.lru_cache(maxsize=8)
def _ict_transferred_deltas(coeffs: tuple) -> np.ndarray:
    """(45, V, 3) read-only: the generic ICT expressions carried to identity ``coeffs`` by
    deformation transfer (Sumner & Popovic 2004); cached, as it takes seconds."""
    from .geometry.deformation_gradients import DeformationTransfer

    data = _load_ict_fixture()
    tri = data["faces"].astype(np.int64)
    face = _ict_identity(data, coeffs, None, "identity")
    generic = data["neutral"].astype(np.float64)
    out = (
        DeformationTransfer(face, tri).transfer(generic, generic + data["expression_deltas"]) - face
    )
    out.setflags(write=False)
    return out


def _ict_masks(mesh: Mesh, landmark_points: np.ndarray) -> np.ndarray:
    """Region masks (3, V) of an ICT-like face cut at the brow/eye and nose landmark heights."""
    y = mesh.vertices[:, 1]
    brow = landmark_points[17:27, 1].mean()
    eye = landmark_points[36:48, 1].mean()
    nose = landmark_points[33, 1]
    return _region_masks(y, 0.5 * (brow + eye), nose, _MASK_SOFTNESS * mesh.height)


def ict(
    source_identity: npt.ArrayLike | None = None,
    target_identity: npt.ArrayLike | None = None,
    n_frames: int = 120,
    fps: float = 30.0,
    seed: int = 0,
    head_motion: bool = True,
    expressions: str = "same",
) -> Case:
    """Real parallel rigs from the ICT-FaceKit face region (9409 vertices, 45 expressions).

    Parameters
    ----------
    source_identity, target_identity : (10,) float, optional
        Coefficients on the ICT identity modes (defaults :data:`ICT_SOURCE_IDENTITY`,
        :data:`ICT_TARGET_IDENTITY`). Each face is ``neutral + sum_k c_k identity_k``.
    n_frames, fps, seed, head_motion : as in :func:`synthetic`
    expressions : "same" | "transferred"
        "same": both rigs add the generic ICT expression deltas to their identity, which
        is the ICT-FaceKit model itself (identity and expression add linearly), so the
        rigs are trivially parallel. "transferred": each identity's expressions are the
        generic ones carried over by deformation transfer (Sumner & Popovic 2004), so the
        two rigs' deltas differ with the face shape (slower: a few seconds per identity).

    Landmarks are the 68 Multi-PIE points; feature lines are the boundary loops of the
    eye and mouth holes plus the outer-lip landmark contour.
    """
    _check_counts(n_frames=n_frames)
    if expressions not in ("same", "transferred"):
        raise UnknownNameError(
            f"ict: expressions must be 'same' or 'transferred', got {expressions!r}"
        )
    data = _load_ict_fixture()

    def identity(coeffs: npt.ArrayLike | None, default: npt.ArrayLike, what: str) -> np.ndarray:
        return _ict_identity(data, coeffs, default, what)

    def key(coeffs: npt.ArrayLike | None, default: npt.ArrayLike) -> tuple:
        return tuple(
            float(c) for c in np.asarray(default if coeffs is None else coeffs, dtype=np.float64)
        )

    tri = data["faces"].astype(np.int64)
    names = [str(n) for n in data["expression_names"]]
    deltas = data["expression_deltas"]
    src = Mesh(
        identity(source_identity, ICT_SOURCE_IDENTITY, "source_identity"),
        tri,
        name="ICT source",
        _trusted=True,
    )
    tgt = Mesh(
        identity(target_identity, ICT_TARGET_IDENTITY, "target_identity"),
        tri,
        name="ICT target",
        _trusted=True,
    )
    if expressions == "transferred":
        source_rig = BlendshapeRig(
            src, _ict_transferred_deltas(key(source_identity, ICT_SOURCE_IDENTITY)), names
        )
        target_rig = BlendshapeRig(
            tgt, _ict_transferred_deltas(key(target_identity, ICT_TARGET_IDENTITY)), names
        )
    else:
        source_rig = BlendshapeRig(src, deltas, names)
        target_rig = BlendshapeRig(tgt, deltas, names)

    lm_ids = data["landmarks68"].astype(np.int64)
    landmarks = Landmarks(lm_ids, names=ICT_LANDMARK_NAMES)
    loops = boundary_loops(tri)
    base = data["neutral"]
    centres = {
        "eye_L": base[lm_ids[42:48]].mean(axis=0),
        "eye_R": base[lm_ids[36:42]].mean(axis=0),
        "mouth_inner": base[lm_ids[60:68]].mean(axis=0),
    }
    lines = {
        k: min(loops, key=lambda lp: np.linalg.norm(base[lp].mean(axis=0) - c))
        for k, c in centres.items()
    }
    lines["mouth_outer"] = lm_ids[48:60]

    def masks(mesh: Mesh) -> np.ndarray:
        return _ict_masks(mesh, mesh.vertices[lm_ids])

    return _assemble(
        "ict",
        _Side(source_rig, landmarks, lines, masks(src)),
        _Side(target_rig, landmarks, lines, masks(tgt)),
        n_frames=n_frames,
        fps=fps,
        seed=seed,
        head_motion=head_motion,
        pivot=np.array([0.0, src.vertices[:, 1].min(), src.vertices[:, 2].min()]),
        meta={"seed": seed, "expressions": expressions},
    )


# =======================================================================================
# A cross-rig pair from the ICT data: different topology, units and shape meanings
# =======================================================================================
_CROSS_RIG_FIXTURE = "ict_cross_rig_fixture.npz"
#: Source units per target unit: the source rig is in metres, the target (ICT) in centimetres.
CROSS_RIG_SOURCE_SCALE = 0.01
#: Expression-track accents: single actions an actor holds alone (ARKit names).
_ACCENT_SHAPES = (
    "browInnerUp",
    "browDownLeft",
    "browDownRight",
    "browOuterUpLeft",
    "browOuterUpRight",
    "eyeSquintLeft",
    "eyeSquintRight",
    "eyeWideLeft",
    "eyeWideRight",
    "cheekSquintLeft",
    "cheekSquintRight",
    "cheekPuff",
    "noseSneerLeft",
    "noseSneerRight",
    "mouthDimpleLeft",
    "mouthDimpleRight",
    "mouthSmileLeft",
    "mouthSmileRight",
    "mouthLeft",
    "mouthRight",
    "mouthShrugUpper",
    "mouthShrugLower",
    "mouthRollUpper",
    "mouthPressLeft",
    "mouthPressRight",
    "jawLeft",
    "jawRight",
    "jawForward",
)


def _load_cross_rig_fixture() -> dict[str, np.ndarray]:
    path = resources.files("faceretarget") / "data" / _CROSS_RIG_FIXTURE
    with resources.as_file(path) as p, np.load(p) as data:
        return {k: data[k] for k in data.files}


def _smooth_keys(times: np.ndarray, values: np.ndarray, t: np.ndarray) -> np.ndarray:
    """Smoothstep between consecutive keys ``(times (K,) increasing, values (K, M))`` at ``t`` -> (len(t), M).

    Equal consecutive keys give exactly constant holds; outside the keys the end values hold.
    """
    k = np.clip(np.searchsorted(times, t, side="right") - 1, 0, len(times) - 2)
    s = np.clip((t - times[k]) / (times[k + 1] - times[k]), 0.0, 1.0)
    s = s * s * (3.0 - 2.0 * s)
    v0 = values[k]
    return v0 + s[:, None] * (values[k + 1] - v0)


class _Track:
    """Keys of one animation track (times in seconds, strictly increasing)."""

    def __init__(self, n_shapes: int) -> None:
        self.times: list[float] = [0.0]
        self.values: list[np.ndarray] = [np.zeros(n_shapes)]

    def key(self, time: float, value: np.ndarray) -> None:
        if time > self.times[-1] + 1e-9:
            self.times.append(time)
            self.values.append(value)

    def sample(self, t: np.ndarray) -> np.ndarray:
        self.key(max(self.times[-1], float(t[-1])) + 1.0, self.values[-1])
        return _smooth_keys(np.asarray(self.times), np.asarray(self.values), t)


def _performance_weights(
    rng: np.random.Generator, n_frames: int, fps: float, names: Sequence[str]
) -> np.ndarray:
    """(F, M) animation-like weight curves in [0, 1] on a rig with shapes ``names``.

    Three tracks, each keyed in seconds and smoothstep-interpolated (C1, exact holds), are
    combined per shape as ``1 - (1 - expression)(1 - speech)(1 - blink)``:

    - expressions: an emotion recipe (scaled 0.5-1, jittered per shape, sometimes with an
      accent) or 1-3 accents alone (brow raise, squint, dimple, jaw shift...), ramping in
      over 0.15-0.5 s and held 1-4 s, then either blended into the next expression or
      released to rest for 0.3-2.5 s;
    - speech: bursts of 1-3.5 s separated by 0.5-3.5 s pauses; inside a burst a viseme key
      (jaw and mouth shapes) every 0.1-0.25 s (4-10 Hz), with lower-lip, mouthClose and
      shrug variations;
    - blinks: both eyes, about 150 ms (close 50-70 ms, open 80-120 ms), every 2-6 s,
      sometimes doubled.
    """
    m = len(names)
    t = np.arange(n_frames, dtype=np.float64) / fps
    t_end = float(t[-1])

    def vec(recipe: Mapping[str, float]) -> np.ndarray:
        return recipes.resolve(recipe, names, on_unmapped="ignore")

    emotions = [vec(r) for k, r in recipes.EMOTIONS.items() if k != "neutral"]
    accents = [vec({a: 1.0}) for a in _ACCENT_SHAPES]
    accents = [a for a in accents if a.any()]
    visemes = {k: vec(r) for k, r in recipes.VISEMES.items()}
    one = {
        n: vec({n: 1.0})
        for n in (
            "jawOpen",
            "mouthClose",
            "mouthLowerDownLeft",
            "mouthLowerDownRight",
            "mouthShrugUpper",
            "mouthRollUpper",
            "eyeBlinkLeft",
            "eyeBlinkRight",
        )
    }
    jaw = int(np.argmax(one["jawOpen"])) if one["jawOpen"].any() else None

    # expressions
    expr = _Track(m)
    time, current = float(rng.uniform(0.0, 0.8)), np.zeros(m)
    while time < t_end:
        if rng.random() < 0.65 and emotions:
            pose = (
                emotions[int(rng.integers(len(emotions)))]
                * rng.uniform(0.5, 1.0)
                * rng.uniform(0.85, 1.15, m)
            )
            if accents and rng.random() < 0.35:
                pose = pose + accents[int(rng.integers(len(accents)))] * rng.uniform(0.2, 0.6)
        else:
            pose = np.zeros(m)
            for i in rng.choice(len(accents), size=int(rng.integers(1, 4)), replace=False):
                pose = pose + accents[i] * rng.uniform(0.3, 0.9)
        pose = np.clip(pose, 0.0, 1.0)
        ramp, hold = rng.uniform(0.15, 0.5), rng.uniform(1.0, 4.0)
        expr.key(time, current)
        expr.key(time + ramp, pose)
        expr.key(time + ramp + hold, pose)
        time, current = time + ramp + hold, pose
        if rng.random() < 0.5:
            ramp = rng.uniform(0.15, 0.5)
            expr.key(time + ramp, np.zeros(m))
            time, current = time + ramp + rng.uniform(0.3, 2.5), np.zeros(m)

    # speech
    speech = _Track(m)
    viseme_names = list(visemes)
    time = float(rng.uniform(0.2, 1.5))
    while time < t_end:
        speech.key(time, np.zeros(m))
        stop, key_t = time + rng.uniform(1.0, 3.5), time
        rate = rng.uniform(4.0, 10.0)
        while True:
            step = float(np.clip(rng.uniform(0.8, 1.25) / rate, 0.1, 0.25))
            if key_t + step >= stop:
                break
            key_t += step
            name = viseme_names[int(rng.integers(len(viseme_names)))]
            pose = visemes[name] * rng.uniform(0.6, 1.15)
            open_ = pose[jaw] if jaw is not None else 0.3
            if name == "MBP" and rng.random() < 0.6:
                closed = rng.uniform(0.05, 0.25)
                pose = pose + closed * (one["jawOpen"] + one["mouthClose"])
            elif rng.random() < 0.25:
                pose = pose + rng.uniform(0.3, 0.9) * open_ * one["mouthClose"]
            if rng.random() < 0.4:
                pose = pose + rng.uniform(0.1, 0.4) * (
                    one["mouthLowerDownLeft"] + one["mouthLowerDownRight"]
                )
            if rng.random() < 0.2:
                pose = (
                    pose
                    + rng.uniform(0.1, 0.3)
                    * one[("mouthShrugUpper", "mouthRollUpper")[int(rng.integers(2))]]
                )
            speech.key(key_t, np.clip(pose, 0.0, 1.0))
        end = key_t + rng.uniform(0.1, 0.25)
        speech.key(end, np.zeros(m))
        time = end + rng.uniform(0.5, 3.5)

    # blinks
    blink = _Track(m)
    time = float(rng.uniform(0.3, 2.0))
    while time < t_end:
        for _ in range(2 if rng.random() < 0.1 else 1):
            depth = rng.uniform(0.85, 1.0)
            pose = depth * (
                one["eyeBlinkLeft"] * rng.uniform(0.95, 1.0)
                + one["eyeBlinkRight"] * rng.uniform(0.95, 1.0)
            )
            close, shut, opening = (
                rng.uniform(0.05, 0.07),
                rng.uniform(0.0, 0.03),
                rng.uniform(0.08, 0.12),
            )
            blink.key(time, np.zeros(m))
            blink.key(time + close, pose)
            blink.key(time + close + shut, pose)
            blink.key(time + close + shut + opening, np.zeros(m))
            time += close + shut + opening + rng.uniform(0.1, 0.2)
        time += rng.uniform(2.0, 6.0)

    rest = (1.0 - expr.sample(t)) * (1.0 - speech.sample(t)) * (1.0 - blink.sample(t))
    return np.clip(1.0 - rest, 0.0, 1.0)


def _random_rotation(rng: np.random.Generator, low_deg: float, high_deg: float) -> np.ndarray:
    axis = rng.normal(size=3)
    axis /= np.linalg.norm(axis)
    angle = np.deg2rad(rng.uniform(low_deg, high_deg))
    k = np.array([[0.0, -axis[2], axis[1]], [axis[2], 0.0, -axis[0]], [-axis[1], axis[0], 0.0]])
    return np.eye(3) + np.sin(angle) * k + (1.0 - np.cos(angle)) * (k @ k)


def _gain_field(
    rng: np.random.Generator, points: np.ndarray, height: float, amplitude: float
) -> np.ndarray:
    """(V,) smooth gains ``1 + amplitude * u``, ``u`` in [-1, 1] a sum of 3 plane waves (0.25-0.6 face heights)."""
    x = (points - points.mean(axis=0)) / height
    u = np.zeros(len(points))
    for _ in range(3):
        direction = rng.normal(size=3)
        direction /= np.linalg.norm(direction)
        u += rng.uniform(0.5, 1.0) * np.sin(
            2 * np.pi * (x @ direction) / rng.uniform(0.25, 0.6) + rng.uniform(0, 2 * np.pi)
        )
    return 1.0 + amplitude * u / max(np.abs(u).max(), 1e-12)


def _cross_family_mix(rng: np.random.Generator, names: Sequence[str]) -> tuple[np.ndarray, dict]:
    """(M, M) mix ``A`` (target shape i = sum_j A_ij transferred shape j) and its drawn parameters."""
    ix = {n: i for i, n in enumerate(names)}
    mix = np.eye(len(names))
    params: dict[str, Any] = {}
    # mouthClose: the source's mouthClose = kappa * target mouthClose + gamma * each mouthFrown
    kappa, gamma = rng.uniform(0.65, 0.75), rng.uniform(0.4, 0.6)
    c = ix["mouthClose"]
    mix[c] = 0.0
    mix[c, c] = 1.0 / kappa
    mix[c, ix["mouthFrown_L"]] = mix[c, ix["mouthFrown_R"]] = -gamma / kappa
    params["mouthClose"] = {"kappa": kappa, "gamma": gamma}
    # mouthPucker takes in mouthFunnel, mouthFunnel is exaggerated away from the pucker:
    # the source's mouthFunnel lands mostly on the target's mouthPucker
    mu, nu = rng.uniform(0.45, 0.55), rng.uniform(0.8, 1.0)
    f, p = ix["mouthFunnel"], ix["mouthPucker"]
    mix[p] = 0.0
    mix[p, p], mix[p, f] = 1.0 - mu, mu
    mix[f] = 0.0
    mix[f, f], mix[f, p] = 1.0 + nu, -nu
    params["mouthFunnel/mouthPucker"] = {"mu": mu, "nu": nu}
    # a fraction of a neighbouring action baked into some mouth shapes (both sides alike)
    for shape, other, low, high in (
        ("mouthSmile", "cheekSquint", 0.15, 0.35),
        ("mouthStretch", "mouthLowerDown", 0.15, 0.35),
        ("mouthUpperUp", "noseSneer", 0.15, 0.35),
        ("jawOpen", "mouthLowerDown", 0.1, 0.2),
    ):
        frac = rng.uniform(low, high)
        for side in ("_L", "_R"):
            row = ix[shape + side] if shape + side in ix else ix[shape]
            mix[row, ix[other + side]] = frac
        params[f"{shape}+{other}"] = frac
    frac = rng.uniform(0.15, 0.35)
    mix[ix["mouthRollLower"], ix["mouthShrugLower"]] = frac
    params["mouthRollLower+mouthShrugLower"] = frac
    return mix, params


@functools.lru_cache(maxsize=4)
def _cross_rig_pair(
    source_identity: tuple, target_identity: tuple, seed: int
) -> tuple[_Side, _Side, dict[str, Any]]:
    """The two sides of :func:`cross_rig` (cached) and the meta entries describing them."""
    data = _load_ict_fixture()
    fixture = _load_cross_rig_fixture()
    tri = data["faces"].astype(np.int64)
    names = [str(n) for n in data["expression_names"]]
    lm_ids = data["landmarks68"].astype(np.int64)
    scale = CROSS_RIG_SOURCE_SCALE

    # source: the remeshed ICT face on the source identity with the generic deltas, in metres
    s_tri = fixture["triangles"].astype(np.int64)
    on_ict, bary = fixture["vertex_triangles"].astype(np.int64), fixture["vertex_barycentric"]
    corners = tri[on_ict]

    def carry(values: np.ndarray) -> np.ndarray:
        return np.einsum("...skd,sk->...sd", values[..., corners, :], bary)

    s_mesh = Mesh(
        scale * carry(_ict_identity(data, source_identity, None, "source_identity", "cross_rig")),
        s_tri,
        name="cross-rig source (m)",
        _trusted=True,
    )
    source_rig = BlendshapeRig(s_mesh, scale * carry(data["expression_deltas"]), names)
    s_landmarks = Landmarks(
        triangle_ids=fixture["landmark_triangles"].astype(np.int64),
        barycentric=fixture["landmark_barycentric"],
        names=ICT_LANDMARK_NAMES,
    )
    s_points = s_landmarks.positions(s_mesh.vertices, s_tri)

    # target: the ICT face on the target identity, deformation-transferred deltas perturbed
    t_mesh = Mesh(
        _ict_identity(data, target_identity, None, "target_identity", "cross_rig"),
        tri,
        name="cross-rig target (cm)",
        _trusted=True,
    )
    transferred = _ict_transferred_deltas(target_identity)
    rng = np.random.default_rng([seed, 7])
    mix, mix_params = _cross_family_mix(rng, names)
    mixed = np.tensordot(mix, transferred, axes=1)
    gains = np.stack(
        [_gain_field(rng, t_mesh.vertices, t_mesh.height, rng.uniform(0.2, 0.3)) for _ in names]
    )
    rotations = np.stack([_random_rotation(rng, 6.0, 12.0) for _ in names])
    deltas = gains[:, :, None] * np.einsum("mij,mvj->mvi", rotations, mixed)
    target_rig = BlendshapeRig(t_mesh, deltas, names)

    def lines(vertices: np.ndarray, triangles: np.ndarray, points: np.ndarray) -> dict:
        loops = boundary_loops(triangles)
        centres = {
            "eye_L": points[42:48].mean(axis=0),
            "eye_R": points[36:42].mean(axis=0),
            "mouth_inner": points[60:68].mean(axis=0),
        }
        out = {
            k: min(loops, key=lambda lp: np.linalg.norm(vertices[lp].mean(axis=0) - c))
            for k, c in centres.items()
        }
        return out

    s_lines = lines(s_mesh.vertices, s_tri, s_points)
    nearest = np.argmin(((s_points[48:60, None] - s_mesh.vertices[None]) ** 2).sum(axis=-1), axis=1)
    s_lines["mouth_outer"] = nearest[np.r_[True, nearest[1:] != nearest[:-1]]]
    t_lines = lines(data["neutral"], tri, data["neutral"][lm_ids])
    t_lines["mouth_outer"] = lm_ids[48:60]

    src = _Side(source_rig, s_landmarks, s_lines, _ict_masks(s_mesh, s_points))
    tgt = _Side(
        target_rig,
        Landmarks(lm_ids, names=ICT_LANDMARK_NAMES),
        t_lines,
        _ict_masks(t_mesh, t_mesh.vertices[lm_ids]),
    )
    for arr in (on_ict, bary, mix, gains, rotations):
        arr.setflags(write=False)
    meta = {
        "source_correspondence": {"triangles": on_ict, "barycentric": bary},
        "perturbation": {
            "transferred": transferred,
            "mix": mix,
            "mix_parameters": mix_params,
            "gain": gains,
            "rotation": rotations,
        },
    }
    return src, tgt, meta


def _identity_key(
    coeffs: npt.ArrayLike | None, default: npt.ArrayLike, what: str, case: str
) -> tuple:
    """Identity coefficients as a hashable key for the cached rig pairs (validated when given)."""
    if coeffs is not None:
        _ict_identity(_load_ict_fixture(), coeffs, default, what, case)
    return tuple(
        float(c) for c in np.asarray(default if coeffs is None else coeffs, dtype=np.float64)
    )


def cross_rig(
    seed: int = 0,
    n_frames: int = 300,
    fps: float = 30.0,
    head_motion: bool = False,
    source_kind: str = "mesh",
    source_identity: npt.ArrayLike | None = None,
    target_identity: npt.ArrayLike | None = None,
) -> Case:
    """A pair of *different* rigs built from the ICT-FaceKit data, like a real production pair.

    Nothing here is parallel by construction except the shape names:

    - **Topology and units.** The source is the ICT face remeshed by quadric decimation to
      2,074 vertices / 4,000 triangles (committed fixture ``data/ict_cross_rig_fixture.npz``:
      each source vertex is a barycentric point on the ICT mesh, so every source vertex and
      delta is interpolated from the ICT data) and scaled to **metres**; the target keeps
      the ICT topology (9,409 vertices) in **centimetres**.
    - **Identities.** Source and target are different ICT identities
      (:data:`ICT_SOURCE_IDENTITY`, :data:`ICT_TARGET_IDENTITY` by default).
    - **Shape meanings.** Source deltas are the generic ICT expressions on the source
      face. Target deltas start from the generic ones carried to the target face by
      deformation transfer (as ``ict(expressions="transferred")``) and are then changed
      per shape, deterministically from ``seed``:

      * cross-family mixes of mouth shapes: the target's ``mouthClose`` is
        ``(close - gamma (frown_L + frown_R)) / kappa`` (kappa 0.65-0.75, gamma 0.4-0.6),
        so the source's mouthClose is the target's mouthClose ~0.7 + each mouthFrown ~0.5;
        the target's ``mouthPucker`` is ``(1 - mu) pucker + mu funnel`` (mu 0.45-0.55)
        and its ``mouthFunnel`` ``(1 + nu) funnel - nu pucker`` (nu 0.8-1.0), so the
        source's mouthFunnel lands mostly on the target's mouthPucker; mouthSmile takes in
        0.15-0.35 of cheekSquint, mouthStretch of mouthLowerDown, mouthUpperUp of
        noseSneer, mouthRollLower of mouthShrugLower, and jawOpen 0.1-0.2 of mouthLowerDown;
      * a smooth spatial gain field per shape, ``1 + a u(x)`` with ``a`` 0.2-0.3 and
        ``u`` in [-1, 1] a sum of three plane waves of 0.25-0.6 face heights (so gains
        within 0.7-1.3);
      * a small rotation of each shape's displacement directions (6-12 degrees).

      ``meta["perturbation"]`` holds ``transferred`` (the unperturbed deltas), ``mix``
      (M, M), ``mix_parameters``, ``gain`` (M, V) and ``rotation`` (M, 3, 3): target
      deltas = ``gain * rotation @ (mix @ transferred)``.
    - **Animation.** Sparse weight curves in [0, 1] like production animation: expressions
      ramped in over 0.15-0.5 s and held 1-4 s, both-eye blinks (~150 ms, every 2-6 s),
      speech bursts with jaw/mouth keys at 4-10 Hz; smooth (C1), several shapes at once.
      No head motion unless asked.

    Parameters
    ----------
    seed : int
        Seeds the weight curves, the head motion and the target's perturbations.
    n_frames : int
        Any length (tested up to 20,000 frames).
    fps : float
        Given explicitly to the source sequence.
    head_motion : bool
        Add smooth rigid head motion (about 10 degrees, 5% of face height) to the source
        and, in target units, to the truth.
    source_kind : "mesh" | "markers"
        "mesh": a MeshSequence of the source rig with the 68 landmarks as barycentric
        points on its triangles, feature lines (its eye/mouth hole loops + the nearest
        vertices to the outer-lip landmarks) and region masks; "markers": a
        MarkerSequence of those 68 landmark positions, named like the target's landmarks
        (:data:`ICT_LANDMARK_NAMES`).
    source_identity, target_identity : (<= 10,) float, optional
        ICT identity coefficients, as in :func:`ict`.

    The case carries 7 example pose pairs (source / target rig expressions of the same
    recipes), the source rig (for the record), the target's blendshapes, layered poses
    with region masks, landmarks and feature lines, and actor layers over the source
    landmarks. The truth is the target rig driven by the same weights. The rigs declare
    no weight bounds. ``meta`` adds ``source_kind``, ``unit_scale`` (target units per
    source unit, 100), ``source_correspondence`` (each source vertex as ``triangles`` +
    ``barycentric`` on the target's triangles: the exact dense correspondence) and
    ``perturbation``.
    """
    _check_counts(n_frames=n_frames)
    if source_kind not in ("mesh", "markers"):
        raise UnknownNameError(
            f"cross_rig: source_kind must be 'mesh' or 'markers', got {source_kind!r}"
        )
    fps = as_fps(fps)
    src, tgt, pair_meta = _cross_rig_pair(
        _identity_key(source_identity, ICT_SOURCE_IDENTITY, "source_identity", "cross_rig"),
        _identity_key(target_identity, ICT_TARGET_IDENTITY, "target_identity", "cross_rig"),
        int(seed),
    )
    weights = _performance_weights(
        np.random.default_rng([int(seed), 3]), int(n_frames), fps, src.rig.names
    )
    s_vertices = src.rig.neutral.vertices
    return _assemble(
        "cross-rig",
        src,
        tgt,
        n_frames=int(n_frames),
        fps=fps,
        seed=seed,
        head_motion=head_motion,
        pivot=np.array([0.0, s_vertices[:, 1].min(), s_vertices[:, 2].min()]),
        meta={
            "seed": seed,
            "source_kind": source_kind,
            "unit_scale": 1.0 / CROSS_RIG_SOURCE_SCALE,
            "source_correspondence": dict(pair_meta["source_correspondence"]),
            "perturbation": {
                **pair_meta["perturbation"],
                "mix_parameters": copy.deepcopy(pair_meta["perturbation"]["mix_parameters"]),
            },
        },
        weights=weights,
        source_kind=source_kind,
        unit_scale=1.0 / CROSS_RIG_SOURCE_SCALE,
    )


# =======================================================================================
# A cross-topology pair: a closed-eye head with a mouth bag onto the open-eye ICT face
# =======================================================================================
_CROSS_TOPOLOGY_FIXTURE = "ict_cross_topology_fixture.npz"
#: Region codes of ``meta["source_region"]`` in :func:`cross_topology`.
CROSS_TOPOLOGY_REGIONS = ("face", "eye_fill", "mouth_bag", "skirt")
#: Shapes the closed-eye source cannot perform (its lids are sewn shut): zero in its curves.
_CLOSED_EYE_SHAPES = ("eyeBlink_L", "eyeBlink_R", "eyeWide_L", "eyeWide_R")


#: Wavelength of the cross-topology wrinkles, in centimetres of the generic ICT face (the
#: material coordinates): 4-7 median edges of the once-subdivided source (and 3.8-7.3 of the
#: target) in the wrinkle windows.
CROSS_TOPOLOGY_WRINKLE_WAVELENGTH = 1.5
#: Depth (amplitude, cm on the source face) of the cross-topology wrinkles at weight 1.
CROSS_TOPOLOGY_WRINKLE_DEPTH = 0.06


def _midpoint_subdivision(
    triangles: np.ndarray, n_vertices: int
) -> tuple[sp.csr_matrix, np.ndarray, np.ndarray]:
    """One 1-to-4 midpoint split: ``(S (V', V) sparse, triangles (4T, 3), edge (V'-V, 2))``.

    New vertex ``n_vertices + k`` is the midpoint of ``edge[k]``; triangle ``4t + c`` is child
    ``c`` of triangle ``t = (a, b, c)``: ``(a, ab, ca)``, ``(ab, b, bc)``, ``(ca, bc, c)``,
    ``(ab, bc, ca)`` (the orientation is kept).
    """
    import scipy.sparse as sp

    tri = np.asarray(triangles, dtype=np.int64)
    half = np.concatenate([tri[:, [0, 1]], tri[:, [1, 2]], tri[:, [2, 0]]])
    key = np.sort(half, axis=1)
    edges, inverse = np.unique(key, axis=0, return_inverse=True)
    mid = n_vertices + inverse.reshape(3, len(tri)).T  # (T, 3): ab, bc, ca
    a, b, c = tri.T
    ab, bc, ca = mid.T
    children = np.stack(
        [
            np.stack([a, ab, ca], 1),
            np.stack([ab, b, bc], 1),
            np.stack([ca, bc, c], 1),
            np.stack([ab, bc, ca], 1),
        ],
        1,
    )
    n_new = n_vertices + len(edges)
    rows = np.concatenate([np.arange(n_vertices), np.repeat(np.arange(n_vertices, n_new), 2)])
    cols = np.concatenate([np.arange(n_vertices), edges.ravel()])
    vals = np.concatenate([np.ones(n_vertices), np.full(2 * len(edges), 0.5)])
    matrix = sp.csr_matrix((vals, (rows, cols)), shape=(n_new, n_vertices))
    return matrix, children.reshape(-1, 3), edges


def _subdivided_landmarks(
    triangle_ids: np.ndarray, barycentric: np.ndarray
) -> tuple[np.ndarray, np.ndarray]:
    """Landmark ``(triangle, barycentric)`` pairs moved into the children of :func:`_midpoint_subdivision`
    (the same surface points)."""
    bary = np.asarray(barycentric, dtype=np.float64)
    al, be, ga = bary.T
    child = np.full(len(bary), 3)
    out = np.stack([1.0 - 2.0 * ga, 1.0 - 2.0 * al, 1.0 - 2.0 * be], 1)  # middle child (ab, bc, ca)
    for c, big in enumerate(
        (al, be, ga)
    ):  # a corner child holds the points with that corner's weight >= 1/2
        on = (big >= 0.5) & (child == 3)
        child[on] = c
        if c == 0:  # (a, ab, ca): a, ab, ca weights
            out[on] = np.stack([2 * al - 1, 2 * be, 2 * ga], 1)[on]
        elif c == 1:  # (ab, b, bc)
            out[on] = np.stack([2 * al, 2 * be - 1, 2 * ga], 1)[on]
        else:  # (ca, bc, c)
            out[on] = np.stack([2 * al, 2 * be, 2 * ga - 1], 1)[on]
    return 4 * np.asarray(triangle_ids, dtype=np.int64) + child, out


def _cross_topology_wrinkle_fields(
    material: np.ndarray, names: Iterable[str]
) -> dict[str, np.ndarray]:
    """Wrinkle depth (P,) per shape at material points ``(P, 3)`` (the generic ICT neutral, cm):
    the normal offset, at weight 1 and on a face of the source's size, of the cross-topology
    wrinkles. Three families, each on the shapes the performance holds (``browDown``,
    ``mouthPress``, ``mouthPucker``):

    - glabella lines (``browDown_L/R``): vertical furrows between the brows, and the procerus
      lines (horizontal, across the nose bridge);
    - chin dimpling (``mouthPress_L/R``): a ``sin x sin y`` pattern on the chin;
    - perioral lines (``mouthPucker``): vertical lines on the upper lip skin.

    Each is a sinusoid of wavelength :data:`CROSS_TOPOLOGY_WRINKLE_WAVELENGTH` under a smooth
    Gaussian window; ``_L`` shapes on ``+x`` (the character's left, as the ICT deltas).
    """
    x, y = material[:, 0], material[:, 1]
    k = 2.0 * np.pi / CROSS_TOPOLOGY_WRINKLE_WAVELENGTH
    amp = CROSS_TOPOLOGY_WRINKLE_DEPTH

    def window(cx: float, cy: float, sx: float, sy: float) -> np.ndarray:
        return np.exp(-(((x - cx) / sx) ** 2) - ((y - cy) / sy) ** 2)

    out = {}
    for side, sg in (("L", 1.0), ("R", -1.0)):
        glabella = window(sg * 0.75, 5.0, 0.7, 0.9) * np.sin(k * x)
        procerus = 0.5 * window(0.0, 3.9, 0.9, 0.6) * np.sin(k * (y - 3.9))
        out[f"browDown_{side}"] = amp * (glabella + procerus)
        out[f"mouthPress_{side}"] = (
            amp * window(sg * 0.8, -6.2, 1.0, 0.9) * np.sin(k * x) * np.sin(k * (y + 6.2))
        )
    out["mouthPucker"] = amp * window(0.0, -1.9, 1.6, 0.45) * np.cos(k * x)
    return {n: f for n, f in out.items() if n in names}


@functools.lru_cache(maxsize=4)
def _cross_topology_pair(
    source_identity: tuple, target_identity: tuple, subdivisions: int = 0, wrinkles: bool = False
) -> tuple[_Side, _Side, dict[str, Any]]:
    """The two sides of :func:`cross_topology` (cached) and the meta entries describing them."""
    import scipy.sparse as sp

    data = _load_ict_fixture()
    path = resources.files("faceretarget") / "data" / _CROSS_TOPOLOGY_FIXTURE
    with resources.as_file(path) as p, np.load(p) as fx:
        fixture = {k: fx[k] for k in fx.files}
    tri = data["faces"].astype(np.int64)
    names = [str(n) for n in data["expression_names"]]
    deltas = data["expression_deltas"]
    lm_ids = data["landmarks68"].astype(np.int64)
    s_tri = fixture["triangles"].astype(np.int64)
    region = fixture["region"].astype(np.int64)
    w = sp.csr_matrix(
        (fixture["w_data"], fixture["w_indices"], fixture["w_indptr"]),
        shape=(len(region), len(data["neutral"])),
    )
    offset = fixture["offset"]
    lm_tri, lm_bary = (
        fixture["landmark_triangles"].astype(np.int64),
        fixture["landmark_barycentric"],
    )
    for _ in range(
        subdivisions
    ):  # a denser source: midpoints, exact in the construction (W and offset interpolated)
        split, s_tri, edges = _midpoint_subdivision(s_tri, len(region))
        w, offset = (split @ w).tocsr(), split @ offset
        # a midpoint is a face vertex only between two face vertices
        region = np.concatenate([region, np.maximum(region[edges[:, 0]], region[edges[:, 1]])])
        lm_tri, lm_bary = _subdivided_landmarks(lm_tri, lm_bary)
    blink = deltas[names.index("eyeBlink_L")] + deltas[names.index("eyeBlink_R")]

    # source: the closed-eye head on the source identity (lids shut by the two blinks)
    s_identity = _ict_identity(data, source_identity, None, "source_identity", "cross_topology")
    s_face = s_identity + blink
    s_vertices = w @ s_face + offset
    s_mesh = Mesh(
        s_vertices, s_tri, name="cross-topology source (closed eyes, mouth bag)", _trusted=True
    )
    s_deltas = np.stack([w @ d for d in deltas])
    s_landmarks = Landmarks(triangle_ids=lm_tri, barycentric=lm_bary, names=ICT_LANDMARK_NAMES)
    s_points = s_landmarks.positions(s_vertices, s_tri)

    # target: the open-eye ICT face on the target identity, the same generic deltas
    t_identity = _ict_identity(data, target_identity, None, "target_identity", "cross_topology")
    t_mesh = Mesh(t_identity, tri, name="cross-topology target (ICT)", _trusted=True)
    t_deltas = deltas
    if wrinkles:
        # one wrinkle field on the generic face's material points (the case's exact correspondence:
        # target vertex j is the generic vertex j, source vertex i the point W_i @ generic), as a
        # normal offset of each neutral, its depth scaled by each face's size
        from .geometry.mesh_ops import vertex_normals

        def size(face: np.ndarray) -> float:
            return float(np.sqrt(np.mean(np.sum((face - face.mean(axis=0)) ** 2, axis=1))))

        ratio = size(t_identity) / size(s_identity)
        s_fields = _cross_topology_wrinkle_fields(w @ data["neutral"], names)
        t_fields = _cross_topology_wrinkle_fields(data["neutral"], names)
        s_normals, t_normals = vertex_normals(s_vertices, s_tri), vertex_normals(t_identity, tri)
        face_only = (region == 0).astype(np.float64)
        s_deltas, t_deltas = s_deltas.copy(), deltas.copy()
        for n in s_fields:
            s_deltas[names.index(n)] += (face_only * s_fields[n])[:, None] * s_normals
            t_deltas[names.index(n)] += (ratio * t_fields[n])[:, None] * t_normals
    source_rig = BlendshapeRig(s_mesh, s_deltas, names)
    target_rig = BlendshapeRig(t_mesh, t_deltas, names)

    # feature lines: the target's hole loops; on the source (no holes) the nearest vertex chains
    loops = boundary_loops(tri)
    base = data["neutral"]
    centres = {
        "eye_L": base[lm_ids[42:48]].mean(axis=0),
        "eye_R": base[lm_ids[36:42]].mean(axis=0),
        "mouth_inner": base[lm_ids[60:68]].mean(axis=0),
    }
    t_lines = {
        k: min(loops, key=lambda lp: np.linalg.norm(base[lp].mean(axis=0) - c))
        for k, c in centres.items()
    }
    t_lines["mouth_outer"] = lm_ids[48:60]
    from scipy.spatial import cKDTree

    tree = cKDTree(s_vertices)

    def chain(points: np.ndarray) -> np.ndarray:
        ids = tree.query(points)[1]
        ids = ids[np.r_[True, ids[1:] != ids[:-1]]]
        _, first = np.unique(ids, return_index=True)
        return ids[np.sort(first)].astype(np.int64)

    s_lines = {
        "eye_L": chain(s_points[42:48]),
        "eye_R": chain(s_points[36:42]),
        "mouth_outer": chain(s_points[48:60]),
        "mouth_inner": chain(s_face[t_lines["mouth_inner"]]),
    }

    src = _Side(source_rig, s_landmarks, s_lines, _ict_masks(s_mesh, s_points))
    tgt = _Side(
        target_rig,
        Landmarks(lm_ids, names=ICT_LANDMARK_NAMES),
        t_lines,
        _ict_masks(t_mesh, t_mesh.vertices[lm_ids]),
    )
    region.setflags(write=False)
    meta = {"source_region": region, "source_weights": w}
    return src, tgt, meta


def cross_topology(
    seed: int = 0,
    n_frames: int = 120,
    fps: float = 30.0,
    head_motion: bool = False,
    source_identity: npt.ArrayLike | None = None,
    target_identity: npt.ArrayLike | None = None,
    wrinkles: bool = False,
    source_subdivisions: int | None = None,
) -> Case:
    """A source mesh of another topology: a closed-eye head with a mouth bag onto the open-eye ICT face.

    The source is what a scanned or sculpted head looks like next to the ICT face
    (committed fixture ``data/ict_cross_topology_fixture.npz``, derived by
    ``data/derive_ict_cross_topology.py``):

    - **eyes closed, eyelid holes filled**: the lids are shut (the ICT ``eyeBlink`` shapes
      at 1), what was hidden behind them removed and the slit sewn, so the source has no
      eye holes where the target has two;
    - **a mouth bag**: a 3 cm pocket continues the lips into the mouth (the target has a
      mouth hole and no bag);
    - **different boundaries**: the forehead cut 4 cm lower than the target's, and a 2.4 cm
      skirt continuing the sides, jaw line and neck beyond the target's outline;
    - **remeshed** to 2,357 vertices / 4,600 triangles (the target: ICT, 9,409 vertices).

    Both rigs are ICT-FaceKit rigs with the same generic expression deltas on different
    identities (as ``ict(expressions="same")``), so the target driven by the source's
    weights is the right answer. Units agree (centimetres). The weights are the
    animation-like curves of :func:`cross_rig` (expressions held, speech) with the shapes
    a sewn-shut eye cannot perform (``eyeBlink``, ``eyeWide``) at zero.

    ``meta`` adds ``source_region`` (V_s,) int (index into :data:`CROSS_TOPOLOGY_REGIONS`:
    face, eye fill, mouth bag, skirt) and ``source_weights``: the (V_s, 9409) sparse
    matrix ``W`` with ``source = W @ (ICT face + blinks) + offset``; for face vertices
    ``W @ target.neutral.vertices`` is the exact corresponding target point.

    **Wrinkles** (``wrinkles=True``; the setting of the dense methods' detail claims: fine
    detail of a dense source carried to a target of another mesh). ``source_subdivisions``
    (default: 1 with wrinkles, else 0) splits every source triangle into 4 at its edge
    midpoints, that many times: 9,313 vertices at 1 (median edge 0.30 cm, the target's 0.29
    cm), the new vertices and their rows of ``W`` and ``offset`` the averages of the edge's
    ends, so the construction stays exact (landmarks are the same surface points). The
    wrinkle field is defined once on the *generic* ICT neutral (material points in cm; see
    ``_cross_topology_wrinkle_fields``): glabella and procerus lines on
    ``browDown_L/R``, chin dimpling on ``mouthPress_L/R``, perioral lines on
    ``mouthPucker``, sinusoids of wavelength :data:`CROSS_TOPOLOGY_WRINKLE_WAVELENGTH`
    (1.5 cm; median edges per wavelength in the three windows: 5.2, 4.1 and 6.8 on the
    subdivided source, 4.6, 3.8 and 7.3 on the target) and
    depth :data:`CROSS_TOPOLOGY_WRINKLE_DEPTH` (0.06 cm) under Gaussian windows. Through the
    case's exact correspondence it is evaluated at each source vertex's material point
    ``W_i @ generic`` (face region only) and at each target vertex's own generic vertex, and
    added to that shape's delta of both rigs along the vertex normals of each neutral, the
    target's depth times the size ratio of the two identities (RMS distance of the ICT
    vertices to their centroid, target / source: 1.14). So the source performance and the
    truth (the target rig driven by the source's weights) hold the same wrinkles, defined
    without any method. ``meta["wrinkles"]``, ``meta["source_subdivisions"]``. With
    ``source_subdivisions=0`` the wrinkles are 2-4 source edges long (aliased).
    """
    _check_counts(n_frames=n_frames)
    fps = as_fps(fps)
    if source_subdivisions is None:
        source_subdivisions = 1 if wrinkles else 0
    if int(source_subdivisions) != source_subdivisions or not 0 <= source_subdivisions <= 2:
        raise InputError(
            f"cross_topology: source_subdivisions must be 0, 1 or 2, got {source_subdivisions!r}"
        )
    src, tgt, pair_meta = _cross_topology_pair(
        _identity_key(source_identity, ICT_SOURCE_IDENTITY, "source_identity", "cross_topology"),
        _identity_key(target_identity, ICT_TARGET_IDENTITY, "target_identity", "cross_topology"),
        int(source_subdivisions),
        bool(wrinkles),
    )
    names = src.rig.names
    weights = _performance_weights(np.random.default_rng([int(seed), 5]), int(n_frames), fps, names)
    weights[:, [names.index(n) for n in _CLOSED_EYE_SHAPES]] = 0.0
    s_vertices = src.rig.neutral.vertices
    return _assemble(
        "cross-topology",
        src,
        tgt,
        n_frames=int(n_frames),
        fps=fps,
        seed=seed,
        head_motion=head_motion,
        pivot=np.array([0.0, s_vertices[:, 1].min(), s_vertices[:, 2].min()]),
        meta={
            "seed": seed,
            "source_region": pair_meta["source_region"],
            "source_weights": pair_meta["source_weights"].copy(),
            **(
                {"wrinkles": bool(wrinkles), "source_subdivisions": int(source_subdivisions)}
                if wrinkles or source_subdivisions
                else {}
            ),
        },
        weights=weights,
    )


#: Built-in case generators by name.
CASES: dict[str, Callable[..., Case]] = {
    "synthetic": synthetic,
    "ict": ict,
    "cross_rig": cross_rig,
    "cross_topology": cross_topology,
}


def get_case(name: str, **options: Any) -> Case:
    """A built-in case by name (``"synthetic"``, ``"ict"``, ``"cross_rig"``) with generator ``options``."""
    try:
        make = CASES[name]
    except KeyError:
        from ._validate import did_you_mean

        raise UnknownNameError(
            f"no case named {name!r}{did_you_mean(name, CASES)}; built-in cases: {', '.join(CASES)}"
        ) from None
    return make(**options)
