"""Fidelity of the dense retargeters (``coating``, ``normalmesh``) against per-frame
``deformation_transfer`` on real-like data (issue 14's figures).

    python benchmarks/bench_dense_fidelity.py [--frames 60] [--detail-resolution 1500] [--skip cross,units,detail,detail-bound,cross-detail,piercing]

A fidelity benchmark: it prints no timings (so it has no time baseline) and ``run_all.py``
does not run it. Prints tables (no pass/fail, no timing), each with the figure it is compared against:

- **cross-topology** (``cases.cross_topology()``): the source resting at its neutral must give
  the target's neutral (RMS < 0.01% of the face height); RMS error of the performance
  (coating and normalmesh below deformation transfer's).
- **units**: the cross-topology pair with the source or the target scaled by 0.01, 100 and
  1000; the result, in the target's units, must equal the unscaled run to 1e-6 relative.
- **detail**: ``detail_error`` / ``detail_correlation`` on the wrinkled synthetic cases (the
  presets' :data:`~faceretarget.evaluation.reproduction.DETAIL_CASES`), with the ratio to
  deformation transfer (goal <= 0.7) and the same measurement on the wrinkle-free twin (what
  the metric sees that is not wrinkles).
- **detail-bound**: what a per-vertex transfer of the source's fine-scale motion can reach on
  the synthetic detail cases, without running a method: the source rig's high-passed
  displacements (the metric's high-pass, per shape, driven by the truth's weights) carried to
  the same vertex of the target exactly, by the conventions the dense methods use (normal
  offset onto the target's normal: coating's Eq. 16 frames, normalmesh's Eq. 8; or the
  displacement's direction kept, as deformation gradients keep it), with and without the
  size ratio, and an oracle per-vertex gain fitted to the truth; against per-frame
  deformation transfer's ``detail_error``. Below 0.7 x DT only the oracle gets there.
- **cross-detail**: the same on the wrinkled cross-topology case (``cases.cross_topology(wrinkles=True)``:
  a once-subdivided 9,313-vertex source of another topology with glabella, procerus, chin and
  perioral wrinkles onto the 9,409-vertex ICT face) and its wrinkle-free twin
  (``wrinkles=False, source_subdivisions=1``), plus what the wrinkles alone change in each result
  (case minus twin, high-passed normal motion) against what they change in the truth: wrinkle
  transfer error, gain (1 = the truth's depth) and correlation.
- **piercing**: ``normalmesh``'s piercing-error share on ICT (goal < 0.5% of the normal-mesh
  vertices) and its coverage.
"""

from __future__ import annotations

import argparse
import sys
import warnings
from pathlib import Path

import numpy as np

import faceretarget as fr
from faceretarget.evaluation.harness import resolve_case
from faceretarget.evaluation.metrics import METRICS, normal_detail, to_head_frame
from faceretarget.evaluation.reproduction import DETAIL_CASES
from faceretarget.testing import _Affine, _moved_source, _moved_target, _static_source

sys.path.insert(0, str(Path(__file__).resolve().parent))
import _common as C  # noqa: E402

METHODS = ("deformation_transfer", "coating", "normalmesh")
SCALES = (0.01, 100.0, 1000.0)


def rms_percent(a, b, height) -> float:
    d = np.asarray(a, dtype=np.float64) - np.asarray(b, dtype=np.float64)
    return float(100.0 * np.sqrt(np.mean(np.sum(d * d, axis=-1))) / height)


def run(method, source, target, **params):
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        return fr.get(method, **params).fit(source, target).retarget(source)


def table(rows, header):
    widths = [max(len(str(h)), *(len(str(r[i])) for r in rows)) for i, h in enumerate(header)]
    print("  ".join(str(h).ljust(w) for h, w in zip(header, widths)))
    for r in rows:
        print("  ".join(str(c).ljust(w) for c, w in zip(r, widths)))
    print()


def cross_topology(frames: int) -> None:
    case = fr.cases.cross_topology(n_frames=frames)
    target, height = case.target, float(case.target.neutral.height)
    still = _static_source(case.source)
    neutral = np.repeat(np.asarray(target.neutral.vertices)[None], still.n_frames, axis=0)
    rows, rms = [], {}
    for m in METHODS:
        rest = rms_percent(run(m, still, target).vertices, neutral, height)
        rms[m] = rms_percent(run(m, case.source, target).vertices, case.truth.vertices, height)
        rows.append(
            (
                m,
                f"{rest:.5f}",
                "yes" if rest < 0.01 else "NO",
                f"{rms[m]:.4f}",
                f"{rms[m] / rms['deformation_transfer']:.2f}",
            )
        )
    print(
        f"cross-topology ({case.source.performance.reference.n_vertices} -> {target.neutral.n_vertices} vertices, {frames} frames)"
    )
    table(rows, ("method", "neutral-in error (% H)", "< 0.01%", "RMS error (% H)", "RMS / DT"))


def units(frames: int) -> None:
    case = fr.cases.cross_topology(n_frames=frames)
    source, target = case.source, case.target
    height = float(target.neutral.height)
    centre = np.asarray(target.neutral.vertices).mean(axis=0)
    rows = []
    for m in METHODS:
        base = np.asarray(run(m, source, target).vertices, dtype=np.float64)
        worst = []
        for s in SCALES:
            got = run(m, _moved_source(source, _Affine(s)), target).vertices
            worst.append((f"source x{s:g}", rms_percent(got, base, height) / 100.0))
            move = _Affine(s, None, centre * (1.0 - s))
            got = move.inverse_points(run(m, source, _moved_target(target, move)).vertices)
            worst.append((f"target x{s:g}", rms_percent(got, base, height) / 100.0))
        label, err = max(worst, key=lambda x: x[1])
        rows.append((m, f"{err:.2e}", label, "yes" if err <= 1e-6 else "NO"))
    print(
        "unit-scaled runs (cross-topology pair; largest RMS difference / face height over x0.01, x100, x1000 of either side)"
    )
    table(rows, ("method", "largest difference", "at", "<= 1e-6"))


def detail(resolution: int | None) -> None:
    rows = []
    for label, spec in DETAIL_CASES:
        if not spec.startswith("synthetic"):
            continue  # the cross-topology case has its own table (cross_detail)
        if resolution is not None:
            spec = spec.replace("resolution=1500", f"resolution={resolution}")
        case = resolve_case(spec)
        twin = resolve_case(spec + "&wrinkles=False")
        got = {}
        for m in METHODS:
            a, b = run(m, case.source, case.target), run(m, twin.source, twin.target)
            got[m] = (
                METRICS["vertex_error_rms"].compute(a, case, {}),
                METRICS["detail_error"].compute(a, case, {}),
                METRICS["detail_correlation"].compute(a, case, {}),
                METRICS["detail_error"].compute(b, twin, {}),
            )
        dt = got["deformation_transfer"]
        for m, (rms, de, corr, de_twin) in got.items():
            rows.append(
                (
                    label,
                    m,
                    f"{rms:.4f}",
                    f"{de:.5f}",
                    f"{de / dt[1]:.2f}",
                    f"{corr:.3f}",
                    f"{de_twin:.5f}",
                    f"{de_twin / dt[3]:.2f}",
                )
            )
    print(
        f"detail (wrinkled synthetic cases{'' if resolution is None else f', resolution {resolution}'}; goal: detail_error ratio to DT <= 0.7)"
    )
    table(
        rows,
        (
            "case",
            "method",
            "RMS (% H)",
            "detail_error (% H)",
            "ratio to DT",
            "detail corr.",
            "wrinkle-free twin",
            "twin ratio",
        ),
    )


def detail_bound(frames: int) -> None:
    """Per-vertex transfer conventions applied exactly to the synthetic rigs (see the module
    docstring, part "detail-bound")."""
    from faceretarget.evaluation.metrics import detail_smoothing_operator, high_pass
    from faceretarget.geometry.mesh_ops import face_areas, vertex_normals

    rows = []
    for kind in ("human", "stylized"):
        case = fr.cases.synthetic(resolution=1500, n_frames=frames, target=kind)
        weights = np.asarray(case.truth.weights, dtype=np.float64)
        src_rig, tgt_rig = case.source.rig, case.target.blendshapes
        ns = np.asarray(src_rig.neutral.vertices, dtype=np.float64)
        nt = np.asarray(case.target.neutral.vertices, dtype=np.float64)
        tri = np.asarray(case.target.neutral.triangles)
        height = float(case.target.neutral.height)
        truth = weights @ normal_detail(np.asarray(tgt_rig.deltas), tri, nt)
        normal = weights @ normal_detail(np.asarray(src_rig.deltas), tri, ns)
        fine = high_pass(np.asarray(src_rig.deltas), detail_smoothing_operator(len(ns), tri))
        kept = np.einsum("fk,kvd,vd->fv", weights, fine, vertex_normals(nt, tri))
        ratio = float(np.sqrt(face_areas(nt, tri).sum() / face_areas(ns, tri).sum()))
        gain = np.sum(normal * truth, axis=0) / np.maximum(np.sum(normal * normal, axis=0), 1e-300)
        dt = METRICS["detail_error"].compute(
            run("deformation_transfer", case.source, case.target), case, {}
        )

        def err(x, truth=truth, height=height):
            return 100.0 * float(np.sqrt(np.mean((x - truth) ** 2))) / height

        for label, x in (
            ("normal -> normal", normal),
            ("normal -> normal x size ratio", ratio * normal),
            ("direction kept", kept),
            ("direction kept x size ratio", ratio * kept),
            ("oracle per-vertex gain (fitted to the truth)", gain * normal),
        ):
            rows.append((kind, label, f"{err(x):.5f}", f"{err(x) / dt:.2f}"))
        rows.append((kind, "deformation_transfer (the method)", f"{dt:.5f}", "1.00"))
    print(
        f"detail bound (synthetic detail cases, 1500 vertices, {frames} frames: the source's fine-scale motion "
        "carried vertex to vertex exactly; goal <= 0.7 x DT)"
    )
    table(rows, ("case", "per-vertex transfer", "detail_error (% H)", "ratio to DT"))


def wrinkle_response(animations, cases):
    """(F, V) high-passed normal motion that the wrinkles alone change: ``animations`` and ``cases``
    are (wrinkled, twin) pairs of results or of cases (their truths)."""
    case = cases[0]
    neutral = np.asarray(case.target.neutral.vertices, dtype=np.float64)
    local = [
        to_head_frame(np.asarray(a.vertices, dtype=np.float64), c.truth.head_motion)
        for a, c in zip(animations, cases)
    ]
    return normal_detail(local[0] - local[1], case.target.neutral.triangles, neutral)


def cross_detail(frames: int, params: dict | None = None) -> None:
    """Detail metrics on the wrinkled cross-topology case and its twin; ``params``: {method: kwargs}."""
    params = params or {}
    case = fr.cases.cross_topology(n_frames=frames, wrinkles=True)
    twin = fr.cases.cross_topology(n_frames=frames, wrinkles=False, source_subdivisions=1)
    height = float(case.target.neutral.height)
    truth = wrinkle_response((case.truth, twin.truth), (case, twin))
    rows, got = [], {}
    for m in METHODS:
        kw = params.get(m, {})
        a, b = run(m, case.source, case.target, **kw), run(m, twin.source, twin.target, **kw)
        resp = wrinkle_response((a, b), (case, twin))
        got[m] = {
            "rms": METRICS["vertex_error_rms"].compute(a, case, {}),
            "de": METRICS["detail_error"].compute(a, case, {}),
            "corr": METRICS["detail_correlation"].compute(a, case, {}),
            "rms_twin": METRICS["vertex_error_rms"].compute(b, twin, {}),
            "de_twin": METRICS["detail_error"].compute(b, twin, {}),
            "corr_twin": METRICS["detail_correlation"].compute(b, twin, {}),
            "w_err": 100.0 * float(np.sqrt(np.mean((resp - truth) ** 2))) / height,
            "w_gain": float(np.sum(resp * truth) / np.sum(truth**2)),
            "w_corr": float(np.corrcoef(resp.ravel(), truth.ravel())[0, 1]),
        }
    dt = got["deformation_transfer"]
    for m, g in got.items():
        rows.append(
            (
                m,
                "yes",
                f"{g['rms']:.4f}",
                f"{g['de']:.5f}",
                f"{g['corr']:.3f}",
                f"{g['de'] / dt['de']:.2f}",
                f"{g['w_err']:.5f}",
                f"{g['w_err'] / dt['w_err']:.2f}",
                f"{g['w_gain']:.2f}",
                f"{g['w_corr']:.3f}",
            )
        )
        rows.append(
            (
                m,
                "no",
                f"{g['rms_twin']:.4f}",
                f"{g['de_twin']:.5f}",
                f"{g['corr_twin']:.3f}",
                f"{g['de_twin'] / dt['de_twin']:.2f}",
                "",
                "",
                "",
                "",
            )
        )
    wrinkle = 100.0 * float(np.sqrt(np.mean(truth**2))) / height
    print(
        f"cross-topology detail ({case.source.performance.reference.n_vertices} -> {case.target.neutral.n_vertices} vertices, {frames} frames; "
        f"the wrinkles' own fine-scale motion in the truth: {wrinkle:.5f}% H; goal: detail_error ratio to DT <= 0.7)"
    )
    table(
        rows,
        (
            "method",
            "wrinkles",
            "RMS (% H)",
            "detail_error (% H)",
            "detail corr.",
            "ratio to DT",
            "wrinkle error (% H)",
            "w. err. / DT",
            "wrinkle gain",
            "wrinkle corr.",
        ),
    )


def piercing(frames: int) -> None:
    case = fr.cases.ict(n_frames=frames)
    rows = []
    for levels in ("auto", 4):
        r = fr.get("normalmesh", levels=levels)
        with warnings.catch_warnings():
            warnings.simplefilter("ignore")
            r.fit(case.source, case.target)
            anim = r.retarget(case.source)
        p = anim.provenance["diagnostics"]["piercing_errors"]
        cov = anim.provenance["diagnostics"]["coverage"]
        rms = rms_percent(anim.vertices, case.truth.vertices, float(case.target.neutral.height))
        per_frame = float(p["source_share_per_frame"])
        rows.append(
            (
                levels,
                r.levels_,
                p["normal_mesh_vertices"],
                f"{100 * p['target_share']:.3f}",
                f"{100 * per_frame:.3f}",
                f"{100 * cov['covered']:.1f}",
                f"{rms:.4f}",
            )
        )
    print("normalmesh piercing errors on ICT (goal < 0.5% of the normal-mesh vertices)")
    table(
        rows,
        (
            "levels",
            "used",
            "normal-mesh vertices",
            "target share (%)",
            "source mean per frame (%)",
            "covered (%)",
            "RMS (% H)",
        ),
    )


def main(argv=None) -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--frames", type=int, default=60)
    ap.add_argument(
        "--detail-resolution",
        type=int,
        default=None,
        help="resolution of the detail cases (default: the presets')",
    )
    ap.add_argument(
        "--skip",
        default="",
        help="comma-separated parts to skip: cross, units, detail, detail-bound, cross-detail, piercing",
    )
    args = ap.parse_args(argv)
    C.print_machine("bench_dense_fidelity (errors only, no timings)")
    skip = set(filter(None, args.skip.split(",")))
    if "cross" not in skip:
        cross_topology(args.frames)
    if "units" not in skip:
        units(min(args.frames, 20))
    if "detail" not in skip:
        detail(args.detail_resolution)
    if "detail-bound" not in skip:
        detail_bound(args.frames)
    if "cross-detail" not in skip:
        cross_detail(max(args.frames, 90))
    if "piercing" not in skip:
        piercing(args.frames)


if __name__ == "__main__":
    main()
