"""Building the simplicial bases of the layered model (Kholgade et al. 2011, sec. 3.1).

- :func:`actor_layers_from_frames`: the actor's simplices from hand-picked frames of a
  performance ("We hand-pick the frames for the actor simplices from actor
  performance"), each frame rigidly aligned to the neutral first.
- :func:`layered_rig_from_blendshapes`: a character's simplices from an ARKit-named
  blendshape rig through expression recipes (``faceretarget.recipes``: EMOTIONS,
  VISEMES, BLINKS), so any ARKit character gets emotion/speech/blink layers without an
  artist posing them (an artist's poses are better; these are a starting point).
- :func:`default_masks`: region masks from the blendshapes' spatial support.
"""

from __future__ import annotations

from collections.abc import Mapping, Sequence

import numpy as np

from faceretarget.errors import (
    CapabilityError,
    IndexRangeError,
    InputError,
    NonFiniteError,
    ShapeError,
)
from faceretarget.geometry.procrustes import fit_rigid
from faceretarget.model import BlendshapeRig, LayeredRig, MarkerSequence, Source

__all__ = [
    "actor_layers_from_frames",
    "layered_rig_from_blendshapes",
    "default_masks",
    "REGION_NAMES",
    "SHAPE_REGIONS",
]

#: Rounds of rigidity-weighted Procrustes when aligning hand-picked frames (after a plain fit).
ALIGN_ROUNDS = 3
#: Default regions, in the order of the paper's masks (upper face, eyes, lower face).
REGION_NAMES = ("upper_face", "eyes", "mouth")
#: ARKit name prefixes -> region (index into REGION_NAMES) for :func:`default_masks`.
SHAPE_REGIONS = {
    "brow": 0,
    "noseSneer": 0,
    "eyeBlink": 1,
    "eyeLook": 1,
    "eyeSquint": 1,
    "eyeWide": 1,
    "cheekSquint": 1,
    "jaw": 2,
    "mouth": 2,
    "cheekPuff": 2,
    "tongue": 2,
}


def actor_layers_from_frames(
    markers,
    frames: Mapping[str, object],
    masks=None,
    *,
    reference=None,
    region_names=None,
    head_motion=None,
    align: bool = True,
) -> LayeredRig:
    """An actor :class:`~faceretarget.model.LayeredRig` from chosen frames of a performance.

    Parameters
    ----------
    markers : MarkerSequence, Source, or (F, N, D) float (D = 3, or 2 for tracks)
        The performance; NaN = missing (a chosen frame must be complete).
    frames : mapping layer -> frame indices, or layer -> {pose name: frame index}
        e.g. ``{"emotion": {"neutral": 0, "joy": 212}, "speech": [40, 57, 93], "blink": [0, 130]}``.
    masks : (R, N) float, optional
        Region masks over the markers (default: one region covering all).
    reference : (N, D) float, optional
        The neutral pose the frames are aligned to (default: the sequence's reference,
        else frame 0).
    head_motion : (F, 4, 4) float, optional
        Known 3D head motion (neutral -> world), removed exactly from the chosen frames
        (default: ``Source.head_motion`` when ``markers`` is a Source that has it).
    align : bool
        Without known head motion, remove it from each chosen frame by Procrustes onto the
        reference (similarity for 2D tracks), so the poses are expression only. The fit is
        weighted by rigidity (points the chosen expressions barely move count most),
        re-estimated from the aligned poses (``ALIGN_ROUNDS``): plain Procrustes would take
        part of each expression for head motion and bake a small rotation into the pose
        (measured on the ICT example: up to 3-5 degrees, which the retargeting then
        reports as head motion).
    """
    if isinstance(markers, Source):
        if head_motion is None:
            head_motion = markers.head_motion
        positions, ref_default = (
            np.asarray(markers.marker_positions(), float),
            np.asarray(markers.marker_reference(), float),
        )
    elif isinstance(markers, MarkerSequence):
        positions, ref_default = (
            np.asarray(markers.positions, float),
            np.asarray(markers.reference, float),
        )
    else:
        positions = np.asarray(markers, dtype=np.float64)
        ref_default = None
    if positions.ndim != 3 or positions.shape[-1] not in (2, 3):
        raise ShapeError(
            f"actor_layers_from_frames: markers must be (F, N, 3) or (F, N, 2), got {positions.shape}"
        )
    n_frames, n_points, dim = positions.shape
    if reference is None:
        reference = ref_default if ref_default is not None else positions[0]
    ref = np.asarray(reference, dtype=np.float64)
    if ref.shape != (n_points, dim) or not np.all(np.isfinite(ref)):
        raise ShapeError(
            f"actor_layers_from_frames: reference must be finite ({n_points}, {dim}), got {ref.shape}"
        )
    if not isinstance(frames, Mapping) or not frames:
        raise InputError(
            "actor_layers_from_frames: frames must map each layer name to its frame indices"
        )
    layers, pose_names, chosen_frames = {}, {}, {}
    for layer, chosen in frames.items():
        names, ids = (
            (list(chosen.keys()), list(chosen.values()))
            if isinstance(chosen, Mapping)
            else (None, list(np.atleast_1d(chosen)))
        )
        if not ids:
            raise ShapeError(f"actor_layers_from_frames: layer {layer!r} has no frames")
        idx = np.asarray(ids)
        if idx.dtype.kind not in "iu":
            raise ShapeError(
                f"actor_layers_from_frames: layer {layer!r}: frame indices must be integers, got {ids}"
            )
        bad = idx[(idx < 0) | (idx >= n_frames)]
        if bad.size:
            raise IndexRangeError(
                f"actor_layers_from_frames: layer {layer!r}: frame {int(bad[0])} out of range 0..{n_frames - 1}"
            )
        poses = positions[idx]
        holes = np.isnan(poses).any(axis=-1)
        if holes.any():
            k, p = (int(i) for i in np.argwhere(holes)[0])
            raise NonFiniteError(
                f"actor_layers_from_frames: layer {layer!r}: frame {int(idx[k])} misses marker {p} "
                f"({int(holes[k].sum())} missing); pick a complete frame or fill the gaps first"
            )
        if head_motion is not None:
            motion = np.asarray(head_motion, dtype=np.float64)
            if dim != 3 or motion.shape != (n_frames, 4, 4):
                raise ShapeError(
                    f"actor_layers_from_frames: head_motion must be ({n_frames}, 4, 4) for 3D markers, got {motion.shape}"
                )
            rot, trans = motion[idx, :3, :3], motion[idx, :3, 3]
            poses = np.einsum("fji,fpj->fpi", rot, poses - trans[:, None, :])
        elif align:
            chosen_frames[str(layer)] = poses
        layers[str(layer)] = poses
        if names is not None:
            pose_names[str(layer)] = [str(n) for n in names]
    if chosen_frames:
        layers.update(_align_poses(ref, chosen_frames, dim))
    if masks is None:
        masks = np.ones((1, n_points))
    return LayeredRig(layers, masks, pose_names=pose_names or None, region_names=region_names)


def _align_poses(ref: np.ndarray, frames: dict, dim: int, rounds: int = ALIGN_ROUNDS) -> dict:
    """The chosen frames (layer -> (K, N, D)) without their head motion, all layers together.

    Plain Procrustes onto the neutral takes part of each expression for head motion (a jaw
    opening tilts the head). We weight it by rigidity instead, as the retargeter does:
    ``1 / (eps^2 + m_p^2)`` with ``m_p`` the RMS displacement of point p over the chosen
    poses once aligned (``eps = config.HEAD_MOTION_RIGIDITY`` face sizes), re-estimated over
    ``rounds`` rounds from the plain fit. 2D tracks: a similarity.
    """
    from faceretarget import config

    names = list(frames)
    stack = np.concatenate([frames[n] for n in names], axis=0)
    size = float(np.sqrt(np.mean(np.sum((ref - ref.mean(axis=0)) ** 2, axis=-1))))
    weights = None
    for _ in range(rounds + 1):
        rot, trans, scale = fit_rigid(ref, stack, weights, scale=(dim == 2))
        aligned = np.einsum("fji,fpj->fpi", rot, stack - trans[:, None, :]) / scale[:, None, None]
        motion2 = np.mean(np.sum((aligned - ref[None]) ** 2, axis=-1), axis=0)
        weights = 1.0 / ((config.HEAD_MOTION_RIGIDITY * size) ** 2 + motion2)
    out, start = {}, 0
    for n in names:
        out[n] = aligned[start : start + len(frames[n])]
        start += len(frames[n])
    return out


def _recipe_tables(recipes):
    if recipes is not None:
        if not isinstance(recipes, Mapping) or not recipes:
            raise InputError(
                "layered_rig_from_blendshapes: recipes must map layer -> {pose: {ARKit shape: weight}}"
            )
        return recipes
    try:
        from faceretarget import recipes as library
    except ImportError:  # pragma: no cover - the recipe library ships with faceretarget
        raise CapabilityError(
            "layered_rig_from_blendshapes: no recipe library installed; pass recipes="
        ) from None
    return {"emotion": library.EMOTIONS, "speech": library.VISEMES, "blink": library.BLINKS}


def layered_rig_from_blendshapes(
    rig: BlendshapeRig,
    recipes: Mapping[str, Mapping[str, Mapping[str, float]]] | None = None,
    masks=None,
    *,
    region_names: Sequence[str] | None = None,
    on_unmapped: str = "warn",
) -> LayeredRig:
    """A character's :class:`~faceretarget.model.LayeredRig` from an ARKit-named blendshape rig.

    Parameters
    ----------
    rig : BlendshapeRig
        Shape names in any spelling :func:`faceretarget.recipes.resolve` understands
        (``eyeBlinkLeft``, ``eyeBlink_L``, ...).
    recipes : mapping layer -> {pose name: {ARKit shape: weight}}, optional
        Default: ``{"emotion": EMOTIONS, "speech": VISEMES, "blink": BLINKS}`` from
        :mod:`faceretarget.recipes` (so the speech layer starts with the closed-lips "MBP").
    masks : (R, V) float, optional
        Region masks; default :func:`default_masks` (upper face, eyes, mouth).
    on_unmapped : "warn" | "raise" | "ignore"
        Recipe shapes the rig lacks (passed to ``resolve``).

    Each pose is ``rig.evaluate(resolve(recipe, rig.names))``: absolute vertices.
    """
    from faceretarget.recipes import resolve

    if not isinstance(rig, BlendshapeRig):
        raise InputError(
            f"layered_rig_from_blendshapes: expected a BlendshapeRig, got {type(rig).__name__}"
        )
    tables = _recipe_tables(recipes)
    layers, pose_names = {}, {}
    for layer, table in tables.items():
        if not isinstance(table, Mapping) or not table:
            raise InputError(
                f"layered_rig_from_blendshapes: layer {layer!r} needs at least one recipe"
            )
        weights = np.stack(
            [resolve(table[name], rig.names, on_unmapped=on_unmapped) for name in table]
        )
        layers[str(layer)] = rig.evaluate(weights)
        pose_names[str(layer)] = [str(n) for n in table]
    if masks is None:
        masks = default_masks(rig)
        region_names = REGION_NAMES if region_names is None else region_names
    return LayeredRig(layers, masks, pose_names=pose_names, region_names=region_names)


def default_masks(rig: BlendshapeRig, *, eps: float = 1e-9) -> np.ndarray:
    """(3, V) soft region masks (upper face, eyes, mouth) from where the blendshapes move.

    Each ARKit shape is assigned a region by name (:data:`SHAPE_REGIONS`: brows and nose
    sneer -> upper face; blinks, eye looks, squints, wides, cheek squint -> eyes; jaw,
    mouth, cheek puff, tongue -> mouth); a vertex's mask value for a region is the share
    of the displacement magnitude the region's shapes give it. Vertices no shape moves
    (relative ``eps``) go to the upper face; their value never matters for the output,
    since no pose displaces them. Shapes with non-ARKit names are ignored.
    """
    from faceretarget.recipes import normalize_shape_name

    deltas = np.asarray(rig.deltas, dtype=np.float64)
    support = np.zeros((len(REGION_NAMES), deltas.shape[1]))
    magnitude = np.linalg.norm(deltas, axis=-1)  # (M, V)
    used = 0
    for i, name in enumerate(rig.names):
        canon = normalize_shape_name(name) or str(name)
        region = next((r for prefix, r in SHAPE_REGIONS.items() if canon.startswith(prefix)), None)
        if region is not None:
            support[region] += magnitude[i]
            used += 1
    if used == 0:
        raise CapabilityError(
            "default_masks: no blendshape has an ARKit name (brow*, eye*, jaw*, mouth*...); pass masks= explicitly"
        )
    total = support.sum(axis=0)
    still = total <= eps * max(float(total.max()), np.finfo(float).tiny)
    support[:, still] = 0.0
    support[0, still] = 1.0
    return support / support.sum(axis=0, keepdims=True)
