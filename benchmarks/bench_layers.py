"""Benchmark of the ``layers`` retargeter at the paper's size (Kholgade et al. 2011, sec. 4).

283 3D markers + 40 2D tracks, 29 + 12 + 3 simplex extremes, 3 region masks, a
10,000-vertex character. With the library's default threading (no BLAS limit is set here:
the library runs its per-frame BLAS on one thread itself, ``faceretarget/_threads.py``):

- frames per second of ``retarget()`` + reading ``.vertices`` (wall time, min and median of
  >= 5 warm calls; issue 16 item 3: >= 3,000 frames/s), CPU time as an extra column;
- streaming latency per frame (``stream()``), the 95th percentile of each run (goal < 2 ms);
- the per-frame scipy SLSQP reference of ``tests/naive/layers.py`` (extraction only), timed
  frame by frame in the same run (>= 5 frames), and the worst objective difference;
- the per-frame breakdown and the peak traced memory of the retarget call.

Usage: python benchmarks/bench_layers.py [--quick] [--json] [--frames 2000] [--vertices 10000] [--slsqp-frames 5]
Prints numbers, asserts nothing.
"""

from __future__ import annotations

import statistics
import sys
import time
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent))
sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "tests"))

import _common as C  # noqa: E402
from naive.layers import frame_objective, make_problem, slsqp_frame  # noqa: E402

from faceretarget.plugins.layers import compose  # noqa: E402
from faceretarget.plugins.layers.retargeter import LayersRetargeter  # noqa: E402
from faceretarget.plugins.layers.solver import fit_block, observe  # noqa: E402


def main(argv=None) -> dict:
    parser = C.parser(__doc__)
    parser.add_argument("--frames", type=int, default=None, help="default 2000 (1000 with --quick)")
    parser.add_argument("--vertices", type=int, default=10000)
    parser.add_argument(
        "--slsqp-frames", type=int, default=5, help="frames of the SLSQP reference (at least 5)"
    )
    parser.add_argument(
        "--soft", action="store_true", help="soft (overlapping) region masks instead of hard ones"
    )
    args = parser.parse_args(argv)
    repeat = C.repeats(args)
    frames = args.frames or (1000 if args.quick else 2000)
    result = {
        "script": "bench_layers",
        "machine": C.print_machine("bench_layers"),
        "rows": [],
        "scaling": [],
    }

    t0 = time.perf_counter()
    problem = make_problem(
        1,
        n_markers=283,
        n_tracks=40,
        sizes=(29, 12, 3),
        n_regions=3,
        n_vertices=args.vertices,
        n_frames=frames,
        soft=args.soft,
        noise=0.01,
        with_truth=False,
    )
    source, target = problem["source"], problem["target"]
    print(
        f"problem: {frames} frames, 283 3D markers + 40 2D tracks, K = 29 + 12 + 3, 3 "
        f"{'soft' if args.soft else 'hard'} masks, {args.vertices} character vertices (built in {time.perf_counter() - t0:.1f} s)"
    )

    r = LayersRetargeter()
    fit = C.timeit(lambda: r.fit(source, target), 1, warmup=0)
    markers, tracks = (
        np.asarray(source.performance.positions),
        np.asarray(source.tracks2d.positions),
    )
    warm = C.timeit(lambda: list(r.stream(zip(markers[:3], tracks[:3]))), 1, warmup=0)
    print(
        f"fit {C.fmt(fit['min_s'], 's')}; kernel load/compile (first stream of 3 frames) {C.fmt(warm['min_s'], 's')}"
    )

    def run():
        anim = r.retarget(source)
        vertices = np.asarray(anim.vertices)
        assert vertices.shape == (frames, args.vertices, 3)
        return None

    batch = C.timeit(run, repeat, cpu=True)
    print("retarget() + .vertices wall s: " + ", ".join(f"{w:.3f}" for w in batch["times_s"]))
    peak, _ = C.peak_memory(lambda: np.asarray(r.retarget(source).vertices))
    print(
        f"peak traced memory during retarget() + .vertices: {peak / 2**20:.0f} MiB "
        f"(the output alone is {frames * args.vertices * 3 * 8 / 2**20:.0f} MiB); process max RSS {C.max_rss_bytes() / 2**20:.0f} MiB"
    )

    # streaming latency: time of each frame, p95 per run
    n_stream = min(frames, 500 if args.quick else 1000)
    p95s, medians = [], []
    list(r.stream(zip(markers[:5], tracks[:5])))
    for _ in range(repeat):
        lat = []
        it = r.stream(zip(markers[:n_stream], tracks[:n_stream]))
        while True:
            t0 = time.perf_counter()
            try:
                next(it)
            except StopIteration:
                break
            lat.append(time.perf_counter() - t0)
        p95s.append(float(np.percentile(lat, 95)))
        medians.append(statistics.median(lat))
    stream = {"min_s": min(p95s), "median_s": statistics.median(p95s), "times_s": p95s}
    print(
        f"stream(): {n_stream} frames a run, p95 latency per run: "
        + ", ".join(f"{1e3 * x:.3f} ms" for x in p95s)
        + f"; median latency {1e3 * statistics.median(medians):.3f} ms"
    )

    # the same work step by step (wall time of one pass each)
    t0 = time.perf_counter()
    detected, _ = r._detect_head_motion(markers)
    t1 = time.perf_counter()
    obs_f, params_f, _ = fit_block(
        r.actor_, r.lip_, markers, tracks, None if detected else "none", **r._settings()
    )
    t2 = time.perf_counter()
    beta = compose.region_coefficients(params_f.weights, params_f.coefficients, r.actor_.layer_of)
    compose.world_vertices(r.character_, beta, obs_f.head_motion)
    t3 = time.perf_counter()
    print(
        "step by step, wall time of one pass "
        f"(head-motion test {1e3 * (t1 - t0) / frames:.3f} ms, alignment + solve {1e3 * (t2 - t1) / frames:.3f} ms, "
        f"character {1e3 * (t3 - t2) / frames:.3f} ms per frame; {params_f.iterations.mean():.2f} LM steps a frame)"
    )

    # per-frame SLSQP reference on the same frames, from the same previous state
    obs = observe(r.actor_, r.lip_, markers, tracks, None, keep_xhat=True)
    params, _ = r._extract(obs)
    actor, lip = r.actor_, r.lip_
    basis, masks = actor.basis_t.T, actor.coord_masks
    gamma = params.gamma
    c_d = (1 - gamma) / obs.n_valid
    additive = r.composition == "additive"
    n = max(5, min(args.slsqp_frames, frames - 1))
    spent, worst = [], -np.inf
    for t in range(1, n + 1):
        w_prev, a_prev = params.weights[t - 1], params.coefficients[t - 1]
        valid = ~obs.missing[t]
        t0 = time.perf_counter()
        _, _, ref = slsqp_frame(
            obs.xhat[t],
            valid,
            basis,
            masks,
            actor.layer_of,
            c_d[t],
            gamma[t],
            r.smoothing,
            lip.mouth,
            lip.speech,
            lip.closed,
            w_prev,
            a_prev,
            w_prev,
            a_prev,
            additive,
        )
        spent.append(time.perf_counter() - t0)
        ours = frame_objective(
            obs.xhat[t],
            valid,
            basis,
            masks,
            actor.layer_of,
            params.weights[t],
            params.coefficients[t],
            c_d[t],
            gamma[t],
            r.smoothing,
            lip.mouth,
            lip.speech,
            lip.closed,
            w_prev,
            a_prev,
            additive,
        )
        worst = max(worst, (ours - ref) / max(ref, 1e-300))
    slsqp = {"min_s": min(spent), "median_s": statistics.median(spent), "times_s": spent}
    print(
        f"SLSQP reference (extraction only), wall time a frame over {n} frames: min {C.fmt(slsqp['min_s'], 's')}, "
        f"median {C.fmt(slsqp['median_s'], 's')}; our objective - SLSQP's, worst relative: {worst:+.2e}"
    )

    result["rows"].append(
        C.rate_row(
            f"layers retarget() + .vertices, {frames:,} frames, {args.vertices:,}-vertex character",
            frames,
            batch,
            3000.0,
            baseline=("per-frame SLSQP reference (extraction only), per frame", slsqp),
            baseline_count=1,
            source="issue 16 item 3",
            note="wall time, default threading; CPU-time rate in the cpu columns",
        )
    )
    result["rows"].append(
        C.time_row(
            "layers stream() p95 latency per frame",
            stream,
            0.002,
            source="issue 16 item 3",
            note=f"{n_stream} frames a run; best / median of the runs' p95",
        )
    )
    C.print_rows(result["rows"])
    return C.finish(result, args)


if __name__ == "__main__":
    main()
