"""Benchmark of the evaluation cases and the cross-topology correspondence.

Times (median of a few runs, after one warm-up for imports and numba caches):
``cases.synthetic()`` at several resolutions and both targets, ``cases.ict()`` (both
expression modes), and ``correspond.resample_to_topology`` + ``transfer_back`` of the
synthetic source onto a differently triangulated target, with its quality report and
the correspondence error against the known answer (same parameter point).

Usage: python benchmarks/bench_cases.py [--repeat 3] [--big 100000]
Prints numbers, asserts nothing.
"""
from __future__ import annotations

import argparse
import time

import numpy as np

from faceretarget import cases
from faceretarget.correspond import resample_to_topology, transfer_back


def timed(fn, repeat):
    times, out = [], None
    for _ in range(repeat):
        t0 = time.perf_counter()
        out = fn()
        times.append(time.perf_counter() - t0)
    return float(np.median(times)), out


def main() -> None:
    ap = argparse.ArgumentParser()
    ap.add_argument("--repeat", type=int, default=3)
    ap.add_argument("--big", type=int, default=100_000)
    args = ap.parse_args()
    cases.synthetic(resolution=500, n_frames=2)  # warm-up (imports)

    print("case                                   vertices   frames   seconds")
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
            t, case = timed(lambda: cases.ict(expressions="transferred"), 1)
        else:
            t, case = timed(lambda kw=kw: cases.synthetic(**kw), args.repeat if "resolution" not in kw else 1)
        print(f"{label:38s} {case.source.performance.n_vertices:8d} {case.source.n_frames:8d} {t:9.3f}")

    print("\nresample_to_topology (source -> target of another triangulation)")
    print("source V  target V   seconds  transfer_back s  residual_max  coverage_max  flips  corr. error mean/max (% height)")
    for res, tres in [(3000, 6000), (10000, 20000)]:
        case = cases.synthetic(resolution=res, target_resolution=tres, n_frames=1)
        src, tgt = case.source.performance.reference, case.target.neutral
        t, (fitted, rep) = timed(lambda: resample_to_topology(src, case.source.landmarks, tgt, case.target.landmarks), 1)
        tb, _ = timed(lambda: transfer_back(fitted, fitted.vertices, tgt), 1)
        truth = cases.face_surface(case.meta["source_uv"], "human")
        err = np.linalg.norm(fitted.vertices - truth, axis=1) / tgt.height * 100
        print(f"{src.n_vertices:8d} {tgt.n_vertices:9d} {t:9.2f} {tb:16.3f} {rep.residual_max:13.2e} {rep.coverage_max:13.2e} "
              f"{rep.flipped_triangles:6d}  {err.mean():.3f} / {err.max():.3f}")


if __name__ == "__main__":
    main()
