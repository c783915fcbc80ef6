"""The report of a comparison: one self-contained HTML file, plus CSV and JSON tables.

``write_report(result, folder)`` writes

- ``report.html``: opens offline (every script, style and figure is inline; no network)
  and fits a 1280 px wide window (no table wider than the page, chart labels that never
  overlap, numbers as ``12,934`` or ``2.99×10⁻⁵``). It starts with, per case, who wins on
  the ranking metric, by how much, where else and why (:mod:`._summary`), the paper
  reproductions that disagree with their paper, and which methods are paper methods and
  which baselines; then the ranking by one named metric (``rank_by``, default
  ``vertex_error_rms``) with the run time apart from numba compile time; per case a
  metric table, an interactive viewer that scrubs through the frames of the source, the
  ground truth and every method side by side (canvas 2D renderer in
  ``assets/report.js``, shaded or coloured by per-vertex error), key frames side by side,
  per-vertex error heat maps on the target mesh, the velocity error over time, weight
  curves, the paper reproductions (presets: each paper's claim and setting, and whether
  the measurement agrees, in red with the numbers when it does not), the metric
  definitions and the runs (fit, retarget, of which compile, peak memory, parameters);
- ``results.csv``: the tidy table ``case, method, metric, value, unit, status, reason``;
- ``results.json``: the rows, the ranking, every run (parameters, timings, errors), the
  metric definitions and the presets.

To keep the HTML a few MB, at most ``max_frames`` frames are embedded per case, meshes
are decimated (graph-Voronoi clustering: seed vertices on a grid, every vertex joins the
seed nearest along mesh edges, triangles whose corners fall in three clusters remain)
to fit ``max_bytes``, and coordinates are quantized to 16 bits.
"""

from __future__ import annotations

import base64
import datetime as _dt
import html
import json
from collections.abc import Callable, Iterable, Mapping, Sequence
from dataclasses import dataclass, field
from importlib import resources
from pathlib import Path
from typing import TYPE_CHECKING, Any, SupportsFloat

import numpy as np

from ..errors import OutputError
from ..model import MarkerSequence, MeshSequence
from ._format import format_number
from .harness import ERROR, NOT_APPLICABLE, OK, ComparisonResult, Run, atomic_write_text
from .metrics import landmark_velocity_curve, per_vertex_error, to_head_frame

if TYPE_CHECKING:
    from .._types import PathLike
    from ..cases import Case
    from ..registry import Registry
    from ._summary import CaseSummary, MethodRole
    from .presets import PresetResult

__all__ = ["write_report", "Plot", "Series", "svg_plot", "decimate", "render_html"]

#: Raw bytes of embedded geometry per report (before base64), frames per case, vertices per mesh.
MAX_BYTES = 4_000_000
MAX_FRAMES = 24
MAX_VERTICES = 2500
MIN_VERTICES = 300
#: Weight curves drawn per case (the shapes with the largest variance in the ground truth).
MAX_WEIGHT_PANELS = 6
#: Columns of the per-case summary table (times are in the ranking and the runs, apart from compilation).
SUMMARY_METRICS = (
    "vertex_error_rms",
    "vertex_error_max",
    "marker_error_mean",
    "velocity_error",
    "lip_closure_error",
    "eyelid_closure_error",
    "lve",
    "fdd_abs",
    "detail_error",
    "detail_correlation",
    "weight_outside_share",
)

_PALETTE = (
    "#1f77b4",
    "#d62728",
    "#2ca02c",
    "#ff7f0e",
    "#9467bd",
    "#8c564b",
    "#e377c2",
    "#17becf",
    "#bcbd22",
    "#7f7f7f",
)


# ---------------------------------------------------------------------------------------
# Plots (inline SVG)
# ---------------------------------------------------------------------------------------
@dataclass
class Series:
    name: str
    x: Sequence[float] | np.ndarray
    y: Sequence[float] | np.ndarray
    dashed: bool = False
    color: str | None = None

    def as_dict(self) -> dict:
        return {
            "name": self.name,
            "x": [float(v) for v in self.x],
            "y": [_finite(v) for v in self.y],
            "dashed": self.dashed,
        }


@dataclass
class Plot:
    """A line plot (``kind="line"``) or a bar chart (``kind="bar"``: one horizontal bar per series, ``y[0]``)."""

    title: str
    series: list[Series] = field(default_factory=list)
    xlabel: str = ""
    ylabel: str = ""
    kind: str = "line"
    log_y: bool = False

    def as_dict(self) -> dict:
        return {
            "title": self.title,
            "kind": self.kind,
            "xlabel": self.xlabel,
            "ylabel": self.ylabel,
            "series": [s.as_dict() for s in self.series],
        }


def _finite(v: SupportsFloat) -> float | None:
    v = float(v)
    return v if np.isfinite(v) else None


def _ticks(lo: float, hi: float, n: int = 5) -> list[float]:
    if hi <= lo:
        hi = lo + 1.0
    raw = (hi - lo) / max(n, 1)
    mag = 10 ** np.floor(np.log10(raw))
    step = min((m * mag for m in (1, 2, 2.5, 5, 10) if m * mag >= raw), default=raw)
    start = np.ceil(lo / step) * step
    return [float(t) for t in np.arange(start, hi + 0.5 * step, step)][: n * 3]


def _fmt(v: SupportsFloat | None) -> str:
    if v is None:
        return ""
    v = float(v)
    if v == 0:
        return "0"
    if abs(v) >= 1e4 or abs(v) < 1e-3:
        return f"{v:.3g}"
    return f"{v:.4g}"


#: Font sizes of the plot's text (``report.css``: ``.tick``/``.legend`` 10.5 px, ``.ptitle`` 13 px bold)
#: and a generous average glyph width, to lay text out without a browser.
TICK_PX, TITLE_PX, GLYPH = 10.5, 13.0, 0.64


def _text_px(text: str, size: float = TICK_PX) -> float:
    return len(text) * size * GLYPH


def _clip(text: str, chars: int) -> str:
    return text if len(text) <= chars else text[: chars - 1] + "\u2026"


def _wrap(text: str, width: float, size: float = TITLE_PX) -> list[str]:
    """``text`` broken at spaces into lines at most ``width`` px wide (estimated)."""
    lines, line = [], ""
    for word in text.split():
        trial = f"{line} {word}".strip()
        if line and _text_px(trial, size) > width:
            lines.append(line)
            line = word
        else:
            line = trial
    return lines + [line] if line else lines


def _spaced_ticks(
    lo: float, hi: float, length: float, label: Callable[[float], str]
) -> list[float]:
    """Ticks whose labels (``label(t)``) fit ``length`` px side by side without touching."""
    tolerance = 1e-9 * (hi - lo)
    for n in (5, 4, 3, 2, 1):
        ticks = [t for t in _ticks(lo, hi, n) if lo - tolerance <= t <= hi + tolerance]
        widest = max((_text_px(label(t)) for t in ticks), default=0.0)
        if len(ticks) < 2 or length / (len(ticks) - 1) > widest + 8:
            return ticks
    return ticks


def _title(plot: Plot, width: int, left: int) -> tuple[str, int]:
    """The title's ``<text>`` lines and the height they take."""
    lines = _wrap(plot.title, width - left - 8) or [""]
    esc = html.escape
    text = "".join(
        f'<text x="{left}" y="{16 + 16 * i}" class="ptitle">{esc(line)}</text>'
        for i, line in enumerate(lines)
    )
    return text, 16 * len(lines)


def svg_plot(plot: Plot, width: int = 640, height: int = 300) -> str:
    """An inline ``<svg>`` of ``plot`` (axes, ticks, legend); bar charts are horizontal, one
    labelled row per series, so long names never overlap."""
    if plot.kind == "bar":
        return _bar_plot(plot, width)
    return _line_plot(plot, width, height)


def _svg_open(width: float, height: float) -> str:
    return f'<svg class="plot" xmlns="http://www.w3.org/2000/svg" viewBox="0 0 {width:.0f} {height:.0f}" width="{width:.0f}" height="{height:.0f}" role="img">'


def _no_values(plot: Plot, width: int) -> str:
    title, th = _title(plot, width, 8)
    return f'{_svg_open(width, th + 40)}{title}<text x="18" y="{th + 26}">no values</text></svg>'


def _bar_plot(plot: Plot, width: int) -> str:
    esc = html.escape
    values = [(_finite(s.y[0]) if len(s.y) else None) for s in plot.series]
    finite = [v for v in values if v is not None]
    if not finite:
        return _no_values(plot, width)
    colors = [s.color or _PALETTE[i % len(_PALETTE)] for i, s in enumerate(plot.series)]
    names = [_clip(s.name, 40) for s in plot.series]
    labels = [format_number(v) for v in values]
    left = 12 + min(max(_text_px(n) for n in names), 0.4 * width)
    right = 12 + max(_text_px(t) for t in labels)
    lo, hi = min(0.0, min(finite)), max(0.0, max(finite))
    if hi == lo:
        hi = lo + 1.0
    w = width - left - right
    title, top = _title(plot, width, 8)
    top += 10
    row = 22
    bottom = top + row * len(values)
    height = bottom + 34 + (14 if plot.ylabel else 0)
    xs = lambda v: left + (v - lo) / (hi - lo) * w  # noqa: E731
    parts = [_svg_open(width, height), title]
    for t in _spaced_ticks(lo, hi, w, format_number):
        parts.append(
            f'<line x1="{xs(t):.1f}" x2="{xs(t):.1f}" y1="{top}" y2="{bottom}" class="grid"/><text x="{xs(t):.1f}" y="{bottom + 14}" class="tick" text-anchor="middle">{format_number(t)}</text>'
        )
    for i, (s, v) in enumerate(zip(plot.series, values)):
        y = top + i * row
        parts.append(
            f'<text x="{left - 6:.1f}" y="{y + 15}" class="tick" text-anchor="end">{esc(names[i])}<title>{esc(s.name)}</title></text>'
        )
        if v is None:
            parts.append(f'<text x="{xs(0.0) + 4:.1f}" y="{y + 15}" class="tick">no value</text>')
            continue
        x0, x1 = sorted((xs(0.0), xs(v)))
        parts.append(
            f'<rect x="{x0:.1f}" y="{y + 4}" width="{max(x1 - x0, 0.5):.1f}" height="{row - 8}" fill="{colors[i]}"><title>{esc(s.name)}: {labels[i]}</title></rect>'
        )
        anchor, at = ("start", x1 + 4) if v >= 0 else ("end", x0 - 4)
        if v < 0 and at - _text_px(labels[i]) < left:
            anchor, at = "start", x1 + 4
        parts.append(
            f'<text x="{at:.1f}" y="{y + 15}" class="tick" text-anchor="{anchor}">{labels[i]}</text>'
        )
    parts.append(
        f'<line x1="{xs(0.0):.1f}" x2="{xs(0.0):.1f}" y1="{top}" y2="{bottom}" class="zero"/>'
    )
    if plot.ylabel:
        parts.append(
            f'<text x="{left + w / 2:.0f}" y="{height - 6}" class="axis" text-anchor="middle">{esc(plot.ylabel)}</text>'
        )
    parts.append("</svg>")
    return "".join(parts)


def _line_plot(plot: Plot, width: int, height: int) -> str:
    esc = html.escape
    xs_all = (
        np.concatenate([np.asarray(s.x, float) for s in plot.series])
        if plot.series
        else np.zeros(0)
    )
    ys_all = (
        np.concatenate([np.asarray(s.y, float) for s in plot.series])
        if plot.series
        else np.zeros(0)
    )
    ok = np.isfinite(ys_all) & np.isfinite(xs_all)
    if plot.log_y:
        ok &= ys_all > 0
    if not ok.any():
        return _no_values(plot, width)
    tf = (
        (lambda a: np.log10(np.maximum(a, 1e-300)))
        if plot.log_y
        else (lambda a: np.asarray(a, float))
    )  # noqa: E731
    x0, x1 = float(xs_all[ok].min()), float(xs_all[ok].max())
    y0, y1 = float(tf(ys_all[ok]).min()), float(tf(ys_all[ok]).max())
    if x1 == x0:
        x1 = x0 + 1.0
    if y1 == y0:
        y0, y1 = y0 - 0.5, y1 + 0.5
    pad = 0.05 * (y1 - y0)
    y0, y1 = y0 - pad, y1 + pad
    ylabel = (lambda t: format_number(10**t)) if plot.log_y else format_number  # noqa: E731
    colors = [s.color or _PALETTE[i % len(_PALETTE)] for i, s in enumerate(plot.series)]
    names = [_clip(s.name, 24) for s in plot.series]
    title, top = _title(plot, width, 8)
    top += 12
    bottom = 42
    h = max(height - top - bottom, 16 * len(names) + 4, 80)
    yticks = _spaced_ticks(y0, y1, h, lambda t: "0")  # vertical spacing: one line of text each
    left = 30 + max(_text_px(ylabel(t)) for t in yticks)
    right = 44 + max((_text_px(n) for n in names), default=0.0)
    w = width - left - right
    height = top + h + bottom
    sx = lambda v: left + (v - x0) / (x1 - x0) * w  # noqa: E731
    sy = lambda v: top + h - (v - y0) / (y1 - y0) * h  # noqa: E731
    parts = [
        _svg_open(width, height),
        title,
        f'<rect x="{left:.1f}" y="{top}" width="{w:.1f}" height="{h}" class="frame"/>',
    ]
    for t in yticks:
        parts.append(
            f'<line x1="{left:.1f}" x2="{left + w:.1f}" y1="{sy(t):.1f}" y2="{sy(t):.1f}" class="grid"/><text x="{left - 6:.1f}" y="{sy(t) + 4:.1f}" class="tick" text-anchor="end">{ylabel(t)}</text>'
        )
    for t in _spaced_ticks(x0, x1, w, format_number):
        parts.append(
            f'<text x="{sx(t):.1f}" y="{top + h + 14}" class="tick" text-anchor="middle">{format_number(t)}</text>'
        )
    for i, s in enumerate(plot.series):
        x, y = np.asarray(s.x, float), tf(np.asarray(s.y, float))
        good = (
            np.isfinite(x) & np.isfinite(y) & ((np.asarray(s.y, float) > 0) if plot.log_y else True)
        )
        if not good.any():
            continue
        pts = " ".join(f"{sx(a):.1f},{sy(b):.1f}" for a, b in zip(x[good], y[good]))
        dash = ' stroke-dasharray="5,4"' if s.dashed else ""
        parts.append(
            f'<polyline points="{pts}" fill="none" stroke="{colors[i]}" stroke-width="1.6"{dash}><title>{esc(s.name)}</title></polyline>'
        )
        ly = top + 12 + 16 * i
        parts.append(
            f'<line x1="{left + w + 10:.1f}" x2="{left + w + 30:.1f}" y1="{ly - 4}" y2="{ly - 4}" stroke="{colors[i]}" stroke-width="2"{dash}/><text x="{left + w + 34:.1f}" y="{ly}" class="legend">{esc(names[i])}</text>'
        )
    parts.append(
        f'<text x="{left + w / 2:.0f}" y="{height - 6}" class="axis" text-anchor="middle">{esc(plot.xlabel)}</text>'
    )
    parts.append(
        f'<text x="12" y="{top + h / 2:.0f}" class="axis" transform="rotate(-90 12 {top + h / 2:.0f})" text-anchor="middle">{esc(plot.ylabel)}</text>'
    )
    parts.append("</svg>")
    return "".join(parts)


# ---------------------------------------------------------------------------------------
# Geometry for the viewer
# ---------------------------------------------------------------------------------------
def decimate(
    vertices: np.ndarray, triangles: np.ndarray, max_vertices: int
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Coarsen a mesh to at most about ``max_vertices`` vertices for display.

    Returns ``(keep (K,) vertex ids, triangles (T', 3) in 0..K-1, labels (V,) cluster of
    each vertex or -1)``. Seeds: per cell of a grid over the surface, the vertex nearest
    the cell's mean; every vertex joins the seed nearest along mesh edges (so clusters
    never bridge holes such as the mouth); a triangle whose corners lie in three
    different clusters becomes a triangle of the seeds (orientation kept).
    """
    vertices = np.asarray(vertices, dtype=np.float64)
    triangles = np.asarray(triangles, dtype=np.int64)
    n = len(vertices)
    if n <= max_vertices:
        return np.arange(n), triangles, np.arange(n)
    import scipy.sparse as sp
    from scipy.sparse.csgraph import dijkstra

    from ..geometry.mesh_ops import face_areas, unique_edges

    lo = vertices.min(axis=0)
    cell = np.sqrt(face_areas(vertices, triangles).sum() / max_vertices)
    while True:
        keys = np.floor((vertices - lo) / cell).astype(np.int64)
        _, cluster = np.unique(keys, axis=0, return_inverse=True)
        cluster = cluster.ravel()
        if cluster.max() + 1 <= max_vertices:
            break
        cell *= 1.15
    k = cluster.max() + 1
    means = np.zeros((k, 3))
    np.add.at(means, cluster, vertices)
    means /= np.bincount(cluster, minlength=k)[:, None]
    dist = np.linalg.norm(vertices - means[cluster], axis=1)
    order = np.lexsort((dist, cluster))
    first = np.ones(n, dtype=bool)
    first[1:] = cluster[order][1:] != cluster[order][:-1]
    seeds = order[first]
    edges = unique_edges(triangles)
    length = np.linalg.norm(vertices[edges[:, 0]] - vertices[edges[:, 1]], axis=1) + 1e-12
    graph = sp.coo_matrix((length, (edges[:, 0], edges[:, 1])), shape=(n, n)).tocsr()
    _, _, sources = dijkstra(
        graph, directed=False, indices=seeds, min_only=True, return_predecessors=True
    )
    seed_index = np.full(n, -1)
    seed_index[seeds] = np.arange(len(seeds))
    labels = np.where(sources >= 0, seed_index[np.maximum(sources, 0)], -1)
    tl = labels[triangles]
    good = (
        (tl >= 0).all(axis=1)
        & (tl[:, 0] != tl[:, 1])
        & (tl[:, 1] != tl[:, 2])
        & (tl[:, 0] != tl[:, 2])
    )
    tl = tl[good]
    _, unique_rows = np.unique(np.sort(tl, axis=1), axis=0, return_index=True)
    return seeds, tl[np.sort(unique_rows)], labels


def _cluster_mean(values: np.ndarray, labels: np.ndarray, k: int) -> np.ndarray:
    ok = labels >= 0
    sums = np.bincount(labels[ok], weights=values[ok], minlength=k)
    counts = np.bincount(labels[ok], minlength=k)
    return sums / np.maximum(counts, 1)


def _b64(array: np.ndarray) -> str:
    return base64.b64encode(np.ascontiguousarray(array).tobytes()).decode("ascii")


def _quantize(points: np.ndarray) -> dict:
    """``points : (F, N, 3)`` (NaN allowed) -> int16 base64 with per-axis offset and step."""
    finite = np.isfinite(points).all(axis=-1)
    if finite.any():
        lo = np.nanmin(points[finite], axis=0)
        hi = np.nanmax(points[finite], axis=0)
    else:
        lo, hi = np.zeros(3), np.ones(3)
    step = np.maximum(hi - lo, 1e-12) / 65534.0
    q = np.round((np.nan_to_num(points, nan=0.0) - lo) / step) - 32767
    q = np.clip(q, -32767, 32767).astype("<i2")
    q[~finite] = -32768
    return {"q": _b64(q), "lo": lo.tolist(), "step": step.tolist()}


def _mesh_block(
    vertices: np.ndarray, triangles: np.ndarray, max_vertices: int
) -> tuple[np.ndarray, np.ndarray, dict[str, Any]]:
    keep, tris, labels = decimate(vertices, triangles, max_vertices)
    return (
        keep,
        labels,
        {"nv": int(len(keep)), "tri": _b64(tris.astype("<u4")), "nt": int(len(tris))},
    )


def _key_frames(
    truth_local: np.ndarray, neutral: np.ndarray, frames: np.ndarray, count: int = 3
) -> list[int]:
    """Indices into ``frames`` of up to ``count`` expressive, well separated frames."""
    amount = np.linalg.norm(truth_local[frames] - neutral, axis=-1).mean(axis=1)
    chosen: list[int] = []
    gap = max(1, len(frames) // (2 * count))
    for i in np.argsort(-amount):
        if all(abs(int(i) - j) >= gap for j in chosen):
            chosen.append(int(i))
        if len(chosen) == count:
            break
    return sorted(chosen)


def _case_view(
    result: ComparisonResult, cname: str, case: Case, max_vertices: int, max_frames: int
) -> dict:
    runs = [
        r for r in result.runs if r.case == cname and r.status == OK and r.animation is not None
    ]
    target = case.target
    neutral = np.asarray(target.neutral.vertices, dtype=np.float64)
    height = float(target.neutral.height) or 1.0
    truth = getattr(case, "truth", None)
    n_frames = case.source.n_frames
    frames = np.unique(np.linspace(0, n_frames - 1, min(n_frames, max_frames)).round().astype(int))
    keep, labels, mesh = _mesh_block(neutral, np.asarray(target.neutral.triangles), max_vertices)
    seqs = []
    reference = None
    if truth is not None:
        truth_v = np.asarray(truth.vertices, dtype=np.float64)
        seqs.append(
            {
                "label": "ground truth",
                "mesh": "target",
                "kind": "truth",
                **_quantize(truth_v[frames][:, keep]),
            }
        )
        reference = truth_v
    heat = []
    for run in runs:
        assert run.animation is not None  # runs keeps those with one
        verts = np.asarray(run.animation.vertices, dtype=np.float64)
        seqs.append(
            {
                "label": run.method,
                "mesh": "target",
                "kind": "method",
                **_quantize(verts[frames][:, keep]),
            }
        )
        if reference is not None:
            err = per_vertex_error(verts, reference, height)
            heat.append(
                {"label": run.method, "values": _cluster_mean(err, labels, len(keep)).tolist()}
            )
    source: dict[str, Any] = {"kind": case.source.kind}
    perf = case.source.performance
    if case.source.kind == "mesh":
        assert isinstance(perf, MeshSequence)  # a Source's kind is its performance's
        s_keep, _, s_mesh = _mesh_block(
            np.asarray(perf.reference.vertices), np.asarray(perf.triangles), max_vertices
        )
        source.update(
            mesh=s_mesh, **_quantize(np.asarray(perf.vertices, dtype=np.float64)[frames][:, s_keep])
        )
    elif case.source.kind == "markers" and isinstance(perf, MarkerSequence) and perf.dim == 3:
        source.update(**_quantize(np.asarray(perf.positions, dtype=np.float64)[frames]))
    heat_max = max([max(h["values"]) for h in heat if h["values"]] + [1e-9])
    for h in heat:
        h["q"] = _b64(np.round(np.asarray(h["values"]) / heat_max * 255).astype(np.uint8))
        del h["values"]
    keys = []
    if truth is not None:
        keys = _key_frames(to_head_frame(truth_v, truth.head_motion), neutral, frames)
    return {
        "name": cname,
        "frames": frames.tolist(),
        "fps": float(case.source.fps),
        "height": height,
        "mesh": mesh,
        "neutral": _quantize(neutral[keep][None]),
        "seqs": seqs,
        "source": source,
        "heat": heat,
        "heatMax": heat_max,
        "keyFrames": keys,
    }


# ---------------------------------------------------------------------------------------
# Figures per case
# ---------------------------------------------------------------------------------------
def _velocity_plot(result: ComparisonResult, cname: str, case: Case) -> Plot | None:
    truth = getattr(case, "truth", None)
    if truth is None or case.target.landmarks is None or case.source.n_frames < 2:
        return None
    plot = Plot(
        f"{cname}: velocity error over time (Seol 2012 fig. 11)",
        xlabel="frame",
        ylabel="||DP - DQ||^2 / H^2",
    )
    for run in result.runs:
        if run.case == cname and run.status == OK and run.animation is not None:
            curve = landmark_velocity_curve(run.animation.vertices, truth, case.target)
            plot.series.append(Series(run.method, np.arange(1, len(curve) + 1), curve))
    return plot if plot.series else None


def _weight_plots(result: ComparisonResult, cname: str, case: Case) -> list[Plot]:
    runs = [
        r
        for r in result.runs
        if r.case == cname
        and r.status == OK
        and r.animation is not None
        and r.animation.weights is not None
    ]
    truth = getattr(case, "truth", None)
    if truth is not None and truth.weights is None:
        truth = None  # no weight curves to show
    has_truth = truth is not None
    if not runs and truth is None:
        return []
    if truth is not None:
        names, w = list(truth.weight_names), np.asarray(truth.weights)
    else:
        first = runs[0].animation
        assert first is not None  # runs keeps those with one
        names, w = list(first.weight_names), np.asarray(first.weights)
    chosen = [names[i] for i in np.argsort(-w.var(axis=0))[:MAX_WEIGHT_PANELS]]
    plots = []
    frames = np.arange(case.source.n_frames)
    for shape in chosen:
        plot = Plot(f"{cname}: {shape}", xlabel="frame", ylabel="weight")
        if truth is not None:
            plot.series.append(
                Series(
                    "ground truth",
                    frames,
                    np.asarray(truth.weights)[:, truth.weight_names.index(shape)],
                    dashed=True,
                    color="#444",
                )
            )
        for i, run in enumerate(runs):
            assert run.animation is not None  # runs keeps those with one
            if shape in run.animation.weight_names:
                col = run.animation.weight_names.index(shape)
                plot.series.append(
                    Series(
                        run.method,
                        frames,
                        np.asarray(run.animation.weights)[:, col],
                        color=_PALETTE[i % len(_PALETTE)],
                    )
                )
        if len(plot.series) > int(has_truth) or (has_truth and not runs):
            plots.append(plot)
    return plots


# ---------------------------------------------------------------------------------------
# HTML
# ---------------------------------------------------------------------------------------
def _asset(name: str) -> str:
    return (
        resources.files("faceretarget.evaluation")
        .joinpath("assets", name)
        .read_text(encoding="utf-8")
    )


def _breakable(name: str) -> str:
    """A metric or method name that may wrap after its underscores (narrow table headers)."""
    return "_<wbr>".join(html.escape(part) for part in name.split("_"))


def _role_tag(role: MethodRole | None) -> str:
    if role is None:
        return ""
    return f'<span class="role {role.kind.split()[0]}" title="{html.escape(role.label)}">{html.escape(role.label)}</span>'


def _method_cell(name: str, roles: Mapping, extra: str = "") -> str:
    return f'<th class="method">{_breakable(name)}{_role_tag(roles.get(name))}{extra}</th>'


def _cell(row: dict | None, best: bool = False) -> str:
    if row is None:
        return '<td class="na">-</td>'
    if row["status"] == OK and row["value"] is not None:
        return f'<td class="num{" best" if best else ""}">{format_number(row["value"])}</td>'
    cls = "err" if row["status"] == ERROR else "na"
    label = "error" if row["status"] == ERROR else "n/a"
    return f'<td class="{cls}" title="{html.escape(row["reason"] or "")}">{label}</td>'


def _best(values: dict[str, float], better: str) -> set[str]:
    if len(values) < 2 or better not in ("lower", "higher"):
        return set()
    target = min(values.values()) if better == "lower" else max(values.values())
    return {k for k, v in values.items() if v == target}


def _best_per_metric(
    result: ComparisonResult, index: dict, metrics: Sequence[str]
) -> dict[str, set[str]]:
    best = {}
    for m in metrics:
        vals = {
            meth: index[(meth, m)]["value"]
            for meth in result.methods
            if (meth, m) in index
            and index[(meth, m)]["status"] == OK
            and index[(meth, m)]["value"] is not None
        }
        best[m] = _best(vals, result.better(m))
    return best


def _metric_header(result: ComparisonResult, metric: str, unit: str, ranked: bool) -> str:
    esc = html.escape
    base = metric.split("[")[0]
    definition = result.metrics[base].description if base in result.metrics else ""
    cls = ' class="ranked"' if ranked else ""
    return f'<th{cls} title="{esc(definition)}">{_breakable(metric)}<br><small>{esc(unit)}</small></th>'


def _metric_table(
    result: ComparisonResult,
    cname: str,
    metrics: Sequence[str],
    roles: Mapping,
    rank_by: str | None,
) -> str:
    """Methods down, metrics across; the best value per metric highlighted, the ranking metric marked."""
    esc = html.escape
    index = {(r["method"], r["metric"]): r for r in result.rows if r["case"] == cname}
    units = {r["metric"]: r["unit"] for r in result.rows if r["case"] == cname}
    head = "".join(_metric_header(result, m, units.get(m, ""), m == rank_by) for m in metrics)
    best = _best_per_metric(result, index, metrics)
    out = [
        f'<table class="metrics case-metrics"><thead><tr><th>method</th>{head}</tr></thead><tbody>'
    ]
    for run in (r for r in result.runs if r.case == cname):
        status = (
            ""
            if run.status == OK
            else f'<span class="{"err" if run.status == ERROR else "na"} status">{esc(run.status)}</span>'
        )
        cells = "".join(_cell(index.get((run.method, m)), run.method in best[m]) for m in metrics)
        out.append(f"<tr>{_method_cell(run.method, roles, status)}{cells}</tr>")
        if run.status != OK:
            out.append(
                f'<tr class="reason"><td colspan="{len(metrics) + 1}">{esc(run.reason)}</td></tr>'
            )
    out.append("</tbody></table>")
    return "".join(out)


def _all_metrics_table(
    result: ComparisonResult, cname: str, metrics: Sequence[str], roles: Mapping
) -> str:
    """Metrics down, methods across (any number of metrics fits the page width)."""
    esc = html.escape
    index = {(r["method"], r["metric"]): r for r in result.rows if r["case"] == cname}
    units = {r["metric"]: r["unit"] for r in result.rows if r["case"] == cname}
    methods = [r.method for r in result.runs if r.case == cname]
    best = _best_per_metric(result, index, metrics)
    head = "".join(f"<th>{_breakable(m)}</th>" for m in methods)
    out = [
        f'<table class="metrics all-metrics"><thead><tr><th>metric</th><th>unit</th><th>better</th>{head}</tr></thead><tbody>'
    ]
    for m in metrics:
        base = m.split("[")[0]
        definition = result.metrics[base].description if base in result.metrics else ""
        cells = "".join(_cell(index.get((meth, m)), meth in best[m]) for meth in methods)
        out.append(
            f'<tr><th title="{esc(definition)}">{_breakable(m)}</th><td>{esc(units.get(m, ""))}</td><td>{esc(result.better(m))}</td>{cells}</tr>'
        )
    out.append("</tbody></table>")
    return "".join(out)


def _excl_compile(run: Run) -> float | None:
    """Seconds of fit + retarget without numba compilation (None when not measured)."""
    if run.fit_s is None or run.retarget_s is None:
        return None
    return max(run.fit_s + run.retarget_s - (run.compile_s or 0.0), 0.0)


def _timings(result: ComparisonResult, method: str) -> tuple[float | None, float | None]:
    """(mean over runs of the time without compilation, total compile seconds) of ``method``."""
    runs = [r for r in result.runs if r.method == method and r.status == OK]
    times = [t for t in (_excl_compile(r) for r in runs) if t is not None]
    compiles = [r.compile_s for r in runs if r.compile_s is not None]
    return (float(np.mean(times)) if times else None), (
        float(np.sum(compiles)) if compiles else None
    )


def _ranking_table(result: ComparisonResult, rank_by: str | None, roles: Mapping) -> str:
    """Rank, method and role, the ranking metric's value per case, mean rank, times, runs that did not count."""
    esc = html.escape
    cases = list(result.cases)
    rows = result.ranking(metrics=[rank_by]) if rank_by else result.ranking()
    unit = result.metrics[rank_by].unit if rank_by in result.metrics else ""
    values = {(r["case"], r["method"]): r for r in result.rows if r["metric"] == rank_by}
    best = {
        c: _best(
            {
                m: r["value"]
                for (cc, m), r in values.items()
                if cc == c and r["status"] == OK and r["value"] is not None
            },
            result.better(rank_by or ""),
        )
        for c in cases
    }
    case_heads = "".join(
        f'<th class="ranked">{_breakable(c)}<br><small>{esc(unit)}</small></th>' for c in cases
    )
    out = [
        '<table class="metrics ranking"><thead><tr><th>rank</th><th>method</th>',
        case_heads,
        "<th>mean rank<br><small>over cases</small></th><th>time<br><small>s, mean, excl. compile</small></th>",
        "<th>compile<br><small>s, total</small></th><th>did not run</th></tr></thead><tbody>",
    ]
    for r in rows:
        method = r["method"]
        per_case = "".join(_cell(values.get((c, method)), method in best[c]) for c in cases)
        run_time, compile_time = _timings(result, method)
        missing = ", ".join(
            part
            for part in (
                f"{r['not_applicable']} n/a" if r["not_applicable"] else "",
                f"{r['failed']} failed" if r["failed"] else "",
            )
            if part
        )
        out.append(
            f'<tr><td class="num">{r["rank"] if r["rank"] is not None else "-"}</td>{_method_cell(method, roles)}{per_case}'
            f'<td class="num">{format_number(r["mean_rank"]) or "-"}</td><td class="num">{format_number(run_time) or "-"}</td>'
            f'<td class="num">{format_number(compile_time) or "-"}</td><td>{esc(missing)}</td></tr>'
        )
    out.append("</tbody></table>")
    return "".join(out)


def _ranking_note(result: ComparisonResult, rank_by: str | None) -> str:
    esc = html.escape
    if rank_by is None:
        return '<p class="note">No accuracy metric was computed, so the methods are not ranked.</p>'
    m = result.metrics[rank_by]
    direction = "lower" if m.better == "lower" else "higher"
    return (
        f'<p class="ranking-metric"><strong>Ranked by {esc(rank_by)}</strong> ({esc(m.unit)}, {direction} is better): '
        f"{esc(m.description)} Within each case the methods are ranked by this one metric (1 = best, ties share ranks); "
        f"a method's rank is the mean of its ranks over the cases it ran on. The other metrics are in each case's table.</p>"
        '<p class="note">Time is the wall clock of fit + retarget without numba compilation; compile is the time spent '
        "compiling (or loading from the disk cache) numerical kernels inside those calls, a one-time cost per process "
        "that falls on whichever run comes first.</p>"
    )


def _summaries_html(summaries: Sequence) -> str:
    items = "".join(_summary_html(s, i) for i, s in enumerate(summaries))
    return f'<ul class="summaries">{items}</ul>'


def _summary_html(summary: CaseSummary, index: int | None = None) -> str:
    esc = html.escape
    link = f' <a href="#case-{index}">details</a>' if index is not None else ""
    notes = "".join(f' <span class="behind">{esc(n)}</span>' for n in summary.notes)
    why = f' <span class="why">{esc(summary.why)}</span>' if summary.why else ""
    others = f" {esc(summary.others)}" if summary.others else ""
    return f'<li class="summary" data-case="{esc(summary.case)}"><strong>{esc(summary.verdict)}</strong>{others}{why}{notes}{link}</li>'


def _reproductions_line(presets: Sequence[PresetResult]) -> str:
    """One line under the summary: how many paper reproductions agree, and which disagree (in red)."""
    if not presets:
        return ""
    esc = html.escape
    verdicts = [getattr(p, "agrees", None) for p in presets]
    disagree = [p for p, v in zip(presets, verdicts) if v is False]
    counts = f"{sum(v is True for v in verdicts)} agree, {len(disagree)} disagree, {sum(v is None for v in verdicts)} not decided"
    links = ", ".join(
        f'<a class="disagree" href="#preset-{esc(p.name)}">{esc(p.name)}</a>' for p in disagree
    )
    flagged = (
        f'; <span class="disagree">disagreeing with their paper: {links}</span>' if disagree else ""
    )
    return f'<p class="reproductions-line">Paper reproductions: {counts}{flagged}.</p>'


def _roles_legend(roles: Mapping) -> str:
    esc = html.escape
    if not roles:
        return ""
    groups: dict[str, list[str]] = {}
    for name, role in roles.items():
        groups.setdefault(role.kind, []).append(name)
    words = {
        "paper method": "paper methods (the retargeter a paper describes)",
        "baseline": "baselines (what a paper compares against)",
        "other": "other methods",
    }
    parts = [
        f"{esc(words.get(kind, kind))}: {esc(', '.join(names))}" for kind, names in groups.items()
    ]
    return f'<p class="note roles">{"; ".join(parts)}.</p>'


def _table_cell(value: object) -> str:
    if isinstance(value, (int, float, np.integer, np.floating)) and not isinstance(value, bool):
        return f'<td class="num">{format_number(value)}</td>'
    return f"<td>{html.escape('' if value is None else str(value))}</td>"


#: CSS class and heading of a reproduction's verdict (``PresetResult.agrees``).
_VERDICTS = {
    True: ("agree", "Agrees with the paper"),
    False: ("disagree", "Disagrees with the paper"),
    None: ("undecided", "Not decided"),
}


def _verdict_html(preset: PresetResult) -> str:
    """The reproduction's verdict: green when it agrees with the paper's claim, red with the
    measured numbers when it disagrees, grey when it was not decided."""
    esc = html.escape
    agrees = getattr(preset, "agrees", None)
    cls, label = _VERDICTS[None if agrees is None else bool(agrees)]
    evidence = getattr(preset, "evidence", "") or (
        "the preset did not run" if preset.status != OK else ""
    )
    return f'<div class="verdict {cls}" data-verdict="{cls}"><strong>{label}</strong>: {esc(evidence)}</div>'


def _claim_html(preset: PresetResult) -> str:
    esc = html.escape
    out = []
    claim, setting = getattr(preset, "claim", ""), getattr(preset, "setting", "")
    if claim:
        out.append(f'<p class="claim"><strong>The paper\'s claim.</strong> {esc(claim)}</p>')
    if setting:
        out.append(
            f'<p class="setting"><strong>The paper\'s setting, as reproduced.</strong> {esc(setting)}</p>'
        )
    return "".join(out)


def _presets_summary(presets: Sequence[PresetResult]) -> str:
    """One line per reproduction: its claim and whether the measurement agrees (coloured as the verdict)."""
    esc = html.escape
    if not presets:
        return ""
    rows = []
    for p in presets:
        agrees = getattr(p, "agrees", None)
        cls, label = _VERDICTS[None if agrees is None else bool(agrees)]
        rows.append(
            f'<tr><th><a href="#preset-{esc(p.name)}">{esc(p.name)}</a></th><td>{esc(getattr(p, "claim", ""))}</td>'
            f'<td class="verdict-cell {cls}">{esc(label)}</td></tr>'
        )
    return (
        '<table class="metrics presets-summary"><thead><tr><th>reproduction</th><th>the paper\'s claim</th><th>measured</th></tr></thead><tbody>'
        + "".join(rows)
        + "</tbody></table>"
    )


def _preset_html(preset: PresetResult) -> str:
    esc = html.escape
    out = [
        f'<section class="preset" id="preset-{esc(preset.name)}"><h3>{esc(preset.title)}</h3><p class="paper">{esc(preset.paper)}</p>'
    ]
    out.append(_claim_html(preset))
    out.append(_verdict_html(preset))
    out.append(f"<p>{esc(preset.description)}</p>")
    if preset.status != OK:
        out.append(
            f'<p class="{"err" if preset.status == ERROR else "na"} note">{esc(preset.status)}: {esc(preset.reason)}</p>'
        )
    for plot in preset.plots:
        out.append(svg_plot(plot))
    if preset.table:
        cols = list(dict.fromkeys(k for row in preset.table for k in row))
        out.append(
            '<table class="metrics"><thead><tr>'
            + "".join(f"<th>{esc(c)}</th>" for c in cols)
            + "</tr></thead><tbody>"
        )
        for row in preset.table:
            out.append("<tr>" + "".join(_table_cell(row.get(c)) for c in cols) + "</tr>")
        out.append("</tbody></table>")
    out.append("</section>")
    return "".join(out)


def _budget(result: ComparisonResult, max_bytes: int, max_frames: int, max_vertices: int) -> int:
    n_cases = max(len(result.cases), 1)
    per_case = max_bytes / n_cases
    n_seqs = max(len(result.methods) + 2, 2)
    return int(np.clip(per_case / (n_seqs * max_frames * 6), MIN_VERTICES, max_vertices))


def _case_section(
    result: ComparisonResult,
    ci: int,
    cname: str,
    case: Case,
    summary: CaseSummary,
    roles: Mapping,
    rank_by: str | None,
) -> str:
    esc = html.escape
    present = {r["metric"] for r in result.rows if r["case"] == cname}
    cols = [m for m in SUMMARY_METRICS if m in present]
    if rank_by is not None and rank_by in present and rank_by not in cols:
        cols.insert(0, rank_by)
    regions = sorted(m for m in present if m.startswith("vertex_error_region["))
    others = [
        m
        for m in dict.fromkeys(r["metric"] for r in result.rows if r["case"] == cname)
        if m not in cols
    ]
    source = case.source
    sec = [
        f'<section class="case" id="case-{ci}"><h2>Case: {esc(cname)}</h2>',
        f'<p class="meta">source: {esc(source.kind)}, {source.n_frames} frames at {source.fps:g} fps; target: {case.target.neutral.n_vertices} vertices, parts: {esc(", ".join(case.target.parts()) or "none")}; ground truth: {"yes" if getattr(case, "truth", None) is not None else "no"}</p>',
        f'<ul class="summaries">{_summary_html(summary)}</ul>',
        "<h3>Metrics</h3>",
        _metric_table(result, cname, cols, roles, rank_by),
        f"<details><summary>all metrics ({len(others)} more, incl. {len(regions)} regions)</summary>{_all_metrics_table(result, cname, others, roles)}</details>",
        f'<h3>Viewer</h3><div class="viewer" data-case="{ci}"></div>',
        f'<h3>Key frames side by side</h3><div class="keyframes" data-case="{ci}"></div>',
        f'<h3>Per-vertex error on the target mesh</h3><p class="note">mean over frames of ||result - truth||, % of face height; shared colour scale per case.</p><div class="heat" data-case="{ci}"></div>',
    ]
    vplot = _velocity_plot(result, cname, case)
    if vplot is not None:
        sec.append("<h3>Velocity error over time</h3>" + svg_plot(vplot, width=760))
    wplots = _weight_plots(result, cname, case)
    if wplots:
        sec.append(
            '<h3>Weight curves</h3><div class="plots">'
            + "".join(svg_plot(p, width=560, height=230) for p in wplots)
            + "</div>"
        )
    sec.append("</section>")
    return "".join(sec)


def _runs_table(result: ComparisonResult, roles: Mapping) -> str:
    esc = html.escape
    status_class = {OK: "ok", NOT_APPLICABLE: "na", ERROR: "err"}
    rows = "".join(
        f'<tr><th>{_breakable(r.case)}</th>{_method_cell(r.method, roles)}<td class="{status_class[r.status]}">{esc(r.status)}</td>'
        f'<td>{esc(r.plugin)} ({esc(r.distribution)} {esc(r.version)})</td><td class="num">{format_number(r.fit_s)}</td><td class="num">{format_number(r.retarget_s)}</td>'
        f'<td class="num">{format_number(r.compile_s)}</td><td class="num">{format_number(_excl_compile(r))}</td>'
        f'<td class="num">{format_number(r.peak_memory_mib)}</td><td><details><summary>{len(r.parameters)} parameters</summary><code>{esc(json.dumps(r.as_dict()["parameters"]))}</code></details></td><td class="reason-text">{esc(r.reason)}</td></tr>'
        for r in result.runs
    )
    return (
        '<table class="metrics runs"><thead><tr><th>case</th><th>method</th><th>status</th><th>plugin</th><th>fit<br><small>s</small></th>'
        "<th>retarget<br><small>s</small></th><th>of which compile<br><small>s</small></th><th>excl. compile<br><small>s</small></th>"
        f"<th>peak<br><small>MiB</small></th><th>parameters</th><th>reason / error</th></tr></thead><tbody>{rows}</tbody></table>"
    )


def render_html(
    result: ComparisonResult,
    *,
    title: str = "faceretarget comparison",
    max_bytes: int = MAX_BYTES,
    max_frames: int = MAX_FRAMES,
    max_vertices: int = MAX_VERTICES,
    rank_by: str | None = None,
    registry: Registry | None = None,
) -> str:
    """The self-contained report page as a string.

    ``rank_by``: the metric that ranks the methods (default ``vertex_error_rms``); ``registry``:
    where the methods' papers and roles are looked up (default the process-wide registry).
    """
    from .._version import __version__
    from ._summary import case_summary, method_roles, ranking_metric

    esc = html.escape
    rank_by = ranking_metric(result, rank_by)
    roles = method_roles(result.methods, registry)
    summaries = [case_summary(result, cname, rank_by, roles) for cname in result.cases]
    vertex_budget = _budget(result, max_bytes, max_frames, max_vertices)
    sections, views = [], []
    for ci, (cname, case) in enumerate(result.cases.items()):
        sections.append(_case_section(result, ci, cname, case, summaries[ci], roles, rank_by))
        views.append(_case_view(result, cname, case, vertex_budget, max_frames))
    presets = (
        _presets_summary(result.presets) + "".join(_preset_html(p) for p in result.presets)
    ) or '<p class="note">No paper reproductions in this run.</p>'
    definitions = "".join(
        f"<tr><th>{_breakable(name)}</th><td>{esc(m.unit)}</td><td>{esc(m.better)}</td><td>{esc(m.description)}</td></tr>"
        for name, m in result.metrics.items()
    )
    nav = "".join(f'<a href="#case-{i}">{esc(n)}</a>' for i, n in enumerate(result.cases))
    data = json.dumps({"cases": views}, separators=(",", ":")).replace("</", "<\\/")
    stamp = _dt.datetime.now().strftime("%Y-%m-%d %H:%M")
    return f"""<!DOCTYPE html>
<html lang="en"><head><meta charset="utf-8"><meta name="viewport" content="width=device-width, initial-scale=1">
<title>{esc(title)}</title><style>{_asset("report.css")}</style></head>
<body data-js-errors="0" data-faces-rendered="0">
<header><h1>{esc(title)}</h1><p class="meta">faceretarget {esc(__version__)}, {stamp}; {len(result.cases)} case(s), {len(result.methods)} method(s). Opens offline; every figure is inline.</p>
<nav><a href="#summary">summary</a><a href="#ranking">ranking</a>{nav}<a href="#presets">paper reproductions</a><a href="#definitions">metric definitions</a><a href="#runs">runs</a></nav></header>
<main>
<section id="summary"><h2>Who wins, and why</h2>{_summaries_html(summaries)}{_reproductions_line(result.presets)}{_roles_legend(roles)}</section>
<section id="ranking"><h2>Ranking</h2>{_ranking_note(result, rank_by)}{_ranking_table(result, rank_by, roles)}</section>
{"".join(sections)}
<section id="presets"><h2>Paper reproductions</h2>{presets}</section>
<section id="definitions"><h2>Metric definitions</h2><table class="metrics defs"><thead><tr><th>metric</th><th>unit</th><th>better</th><th>definition</th></tr></thead><tbody>{definitions}</tbody></table></section>
<section id="runs"><h2>Runs</h2>{_runs_table(result, roles)}</section>
</main>
<script type="application/json" id="report-data">{data}</script>
<script>{_asset("report.js")}</script>
</body></html>
"""


#: the files :func:`write_report` writes into its folder
REPORT_FILES = ("report.html", "results.csv", "results.json")


def check_report_folder(folder: PathLike) -> Path:
    """Refuse a report folder that is a file or whose parent does not exist."""
    folder = Path(folder)
    if folder.exists() and not folder.is_dir():
        raise OutputError(f"report folder {folder} exists and is not a folder; choose another path")
    if not folder.parent.is_dir():
        raise OutputError(f"cannot create report folder {folder}: {folder.parent} does not exist")
    return folder


def write_report(
    result: ComparisonResult,
    folder: PathLike,
    *,
    title: str = "faceretarget comparison",
    max_bytes: int = MAX_BYTES,
    max_frames: int = MAX_FRAMES,
    max_vertices: int = MAX_VERTICES,
    force: bool = False,
    inputs: Iterable = (),
    rank_by: str | None = None,
    registry: Registry | None = None,
) -> dict[str, Path]:
    """Write ``report.html``, ``results.csv`` and ``results.json`` into ``folder``.

    The folder is created if missing (its parent must exist); each file is written
    atomically, never over an input (``inputs``, or a file read by this process) and
    over an existing file only with ``force`` (all three are checked before any is
    written). ``rank_by`` and ``registry`` as in :func:`render_html`. Returns ``{"html": path, "csv": path, "json": path}``.
    """
    from ..io._atomic import check_destination
    from ._summary import ranking_metric

    ranking_metric(result, rank_by)  # a bad name fails before anything is written
    folder = check_report_folder(folder)
    if folder.is_dir():
        for name in REPORT_FILES:
            check_destination(folder / name, inputs=inputs, force=force)
    folder.mkdir(exist_ok=True)
    page = render_html(
        result,
        title=title,
        max_bytes=max_bytes,
        max_frames=max_frames,
        max_vertices=max_vertices,
        rank_by=rank_by,
        registry=registry,
    )
    return {
        "html": atomic_write_text(folder / "report.html", page, force=force, inputs=inputs),
        "csv": result.to_csv(folder / "results.csv", force=force, inputs=inputs),
        "json": result.to_json(folder / "results.json", force=force, inputs=inputs),
    }
