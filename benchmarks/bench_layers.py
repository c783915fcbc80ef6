"""Benchmark of the ``layers`` retargeter at the paper's size (Kholgade et al. 2011, sec. 4).

283 3D markers + 40 2D tracks, 29 + 12 + 3 simplex extremes, 3 region masks, a
10,000-vertex character: frames per second of extraction + retargeting (Procrustes,
the per-frame bilinear problem, the character's vertices with head motion), on one core
(BLAS limited to one thread), against the per-frame scipy SLSQP reference of
``tests/naive/layers.py`` timed in the same run; peak memory of the retarget call.

Usage: python benchmarks/bench_layers.py [--frames 2000] [--vertices 10000] [--slsqp-frames 3]
Prints numbers, asserts nothing.
"""
from __future__ import annotations

import os

for _var in ("OPENBLAS_NUM_THREADS", "OMP_NUM_THREADS", "MKL_NUM_THREADS", "NUMBA_NUM_THREADS"):
    os.environ.setdefault(_var, "1")

import argparse  # noqa: E402
import resource  # noqa: E402
import sys  # noqa: E402
import time  # noqa: E402
import tracemalloc  # noqa: E402
from pathlib import Path  # noqa: E402

import numpy as np  # noqa: E402

sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "tests"))

from naive.layers import frame_objective, make_problem, slsqp_frame  # noqa: E402

from faceretarget.plugins.layers import compose  # noqa: E402
from faceretarget.plugins.layers.retargeter import LayersRetargeter  # noqa: E402
from faceretarget.plugins.layers.solver import fit_block, observe  # noqa: E402


def main(argv=None) -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--frames", type=int, default=2000)
    parser.add_argument("--vertices", type=int, default=10000)
    parser.add_argument("--slsqp-frames", type=int, default=3)
    parser.add_argument("--soft", action="store_true", help="soft (overlapping) region masks instead of hard ones")
    parser.add_argument("--repeat", type=int, default=3, help="retarget calls; the best (CPU time) is reported")
    args = parser.parse_args(argv)

    t0 = time.perf_counter()
    problem = make_problem(1, n_markers=283, n_tracks=40, sizes=(29, 12, 3), n_regions=3, n_vertices=args.vertices,
                           n_frames=args.frames, soft=args.soft, noise=0.01, with_truth=False)
    source, target = problem["source"], problem["target"]
    print(f"problem: {args.frames} frames, 283 3D markers + 40 2D tracks, K = 29 + 12 + 3, 3 "
          f"{'soft' if args.soft else 'hard'} masks, {args.vertices} character vertices (built in {time.perf_counter() - t0:.1f} s)")

    r = LayersRetargeter()
    t0 = time.perf_counter()
    r.fit(source, target)
    fit_s = time.perf_counter() - t0
    # warm-up: load / compile the numba kernels on a few frames
    t0 = time.perf_counter()
    markers, tracks = np.asarray(source.performance.positions), np.asarray(source.tracks2d.positions)
    list(r.stream(zip(markers[:3], tracks[:3])))
    warm_s = time.perf_counter() - t0

    runs = []
    for _ in range(args.repeat):
        c0, t0 = time.process_time(), time.perf_counter()
        anim = r.retarget(source)
        vertices = anim.vertices
        runs.append((time.perf_counter() - t0, time.process_time() - c0))
        assert vertices.shape == (args.frames, args.vertices, 3)
        del anim, vertices
    total_s, cpu_s = min(runs, key=lambda x: x[1])
    tracemalloc.start()  # (tracing slows numpy a little: a separate run for the memory figure)
    vertices = r.retarget(source).vertices
    _, peak = tracemalloc.get_traced_memory()
    tracemalloc.stop()

    # the same work step by step, for the breakdown (CPU time of this process)
    t0 = time.process_time()
    detected, _ = r._detect_head_motion(markers)
    t1 = time.process_time()
    obs_f, params_f, _ = fit_block(r.actor_, r.lip_, markers, tracks, None if detected else "none", **r._settings())
    t2 = time.process_time()
    beta = compose.region_coefficients(params_f.weights, params_f.coefficients, r.actor_.layer_of)
    compose.world_vertices(r.character_, beta, obs_f.head_motion)
    t3 = time.process_time()
    # the solver check below: one plain solve of Eq. 7 on the paper's alignment
    obs = observe(r.actor_, r.lip_, markers, tracks, None, keep_xhat=True)
    params, _ = r._extract(obs)
    fps = args.frames / total_s
    load = os.getloadavg()[0]
    print(f"fit {fit_s * 1e3:.0f} ms; kernel load/compile {warm_s:.2f} s; machine load average {load:.1f} on {os.cpu_count()} cores")
    print("retarget calls (wall s / CPU s): " + ", ".join(f"{w:.3f} / {c:.3f}" for w, c in runs)
          + " (the first pays for fresh output pages: ~240 KB a frame)")
    print(f"best: {total_s:.3f} s wall for {args.frames} frames = {fps:,.0f} frames/s; "
          f"CPU time {cpu_s:.3f} s = {args.frames / cpu_s:,.0f} frames/s of one core")
    print("step by step, CPU time "
          f"(head-motion test {1e3 * (t1 - t0) / args.frames:.3f} ms, alignment + solve {1e3 * (t2 - t1) / args.frames:.3f} ms, "
          f"character {1e3 * (t3 - t2) / args.frames:.3f} ms per frame; {params_f.iterations.mean():.2f} LM steps a frame)")
    print(f"peak traced memory during retarget: {peak / 2**20:.0f} MiB (the output alone is "
          f"{vertices.nbytes / 2**20:.0f} MiB); process max RSS {resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024:.0f} MiB")

    # per-frame SLSQP reference on the same frames, from the same previous state
    actor, lip = r.actor_, r.lip_
    basis, masks = actor.basis_t.T, actor.coord_masks
    gamma = params.gamma
    c_d = (1 - gamma) / obs.n_valid
    additive = r.composition == "additive"
    n = max(1, min(args.slsqp_frames, args.frames - 1))
    spent, worst = 0.0, -np.inf
    for t in range(1, n + 1):
        w_prev, a_prev = params.weights[t - 1], params.coefficients[t - 1]
        valid = ~obs.missing[t]
        t0 = time.process_time()
        _, _, ref = slsqp_frame(obs.xhat[t], valid, basis, masks, actor.layer_of, c_d[t], gamma[t], r.smoothing,
                                lip.mouth, lip.speech, lip.closed, w_prev, a_prev, w_prev, a_prev, additive)
        spent += time.process_time() - t0
        ours = frame_objective(obs.xhat[t], valid, basis, masks, actor.layer_of, params.weights[t], params.coefficients[t],
                               c_d[t], gamma[t], r.smoothing, lip.mouth, lip.speech, lip.closed, w_prev, a_prev, additive)
        worst = max(worst, (ours - ref) / max(ref, 1e-300))
    per_frame = spent / n
    print(f"SLSQP reference (extraction only): {per_frame:.2f} s CPU a frame ({n} frames) -> {1 / per_frame:.2f} frames/s; "
          f"speed-up of our extraction + retargeting {per_frame * args.frames / cpu_s:,.0f}x (CPU time); "
          f"our objective - SLSQP's, worst relative: {worst:+.2e}")


if __name__ == "__main__":
    main()
