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

Run: ``python benchmarks/bench_cross_rig.py [--repeat N] [--frames 300 1200] [--seeds 0 1 2] [--fidelity]``.
"""
from __future__ import annotations

import argparse
import os
import statistics
import time

import numpy as np

import faceretarget as fr

METHODS = [
    ("spacetime_noconst", {}, "per-frame least squares (baseline)"),
    ("spacetime_rangepf", {"lower": 0.0, "upper": 1.0}, "bounded per-frame [0, 1] (baseline)"),
    ("spacetime_paper", {}, "spacetime as published"),
    ("spacetime", {"example_weight": 0.0}, "spacetime default without examples"),
    ("spacetime", {}, "spacetime default"),
    ("layers", {}, "layers default"),
]


def blas_threads() -> str:
    try:
        from threadpoolctl import threadpool_info

        return ", ".join(f"{i['internal_api']} {i['num_threads']}" for i in threadpool_info() if i.get("user_api") == "blas") or "?"
    except ImportError:
        return os.environ.get("OPENBLAS_NUM_THREADS", "default (threadpoolctl not installed)")


def measure(case, name, params, repeat):
    r = fr.get(name, **params).fit(case.source, case.target)
    anim = r.retarget(case.source)
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
    vel = 100 * np.sqrt(np.mean(np.sum((np.diff(got, axis=0) - np.diff(want, axis=0)) ** 2, axis=-1))) / height
    w = anim.weights
    outside = float(np.mean((w < -1e-9) | (w > 1 + 1e-9))) if w is not None else float("nan")
    if not times:
        return rms, vel, outside, float("nan"), float("nan"), float("nan")
    return rms, vel, outside, min(times), statistics.median(times), statistics.median(vertex_times)


def fidelity(frames: list[int], seeds: list[int]) -> None:
    """Per seed: bounded per-frame fit (markers) and default spacetime / layers, RMS % and the
    reduction against the bounded per-frame fit."""
    print(f"{'frames':>6s} {'seed':>4s} {'bounded pf':>10s} {'st markers':>15s} {'st dense':>15s} {'layers':>15s}")
    for n in frames:
        for seed in seeds:
            cases = {kind: fr.cases.cross_rig(seed=seed, n_frames=n, source_kind=kind) for kind in ("markers", "mesh")}
            base = measure(cases["markers"], "spacetime_rangepf", {"lower": 0.0, "upper": 1.0}, 0)[0]
            row = []
            for kind, name in (("markers", "spacetime"), ("mesh", "spacetime"), ("markers", "layers")):
                rms = measure(cases[kind], name, {}, 0)[0]
                row.append(f"{rms:6.3f} ({100 * (1 - rms / base):+4.0f}%)")
            print(f"{n:6d} {seed:4d} {base:10.3f} " + " ".join(f"{r:>15s}" for r in row), flush=True)


def main(repeat: int, frames: list[int], seeds: list[int]) -> None:
    load = os.getloadavg()[0]
    print(f"{os.cpu_count()} CPUs, load average {load:.2f}, BLAS threads: {blas_threads()}; retarget() wall time, "
          f"min / median of {repeat} warm runs; .vertices (evaluated lazily) timed apart")
    for n, seed, kind in ((n, seed, kind) for n in frames for seed in seeds for kind in ("markers", "mesh")):
            case = fr.cases.cross_rig(seed=seed, n_frames=n, source_kind=kind)
            print(f"\ncross_rig, seed {seed}, {n} frames, {kind} source")
            print(f"{'method':40s} {'RMS %':>7s} {'vel %/fr':>9s} {'outside':>8s} {'min ms':>8s} {'med ms':>8s} {'.vertices med ms':>17s}")
            for name, params, label in METHODS:
                rms, vel, outside, tmin, tmed, tvert = measure(case, name, params, repeat)
                print(f"{label:40s} {rms:7.3f} {vel:9.4f} {100 * outside:7.1f}% {1e3 * tmin:8.1f} {1e3 * tmed:8.1f} {1e3 * tvert:17.1f}")


if __name__ == "__main__":
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--repeat", type=int, default=5)
    parser.add_argument("--frames", type=int, nargs="+", default=[300, 1200])
    parser.add_argument("--seeds", type=int, nargs="+", default=[0])
    parser.add_argument("--fidelity", action="store_true", help="errors only, one row per seed")
    args = parser.parse_args()
    if args.fidelity:
        fidelity(args.frames, args.seeds)
    else:
        main(args.repeat, args.frames, args.seeds)
