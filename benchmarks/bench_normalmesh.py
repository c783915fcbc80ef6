"""Benchmark of the ``normalmesh`` retargeter at the paper's size (Na & Jung 2004: 69,246
vertices, normal meshes of 5 levels), on a synthetic parallel-rig case.

    python benchmarks/bench_normalmesh.py [--quick] [--json] [--vertices 69000] [--frames 64] [--levels 5]

Wall time, min and median of >= 5 warm repeats (CPU time of all threads as an extra
column): building one normal mesh (goal < 3 s), retargeting per frame (goal < 20 ms on
2 cores) against per-frame ``deformation_transfer`` on the same case in the same process,
fitting, piercing errors per mesh (the paper's Table 1), the error against ground truth, ray
casting of Embree and the numba BVH against brute force (the paper's O(N*M): the plain-numpy
reference of the tests at a size where it finishes, the numba brute force on a sample of
rays at full size), and peak memory. No pass/fail.
"""

from __future__ import annotations

import resource
import sys
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent))

import _common as C  # noqa: E402

import faceretarget as fr  # noqa: E402
from faceretarget.geometry.raycast import RayCaster, embree_available  # noqa: E402
from faceretarget.plugins.normalmesh.normal_mesh import (  # noqa: E402
    Surface,
    build_normal_mesh,
    feature_point_loops,
    make_hierarchy,
)

sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "tests"))
from naive.raycast import cast_rays as naive_cast_rays  # noqa: E402


def timed(fn, *args, repeat: int = 1, **kwargs):
    """(result, min wall s, CPU s of that run, timing dict) over ``repeat`` calls after one warm-up."""
    t = C.timeit(lambda: fn(*args, **kwargs), repeat, warmup=1 if repeat > 1 else 0, cpu=True)
    return t["result"], t["min_s"], t["cpu_min_s"], t


def rel_rms(a, b, height):
    return float(np.sqrt(np.mean(np.sum((np.asarray(a) - np.asarray(b)) ** 2, axis=-1))) / height)


def rays_of(mesh: fr.Mesh, n: int, seed: int = 0):
    """Lines along the vertex normals from points 0.5 mm off the surface (like normal-mesh rays)."""
    rng = np.random.default_rng(seed)
    ids = rng.choice(mesh.n_vertices, size=min(n, mesh.n_vertices), replace=False)
    return mesh.vertices[ids] + 0.05 * mesh.vertex_normals[ids], np.asarray(
        mesh.vertex_normals[ids]
    )


def main(argv=None) -> dict:
    ap = C.parser(__doc__)
    ap.add_argument("--vertices", type=int, default=69000)
    ap.add_argument("--frames", type=int, default=None, help="default 64 (16 with --quick)")
    ap.add_argument("--levels", type=int, default=5)
    args = ap.parse_args(argv)
    args.frames = args.frames or (16 if args.quick else 64)
    repeat = C.repeats(args)
    result = {
        "script": "bench_normalmesh",
        "machine": C.print_machine("bench_normalmesh"),
        "rows": [],
        "scaling": [],
    }
    print(f"Embree available: {embree_available()}")

    fr.get("normalmesh").fit(
        *(lambda c: (c.source, c.target))(fr.cases.synthetic(resolution=800, n_frames=4))
    ).retarget(
        fr.cases.synthetic(resolution=800, n_frames=4).source
    )  # compile / load the numba kernels

    case, wall, _, _ = timed(fr.cases.synthetic, resolution=args.vertices, n_frames=args.frames)
    rss_case = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024
    src, tgt = case.source, case.target
    h = tgt.neutral.height
    print(
        f"case: source {src.performance.n_vertices} vertices x {src.n_frames} frames, target {tgt.neutral.n_vertices} vertices ({wall:.1f} s to generate)"
    )

    r = fr.get("normalmesh", levels=args.levels)
    _, fit_wall, fit_cpu, _ = timed(r.fit, src, tgt)
    hier = r.hierarchy_

    # one normal mesh, from scratch (Embree scene / BVH included)
    mesh = tgt.neutral
    pts = tgt.landmarks.positions(mesh.vertices, mesh.triangles)

    def build(backend):
        surface = Surface.of(mesh.triangles, mesh.n_vertices)
        h_ = make_hierarchy(r.base_triangles_, len(pts), args.levels)
        loops = feature_point_loops(pts, np.asarray(mesh.vertices), surface)
        return build_normal_mesh(
            mesh.vertices,
            surface,
            pts,
            loops,
            h_,
            max_offset=r.max_offset,
            caster=RayCaster(mesh.vertices, mesh.triangles, backend=backend),
        )

    print(
        f"\nnormal mesh: {len(r.base_triangles_)} base triangles, {args.levels} levels, {hier.n_vertices(args.levels)} vertices, {len(hier.triangles(args.levels))} triangles"
    )
    for backend in (["embree"] if embree_available() else []) + ["bvh"]:
        _, wall, cpu, t = timed(build, backend, repeat=repeat)
        print(
            f"  build one normal mesh ({backend:6s}): {wall:6.2f} s wall (median {t['median_s']:.2f}), {cpu:6.2f} s CPU   (goal < 3 s)"
        )
        if (backend == "bvh" or embree_available()) and not any(
            row["name"].startswith("normalmesh: build one normal mesh") for row in result["rows"]
        ):
            result["rows"].append(
                C.time_row(
                    f"normalmesh: build one normal mesh ({backend}), {mesh.n_vertices:,} vertices, {args.levels} levels",
                    t,
                    3.0,
                    source="bench (normalmesh docs)",
                    note="no baseline",
                )
            )
    print(
        f"  fit (base mesh, two normal meshes, RBF, attachment): {fit_wall:.2f} s wall, {fit_cpu:.2f} s CPU"
    )

    anim, wall, cpu, ours = timed(lambda: r.retarget(src), repeat=repeat)
    n = src.n_frames
    dt = fr.get("deformation_transfer").fit(src, tgt)
    _, dt_wall, _, base = timed(lambda: dt.retarget(src), repeat=repeat)
    print(
        f"\nretarget: {1000 * wall / n:.1f} ms per frame wall (median {1000 * ours['median_s'] / n:.1f}), "
        f"{1000 * cpu / n:.1f} ms CPU per frame (all threads)   (goal < 20 ms on 2 cores); "
        f"deformation_transfer {1000 * dt_wall / n:.1f} ms per frame (median {1000 * base['median_s'] / n:.1f})"
    )
    result["rows"].append(
        C.time_row(
            f"normalmesh retarget() per frame, {src.performance.n_vertices:,} vertices, {args.levels} levels, {n} frames",
            ours,
            0.020,
            per=n,
            baseline=("deformation_transfer retarget() per frame", base),
            source="bench (normalmesh docs)",
            note="wall time; CPU time of all threads in the cpu columns",
        )
    )
    print(
        f"  error vs ground truth: {100 * rel_rms(anim.vertices, case.truth.vertices, h):.3f}% of face height RMS"
    )

    pe = r.piercing_errors_
    total = hier.n_vertices(args.levels)
    print("\npiercing errors (paper Table 1)")
    print(f"  {'mesh':10s} {'vertices':>9s} {'with piercing error':>22s} {'%':>8s}")
    print(
        f"  {'source':10s} {total:9d} {anim.extras['piercing_errors_per_frame'].mean():13.1f} (mean/frame) {100 * anim.extras['piercing_errors_per_frame'].mean() / total:8.4f}"
    )
    print(
        f"  {'target':10s} {total:9d} {pe['target']:13d} (neutral)    {100 * pe['target'] / total:8.4f}"
    )

    print(
        "\nray casting (lines both ways, nearest hit), target mesh",
        f"{mesh.n_vertices} vertices / {mesh.n_triangles} triangles",
    )
    o, d = rays_of(mesh, 68000)
    for backend in (["embree"] if embree_available() else []) + ["bvh"]:
        _, build_wall, _, _ = timed(
            lambda backend=backend: (
                RayCaster(mesh.vertices, mesh.triangles, backend=backend)._embree_scene()
                if backend == "embree"
                else RayCaster(mesh.vertices, mesh.triangles, backend=backend).bvh
            )
        )
        caster = RayCaster(mesh.vertices, mesh.triangles, backend=backend)
        caster.cast(o[:10], d[:10])
        _, wall, cpu, _ = timed(caster.cast, o, d, repeat=repeat)
        print(
            f"  {backend:6s}: {len(o)} rays in {1000 * wall:7.1f} ms wall, {1000 * cpu:7.1f} ms CPU ({len(o) / wall / 1e6:.2f} M rays/s), set-up {build_wall:.2f} s"
        )
    sample = 256
    brute = RayCaster(mesh.vertices, mesh.triangles, backend="brute")
    brute.cast(o[:2], d[:2])
    _, wall, _, _ = timed(brute.cast, o[:sample], d[:sample])
    print(
        f"  numba brute force O(N*M): {sample} rays in {wall:.2f} s -> {wall * len(o) / sample:.0f} s for all {len(o)}"
    )

    small = fr.cases.synthetic(resolution=2500, n_frames=2).target.neutral
    so, sd = rays_of(small, 300, seed=1)
    _, naive_wall, _, naive_t = timed(
        naive_cast_rays, small.vertices, small.triangles, so, sd, repeat=repeat
    )
    fast = RayCaster(small.vertices, small.triangles, backend="bvh")
    fast.cast(so[:2], sd[:2])
    _, fast_wall, _, fast_t = timed(fast.cast, so, sd, repeat=repeat)
    print(
        f"  at {small.n_triangles} triangles, {len(so)} rays: numpy brute force (tests/naive) {1000 * naive_wall:.0f} ms, "
        f"numba BVH {1000 * fast_wall:.2f} ms: {naive_wall / fast_wall:.0f}x"
    )

    result["rows"].append(
        C.time_row(
            f"ray casting, numba BVH, {len(so)} rays on {small.n_triangles:,} triangles",
            fast_t,
            None,
            baseline=("numpy brute force (tests/naive)", naive_t),
            source="bench",
            note="no goal: speed-up over the baseline",
        )
    )
    peak = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024
    print(
        f"\npeak memory (max RSS): {peak:.0f} MiB, of which {rss_case:.0f} MiB once the case (source, target rig, truth) existed"
    )
    C.print_rows(result["rows"])
    return C.finish(result, args)


if __name__ == "__main__":
    main()
