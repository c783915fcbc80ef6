"""Benchmark of the evaluation cases and the cross-topology correspondence.

Wall times, min and median of >= 5 runs after one warm-up (imports, numba caches); the
largest cases run fewer times without ``--repeat`` (their count is printed). No baseline
and no goal: these are set-up costs of the evaluation, reported for reference.
``cases.synthetic()`` at several resolutions and both targets, ``cases.ict()`` (both
expression modes), and ``correspond.resample_to_topology`` + ``transfer_back`` of the
synthetic source onto a differently triangulated target, with its quality report and
the correspondence error against the known answer (same parameter point).

Usage: python benchmarks/bench_cases.py [--quick] [--json] [--repeat 5] [--big 100000]
Prints numbers, asserts nothing.
"""

from __future__ import annotations

import sys
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent))

import _common as C  # noqa: E402

from faceretarget import cases  # noqa: E402
from faceretarget.correspond import resample_to_topology, transfer_back  # noqa: E402

TIMINGS: list = []


def timed(fn, repeat):
    t = C.timeit(fn, repeat, warmup=0)
    TIMINGS.append(t)
    return t["min_s"], t["result"]


def main(argv=None) -> dict:
    ap = C.parser(__doc__)
    ap.add_argument("--big", type=int, default=100_000)
    args = ap.parse_args(argv)
    args.repeat = C.repeats(args)
    result = {
        "script": "bench_cases",
        "machine": C.print_machine("bench_cases"),
        "rows": [],
        "scaling": [],
    }
    if args.quick:
        args.big = 20_000
    cases.synthetic(resolution=500, n_frames=2)  # warm-up (imports)

    print("case                                   vertices   frames   min s  (median s, runs)")
    for label, kw in [
        ("synthetic() default (human)", {}),
        ("synthetic(target='stylized')", {"target": "stylized"}),
        ("synthetic(resolution=20000)", {"resolution": 20_000}),
        (f"synthetic(resolution={args.big}, 30 frames)", {"resolution": args.big, "n_frames": 30}),
        ("ict() default", None),
        ("ict(expressions='transferred')", "transferred"),
    ]:
        if kw is None:
            t, case = timed(lambda: cases.ict(), args.repeat)
        elif kw == "transferred":
            t, case = timed(
                lambda: cases.ict(expressions="transferred"), 1 if args.quick else args.repeat
            )
        else:
            t, case = timed(
                lambda kw=kw: cases.synthetic(**kw),
                args.repeat if "resolution" not in kw else (1 if args.quick else 3),
            )
        print(
            f"{label:38s} {case.source.performance.n_vertices:8d} {case.source.n_frames:8d} {t:9.3f}  "
            f"({TIMINGS[-1]['median_s']:.3f}, {len(TIMINGS[-1]['times_s'])})"
        )

    print("\nresample_to_topology (source -> target of another triangulation)")
    print(
        "source V  target V   seconds  transfer_back s  residual_max  coverage_max  flips  corr. error mean/max (% height)"
    )
    for res, tres in [(3000, 6000)] + ([] if args.quick else [(10000, 20000)]):
        case = cases.synthetic(resolution=res, target_resolution=tres, n_frames=1)
        src, tgt = case.source.performance.reference, case.target.neutral
        t, (fitted, rep) = timed(
            lambda case=case, src=src, tgt=tgt: resample_to_topology(
                src, case.source.landmarks, tgt, case.target.landmarks
            ),
            1,
        )
        tb, _ = timed(lambda fitted=fitted, tgt=tgt: transfer_back(fitted, fitted.vertices, tgt), 1)
        truth = cases.face_surface(case.meta["source_uv"], "human")
        err = np.linalg.norm(fitted.vertices - truth, axis=1) / tgt.height * 100
        print(
            f"{src.n_vertices:8d} {tgt.n_vertices:9d} {t:9.2f} {tb:16.3f} {rep.residual_max:13.2e} {rep.coverage_max:13.2e} "
            f"{rep.flipped_triangles:6d}  {err.mean():.3f} / {err.max():.3f}"
        )
    return C.finish(result, args)


if __name__ == "__main__":
    main()
