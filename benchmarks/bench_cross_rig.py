"""Fidelity on the cross-rig case: default spacetime and layers against per-frame fits.

For 300 and 1,200 frames, markers (68 landmarks) and the dense mesh source of
``faceretarget.cases.cross_rig``, prints per method: RMS vertex error and velocity error
(% of the target's face height, per frame for velocity), the share of weights outside
[0, 1], the wall time of ``retarget()`` (fit done once; min and median of the repeats,
warm) and, apart, of reading ``.vertices`` (lazy for blendshape results). Baselines run in the same process: unconstrained and bounded per-frame least
squares (the paper's baselines, RBF scale-proportion matching) and the bounded fit with
[0, 1] bounds. Prints numbers only (no pass/fail).

With ``--seeds`` the case is drawn again with other seeds (other curves and other per-shape
perturbations of the target rig); ``--fidelity`` prints a compact table of the dense and
marker figures against the bounded per-frame fit, one row per seed (errors only, no timing).

Rows for ``run_all.py`` (``--json``), on the markers case at 300 frames: default ``spacetime``
``retarget()`` (issue 13: under 10 ms warm) against the bounded per-frame fit, and reading
``Animation.vertices`` of the result (issue 16 item 5: 300 x 9,409 under 20 ms) against the
same product written as one numpy matmul.

``--extra-examples`` prints the dense figure with the case's 7 example pairs and with 9 more,
one per shape whose meaning the target changes (how much of the remaining error is example
coverage rather than method).

Run: ``python benchmarks/bench_cross_rig.py [--quick] [--json] [--repeat N] [--frames 300 1200] [--seeds 0 1 2] [--fidelity] [--extra-examples]``.
"""

from __future__ import annotations

import dataclasses
import statistics
import sys
import time
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent))

import _common as C  # noqa: E402

import faceretarget as fr  # noqa: E402

METHODS = [
    ("spacetime_noconst", {}, "per-frame least squares (baseline)"),
    ("spacetime_rangepf", {"lower": 0.0, "upper": 1.0}, "bounded per-frame [0, 1] (baseline)"),
    ("spacetime_paper", {}, "spacetime as published"),
    ("spacetime", {"example_weight": 0.0}, "spacetime default without examples"),
    ("spacetime", {}, "spacetime default"),
    ("layers", {}, "layers default"),
]


def measure(case, name, params, repeat, timings=None):
    """Errors and times of one method; ``timings`` (a dict) receives the raw ``retarget()`` and
    ``.vertices`` times."""
    r = fr.get(name, **params).fit(case.source, case.target)
    anim = r.retarget(case.source)
    np.asarray(anim.vertices)  # warm: first evaluation of the lazy vertices
    times, vertex_times = [], []
    for _ in range(repeat):
        start = time.perf_counter()
        anim = r.retarget(case.source)
        times.append(time.perf_counter() - start)
        start = time.perf_counter()
        np.asarray(anim.vertices)
        vertex_times.append(time.perf_counter() - start)
    got, want = np.asarray(anim.vertices), np.asarray(case.truth.vertices)
    height = np.ptp(want[0][:, 1])
    rms = 100 * np.sqrt(np.mean(np.sum((got - want) ** 2, axis=-1))) / height
    vel = (
        100
        * np.sqrt(np.mean(np.sum((np.diff(got, axis=0) - np.diff(want, axis=0)) ** 2, axis=-1)))
        / height
    )
    w = anim.weights
    outside = float(np.mean((w < -1e-9) | (w > 1 + 1e-9))) if w is not None else float("nan")
    if timings is not None and times:
        timings["retarget"] = {
            "min_s": min(times),
            "median_s": statistics.median(times),
            "times_s": times,
        }
        timings["vertices"] = {
            "min_s": min(vertex_times),
            "median_s": statistics.median(vertex_times),
            "times_s": vertex_times,
        }
        timings["anim"] = anim
    if not times:
        return rms, vel, outside, float("nan"), float("nan"), float("nan")
    return rms, vel, outside, min(times), statistics.median(times), statistics.median(vertex_times)


def fidelity(frames: list[int], seeds: list[int]) -> None:
    """Per seed: bounded per-frame fit (markers) and default spacetime / layers, RMS % and the
    reduction against the bounded per-frame fit."""
    print(
        f"{'frames':>6s} {'seed':>4s} {'bounded pf':>10s} {'st markers':>15s} {'st dense':>15s} {'layers':>15s}"
    )
    for n in frames:
        for seed in seeds:
            cases = {
                kind: fr.cases.cross_rig(seed=seed, n_frames=n, source_kind=kind)
                for kind in ("markers", "mesh")
            }
            base = measure(cases["markers"], "spacetime_rangepf", {"lower": 0.0, "upper": 1.0}, 0)[
                0
            ]
            row = []
            for kind, name in (
                ("markers", "spacetime"),
                ("mesh", "spacetime"),
                ("markers", "layers"),
            ):
                rms = measure(cases[kind], name, {}, 0)[0]
                row.append(f"{rms:6.3f} ({100 * (1 - rms / base):+4.0f}%)")
            print(
                f"{n:6d} {seed:4d} {base:10.3f} " + " ".join(f"{r:>15s}" for r in row), flush=True
            )


#: Shapes whose meaning the case's target changes (cross-family mixes, ``cases.cross_rig``)
#: and that its 7 example pairs cover little or not at all (``--extra-examples``).
EXTRA_EXAMPLE_SHAPES = (
    "mouthClose",
    "mouthFunnel",
    "mouthStretch_L",
    "mouthStretch_R",
    "mouthRollLower",
    "mouthUpperUp_L",
    "mouthUpperUp_R",
    "mouthSmile_L",
    "mouthSmile_R",
)


def with_extra_examples(case):
    """The case with one more example pair per :data:`EXTRA_EXAMPLE_SHAPES` (that shape at 0.8
    on the source rig and on the target rig): how much of the dense error is example coverage."""
    names = list(case.target.blendshapes.names)
    w = np.zeros((len(EXTRA_EXAMPLE_SHAPES), len(names)))
    for i, shape in enumerate(EXTRA_EXAMPLE_SHAPES):
        w[i, names.index(shape)] = 0.8
    src, tgt = case.source, case.target
    extra = list(EXTRA_EXAMPLE_SHAPES)
    src = src.replace(
        examples=np.concatenate([src.examples, src.rig.evaluate(w)]),
        example_names=list(src.example_names) + extra,
    )
    tgt = tgt.replace(
        examples=np.concatenate([tgt.examples, tgt.blendshapes.evaluate(w)]),
        example_names=list(tgt.example_names) + extra,
    )
    return dataclasses.replace(case, source=src, target=tgt)


def extra_examples(frames: list[int], seeds: list[int]) -> None:
    """Dense spacetime with the case's 7 example pairs and with 9 more (one per shape of
    :data:`EXTRA_EXAMPLE_SHAPES`), against the bounded per-frame fit on markers."""
    print(f"{'frames':>6s} {'seed':>4s} {'bounded pf':>10s} {'st dense':>15s} {'+9 examples':>15s}")
    for n in frames:
        for seed in seeds:
            markers = fr.cases.cross_rig(seed=seed, n_frames=n, source_kind="markers")
            mesh = fr.cases.cross_rig(seed=seed, n_frames=n)
            base = measure(markers, "spacetime_rangepf", {"lower": 0.0, "upper": 1.0}, 0)[0]
            row = [measure(c, "spacetime", {}, 0)[0] for c in (mesh, with_extra_examples(mesh))]
            print(
                f"{n:6d} {seed:4d} {base:10.3f} "
                + " ".join(f"{f'{r:6.3f} ({100 * (1 - r / base):+4.0f}%)':>15s}" for r in row),
                flush=True,
            )


def main(argv=None) -> dict:
    parser = C.parser(__doc__)
    parser.add_argument(
        "--frames", type=int, nargs="+", default=None, help="default 300 1200 (300 with --quick)"
    )
    parser.add_argument("--seeds", type=int, nargs="+", default=[0])
    parser.add_argument("--fidelity", action="store_true", help="errors only, one row per seed")
    parser.add_argument(
        "--extra-examples",
        action="store_true",
        help="errors only: dense spacetime with 9 more single-shape example pairs",
    )
    args = parser.parse_args(argv)
    frames = args.frames or ([300] if args.quick else [300, 1200])
    if args.fidelity:
        fidelity(frames, args.seeds)
        return {}
    if args.extra_examples:
        extra_examples(frames, args.seeds)
        return {}
    repeat = C.repeats(args)
    result = {
        "script": "bench_cross_rig",
        "machine": C.print_machine("bench_cross_rig"),
        "rows": [],
        "scaling": [],
    }
    print(
        f"retarget() wall time, min / median of {repeat} warm runs; .vertices (evaluated lazily) timed apart"
    )
    kinds = ("markers",) if args.quick else ("markers", "mesh")
    for n, seed, kind in ((n, seed, kind) for n in frames for seed in args.seeds for kind in kinds):
        case = fr.cases.cross_rig(seed=seed, n_frames=n, source_kind=kind)
        print(f"\ncross_rig, seed {seed}, {n} frames, {kind} source")
        print(
            f"{'method':40s} {'RMS %':>7s} {'vel %/fr':>9s} {'outside':>8s} {'min ms':>8s} {'med ms':>8s} {'.vertices med ms':>17s}"
        )
        got = {}
        for name, params, label in METHODS:
            timings = {}
            rms, vel, outside, tmin, tmed, tvert = measure(case, name, params, repeat, timings)
            got[label] = timings
            print(
                f"{label:40s} {rms:7.3f} {vel:9.4f} {100 * outside:7.1f}% {1e3 * tmin:8.1f} {1e3 * tmed:8.1f} {1e3 * tvert:17.1f}",
                flush=True,
            )
        if (n, seed, kind) == (frames[0], args.seeds[0], "markers") and n == 300:
            ours, base = got["spacetime default"], got["bounded per-frame [0, 1] (baseline)"]
            result["rows"].append(
                C.time_row(
                    "spacetime retarget(), cross_rig markers (68 landmarks), 300 frames",
                    ours["retarget"],
                    0.010,
                    baseline=(
                        "bounded per-frame fit (spacetime_rangepf) retarget()",
                        base["retarget"],
                    ),
                    source="issue 13",
                )
            )
            anim = ours["anim"]
            rig = case.target.blendshapes
            w = np.asarray(anim.weights, dtype=np.float64)
            flat = np.asarray(rig.deltas, dtype=np.float64).reshape(len(rig.names), -1)
            neutral = np.asarray(case.target.neutral.vertices, dtype=np.float64).ravel()
            plain = C.timeit(
                lambda flat=flat, neutral=neutral, w=w: (w @ flat + neutral).reshape(len(w), -1, 3),
                repeat,
            )
            n_vertices = case.target.neutral.n_vertices
            result["rows"].append(
                C.time_row(
                    f"Animation.vertices of a blendshape result, {len(w)} frames x {n_vertices:,} vertices",
                    ours["vertices"],
                    0.020,
                    baseline=("numpy weights @ deltas + neutral (no head motion)", plain),
                    source="issue 16 item 5",
                    note="spacetime default on cross_rig markers",
                )
            )
    C.print_rows(result["rows"])
    return C.finish(result, args)


if __name__ == "__main__":
    main()
