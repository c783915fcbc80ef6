"""Paper reproductions ("presets"): running them and their results, for the report.

The reproductions themselves belong to the plugins: each registers
:class:`faceretarget.Preset` records through the ``faceretarget_presets`` hook (the
built-in methods' are in ``faceretarget/plugins/<method>/presets.py``). This module runs
them on the comparison's cases and keeps what each produced in a :class:`PresetResult`;
:mod:`.reproduction` has the helpers a reproduction is written with.

A preset states **the paper's claim** (``claim``), reproduces **the paper's setting** as far
as the cases allow (``setting``) and decides whether the measured result agrees with the
claim (``agrees``: True, False, or None when it could not be decided, with the measured
numbers in ``evidence``). A preset whose retargeter is not installed, or that fails, is
returned with status ``not applicable`` / ``error`` and the reason, and the report shows it.

    from faceretarget.evaluation import compare, run_presets, write_report
    result = compare(["synthetic-human"])
    run_presets(result)                      # attaches every preset to result.presets
    write_report(result, "report/")
"""

from __future__ import annotations

from collections.abc import Iterable, Mapping
from dataclasses import dataclass, field
from typing import TYPE_CHECKING, Any

from .._json import jsonable
from ..errors import CapabilityError, UnknownNameError
from ..hookspecs import Preset
from .harness import ERROR, NOT_APPLICABLE, OK, resolve_case

if TYPE_CHECKING:
    from ..cases import Case
    from .harness import ComparisonResult

__all__ = [
    "PresetResult",
    "Cases",
    "available_presets",
    "run_preset",
    "run_presets",
    "PRESET_CASES",
]

#: Cases the presets build when the caller gives none (kept small: seconds each).
PRESET_CASES = {
    "synthetic-human": "synthetic-human?resolution=1500&n_frames=90",
    "synthetic-stylized": "synthetic-stylized?resolution=1500&n_frames=90",
    "ict": "ict?n_frames=60",
}


@dataclass
class PresetResult:
    """What one preset produced: its plots and table, and its verdict on the paper's claim."""

    name: str
    title: str
    paper: str
    description: str
    status: str = OK
    reason: str = ""
    plots: list = field(default_factory=list)  # faceretarget.evaluation.report.Plot
    table: list[dict] = field(default_factory=list)
    #: The paper's claim that this preset checks (one sentence, quoting the paper where it can).
    claim: str = ""
    #: The paper's setting as reproduced here (inputs, parameters, what differs from the paper).
    setting: str = ""
    #: Whether the measured result agrees with the claim; None: not decided (the preset did
    #: not run, or the case does not reproduce the paper's setting; ``evidence`` says why).
    agrees: bool | None = None
    #: The measured numbers behind ``agrees``, one clause per part of the claim.
    evidence: str = ""

    @property
    def verdict(self) -> str:
        """``"agrees"``, ``"disagrees"`` or ``"undecided"``."""
        return "undecided" if self.agrees is None else ("agrees" if self.agrees else "disagrees")

    def as_dict(self) -> dict:
        return {
            "name": self.name,
            "title": self.title,
            "paper": self.paper,
            "description": self.description,
            "claim": self.claim,
            "setting": self.setting,
            "agrees": self.agrees,
            "verdict": self.verdict,
            "evidence": self.evidence,
            "status": self.status,
            "reason": self.reason,
            "plots": [p.as_dict() for p in self.plots],
            "table": jsonable(self.table),
        }


class Cases:
    """Cases by name or case spec: the caller's, else built on first use (a name of
    :data:`PRESET_CASES` by its spec there, anything else as
    :func:`faceretarget.evaluation.harness.resolve_case` reads it)."""

    def __init__(self, given: Mapping[str, Any] | None = None) -> None:
        self.given = dict(given or {})

    def __call__(self, name: str) -> Case:
        if name not in self.given:
            self.given[name] = resolve_case(PRESET_CASES.get(name, name))
        return self.given[name]


def available_presets() -> dict[str, Preset]:
    """Every registered preset by name, in plugin load order."""
    from ..registry import registry

    return {name: preset for name, (preset, _) in registry().presets.items()}


def run_preset(
    preset: str | Preset, cases: Mapping[str, Any] | Cases | None = None
) -> PresetResult:
    """Run one preset (a registered name, or a :class:`~faceretarget.Preset`); never raises for
    a missing or failing retargeter (see ``status``).

    cases : optional ``{case name: case}`` to reuse (e.g. ``result.cases``); missing ones are built.
    """
    if not isinstance(preset, Preset):
        known = available_presets()
        if preset not in known:
            raise UnknownNameError(
                f"no preset named {preset!r}; valid presets: {', '.join(known) or 'none installed'}"
            )
        preset = known[preset]
    pool = cases if isinstance(cases, Cases) else Cases(cases)
    res = PresetResult(
        preset.name,
        preset.title,
        preset.paper,
        preset.description,
        claim=preset.claim,
        setting=preset.setting,
    )
    try:
        preset.run(pool, res)
    except Exception as exc:  # a missing or failing retargeter is reported in the report
        res.status = (
            NOT_APPLICABLE if isinstance(exc, (UnknownNameError, CapabilityError)) else ERROR
        )
        res.reason = f"{type(exc).__name__}: {' '.join(str(exc).split())}"
        res.agrees, res.evidence = None, f"not decided: the reproduction did not run ({res.status})"
    return res


def run_presets(
    result: ComparisonResult | None = None,
    names: Iterable[str] | None = None,
    cases: Mapping[str, Any] | None = None,
) -> list[PresetResult]:
    """Run presets (default all); with ``result``, reuse its cases and attach to ``result.presets``."""
    pool = Cases({**(result.cases if result is not None else {}), **(cases or {})})
    out = [run_preset(n, pool) for n in (names or list(available_presets()))]
    if result is not None:
        result.presets.extend(out)
    return out


def __getattr__(name: str) -> Any:
    if name == "PRESETS":  # the registered presets by name (read when asked: plugins register them)
        return available_presets()
    raise AttributeError(f"module {__name__!r} has no attribute {name!r}")
