"""Hierarchical retargeting through normal meshes (Na & Jung 2004) on the ICT-FaceKit parallel rigs.

Builds ``faceretarget.cases.ict()`` (two ICT identities, a dense source performance with
rigid head motion, 7 example pose pairs, 68 landmarks, ground truth), retargets it with
``normalmesh``, and prints the error against the ground truth (with and without the detail
levels, and against the 'no expression' answer), the normal meshes' sizes, the piercing
errors per mesh (the paper's Table 1) and timings. With ``--out``, writes the retargeted
animation and the target's normal mesh at a level of your choice.

    python examples/normalmesh_ict.py                      # 120 frames, default parameters
    python examples/normalmesh_ict.py --levels 5           # the paper's gorilla setting
    python examples/normalmesh_ict.py --out results/ --level 2

The ICT data (MIT licence, see ``faceretarget/data/ICT-FaceKit-LICENSE.txt``) ships with the
package as a fixture (the face region of the ICT-FaceKit model, https://github.com/ICT-VGL/ICT-FaceKit).
"""

from __future__ import annotations

import argparse
import time
from pathlib import Path

import numpy as np

import faceretarget as fr


def rms(a, b) -> float:
    return float(np.sqrt(np.mean(np.sum((np.asarray(a) - np.asarray(b)) ** 2, axis=-1))))


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--frames", type=int, default=120)
    parser.add_argument("--levels", type=int, default=4, help="normal-mesh levels (paper: 4-5)")
    parser.add_argument(
        "--expressions",
        choices=("same", "transferred"),
        default="transferred",
        help="'transferred': each identity's expressions adapted to its shape (harder)",
    )
    parser.add_argument(
        "--out",
        type=Path,
        default=None,
        help="folder for the animation (.npz, .glb) and a normal mesh (.npz)",
    )
    parser.add_argument("--level", type=int, default=2, help="normal-mesh level written with --out")
    args = parser.parse_args()

    start = time.perf_counter()
    case = fr.cases.ict(n_frames=args.frames, expressions=args.expressions)
    truth = np.asarray(case.truth.vertices)
    height = case.target.neutral.height
    print(
        f"{case!r}: {args.frames} frames, {len(case.target.landmarks)} landmarks, "
        f"{len(case.target.example_names)} example pairs, face height {height:.1f} cm ({time.perf_counter() - start:.1f} s)"
    )

    start = time.perf_counter()
    retargeter = fr.get("normalmesh", levels=args.levels).fit(case.source, case.target)
    fit_s = time.perf_counter() - start
    start = time.perf_counter()
    anim = retargeter.retarget(case.source)
    per_frame = (time.perf_counter() - start) / case.source.n_frames
    hier = retargeter.hierarchy_
    print(
        f"\nbase mesh: {len(retargeter.base_triangles_)} triangles over {hier.n_base} feature points; "
        f"normal mesh: {hier.levels} levels, {hier.n_vertices(hier.levels)} vertices; delta = {retargeter.delta_:.3f}"
    )
    print(f"fit {fit_s:.2f} s, retarget {1e3 * per_frame:.1f} ms per frame")

    hm = np.asarray(case.truth.head_motion)
    static = (
        np.einsum("fij,pj->fpi", hm[:, :3, :3], case.target.neutral.vertices) + hm[:, None, :3, 3]
    )
    base_only = (
        fr.get("normalmesh", levels=args.levels, detail_levels=0)
        .fit(case.source, case.target)
        .retarget(case.source)
    )
    print("\nRMS error vs ground truth (% of face height):")
    print(f"  normalmesh, all detail levels    {100 * rms(anim.vertices, truth) / height:7.3f}%")
    print(
        f"  normalmesh, base mesh only       {100 * rms(base_only.vertices, truth) / height:7.3f}%"
    )
    print(f"  no expression (head motion only) {100 * rms(static, truth) / height:7.3f}%")

    pe = anim.provenance["diagnostics"]["piercing_errors"]
    n = pe["normal_mesh_vertices"]
    print("\npiercing errors (paper Table 1)   vertices  with error       %")
    print(
        f"  source (mean per frame)         {n:8d}  {pe['source_mean_per_frame']:10.1f}  {100 * pe['source_mean_per_frame'] / n:6.3f}"
    )
    print(
        f"  target (neutral)                {n:8d}  {pe['target']:10d}  {100 * pe['target'] / n:6.3f}"
    )

    if args.out is not None:
        args.out.mkdir(parents=True, exist_ok=True)
        for path in (args.out / "normalmesh_ict.npz", args.out / "normalmesh_ict.glb"):
            fr.save(anim, path, force=True)
            print(f"wrote {path}")
        nm = retargeter.normal_mesh_sequence(case.source, level=args.level)
        path = args.out / f"normalmesh_ict_level{args.level}.npz"
        np.savez_compressed(
            path, vertices=np.asarray(nm.vertices, dtype=np.float32), triangles=nm.triangles
        )
        print(f"wrote {path} (target normal mesh at level {args.level}: {nm.n_vertices} vertices)")


if __name__ == "__main__":
    main()
