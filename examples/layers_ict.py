"""Parameter-parallel layers (Kholgade et al. 2011) on the ICT-FaceKit face.

What it does, end to end:

1. The actor: a performance of the ICT face with another identity (``faceretarget.cases.ict``),
   seen only through its 68 landmarks, used as motion-capture markers (with head motion).
2. The actor's simplices, the paper's way: a range-of-motion take in which the actor
   holds each emotion / viseme / blink pose in turn; we *hand-pick* those frames
   (``actor_layers_from_frames``), and masks come from where the ARKit shapes move.
3. The character: the real ICT-FaceKit generic face (``ict_face.npz``, 9409 vertices,
   ARKit names with ``_L``/``_R``), whose layered rig is built from its blendshapes through
   the emotion/viseme/blink recipes (``layered_rig_from_blendshapes``).
4. Retarget, compare with the ground truth (the character driven by the actor's true
   weights), stream a few frames, write a GLB, and run the same through the CLI.

Usage: python examples/layers_ict.py [--ict PATH/ict_face.npz] [--frames 120] [--out DIR]
"""

from __future__ import annotations

import argparse
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

import faceretarget as fr
from faceretarget import recipes
from faceretarget.plugins.layers import (
    actor_layers_from_frames,
    default_masks,
    layered_rig_from_blendshapes,
)


def range_of_motion(rig: fr.BlendshapeRig, landmarks: fr.Landmarks, hold: int = 6, seed: int = 1):
    """The actor holds every recipe pose for ``hold`` frames, moving the head; returns the
    markers (F, 68, 3) and, per layer, {pose name: the frame in the middle of its hold}."""
    rng = np.random.default_rng(seed)
    tables = {"emotion": recipes.EMOTIONS, "speech": recipes.VISEMES, "blink": recipes.BLINKS}
    weights, picks = [], {}
    for layer, table in tables.items():
        picks[layer] = {}
        for name, recipe in table.items():
            w = recipes.resolve(recipe, rig.names, on_unmapped="ignore")
            picks[layer][name] = len(weights) + hold // 2
            weights += [w] * hold
    local = landmarks.positions(rig.evaluate(np.array(weights)))
    n = len(local)
    angles = np.deg2rad(np.cumsum(rng.normal(0, 0.6, size=(n, 3)), axis=0))
    cx, sx, cy, sy = (
        np.cos(angles[:, 0]),
        np.sin(angles[:, 0]),
        np.cos(angles[:, 1]),
        np.sin(angles[:, 1]),
    )
    rot = np.einsum(
        "fij,fjk->fik",
        np.stack(
            [
                np.stack([cy, 0 * cy, sy], 1),
                np.stack([0 * cy, 1 + 0 * cy, 0 * cy], 1),
                np.stack([-sy, 0 * cy, cy], 1),
            ],
            1,
        ),
        np.stack(
            [
                np.stack([1 + 0 * cx, 0 * cx, 0 * cx], 1),
                np.stack([0 * cx, cx, -sx], 1),
                np.stack([0 * cx, sx, cx], 1),
            ],
            1,
        ),
    )
    shift = np.cumsum(rng.normal(0, 0.05, size=(n, 3)), axis=0)
    return np.einsum("fij,fpj->fpi", rot, local) + shift[:, None], picks


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument(
        "--ict",
        type=Path,
        default=None,
        help="an ICT-FaceKit rig export (neutral, expression deltas/names); default: the committed fixture",
    )
    parser.add_argument("--frames", type=int, default=120)
    parser.add_argument(
        "--out", type=Path, default=None, help="output folder (default: a temporary one)"
    )
    args = parser.parse_args(argv)
    out = args.out or Path(tempfile.mkdtemp(prefix="layers_ict_"))
    out.mkdir(parents=True, exist_ok=True)

    # 1. the actor's performance: 68 landmarks of an ICT identity, with head motion
    case = fr.cases.ict(n_frames=args.frames)
    actor_rig, landmarks = case.source.rig, case.source.landmarks
    markers = fr.MarkerSequence(
        case.source.marker_positions(),
        names=landmarks.names,
        fps=case.source.fps,
        reference=case.source.marker_reference(),
    )

    # 2. the actor's simplices from hand-picked frames of a range-of-motion take
    rom, picks = range_of_motion(actor_rig, landmarks)
    actor_masks = default_masks(actor_rig)[:, landmarks.vertex_ids]
    actor_layers = actor_layers_from_frames(
        rom,
        picks,
        actor_masks,
        reference=markers.reference,
        region_names=("upper_face", "eyes", "mouth"),
    )
    source = fr.Source(markers, actor_layers=actor_layers, name="ICT actor (68 markers)")
    print(f"actor: {markers}, layers {actor_layers}")

    # 3. the character: the ICT generic face, layers from its ARKit blendshapes
    if args.ict is not None:
        char_rig = fr.load(args.ict, kind="rig")
        where = str(args.ict)
    else:  # the committed fixture of the same data (fewer expressions)
        char_rig = case.target.blendshapes
        where = "faceretarget.cases.ict fixture"
    char_layers = layered_rig_from_blendshapes(char_rig, on_unmapped="ignore")
    target = fr.TargetRig(
        char_rig.neutral, blendshapes=char_rig, layers=char_layers, name="ICT generic face"
    )
    print(f"character: {target} from {where}; {char_layers}")

    # ground truth: the character driven by the actor's true weights, with the actor's head motion
    index = {n: i for i, n in enumerate(char_rig.names)}
    true_w = np.zeros((args.frames, char_rig.n_shapes))
    for k, name in enumerate(case.meta["weight_names"]):
        true_w[:, index[name]] = case.meta["weights"][:, k]
    truth = fr.Animation(
        weights=true_w, rig=char_rig, head_motion=case.meta["head_motion"]
    ).vertices
    height = char_rig.neutral.height

    # 4. retarget (defaults), and with the projection onto the character's blendshapes
    for params in ({}, {"project_blendshapes": True}):
        r = fr.get("layers", **params)
        t0 = time.perf_counter()
        anim = r.fit(source, target).retarget(source)
        took = time.perf_counter() - t0
        err = np.sqrt(np.mean(np.sum((np.asarray(anim.vertices) - truth) ** 2, axis=-1))) / height
        print(
            f"layers {params or '(defaults)'}: {args.frames} frames in {took:.2f} s (first call compiles), "
            f"RMS error {100 * err:.2f}% of face height; {anim.provenance['diagnostics']}"
        )
    w = anim.extras["layer_weights"]
    for l, region in enumerate(anim.extras["region_names"]):
        share = ", ".join(
            f"{layer} {w[:, l, j].mean():.2f}" for j, layer in enumerate(anim.extras["layer_names"])
        )
        print(f"  region {region}: mean layer weights {share}")
    emotion = anim.extras["coefficients"]["emotion"]
    names = char_layers.pose_names["emotion"]
    print("  dominant emotion every 20 frames:", [names[i] for i in emotion[::20].argmax(axis=1)])

    streamed = np.stack(list(r.stream(markers.positions[:10])))
    print(
        f"stream: first 10 frames agree with batch to {np.abs(streamed - anim.vertices[:10]).max():.1e}"
    )

    fr.save(anim, out / "layers_ict.glb", force=True)
    fr.io.save_bundle(source, out / "actor.npz", force=True)
    fr.io.save_bundle(target, out / "character.npz", force=True)
    cmd = [
        "faceretarget",
        "run",
        "layers",
        "--source",
        str(out / "actor.npz"),
        "--target",
        str(out / "character.npz"),
        "--out",
        str(out / "layers_cli.glb"),
        "--force",
    ]
    done = subprocess.run(cmd, capture_output=True, text=True)
    print(
        f"wrote {out / 'layers_ict.glb'}; CLI: {' '.join(cmd)} -> {(done.stdout or done.stderr).strip().splitlines()[-1]}"
    )
    return done.returncode


if __name__ == "__main__":
    sys.exit(main())
