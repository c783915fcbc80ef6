"""The words of the report: who each method is, which metric ranks them, and who wins a case and why.

- :func:`method_roles`: each compared method labelled *paper method* (the retargeter of a
  published paper), *baseline* (what a paper compares against) or *other*, with a short
  citation;
- :func:`ranking_metric`: the one metric the report ranks by (default RMS vertex error),
  checked against the metrics of the comparison;
- :func:`case_summary`: per case, who wins on the ranking metric, by how much, where else
  it wins or loses, why (from what the case's ground truth is made of and what the methods
  consume), and a note when a paper method is behind its own baseline.
"""

from __future__ import annotations

import re
from collections.abc import Iterable, Mapping
from dataclasses import dataclass, field
from typing import TYPE_CHECKING, Any

from ._format import format_number
from .harness import DEFAULT_RANKING_METRIC, OK, ComparisonResult, ranking_metric

if TYPE_CHECKING:
    from ..registry import Registry

__all__ = [
    "MethodRole",
    "method_roles",
    "ranking_metric",
    "case_summary",
    "DEFAULT_RANKING_METRIC",
    "CaseSummary",
]

PAPER, BASELINE, OTHER = "paper method", "baseline", "other"


@dataclass(frozen=True)
class MethodRole:
    """What a method is in the comparison: ``kind`` is :data:`PAPER`, :data:`BASELINE` or
    :data:`OTHER`; ``citation`` a short reference ("Seol et al. 2012") or ""; ``baseline_of``
    the paper methods a baseline stands against."""

    kind: str
    citation: str = ""
    baseline_of: tuple[str, ...] = ()
    #: the retargeter class when the registry knows it (its capabilities explain results)
    cls: Any = field(default=None, compare=False, repr=False)

    @property
    def label(self) -> str:
        """``"paper method, Xu et al. 2014"``, ``"baseline of NAME"``, ``"other"``."""
        if self.kind == BASELINE and self.baseline_of:
            return f"baseline of {' / '.join(self.baseline_of)}"
        return (
            f"{self.kind}, {self.citation}" if self.citation and self.kind == PAPER else self.kind
        )


def short_citation(paper: str) -> str:
    """``"Seol, Lewis, Seo & Noh 2012, Title, ..."`` -> ``"Seol et al. 2012"``; ``"Na & Jung 2004, ..."``
    -> ``"Na & Jung 2004"``; "" when no year is found."""
    match = re.match(r"\s*(.+?)\s+((?:19|20)\d\d)\b", paper or "")
    if not match:
        return ""
    authors = [a.strip() for a in re.split(r",|&|\band\b", match.group(1)) if a.strip()]
    if len(authors) > 2:
        return f"{authors[0]} et al. {match.group(2)}"
    return f"{' & '.join(authors)} {match.group(2)}"


def method_roles(methods: Iterable[str], registry: Registry | None = None) -> dict[str, MethodRole]:
    """The :class:`MethodRole` of each method name, from the registry's catalogue (default the
    process-wide registry): a method whose manifest declares ``baseline_of``, or whose summary
    calls it a baseline, is a baseline; one with a paper citation is a paper method; the rest
    are "other"."""
    infos = _registry_infos(registry)
    roles = {}
    for name in methods:
        info = infos.get(name)
        citation, cls = short_citation(getattr(info, "paper", "") or ""), _class_of(info)
        baseline_of = getattr(info, "baseline_of", ())
        if baseline_of:
            roles[name] = MethodRole(BASELINE, citation, tuple(baseline_of), cls)
        elif info is not None and re.search(r"\bbaseline\b", info.summary or "", re.I):
            roles[name] = MethodRole(BASELINE, citation, (), cls)
        elif citation:
            roles[name] = MethodRole(PAPER, citation, (), cls)
        else:
            roles[name] = MethodRole(OTHER, "", (), cls)
    return _pair_baselines(roles)


def _class_of(info: object) -> type | None:
    """The entry's class (imported on first use by the registry); None when it cannot be had."""
    try:
        return getattr(info, "cls", None)
    except Exception:  # noqa: BLE001 - a plugin that no longer imports: label it, explain nothing
        return None


def _pair_baselines(roles: dict[str, MethodRole]) -> dict[str, MethodRole]:
    """A baseline without a known paper method stands against the paper methods of its citation."""
    for name, role in roles.items():
        if role.kind == BASELINE and not role.baseline_of and role.citation:
            papers = tuple(
                m for m, r in roles.items() if r.kind == PAPER and r.citation == role.citation
            )
            roles[name] = MethodRole(BASELINE, role.citation, papers, role.cls)
    return roles


def _registry_infos(registry: Registry | None) -> Mapping[str, Any]:
    if registry is None:
        from ..registry import registry as _registry

        registry = _registry()
    return getattr(registry, "retargeters", {}) or {}


# ---------------------------------------------------------------------------------------
# Per case
# ---------------------------------------------------------------------------------------
@dataclass
class CaseSummary:
    """The parts of a case's summary (``text`` joins them)."""

    case: str
    metric: str | None
    winner: str | None = None
    verdict: str = ""
    others: str = ""
    why: str = ""
    notes: list[str] = field(default_factory=list)

    @property
    def text(self) -> str:
        return " ".join(p for p in (self.verdict, self.others, self.why, *self.notes) if p)


def _values(result: ComparisonResult, case: str, metric: str) -> dict[str, float]:
    return {
        r["method"]: r["value"]
        for r in result.rows
        if r["case"] == case
        and r["metric"] == metric
        and r["status"] == OK
        and r["value"] is not None
    }


def _order(values: Mapping[str, float], better: str) -> list[str]:
    return sorted(values, key=lambda m: values[m] if better == "lower" else -values[m])


def _num(v: float) -> str:
    return format_number(v)


def _who(name: str, roles: Mapping[str, MethodRole]) -> str:
    role = roles.get(name)
    return f"{name} ({role.label})" if role is not None else name


def _margin(best: float, second: float, better: str) -> str:
    """ "3.2 times lower than", "12% lower than", "0.01 higher than" (``best`` differs from ``second``)."""
    if better == "lower":
        ratio = second / best if best > 0 else float("inf")
        if ratio >= 1000:
            return "more than 1,000 times lower than"
        return (
            f"{ratio:.1f} times lower than"
            if ratio >= 1.5
            else f"{100 * (1 - best / second):.0f}% lower than"
        )
    if second > 0 and best / second >= 1.5:
        return f"{best / second:.1f} times higher than"
    return f"{_num(abs(best - second))} higher than"


def case_summary(
    result: ComparisonResult, case: str, metric: str | None, roles: Mapping[str, MethodRole]
) -> CaseSummary:
    """Who wins ``case`` on ``metric``, by how much, where else, why, and paper-vs-baseline notes."""
    out = CaseSummary(case, metric)
    if metric is None:
        out.verdict = f"On {case}, no ranking metric was computed."
        return out
    values = _values(result, case, metric)
    better = result.better(metric)
    unit = result.metrics[metric].unit if metric in result.metrics else ""
    if not values:
        out.verdict = (
            f"On {case}, no method has a value of {metric} ({_reason(result, case, metric)})."
        )
        return out
    order = _order(values, better)
    out.winner = winner = order[0]
    if len(order) == 1:
        out.verdict = f"On {case}, only {_who(winner, roles)} has a value of {metric}: {_num(values[winner])} {unit}."
    elif values[order[0]] == values[order[1]]:
        out.winner = None
        out.verdict = f"On {case}, {_who(order[0], roles)} and {_who(order[1], roles)} tie on {metric}: {_num(values[winner])} {unit}."
        return out
    else:
        runner = order[1]
        out.verdict = (
            f"On {case}, {_who(winner, roles)} wins on {metric}: {_num(values[winner])} {unit}, "
            f"{_margin(values[winner], values[runner], better)} the next best, {_who(runner, roles)} at {_num(values[runner])}."
        )
    out.others = _other_winners(result, case, metric, winner)
    out.why = _why(result, case, winner, order[1] if len(order) > 1 else None, roles)
    out.notes = _behind_baseline(values, better, metric, roles)
    return out


def _reason(result: ComparisonResult, case: str, metric: str) -> str:
    reasons = [
        r["reason"]
        for r in result.rows
        if r["case"] == case and r["metric"] == metric and r["reason"]
    ]
    return reasons[0] if reasons else "no successful run"


def _other_winners(result: ComparisonResult, case: str, metric: str, winner: str) -> str:
    """ "It is also best on a, b; METHOD is best on c." over the ranked metrics
    (:data:`faceretarget.evaluation.metrics.RANKED_METRICS`, in their order)."""
    from .metrics import RANKED_METRICS

    also: list[str] = []
    elsewhere: dict[str, list[str]] = {}
    for m in RANKED_METRICS:
        if m == metric or m not in result.metrics:
            continue
        values = _values(result, case, m)
        if len(values) < 2:
            continue
        best = _order(values, result.better(m))
        if values[best[0]] == values[best[1]]:
            continue
        if best[0] == winner:
            also.append(m)
        else:
            elsewhere.setdefault(best[0], []).append(m)
    parts = []
    if also:
        parts.append(f"It is also best on {', '.join(also)}.")
    for method, metrics in elsewhere.items():
        parts.append(f"{method} is best on {', '.join(metrics)}.")
    return " ".join(parts)


def _needs(cls: type | None) -> set[str]:
    needs = getattr(getattr(cls, "capabilities", None), "needs", ()) or ()
    flat: set[str] = set()
    for need in needs:
        flat.update(need if isinstance(need, tuple) else (need,))
    return flat


def _outputs(cls: type | None) -> str:
    return getattr(getattr(cls, "capabilities", None), "outputs", "")


def _why(
    result: ComparisonResult,
    case: str,
    winner: str,
    runner: str | None,
    roles: Mapping[str, MethodRole],
) -> str:
    """A reason from what the case's ground truth is made of and what the methods consume."""
    meta = getattr(result.cases.get(case), "meta", None) or {}
    cls = getattr(roles.get(winner), "cls", None)
    other = getattr(roles.get(runner), "cls", None) if runner is not None else None
    if cls is None:
        return ""
    if "layers" in _needs(cls) and meta.get("layer_coefficients") is not None:
        return (
            f"Why: this case's ground truth is made from the same emotion, speech and blink layers that "
            f"{winner} fits (the case's weights are layer mixes), so its model can hold the answer exactly."
        )
    if _outputs(cls) == "weights" and meta.get("weights") is not None:
        return (
            f"Why: {winner}'s result is a mix of the target's own blendshapes, and this case's ground truth is "
            f"those blendshapes driven by the source's true weights, so good weights reproduce it exactly."
        )
    if _outputs(cls) == "vertices" and other is not None and _outputs(other) == "weights":
        return (
            f"Why: {winner} moves the target's vertices directly from the source's motion, while {runner} "
            f"can only reach shapes that the target's blendshapes span."
        )
    if "examples" in _needs(cls):
        return f"Why: {winner} learns the mapping from the example pose pairs of source and target."
    return ""


def _behind_baseline(
    values: Mapping[str, float], better: str, metric: str, roles: Mapping[str, MethodRole]
) -> list[str]:
    """ "Note: the paper method P is behind its baseline B on ..." per pair."""
    notes = []
    for base, role in roles.items():
        if role.kind != BASELINE or base not in values:
            continue
        for paper in role.baseline_of:
            if paper not in values:
                continue
            ahead = (
                values[base] < values[paper] if better == "lower" else values[base] > values[paper]
            )
            if ahead:
                notes.append(
                    f"Note: the paper method {paper} is behind its baseline {base} on {metric} "
                    f"({_num(values[paper])} vs {_num(values[base])})."
                )
    return notes
