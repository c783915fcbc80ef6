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

``compare(..., presets=True)`` runs them with the comparison, in its worker processes
when it has some (each preset is one task, so two presets run side by side on two cores).
"""

from __future__ import annotations

from collections.abc import Callable, Iterable, Mapping, Sequence
from dataclasses import dataclass, field
from typing import TYPE_CHECKING, Any, cast

from .._json import jsonable
from .._validate import did_you_mean
from ..errors import CapabilityError, ConfigError, UnknownNameError
from ..hookspecs import Preset
from .harness import ERROR, NOT_APPLICABLE, OK, resolve_case

if TYPE_CHECKING:
    from ..cases import Case
    from ..registry import Registry
    from ._workers import Outcome, Task
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
    """Cases by name or case spec: the caller's (a case, or a case spec built on first use),
    else built on first use (a name of :data:`PRESET_CASES` by its spec there, anything else
    as :func:`faceretarget.evaluation.harness.resolve_case` reads it).

    resolve : builds a case from its spec (default ``resolve_case``).
    """

    def __init__(
        self, given: Mapping[str, Any] | None = None, resolve: Callable[[str], Case] | None = None
    ) -> None:
        self.given = dict(given or {})
        self.resolve = resolve or resolve_case

    def __call__(self, name: str) -> Case:
        value = self.given.get(name)
        if value is None or isinstance(value, str):
            value = self.given[name] = self.resolve(
                PRESET_CASES.get(name, name) if value is None else value
            )
        return value


def available_presets() -> dict[str, Preset]:
    """Every registered preset by name, in plugin load order."""
    from ..registry import registry

    return {name: preset for name, (preset, _) in registry().presets.items()}


def chosen_presets(
    names: Iterable[str] | None = None, registry: Registry | None = None
) -> list[tuple[Preset, str]]:
    """``(preset, name of the plugin that registered it)`` for ``names`` (default every
    registered preset), in that order; raises :class:`UnknownNameError` for a name that is
    not registered."""
    if registry is None:
        from ..registry import registry as _registry

        registry = _registry()
    if isinstance(names, str):
        raise ConfigError(f"presets: give a list of preset names, got the string {names!r}")
    known = registry.presets
    wanted = list(known) if names is None else list(names)
    missing = [n for n in wanted if n not in known]
    if missing:
        named = ", ".join(f"{n!r}{did_you_mean(n, known)}" for n in missing)
        raise UnknownNameError(
            f"no preset(s) {named}; valid presets: {', '.join(known) or 'none installed'}"
        )
    return [(known[n][0], known[n][1].name) for n in wanted]


def run_preset(
    preset: str | Preset, cases: Mapping[str, Any] | Cases | None = None
) -> PresetResult:
    """Run one preset (a registered name, or a :class:`~faceretarget.Preset`); never raises for
    a missing or failing retargeter (see ``status``).

    cases : optional ``{case name: case}`` to reuse (e.g. ``result.cases``); missing ones are built.
    """
    if not isinstance(preset, Preset):
        ((preset, _),) = chosen_presets([preset])
    pool = cases if isinstance(cases, Cases) else Cases(cases)
    res = _result(preset)
    try:
        preset.run(pool, res)
    except Exception as exc:  # a missing or failing retargeter is reported in the report
        _did_not_run(
            res,
            NOT_APPLICABLE if isinstance(exc, (UnknownNameError, CapabilityError)) else ERROR,
            f"{type(exc).__name__}: {' '.join(str(exc).split())}",
        )
    return res


def _result(preset: Preset) -> PresetResult:
    return PresetResult(
        preset.name,
        preset.title,
        preset.paper,
        preset.description,
        claim=preset.claim,
        setting=preset.setting,
    )


def _did_not_run(res: PresetResult, status: str, reason: str) -> PresetResult:
    res.status, res.reason = status, reason
    res.agrees, res.evidence = None, f"not decided: the reproduction did not run ({status})"
    return res


def run_presets(
    result: ComparisonResult | None = None,
    names: Iterable[str] | None = None,
    cases: Mapping[str, Any] | None = None,
    *,
    n_jobs: int = 1,
    timeout: float | None = None,
) -> list[PresetResult]:
    """Run presets (default all); with ``result``, reuse its cases and attach to ``result.presets``.

    n_jobs : worker processes; > 1 runs the presets side by side (one task each).
    timeout : seconds one preset may take; given, every preset runs in a worker process
        that is killed when it overruns (the preset is then reported with status
        ``error`` and the reason). None or 0: no limit.
    """
    from .. import config

    config.check_jobs(n_jobs)
    timeout = config.check_timeout(timeout, "run_presets: timeout")
    chosen = chosen_presets(names or None)  # no names: all of them
    given = {**(result.cases if result is not None else {}), **(cases or {})}
    if timeout is None and (n_jobs == 1 or len(chosen) < 2):
        pool = Cases(given)
        out = [run_preset(preset, pool) for preset, _ in chosen]
    else:
        from ._workers import run_supervised, single_threaded_environ

        done: dict[str, PresetResult] = {}
        run_supervised(
            isolated_groups(chosen, given, timeout),
            workers=max(1, min(n_jobs, len(chosen))),
            on_outcome=lambda outcome: done.update([outcome_result(chosen, outcome)]),
            env=single_threaded_environ(),
        )
        out = [done[preset.name] for preset, _ in chosen]
    if result is not None:
        result.presets.extend(out)
    return out


# ---------------------------------------------------------------------------------------
# In worker processes (faceretarget.evaluation._workers): one task per preset
# ---------------------------------------------------------------------------------------
@dataclass(frozen=True)
class PresetKey:
    """The key of a preset's worker task (:func:`isolated_groups`)."""

    name: str


def _run_in_worker(preset: Preset, given: dict[str, Any]) -> PresetResult:
    """Worker side: ``preset`` on the caller's cases (case specs are built here, once per
    worker process)."""
    from .harness import cached_case

    return run_preset(preset, Cases(given, resolve=cached_case))


def isolated_groups(
    chosen: Sequence[tuple[Preset, str]],
    given: Mapping[str, Any],
    timeout: float | None,
    registry: Registry | None = None,
) -> list[list[Task]]:
    """The presets of :func:`chosen_presets` (chosen from ``registry``, default the global
    one) as worker tasks (key :class:`PresetKey`), grouped by the plugin that registered
    them (owned as :func:`._workers.plugin_owner` says). ``given``: the caller's cases by
    name, as case objects or case specs."""
    from ..registry import registry as _registry
    from ._workers import Task, plugin_owner

    builtin = {p.name for p in (registry or _registry()).plugins if p.builtin}

    groups: dict[str, list[Task]] = {}
    for preset, plugin in chosen:
        groups.setdefault(plugin, []).append(
            Task(
                PresetKey(preset.name),
                _run_in_worker,
                (preset, dict(given)),
                timeout,
                owner=plugin_owner(plugin, plugin in builtin),
            )
        )
    return list(groups.values())


def outcome_result(
    chosen: Sequence[tuple[Preset, str]], outcome: Outcome
) -> tuple[str, PresetResult]:
    """``(preset name, result)`` of a task of :func:`isolated_groups`: the worker's result,
    or an ``error`` result saying why the preset did not finish (timeout, crashed worker,
    a preset that could not be handed to a worker)."""
    from ._workers import DONE

    name = cast("PresetKey", outcome.key).name
    if outcome.status == DONE:
        return name, outcome.value
    preset, plugin = next((p, owner) for p, owner in chosen if p.name == name)
    return name, _did_not_run(
        _result(preset), ERROR, f"{outcome.message} (preset of plugin {plugin!r})"
    )


def __getattr__(name: str) -> Any:
    if name == "PRESETS":  # the registered presets by name (read when asked: plugins register them)
        return available_presets()
    raise AttributeError(f"module {__name__!r} has no attribute {name!r}")
