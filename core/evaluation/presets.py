"""Paper reproductions as harness presets, each producing its plot for the report.

==================  ==========================================================================
``seol_fig11``      Seol et al. 2012, fig. 11: velocity error of No Const, Range PF, Prior PF
                    and movement matching: (a) the sum, (b) the delta from No Const over time
``kholgade_fig8``   Kholgade et al. 2011, fig. 8: RMS reconstruction error over time of the
                    layered model versus emotion-only, speech-only and blink-only models
``najung_table1``   Na & Jung 2004, table 1: vertices with piercing errors per mesh
``xu_fig4``         Xu et al. 2014, fig. 4: propagation of a large-scale edit when updating the
                    bases only, bases and weights jointly, or the weights only
==================  ==========================================================================

Presets use the retargeters only through :func:`faceretarget.get` (never importing a
plugin), on the built-in cases (modest sizes by default, or the caller's cases). A preset
whose retargeter is not installed, or that fails, is returned with status ``not
applicable`` / ``error`` and the reason, and the report shows it.

    from faceretarget.evaluation import compare, run_presets, write_report
    result = compare(["synthetic-human"])
    run_presets(result)                      # attaches every preset to result.presets
    write_report(result, "report/")
"""
from __future__ import annotations

import copy
from dataclasses import dataclass, field
from types import SimpleNamespace
from typing import Any, Callable, Mapping

import numpy as np

from ..errors import CapabilityError, PluginOutputError, UnknownNameError
from ..model import LayeredRig
from .harness import ERROR, NOT_APPLICABLE, OK, _jsonable, resolve_case
from .metrics import landmark_velocity_curve, to_head_frame
from .report import Plot, Series

__all__ = ["PresetResult", "PRESETS", "run_preset", "run_presets", "PRESET_CASES"]

#: Cases the presets build when the caller gives none (kept small: seconds each).
PRESET_CASES = {
    "synthetic-human": "synthetic-human?resolution=1500&n_frames=90",
    "synthetic-stylized": "synthetic-stylized?resolution=1500&n_frames=90",
    "ict": "ict?n_frames=60",
}


@dataclass
class PresetResult:
    name: str
    title: str
    paper: str
    description: str
    status: str = OK
    reason: str = ""
    plots: list[Plot] = field(default_factory=list)
    table: list[dict] = field(default_factory=list)

    def as_dict(self) -> dict:
        return {
            "name": self.name,
            "title": self.title,
            "paper": self.paper,
            "description": self.description,
            "status": self.status,
            "reason": self.reason,
            "plots": [p.as_dict() for p in self.plots],
            "table": _jsonable(self.table),
        }


#: name -> (title, paper, description, run(cases, result))
PRESETS: dict[str, tuple[str, str, str, Callable]] = {}


def _preset(name: str, title: str, paper: str, description: str):
    def register(fn):
        PRESETS[name] = (title, paper, description, fn)
        return fn

    return register


class _Cases:
    """Cases by name: the caller's, else built on first use from :data:`PRESET_CASES`."""

    def __init__(self, given: Mapping[str, Any] | None):
        self.given = dict(given or {})

    def __call__(self, name: str):
        if name not in self.given:
            self.given[name] = resolve_case(PRESET_CASES.get(name, name))
        return self.given[name]


def _require(*names: str) -> None:
    from ..registry import registry

    for name in names:
        registry().resolve(name)


def _run(name: str, case, **params):
    import faceretarget

    return faceretarget.get(name, **params).fit(case.source, case.target).retarget(case.source)


def _rms_per_frame(animation, case) -> np.ndarray:
    height = float(case.target.neutral.height)
    diff = np.asarray(animation.vertices, dtype=np.float64) - np.asarray(case.truth.vertices, dtype=np.float64)
    return 100.0 * np.sqrt(np.einsum("fvd,fvd->fv", diff, diff).mean(axis=1)) / height


# ---------------------------------------------------------------------------------------
# Seol 2012 fig. 11
# ---------------------------------------------------------------------------------------
_SEOL = (("No Const", "spacetime_noconst"), ("Range PF", "spacetime_rangepf"), ("Prior PF", "spacetime_priorpf"), ("movement matching", "spacetime"))


@_preset(
    "seol_fig11",
    "Seol 2012 fig. 11: velocity error of per-frame matching vs movement matching",
    "Seol, Lewis, Seo, Choi, Anjyo, Noh. Spacetime Expression Cloning for Blendshapes. ACM TOG 31(2), 2012",
    "The four retargeters on the synthetic human case. (a) Sum over frames of the velocity error "
    "||D P - D Q||_F^2 / H^2 of the target landmarks P against the ground truth's Q (the paper compares "
    "with the warped source markers; the plugin's own value of that is in the table as 'paper velocity "
    "error'). (b) Per frame, each method's velocity error minus No Const's: per-frame matching with "
    "constraints (Range PF, Prior PF) should add more than movement matching does.",
)
def seol_fig11(cases: _Cases, res: PresetResult) -> None:
    """Velocity error ||D P - D Q||_F^2 / H^2 of the landmarks against the ground truth."""
    _require(*(n for _, n in _SEOL))
    case = cases("synthetic-human")
    curves = {}
    for label, name in _SEOL:
        anim = _run(name, case)
        curves[label] = landmark_velocity_curve(anim.vertices, case.truth, case.target)
        diag = anim.provenance.get("diagnostics", {})
        res.table.append(
            {
                "method": label,
                "retargeter": name,
                "velocity error (vs truth)": float(curves[label].sum()),
                "added over No Const": float(curves[label].sum() - curves["No Const"].sum()),
                "paper velocity error (vs source)": diag.get("velocity_error"),
                "weights in range": diag.get("fraction_in_range"),
            }
        )
    res.plots.append(Plot("(a) sum of velocity errors", [Series(k, [0], [v.sum()]) for k, v in curves.items()], ylabel="sum ||DP - DQ||^2 / H^2", kind="bar"))
    frames = np.arange(1, len(curves["No Const"]) + 1)
    res.plots.append(
        Plot(
            "(b) velocity error minus No Const's, per frame",
            [Series(k, frames, v - curves["No Const"], dashed=k in ("Range PF", "Prior PF")) for k, v in curves.items() if k != "No Const"],
            xlabel="frame",
            ylabel="delta ||DP - DQ||^2 / H^2",
        )
    )


# ---------------------------------------------------------------------------------------
# Kholgade 2011 fig. 8
# ---------------------------------------------------------------------------------------
def _single_layer(rig: LayeredRig, layer: str) -> LayeredRig:
    return LayeredRig({layer: rig.layers[layer]}, rig.masks, pose_names={layer: rig.pose_names[layer]}, region_names=rig.region_names)


def _with_layer(case, layer: str):
    """The case with actor and character layers restricted to ``layer`` (shallow copies)."""
    source, target = copy.copy(case.source), copy.copy(case.target)
    source.actor_layers = _single_layer(case.source.actor_layers, layer)
    target.layers = _single_layer(case.target.layers, layer)
    return SimpleNamespace(name=getattr(case, "name", "case"), source=source, target=target, truth=case.truth)


@_preset(
    "kholgade_fig8",
    "Kholgade 2011 fig. 8: layered model vs single-layer models",
    "Kholgade, Matthews, Sheikh. Content Retargeting Using Parameter-Parallel Facial Layers. SCA 2011",
    "The layers retargeter on the synthetic human case with all layers, and with the actor and character "
    "bases restricted to one layer (emotion only, speech only, blink only). Plotted: per-frame RMS error "
    "of the character against the ground truth, % of face height (the paper plots the actor's "
    "reconstruction error; the synthetic case is generated from the same layered model, so the character "
    "error measures the same thing through the public API). Expected order: layered < emotion < speech < blink.",
)
def kholgade_fig8(cases: _Cases, res: PresetResult) -> None:
    _require("layers")
    case = cases("synthetic-human")
    if case.source.actor_layers is None or case.target.layers is None:
        res.status, res.reason = NOT_APPLICABLE, "the case has no actor layers or character layers"
        return
    variants = [("layered", case)] + [(f"{layer} only", _with_layer(case, layer)) for layer in case.source.actor_layers.layer_names]
    curves = {}
    for label, variant in variants:
        curves[label] = _rms_per_frame(_run("layers", variant), variant)
        res.table.append({"model": label, "mean RMS error (% face height)": float(curves[label].mean()), "frames where best": 0})
    stacked = np.stack(list(curves.values()))
    best = np.argmin(stacked, axis=0)
    for i, row in enumerate(res.table):
        row["frames where best"] = int((best == i).sum())
    frames = np.arange(stacked.shape[1])
    res.plots.append(Plot("RMS reconstruction error per frame", [Series(k, frames, v) for k, v in curves.items()], xlabel="frame", ylabel="RMS error, % face height", log_y=True))


# ---------------------------------------------------------------------------------------
# Na & Jung 2004 table 1
# ---------------------------------------------------------------------------------------
@_preset(
    "najung_table1",
    "Na & Jung 2004 table 1: piercing errors of the normal meshes",
    "Na, Jung. Hierarchical Retargetting of Fine Facial Motions. Eurographics 2004",
    "The normalmesh retargeter (default levels) on each built-in case: vertices of the normal mesh whose "
    "normal ray pierced the wrong part of the surface (detected and repaired), for the target at its "
    "neutral and for the source as the mean over frames, as counted by the plugin.",
)
def najung_table1(cases: _Cases, res: PresetResult) -> None:
    _require("normalmesh")
    counts, failures = [], []
    for cname in ("synthetic-human", "synthetic-stylized", "ict"):
        try:
            anim = _run("normalmesh", cases(cname))
        except Exception as exc:  # one mesh failing must not hide the others
            failures.append(exc)
            res.table.append({"mesh": cname, "error": f"{type(exc).__name__}: {' '.join(str(exc).split())}"})
            continue
        diag = anim.provenance.get("diagnostics", {}).get("piercing_errors", {})
        total = diag.get("normal_mesh_vertices", diag.get("target_vertices"))
        if total is None:
            raise PluginOutputError(
                "the normalmesh retargeter did not report provenance['diagnostics']['piercing_errors'] with "
                f"'normal_mesh_vertices', 'target' and 'source_mean_per_frame'; it reported {sorted(diag)}"
            )
        for mesh, key, when in ((f"{cname} source", "source_mean_per_frame", "average of all frames"), (f"{cname} target", "target", "init frame")):
            value = float(diag.get(key, np.nan))
            counts.append((mesh, value, total))
            res.table.append({"mesh": mesh, "vertices": int(total), "vertices with piercing error": value, "when": when, "%": 100.0 * value / total})
        per_frame = anim.extras.get("piercing_errors_per_frame")
        if per_frame is not None and cname == "synthetic-human":
            res.plots.append(Plot("source piercing errors per frame (synthetic human)", [Series("source", np.arange(len(per_frame)), per_frame)], xlabel="frame", ylabel="vertices"))
    if not counts:
        raise failures[0]
    if failures:
        res.reason = f"{len(failures)} case(s) failed; see the table"
    res.plots.insert(0, Plot("vertices with piercing error, % of the normal mesh", [Series(m, [0], [100.0 * v / t]) for m, v, t in counts], ylabel="%", kind="bar"))


# ---------------------------------------------------------------------------------------
# Xu 2014 fig. 4
# ---------------------------------------------------------------------------------------
@_preset(
    "xu_fig4",
    "Xu 2014 fig. 4: propagation of a large-scale edit",
    "Xu, Chai, et al. Controllable High-fidelity Facial Performance Transfer. ACM TOG 33(4), 2014",
    "The coating retargeter on the synthetic human case; one expressive frame is edited (a point constraint "
    "moving the lower-lip landmark down by 3% of the face height) with a temporal window of +-10 frames, solved by "
    "updating the bases only, bases and weights jointly, or the weights only. Plotted: per frame, the mean "
    "displacement of the edited result from the unedited one (% face height): bases-only editing changes "
    "similar expressions anywhere in the sequence, weights-only editing stays inside the window.",
)
def xu_fig4(cases: _Cases, res: PresetResult) -> None:
    _require("coating")
    import faceretarget

    case = cases("synthetic-human")
    retargeter = faceretarget.get("coating").fit(case.source, case.target)
    base = retargeter.retarget(case.source)
    height = float(case.target.neutral.height)
    frame, window = _edit_frame(base, case), 10
    lm = case.target.landmarks
    lower = _lower_lip_landmark(case)
    vertex = int(lm.vertex_ids[lower]) if lm.vertex_ids is not None else None
    if vertex is None:
        res.status, res.reason = NOT_APPLICABLE, "the case's landmarks are barycentric; the edit needs a vertex"
        return
    offset = np.array([0.0, -0.03 * height, 0.0])
    if base.head_motion is not None:
        offset = np.asarray(base.head_motion[frame, :3, :3]) @ offset
    goal = np.asarray(base.vertices[frame, vertex], dtype=np.float64) + offset
    span = (max(0, frame - window), min(base.n_frames - 1, frame + window))
    frames = np.arange(base.n_frames)
    inside = (frames >= span[0]) & (frames <= span[1])
    series = []
    for label, mode in (("bases only", "bases"), ("bases and weights", "both"), ("weights only", "weights")):
        edited = retargeter.edit(base, points=[(frame, vertex, goal)], window=span, mode=mode)
        moved = np.asarray(edited.vertices, dtype=np.float64)
        change = 100.0 * np.linalg.norm(moved - np.asarray(base.vertices), axis=-1).mean(axis=1) / height
        series.append(Series(label, frames, change))
        res.table.append(
            {
                "mode": label,
                "constraint error (% face height)": float(100.0 * np.linalg.norm(moved[frame, vertex] - goal) / height),
                "mean change inside window": float(change[inside].mean()),
                "mean change outside window": float(change[~inside].mean()) if (~inside).any() else 0.0,
                "frames changed": int((change > 1e-6).sum()),
            }
        )
    res.plots.append(Plot(f"change from the unedited result (edit at frame {frame}, window {span[0]}-{span[1]})", series, xlabel="frame", ylabel="mean |change|, % face height"))


def _edit_frame(animation, case) -> int:
    truth = to_head_frame(np.asarray(case.truth.vertices, dtype=np.float64), case.truth.head_motion)
    amount = np.linalg.norm(truth - np.asarray(case.target.neutral.vertices), axis=-1).mean(axis=1)
    middle = slice(animation.n_frames // 4, max(animation.n_frames // 4 + 1, 3 * animation.n_frames // 4))
    return int(middle.start + np.argmax(amount[middle]))


def _lower_lip_landmark(case) -> int:
    names = [n.lower() for n in case.target.landmarks.names]
    for i, n in enumerate(names):
        if "lip" in n and ("lower" in n or "bottom" in n) and ("mid" in n or "center" in n or "centre" in n):
            return i
    for i, n in enumerate(names):
        if "lip" in n and ("lower" in n or "bottom" in n):
            return i
    neutral = np.asarray(case.target.landmarks.positions(case.target.neutral.vertices, case.target.neutral.triangles))
    return int(np.argmin(neutral[:, 1] + 10 * np.abs(neutral[:, 0] - neutral[:, 0].mean())))


def run_preset(name: str, cases: Mapping[str, Any] | None = None) -> PresetResult:
    """Run one preset; never raises for a missing or failing retargeter (see ``status``).

    cases : optional ``{case name: case}`` to reuse (e.g. ``result.cases``); missing ones
        are built from :data:`PRESET_CASES`.
    """
    if name not in PRESETS:
        raise UnknownNameError(f"no preset named {name!r}; valid presets: {', '.join(PRESETS)}")
    pool = cases if isinstance(cases, _Cases) else _Cases(cases)
    title, paper, description, run = PRESETS[name]
    res = PresetResult(name, title, paper, description)
    try:
        run(pool, res)
    except Exception as exc:  # a missing or failing retargeter is reported in the report
        res.status = NOT_APPLICABLE if isinstance(exc, (UnknownNameError, CapabilityError)) else ERROR
        res.reason = f"{type(exc).__name__}: {' '.join(str(exc).split())}"
    return res


def run_presets(result=None, names=None, cases: Mapping[str, Any] | None = None) -> list[PresetResult]:
    """Run presets (default all); with ``result``, reuse its cases and attach to ``result.presets``."""
    pool = _Cases({**(result.cases if result is not None else {}), **(cases or {})})
    out = [run_preset(n, pool) for n in (names or list(PRESETS))]
    if result is not None:
        result.presets.extend(out)
    return out
