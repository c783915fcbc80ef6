"""FACS-based expression recipes over ARKit-named blendshapes, as plain data.

A *recipe* maps ARKit shape names (``eyeBlinkLeft``, ``jawOpen``...) to weights in
[0, 1]. The emotion recipes follow the EMFACS prototypes (Ekman & Friesen), each
action unit read as the ARKit shape that animates it:

- AU1 inner brow raiser -> ``browInnerUp``; AU2 outer brow raiser -> ``browOuterUp*``;
  AU4 brow lowerer -> ``browDown*``; AU5 upper lid raiser -> ``eyeWide*``;
  AU6 cheek raiser -> ``cheekSquint*``; AU9 nose wrinkler -> ``noseSneer*``;
  AU10 upper lip raiser -> ``mouthUpperUp*``; AU12 lip corner puller -> ``mouthSmile*``;
  AU15 lip corner depressor -> ``mouthFrown*``; AU18 lip pucker -> ``mouthPucker``;
  AU20 lip stretcher -> ``mouthStretch*``; AU22 lip funneler -> ``mouthFunnel``;
  AU24 lip presser -> ``mouthPress*``; AU26/27 jaw drop -> ``jawOpen``;
  AU28 lip suck -> ``mouthRollLower``; AU45 blink -> ``eyeBlink*``.

Every recipe uses only the 17 base shapes listed in :data:`RECIPE_SHAPES` (28 with
sides), which every ARKit rig and ICT-FaceKit have, and keeps the sum of one emotion
and one viseme at most 1 per shape, so layered poses combine without leaving [0, 1].

:func:`resolve` turns a recipe into the weight vector of a given rig, matching names
case-insensitively and through the usual spellings (``eyeBlink_L``, ``EyeBlinkLeft``,
``eye_blink_left``); split or merged left/right shapes are handled, and names the rig
lacks are reported (warning, error or list, as asked), never dropped silently.
"""

from __future__ import annotations

import re
import warnings
from collections.abc import Iterable, Mapping, Sequence

import numpy as np

from .errors import UnknownNameError

__all__ = [
    "ARKIT_NAMES",
    "RECIPE_SHAPES",
    "EMOTIONS",
    "VISEMES",
    "BLINKS",
    "RecipeWarning",
    "normalize_shape_name",
    "resolve",
    "resolve_all",
    "unmapped_names",
]

#: The 52 ARKit blendshape names (Apple ``ARFaceAnchor.BlendShapeLocation``).
ARKIT_NAMES: tuple[str, ...] = (
    "browDownLeft",
    "browDownRight",
    "browInnerUp",
    "browOuterUpLeft",
    "browOuterUpRight",
    "cheekPuff",
    "cheekSquintLeft",
    "cheekSquintRight",
    "eyeBlinkLeft",
    "eyeBlinkRight",
    "eyeLookDownLeft",
    "eyeLookDownRight",
    "eyeLookInLeft",
    "eyeLookInRight",
    "eyeLookOutLeft",
    "eyeLookOutRight",
    "eyeLookUpLeft",
    "eyeLookUpRight",
    "eyeSquintLeft",
    "eyeSquintRight",
    "eyeWideLeft",
    "eyeWideRight",
    "jawForward",
    "jawLeft",
    "jawOpen",
    "jawRight",
    "mouthClose",
    "mouthDimpleLeft",
    "mouthDimpleRight",
    "mouthFrownLeft",
    "mouthFrownRight",
    "mouthFunnel",
    "mouthLeft",
    "mouthLowerDownLeft",
    "mouthLowerDownRight",
    "mouthPressLeft",
    "mouthPressRight",
    "mouthPucker",
    "mouthRight",
    "mouthRollLower",
    "mouthRollUpper",
    "mouthShrugLower",
    "mouthShrugUpper",
    "mouthSmileLeft",
    "mouthSmileRight",
    "mouthStretchLeft",
    "mouthStretchRight",
    "mouthUpperUpLeft",
    "mouthUpperUpRight",
    "noseSneerLeft",
    "noseSneerRight",
    "tongueOut",
)

#: The shapes the recipes below use (the synthetic rigs of ``faceretarget.cases`` have all).
RECIPE_SHAPES: tuple[str, ...] = (
    "jawOpen",
    "mouthClose",
    "mouthFunnel",
    "mouthPucker",
    "mouthSmileLeft",
    "mouthSmileRight",
    "mouthFrownLeft",
    "mouthFrownRight",
    "mouthStretchLeft",
    "mouthStretchRight",
    "mouthPressLeft",
    "mouthPressRight",
    "mouthUpperUpLeft",
    "mouthUpperUpRight",
    "mouthRollLower",
    "eyeBlinkLeft",
    "eyeBlinkRight",
    "eyeWideLeft",
    "eyeWideRight",
    "browInnerUp",
    "browOuterUpLeft",
    "browOuterUpRight",
    "browDownLeft",
    "browDownRight",
    "cheekSquintLeft",
    "cheekSquintRight",
    "noseSneerLeft",
    "noseSneerRight",
)


def _both(base: str, value: float) -> dict[str, float]:
    return {base + "Left": value, base + "Right": value}


#: Emotion prototypes (EMFACS action units, see the module docstring).
EMOTIONS: dict[str, dict[str, float]] = {
    "neutral": {},
    # AU6 + AU12
    "happiness": {**_both("cheekSquint", 0.6), **_both("mouthSmile", 0.8)},
    # AU1 + AU4 + AU15
    "sadness": {"browInnerUp": 0.7, **_both("browDown", 0.25), **_both("mouthFrown", 0.6)},
    # AU4 + AU5 + AU7 + AU24 (lid tightening read as a light cheek raise)
    "anger": {
        **_both("browDown", 0.8),
        **_both("eyeWide", 0.25),
        **_both("mouthPress", 0.5),
        **_both("noseSneer", 0.2),
    },
    # AU1 + AU2 + AU5 + AU26
    "surprise": {
        "browInnerUp": 0.7,
        **_both("browOuterUp", 0.8),
        **_both("eyeWide", 0.7),
        "jawOpen": 0.3,
    },
    # AU1 + AU2 + AU4 + AU5 + AU20 + AU26
    "fear": {
        "browInnerUp": 0.8,
        **_both("browOuterUp", 0.35),
        **_both("browDown", 0.2),
        **_both("eyeWide", 0.75),
        **_both("mouthStretch", 0.5),
        "jawOpen": 0.2,
    },
    # AU9 + AU10 + AU15
    "disgust": {
        **_both("noseSneer", 0.8),
        **_both("mouthUpperUp", 0.5),
        **_both("mouthFrown", 0.3),
        **_both("cheekSquint", 0.3),
    },
    # unilateral AU12 + AU14 (left side)
    "contempt": {"mouthSmileLeft": 0.45, "mouthStretchLeft": 0.2, "cheekSquintLeft": 0.2},
}

#: Viseme prototypes (Preston Blair / Disney mouth chart classes). "MBP" (closed lips)
#: comes first: it is the rest pose of a speech layer.
VISEMES: dict[str, dict[str, float]] = {
    "MBP": _both("mouthPress", 0.35),
    "AA": {"jawOpen": 0.6, **_both("mouthStretch", 0.1)},
    "E": {"jawOpen": 0.3, **_both("mouthStretch", 0.4), **_both("mouthSmile", 0.15)},
    "I": {"jawOpen": 0.15, **_both("mouthStretch", 0.45), **_both("mouthSmile", 0.2)},
    "O": {"jawOpen": 0.35, "mouthFunnel": 0.6, "mouthPucker": 0.2},
    "U": {"jawOpen": 0.1, "mouthPucker": 0.7, "mouthFunnel": 0.3},
    "FV": {"mouthRollLower": 0.6, **_both("mouthUpperUp", 0.2), "jawOpen": 0.05},
    "L": {"jawOpen": 0.35, **_both("mouthUpperUp", 0.1), **_both("mouthStretch", 0.1)},
    "WQ": {"mouthPucker": 0.9, "jawOpen": 0.05},
    "CH": {"jawOpen": 0.15, "mouthFunnel": 0.45, **_both("mouthUpperUp", 0.25)},
    "S": {"jawOpen": 0.05, **_both("mouthStretch", 0.3), **_both("mouthSmile", 0.1)},
    "TH": {"jawOpen": 0.2, "mouthRollLower": 0.2, **_both("mouthUpperUp", 0.1)},
}

#: Eyelid poses.
BLINKS: dict[str, dict[str, float]] = {
    "open": {},
    "half": _both("eyeBlink", 0.5),
    "closed": _both("eyeBlink", 1.0),
    "winkLeft": {"eyeBlinkLeft": 1.0},
    "winkRight": {"eyeBlinkRight": 1.0},
}


class RecipeWarning(UserWarning):
    """A recipe names shapes the rig does not have (they are reported, not used)."""


_SIDES = {"left": "Left", "right": "Right", "l": "Left", "r": "Right", "lf": "Left", "rt": "Right"}
_ARKIT_KEY = {n.lower(): n for n in ARKIT_NAMES}
_UNSIDED = {n.lower(): n for n in ARKIT_NAMES if not n.endswith(("Left", "Right"))}
_SIDED_BASE = {
    n[: -len(s)].lower(): n[: -len(s)]
    for n in ARKIT_NAMES
    for s in ("Left", "Right")
    if n.endswith(s)
}


def normalize_shape_name(name: str) -> str | None:
    """Canonical ARKit spelling of a blendshape name, or None if it is not an ARKit shape.

    Accepts case variants (``EyeBlinkLeft``), separators (``eye_blink_left``,
    ``eye-blink-left``), side suffixes ``_L``/``_R``/``.L``/``Left``/``L`` and namespace
    prefixes (``blendShape1.eyeBlink_L``, ``face:eyeBlinkLeft``). Split versions of the
    unsided ARKit shapes (ICT-FaceKit's ``browInnerUp_L``) become ``browInnerUpLeft``.
    """
    raw = str(name).strip()
    for sep in (":", "|"):
        raw = raw.rsplit(sep, 1)[-1]
    parts = [p for p in re.split(r"[\s_\-.]+", raw) if p]
    if not parts:
        return None
    candidates = []
    # a prefix before a dot (blendShape1.eyeBlink_L) is tried both kept and dropped
    for start in range(len(parts)):
        tokens = parts[start:]
        side = None
        if len(tokens) > 1 and tokens[-1].lower() in _SIDES:
            side = _SIDES[tokens[-1].lower()]
            tokens = tokens[:-1]
        candidates.append(("".join(tokens).lower(), side))
    for key, side in candidates:
        found = _lookup(key, side)
        if found is not None:
            return found
    return None


def _lookup(key: str, side: str | None) -> str | None:
    if side is None:
        if key in _ARKIT_KEY:
            return _ARKIT_KEY[key]
        for suffix, s in (("l", "Left"), ("r", "Right")):  # eyeBlinkL
            if key.endswith(suffix) and key[:-1] in _SIDED_BASE:
                return _SIDED_BASE[key[:-1]] + s
        for suffix, s in (("left", "Left"), ("right", "Right")):  # browInnerUpLeft (split unsided)
            if key.endswith(suffix) and key[: -len(suffix)] in _UNSIDED:
                return _UNSIDED[key[: -len(suffix)]] + s
        return None
    if key + side.lower() in _ARKIT_KEY:
        return _ARKIT_KEY[key + side.lower()]
    if key in _UNSIDED:
        return _UNSIDED[key] + side
    return None


def _rig_index(rig_names: Sequence[str]) -> dict[str, int]:
    index: dict[str, int] = {}
    for i, n in enumerate(rig_names):
        canon = normalize_shape_name(n)
        key = canon if canon is not None else str(n)
        index.setdefault(key, i)
    return index


def _targets(name: str, index: Mapping[str, int]) -> list[tuple[int, float]] | None:
    """Rig columns (and factors) that a canonical recipe name drives; None if none."""
    if name in index:
        return [(index[name], 1.0)]
    for side in ("Left", "Right"):
        if name.endswith(side) and name[: -len(side)] in index:
            # a merged rig shape: a sided recipe weight counts half
            return [(index[name[: -len(side)]], 0.5)]
    left, right = name + "Left", name + "Right"
    if left in index and right in index:
        # a split rig (ICT browInnerUp_L / _R): drive both halves
        return [(index[left], 1.0), (index[right], 1.0)]
    return None


def unmapped_names(recipe: Mapping[str, float], rig_names: Sequence[str]) -> list[str]:
    """The recipe's shape names that ``rig_names`` cannot express (in recipe order)."""
    index = _rig_index(rig_names)
    return [n for n in recipe if _targets(normalize_shape_name(n) or n, index) is None]


def resolve(
    recipe: Mapping[str, float], rig_names: Sequence[str], *, on_unmapped: str = "warn"
) -> np.ndarray:
    """The weight vector ``(M,)`` float64 of a recipe on a rig with shapes ``rig_names``.

    Parameters
    ----------
    recipe : mapping ARKit name -> weight
    rig_names : sequence of M str
        The rig's shape names in any supported spelling (see :func:`normalize_shape_name`).
    on_unmapped : "warn" | "raise" | "ignore"
        What to do with recipe names the rig lacks: a :class:`RecipeWarning` naming them,
        an :class:`~faceretarget.errors.UnknownNameError`, or nothing (use
        :func:`unmapped_names` to list them yourself).
    """
    if on_unmapped not in ("warn", "raise", "ignore"):
        raise UnknownNameError(
            f"resolve: on_unmapped must be 'warn', 'raise' or 'ignore', got {on_unmapped!r}"
        )
    names = list(rig_names)
    index = _rig_index(names)
    out = np.zeros(len(names))
    missing = []
    for name, weight in recipe.items():
        targets = _targets(normalize_shape_name(name) or name, index)
        if targets is None:
            missing.append(name)
            continue
        for column, factor in targets:
            out[column] += factor * float(weight)
    if missing:
        message = (
            f"recipe shape(s) {', '.join(missing)} not found in the rig (its shapes: {', '.join(names[:8])}"
            f"{', ...' if len(names) > 8 else ''}); add them or map their names"
        )
        if on_unmapped == "raise":
            raise UnknownNameError(message)
        if on_unmapped == "warn":
            warnings.warn(message, RecipeWarning, stacklevel=2)
    return out


def resolve_all(
    recipes: Mapping[str, Mapping[str, float]],
    rig_names: Sequence[str],
    *,
    names: Iterable[str] | None = None,
    on_unmapped: str = "warn",
) -> np.ndarray:
    """Weight vectors of several recipes stacked ``(K, M)`` (``names`` picks and orders them)."""
    keys = list(recipes) if names is None else list(names)
    unknown = [k for k in keys if k not in recipes]
    if unknown:
        raise UnknownNameError(f"no recipe named {', '.join(unknown)}; known: {', '.join(recipes)}")
    return (
        np.stack([resolve(recipes[k], rig_names, on_unmapped=on_unmapped) for k in keys])
        if keys
        else np.zeros((0, len(rig_names)))
    )
