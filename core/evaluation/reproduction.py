"""Helpers for writing a paper reproduction (a :class:`faceretarget.Preset`'s ``run``).

Nothing here knows a method: the names come from the preset that calls.

- methods: :func:`require`, :func:`run_method`, :func:`paper_params` (a method's paper-exact
  settings, only those the installed version accepts, so later changes of its defaults do
  not change the reproduction);
- inputs: :func:`noisy_markers` (an optical capture of a case's source, optionally with the
  Procrustes head motion of :func:`procrustes_head_motion`);
- measures: :func:`rms_per_frame`, :func:`face_size`;
- the verdict: :func:`set_verdict`, numbers for people with :func:`num`;
- a whole reproduction shared by papers about fine-scale detail: :func:`detail_transfer`.

Presets use the retargeters only through :func:`faceretarget.get` (never importing a
plugin), on the built-in cases (modest sizes by default, or the caller's cases). Nothing is
tuned to make a reproduction agree: one that disagrees with its paper is reported as
disagreeing, and the report shows it in red with the numbers.
"""

from __future__ import annotations

from collections.abc import Mapping
from typing import TYPE_CHECKING, Any

import numpy as np

from .metrics import METRICS, normal_detail, to_head_frame
from .presets import Cases, PresetResult

if TYPE_CHECKING:
    from ..cases import Case
    from ..model import Animation, Source

__all__ = [
    "OPTICAL_NOISE",
    "NOISE_SEED",
    "DETAIL_CASES",
    "DETAIL_MIN_WRINKLE",
    "paper_params",
    "require",
    "run_method",
    "set_verdict",
    "num",
    "rms_per_frame",
    "face_size",
    "noisy_markers",
    "procrustes_head_motion",
    "detail_transfer",
]

#: Marker noise of optical motion capture, relative to the face size: 0.3 mm (standard
#: deviation per coordinate) on a face whose neutral markers have an RMS radius of 60 mm.
#: Multiplied by the RMS radius of the source's neutral markers, so it means the same in any
#: length unit.
OPTICAL_NOISE = 0.3 / 60.0
#: Seed of the simulated capture noise (fixed: a preset is deterministic).
NOISE_SEED = 0


def paper_params(name: str, params: Mapping[str, Any]) -> dict:
    """The entries of ``params`` that retargeter ``name`` accepts (its ``get_params()``).

    Lets a reproduction pass a method's paper-exact settings explicitly, before and after
    the method grows (or drops) parameters: unknown ones are left out, since a version
    without a parameter has the paper's behaviour for it.
    """
    import faceretarget

    known = faceretarget.get(name).get_params()
    return {k: v for k, v in params.items() if k in known}


def require(*names: str) -> None:
    """Raise :class:`~faceretarget.errors.UnknownNameError` (preset "not applicable") unless
    every retargeter of ``names`` is installed."""
    from ..registry import registry

    for name in names:
        registry().resolve(name)


def run_method(name: str, case: Case, source: Source | None = None, **params: Any) -> Animation:
    """``faceretarget.get(name, **params)`` fitted to the case and run on ``source`` (default the case's)."""
    import faceretarget

    source = case.source if source is None else source
    return faceretarget.get(name, **params).fit(source, case.target).retarget(source)


def set_verdict(res: PresetResult, parts: list[tuple[str, bool]], note: str = "") -> None:
    """Set ``agrees`` (all parts hold) and ``evidence`` (each part with its measured numbers)."""
    res.agrees = bool(all(ok for _, ok in parts))
    text = "; ".join(f"{'agrees' if ok else 'DISAGREES'}: {what}" for what, ok in parts)
    res.evidence = f"{text}. {note}".strip() if note else text + "."


def num(v: float) -> str:
    """Three significant digits, for people (``2.99×10⁻⁵``, never ``2.99e-05``)."""
    from .report import format_number

    return format_number(float(f"{v:.3g}"))


def _truth(case: Case) -> Animation:
    """The ground truth of a case these reproductions use (the built-in cases all have one)."""
    assert case.truth is not None  # the built-in cases are made with their ground truth
    return case.truth


def rms_per_frame(animation: Animation, case: Case) -> np.ndarray:
    """Per frame, the RMS distance of the result from the ground truth, % of the target face height."""
    height = float(case.target.neutral.height)
    diff = np.asarray(animation.vertices, dtype=np.float64) - np.asarray(
        _truth(case).vertices, dtype=np.float64
    )
    return 100.0 * np.sqrt(np.einsum("fvd,fvd->fv", diff, diff).mean(axis=1)) / height


def face_size(points: np.ndarray) -> float:
    """RMS distance of ``points (N, 3)`` from their centroid."""
    p = np.asarray(points, dtype=np.float64)
    return float(np.sqrt(np.mean(np.sum((p - p.mean(axis=0)) ** 2, axis=1))))


def noisy_markers(
    source: Source,
    relative_sigma: float = OPTICAL_NOISE,
    seed: int = NOISE_SEED,
    *,
    procrustes: bool = False,
) -> tuple[Source, float]:
    """``(Source, sigma)``: the source's markers (a mesh source sampled at its landmarks) plus
    Gaussian noise of ``relative_sigma`` times the RMS radius of its neutral markers, as an
    optical capture would deliver them (actor layers kept). Head motion: none known, or with
    ``procrustes`` the estimate of :func:`procrustes_head_motion` as a known head motion."""
    from ..model import MarkerSequence, Source

    x = np.asarray(source.marker_positions(), dtype=np.float64)
    reference = np.asarray(source.marker_reference(), dtype=np.float64)
    sigma = relative_sigma * face_size(reference)
    noisy = x + sigma * np.random.default_rng(seed).normal(size=x.shape)  # NaN (missing) stays NaN
    perf, landmarks = source.performance, source.landmarks
    if source.kind == "markers":
        assert isinstance(perf, MarkerSequence)  # a Source's kind is its performance's
        names = perf.names
    else:
        assert landmarks is not None  # marker_positions() above needs them
        names = landmarks.names
    markers = MarkerSequence(noisy, names=names, reference=reference, fps=source.fps)
    motion = procrustes_head_motion(reference, noisy) if procrustes else None
    return Source(markers, head_motion=motion, actor_layers=source.actor_layers), sigma


def procrustes_head_motion(reference: np.ndarray, markers: np.ndarray) -> np.ndarray:
    """(F, 4, 4) rigid head motion: per frame, the rotation and translation that best align the
    neutral markers with the frame's markers (Kabsch)."""
    from ..geometry import procrustes

    rotation, translation, _ = procrustes.fit_rigid(reference, markers)
    return procrustes.to_matrix(rotation, translation)


# ---------------------------------------------------------------------------------------
# Fine-scale detail: a method with and without its detail layer, against a baseline
# ---------------------------------------------------------------------------------------
#: Cases of the detail reproductions: (label, case spec). Synthetic parallel rigs whose
#: blendshapes carry wrinkle fields (forehead furrows, glabella lines, crow's feet, nasolabial
#: folds, bunny lines), 90 frames so that the wrinkle shapes are active; and the papers' own
#: setting, fine detail of a dense source carried to a target of another mesh: the wrinkled
#: cross-topology case (a 9,313-vertex closed-eye source with a mouth bag, glabella, procerus,
#: chin and perioral wrinkles, onto the 9,409-vertex ICT face; its twin keeps the subdivided
#: source). Each is compared with its wrinkle-free twin (the same spec with ``wrinkles=False``)
#: to measure the wrinkles' own fine-scale motion. Both specs are looked up in the caller's
#: cases first.
DETAIL_CASES = (
    ("human", "synthetic-human?resolution=1500&n_frames=90"),
    ("stylized", "synthetic-stylized?resolution=1500&n_frames=90"),
    ("cross-topology", "cross_topology?wrinkles=True&source_subdivisions=1&n_frames=90"),
)
#: Below this RMS (% of the face height) the wrinkles move too little for a verdict.
DETAIL_MIN_WRINKLE = 1e-4


def _no_wrinkles(spec: str) -> str:
    return spec + ("&" if "?" in spec else "?") + "wrinkles=False"


def _measure(animation: Animation, case: Case) -> dict:
    return {
        m: METRICS[m].compute(animation, case, {})
        for m in ("detail_error", "detail_correlation", "vertex_error_rms")
    }


def detail_transfer(
    cases: Cases,
    res: PresetResult,
    method: str,
    params: dict,
    *,
    ablation: dict,
    baseline: str,
    baseline_label: str,
    large_scale: bool,
) -> None:
    """``method`` (with ``params``), the same with its detail layer switched off (``params``
    updated by ``ablation``, public parameters) and ``baseline`` (default parameters; called
    ``baseline_label`` in the evidence) on each of :data:`DETAIL_CASES`; the verdict compares
    detail errors (and with ``large_scale`` the RMS error too)."""
    from .report import Plot, Series

    require(method, baseline)
    labels = {"method": method, "without": f"{method} without details", "baseline": baseline}
    short = {
        "method": method,
        "without": "no detail",
        "baseline": "".join(w[0] for w in baseline_label.split()).upper(),
    }
    parts, bars, skipped = [], [], []
    for label, spec in DETAIL_CASES:
        case = cases(spec)
        height = float(case.target.neutral.height)
        twin = cases(_no_wrinkles(spec))
        if np.shape(_truth(twin).vertices) != np.shape(_truth(case).vertices):
            skipped.append(f"{label}: the wrinkle-free twin does not match the case")
            continue
        neutral = np.asarray(case.target.neutral.vertices, dtype=np.float64)
        local = [
            to_head_frame(np.asarray(_truth(c).vertices, dtype=np.float64), _truth(c).head_motion)
            for c in (case, twin)
        ]
        truth_wrinkle = normal_detail(local[0] - local[1], case.target.neutral.triangles, neutral)
        wrinkle = 100.0 * float(np.sqrt(np.mean(truth_wrinkle**2))) / height
        if not wrinkle > DETAIL_MIN_WRINKLE:
            skipped.append(
                f"{label}: no wrinkle is active in the performance (fine-scale wrinkle motion {num(wrinkle)}% of H)"
            )
            continue
        settings = {
            "method": (method, params),
            "without": (method, paper_params(method, {**params, **ablation})),
            "baseline": (baseline, {}),
        }
        got = {}
        for key, (name, kw) in settings.items():
            anim, plain = run_method(name, case, **kw), run_method(name, twin, **kw)
            got[key] = _measure(anim, case)
            # what the wrinkles alone change in the result (the twin differs only by them)
            moved = [
                to_head_frame(np.asarray(a.vertices, dtype=np.float64), _truth(c).head_motion)
                for a, c in ((anim, case), (plain, twin))
            ]
            response = normal_detail(moved[0] - moved[1], case.target.neutral.triangles, neutral)
            got[key]["twin"] = METRICS["detail_error"].compute(plain, twin, {})
            got[key]["wrinkle error"] = (
                100.0 * float(np.sqrt(np.mean((response - truth_wrinkle) ** 2))) / height
            )
            got[key]["wrinkle gain"] = float(
                np.sum(response * truth_wrinkle) / np.sum(truth_wrinkle**2)
            )
        for key, values in got.items():
            res.table.append(
                {
                    "case": label,
                    "retargeter": labels[key],
                    "detail error (% face height)": values["detail_error"],
                    "detail correlation": values["detail_correlation"],
                    "RMS error (% face height)": values["vertex_error_rms"],
                    "wrinkle fine-scale motion (% face height)": wrinkle,
                    "detail error without wrinkles (% face height)": values["twin"],
                    "wrinkle transfer error (% face height)": values["wrinkle error"],
                    "wrinkle gain": values["wrinkle gain"],
                }
            )
            bars.append(Series(f"{label} {short[key]}", [0], [values["detail_error"]]))
        m, w, d = got["method"], got["without"], got["baseline"]
        parts.append(
            (
                f"{label}: the detail transfer lowers the detail error ({num(m['detail_error'])}% vs {num(w['detail_error'])}% without it)",
                m["detail_error"] < w["detail_error"],
            )
        )
        parts.append(
            (
                f"{label}: detail error below {baseline_label}'s ({num(m['detail_error'])}% vs {num(d['detail_error'])}%; correlation "
                f"{num(m['detail_correlation'])} vs {num(d['detail_correlation'])}; without wrinkles {num(m['twin'])}% vs {num(d['twin'])}%, "
                f"wrinkle transfer error {num(m['wrinkle error'])}% vs {num(d['wrinkle error'])}%)",
                m["detail_error"] < d["detail_error"],
            )
        )
        if large_scale:
            parts.append(
                (
                    f"{label}: large-scale expression at least as close as {baseline_label}'s (RMS error {num(m['vertex_error_rms'])}% vs {num(d['vertex_error_rms'])}%)",
                    m["vertex_error_rms"] <= d["vertex_error_rms"],
                )
            )
    if bars:
        res.plots.append(
            Plot(
                "detail error (fine-scale normal motion, RMS % face height)",
                bars,
                ylabel="% face height",
                kind="bar",
            )
        )
    note = (
        "Detail error and correlation as the metrics detail_error and detail_correlation (% of the face height). "
        "'Detail error without wrinkles' is the same metric on the wrinkle-free twin: the fine-scale error of the "
        "large-scale motion (lids, lips, jaw crease), which the metric sees as well; 'wrinkle transfer error' and "
        "'wrinkle gain' compare what the wrinkles alone change in the result (case minus twin, high-passed normal "
        "motion) with what they change in the ground truth (gain 1 = the truth's wrinkle depth)."
        + (" Not measured: " + "; ".join(skipped) + "." if skipped else "")
    )
    if not parts:
        res.agrees, res.evidence = None, "not decided: " + "; ".join(skipped)
        return
    set_verdict(res, parts, note)
