"""The comparison harness: every applicable retargeter on every case, measured.

    from faceretarget.evaluation import compare, write_report
    result = compare(["synthetic", "ict"])           # every registered retargeter
    result.to_csv("results.csv"); print(result.ranking())
    write_report(result, "report/")

For each (case, method) the harness

1. asks ``cls.why_not(source, target)``; a method that does not apply is listed as
   ``not applicable`` with that reason (a :class:`~faceretarget.errors.CapabilityError`
   raised by ``fit`` counts the same way);
2. fits and retargets under ``tracemalloc`` and a wall clock (with ``timeout``, in a
   supervised worker process killed when it overruns); any other exception, an overrun
   or a crashed worker is recorded as ``error`` (type, message, plugin name and
   distribution) and the run goes on;
3. validates the output (an :class:`~faceretarget.Animation`, the ground truth's shape,
   finite values) before any metric sees it;
4. computes every registered metric (``faceretarget_metrics`` hook), each value a row
   of the tidy table ``(case, method, metric, value, unit, status, reason)``.
"""

from __future__ import annotations

import csv
import io
import json
import math
import os
import time
import traceback
import tracemalloc
from collections.abc import Callable, Hashable, Iterable, Iterator, Mapping, Sequence
from contextlib import contextmanager
from dataclasses import dataclass, field
from pathlib import Path
from typing import TYPE_CHECKING, Any, cast

import numpy as np

from .._args import literal
from .._json import jsonable
from .._validate import did_you_mean
from ..errors import (
    CapabilityError,
    ConfigError,
    UnknownNameError,
)
from ..hookspecs import Metric
from ..model import Animation
from ..retargeter import Retargeter

if TYPE_CHECKING:
    from .._types import PathLike
    from ..cases import Case
    from ..registry import Registry, RetargeterInfo
    from ._workers import Outcome

__all__ = [
    "ComparisonResult",
    "Run",
    "compare",
    "resolve_case",
    "cached_case",
    "CASE_NAMES",
    "OK",
    "NOT_APPLICABLE",
    "ERROR",
    "COLUMNS",
]

#: The metric the report ranks by unless told otherwise: distance to the ground truth.
DEFAULT_RANKING_METRIC = "vertex_error_rms"
OK = "ok"
NOT_APPLICABLE = "not applicable"
ERROR = "error"

#: Columns of the tidy table, in order.
COLUMNS = ("case", "method", "metric", "value", "unit", "status", "reason")

#: Case names understood by :func:`resolve_case` -> (factory in faceretarget.cases, fixed keywords).
CASE_NAMES = {
    "synthetic": ("synthetic", {}),
    "synthetic-human": ("synthetic", {"target": "human"}),
    "synthetic-stylized": ("synthetic", {"target": "stylized"}),
    "ict": ("ict", {}),
    "cross_rig": ("cross_rig", {}),
    "cross_topology": ("cross_topology", {}),
}
DEFAULT_CASES = ("synthetic-human", "synthetic-stylized", "ict")


# ---------------------------------------------------------------------------------------
# Cases
# ---------------------------------------------------------------------------------------
def resolve_case(spec: str | Case) -> Case:
    """A case object from a name such as ``"synthetic-stylized"`` or ``"ict?n_frames=40"``.

    The part after ``?`` gives keyword arguments (``k=v`` joined by ``&``; values are
    Python literals, else strings) for the factory in :mod:`faceretarget.cases`. A case
    object (anything with ``.source`` and ``.target``) is returned unchanged.
    """
    if not isinstance(spec, str):
        if hasattr(spec, "source") and hasattr(spec, "target"):
            return spec
        raise UnknownNameError(
            f"a case is a name ({', '.join(CASE_NAMES)}) or a case object with .source and .target; got {spec!r}"
        )
    name, kwargs = parse_case_spec(spec)
    factory_name, fixed = CASE_NAMES[name]
    from .. import cases

    factory = getattr(cases, factory_name)
    return factory(**{**fixed, **kwargs})


def parse_case_spec(spec: str) -> tuple[str, dict[str, Any]]:
    """``"ict?n_frames=40&seed=2"`` -> ``("ict", {"n_frames": 40, "seed": 2})``; checks the name."""
    name, _, query = spec.partition("?")
    name = name.strip()
    if name not in CASE_NAMES:
        raise UnknownNameError(
            f"no case named {name!r}{did_you_mean(name, CASE_NAMES)}; valid cases: {', '.join(CASE_NAMES)} (optionally with ?key=value&...)"
        )
    kwargs: dict[str, Any] = {}
    for pair in filter(None, query.split("&")):
        key, sep, value = pair.partition("=")
        if not sep or not key.strip().isidentifier():
            raise ConfigError(f"case {spec!r}: {pair!r} is not key=value (e.g. ict?n_frames=40)")
        kwargs[key.strip()] = literal(value)
    return name, kwargs


def case_name(case: object, index: int) -> str:
    for value in (getattr(case, "name", None), (getattr(case, "meta", None) or {}).get("name")):
        if isinstance(value, str) and value:
            return value
    return f"case{index}"


# ---------------------------------------------------------------------------------------
# Methods
# ---------------------------------------------------------------------------------------
@dataclass(frozen=True)
class _Method:
    name: str
    cls: type[Retargeter]
    plugin: str
    distribution: str
    version: str
    builtin: bool = False  # one of our own plugins (they share workers)


def _methods(methods: Iterable[str | type[Retargeter]] | None, registry: Registry) -> list[_Method]:
    if methods is None:
        return [_from_info(info) for _, info in sorted(registry.retargeters.items())]
    out = []
    for item in methods:
        if isinstance(item, str):
            out.append(_from_info(registry.resolve(item)))
        elif isinstance(item, type) and issubclass(item, Retargeter):
            out.append(_Method(item.name or item.__name__, item, item.__module__, "local", "-"))
        else:
            raise UnknownNameError(
                f"methods are retargeter names or Retargeter subclasses; got {item!r}"
            )
    names = [m.name for m in out]
    if len(set(names)) != len(names):
        raise ConfigError(f"methods: each retargeter once please; got {names}")
    return out


def _owner(method: _Method) -> Hashable:
    """Who answers for ``method``'s runs in a worker (:func:`._workers.plugin_owner`; a
    class passed directly: its module, as a third-party plugin)."""
    from ._workers import plugin_owner

    return plugin_owner(method.plugin, method.builtin)


def _from_info(info: RetargeterInfo) -> _Method:
    plugin = info.plugin
    return _Method(
        info.name, info.cls, plugin.name, plugin.distribution, plugin.version, plugin.builtin
    )


def _params_for(method: _Method, params: Mapping | None) -> dict:
    given = dict((params or {}).get(method.name, {}))
    defaults = method.cls.default_params()
    unknown = sorted(set(given) - set(defaults))
    if unknown:
        named = ", ".join(f"{k!r}{did_you_mean(k, defaults)}" for k in unknown)
        raise UnknownNameError(
            f"params for {method.name}: no parameter(s) {named}; valid: {', '.join(sorted(defaults)) or '(none)'}"
        )
    return given


# ---------------------------------------------------------------------------------------
# Results
# ---------------------------------------------------------------------------------------
@dataclass
class Run:
    """One (case, method) run: status, timings, the result (kept in memory) and any error."""

    case: str
    method: str
    status: str
    reason: str = ""
    plugin: str = ""
    distribution: str = ""
    version: str = ""
    parameters: dict = field(default_factory=dict)
    fit_s: float | None = None
    retarget_s: float | None = None
    #: seconds of ``fit_s + retarget_s`` spent in numba's compiler (compiling kernels or
    #: loading them from the on-disk cache): a one-time cost per process, not the method's speed
    compile_s: float | None = None
    peak_memory_mib: float | None = None
    error: dict | None = None
    animation: Animation | None = None

    def as_dict(self) -> dict:
        return {
            "case": self.case,
            "method": self.method,
            "status": self.status,
            "reason": self.reason,
            "plugin": self.plugin,
            "distribution": self.distribution,
            "version": self.version,
            "parameters": jsonable(self.parameters),
            "fit_s": self.fit_s,
            "retarget_s": self.retarget_s,
            "compile_s": self.compile_s,
            "peak_memory_mib": self.peak_memory_mib,
            "error": self.error,
        }


class ComparisonResult:
    """The outcome of :func:`compare`.

    rows : the tidy table, a list of dicts with keys :data:`COLUMNS`
    runs : one :class:`Run` per (case, method), with the animations
    cases : case name -> case object (in order)
    metrics : metric name -> :class:`~faceretarget.Metric` used
    presets : paper reproductions attached by :func:`faceretarget.evaluation.presets.run_presets`
    """

    def __init__(
        self,
        rows: list[dict],
        runs: list[Run],
        cases: dict[str, Any],
        metrics: dict[str, Metric],
        presets: Iterable | None = None,
    ) -> None:
        self.rows: list[dict] = rows
        self.runs: list[Run] = runs
        self.cases: dict[str, Any] = cases
        self.metrics: dict[str, Metric] = metrics
        self.presets: list = list(presets or [])

    # -- access ------------------------------------------------------------------------
    def run(self, case: str, method: str) -> Run:
        for r in self.runs:
            if r.case == case and r.method == method:
                return r
        raise UnknownNameError(
            f"no run of {method!r} on case {case!r}; runs: {sorted({(r.case, r.method) for r in self.runs})}"
        )

    def value(self, case: str, method: str, metric: str) -> float | None:
        """The value of ``metric`` for (case, method), None when not computed."""
        for row in self.rows:
            if row["case"] == case and row["method"] == method and row["metric"] == metric:
                return row["value"]
        raise UnknownNameError(f"no row for ({case!r}, {method!r}, {metric!r})")

    @property
    def methods(self) -> list[str]:
        return list(dict.fromkeys(r.method for r in self.runs))

    def better(self, metric: str) -> str:
        base = metric.split("[", 1)[0]
        m = self.metrics.get(base)
        return m.better if m is not None else "none"

    # -- ranking -----------------------------------------------------------------------
    def ranking(self, metrics: Sequence[str] | None = None) -> list[dict]:
        """Methods ordered by their mean rank over cases and metrics.

        For each case and each metric (default: the report's one ranking metric,
        :func:`ranking_metric`, RMS vertex error when computed,
        so the console, ``results.json`` and the report agree) with a value for at least two methods, methods get ranks
        1..n (ties share the mean rank; "higher is better" metrics are ranked
        descending). A method's score is the mean of its ranks; methods with no rank
        (not applicable or failed everywhere) come last. Each row: ``rank, method,
        mean_rank, ranked_cases, not_applicable, failed`` and the mean over cases of
        ``vertex_error_rms`` and ``time_total``.
        """
        if metrics is None:
            default = ranking_metric(self)
            metrics = [] if default is None else [default]
        chosen = [m for m in metrics if m in self.metrics]
        table: dict[tuple[str, str], dict[str, float]] = {}
        for row in self.rows:
            if row["status"] == OK and row["value"] is not None:
                table.setdefault((row["case"], row["metric"]), {})[row["method"]] = row["value"]
        ranks: dict[str, list[float]] = {m: [] for m in self.methods}
        for (_case, metric), values in table.items():
            if (
                metric not in chosen
                or len(values) < 2
                or self.better(metric) not in ("lower", "higher")
            ):
                continue
            names = list(values)
            arr = np.array([values[n] for n in names], dtype=float)
            if self.better(metric) == "higher":
                arr = -arr
            for name, rank in zip(names, _mean_ranks(arr)):
                ranks[name].append(rank)
        out = []
        for method in self.methods:
            runs = [r for r in self.runs if r.method == method]
            out.append(
                {
                    "method": method,
                    "mean_rank": float(np.mean(ranks[method])) if ranks[method] else None,
                    "ranked_cases": sum(r.status == OK for r in runs),
                    "not_applicable": sum(r.status == NOT_APPLICABLE for r in runs),
                    "failed": sum(r.status == ERROR for r in runs),
                    "vertex_error_rms": self._mean_value(method, "vertex_error_rms"),
                    "time_total": self._mean_value(method, "time_total"),
                }
            )
        out.sort(
            key=lambda r: (
                r["mean_rank"] is None,
                r["mean_rank"] if r["mean_rank"] is not None else 0.0,
                r["method"],
            )
        )
        for i, row in enumerate(out, 1):
            row["rank"] = i if row["mean_rank"] is not None else None
        return [{"rank": r.pop("rank"), **r} for r in out]

    def _mean_value(self, method: str, metric: str) -> float | None:
        vals = [
            r["value"]
            for r in self.rows
            if r["method"] == method and r["metric"] == metric and r["value"] is not None
        ]
        return float(np.mean(vals)) if vals else None

    # -- export ------------------------------------------------------------------------
    def to_csv(self, path: PathLike, *, force: bool = False, inputs: Iterable = ()) -> Path:
        """Write the tidy table as CSV (atomically; an existing file only with ``force``,
        never an input); returns the path."""
        buf = io.StringIO()
        writer = csv.DictWriter(buf, fieldnames=COLUMNS, lineterminator="\n")
        writer.writeheader()
        for row in self.rows:
            writer.writerow({k: ("" if row[k] is None else _fmt_csv(row[k])) for k in COLUMNS})
        return atomic_write_text(path, buf.getvalue(), force=force, inputs=inputs)

    def as_dict(self) -> dict:
        return {
            "columns": list(COLUMNS),
            "rows": [{k: jsonable(row[k]) for k in COLUMNS} for row in self.rows],
            "ranking": self.ranking(),
            "runs": [r.as_dict() for r in self.runs],
            "metrics": {
                name: {"description": m.description, "unit": m.unit, "better": m.better}
                for name, m in self.metrics.items()
            },
            "presets": [p.as_dict() for p in self.presets],
        }

    def to_json(self, path: PathLike, *, force: bool = False, inputs: Iterable = ()) -> Path:
        """Write rows, ranking, runs (with errors), metric definitions and presets as JSON
        (atomically; an existing file only with ``force``, never an input)."""
        return atomic_write_text(
            path,
            json.dumps(jsonable(self.as_dict()), indent=1, allow_nan=False) + "\n",
            force=force,
            inputs=inputs,
        )

    def __repr__(self) -> str:
        counts = {s: sum(r.status == s for r in self.runs) for s in (OK, NOT_APPLICABLE, ERROR)}
        return f"ComparisonResult({len(self.cases)} cases, {len(self.methods)} methods, {counts}, {len(self.rows)} rows)"


def _mean_ranks(values: np.ndarray) -> np.ndarray:
    order = np.argsort(values, kind="stable")
    ranks = np.empty(len(values))
    ranks[order] = np.arange(1, len(values) + 1)
    for v in np.unique(values):
        tie = values == v
        ranks[tie] = ranks[tie].mean()
    return ranks


def _fmt_csv(value: object) -> object:
    if isinstance(value, float):
        return repr(value)
    return value


def atomic_write_bytes(
    path: PathLike, data: bytes, *, force: bool = False, inputs: Iterable = ()
) -> Path:
    """Write ``data`` to ``path`` atomically (``faceretarget.io``'s temp file + fsync + rename),
    with its destination check: never an input, an existing file only with ``force``."""
    from ..io._atomic import write_bytes

    return write_bytes(path, data, force=force, inputs=inputs)


def atomic_write_text(
    path: PathLike, text: str, *, force: bool = False, inputs: Iterable = ()
) -> Path:
    return atomic_write_bytes(path, text.encode("utf-8"), force=force, inputs=inputs)


# ---------------------------------------------------------------------------------------
# Running
# ---------------------------------------------------------------------------------------
def _error_record(exc: BaseException, method: _Method, stage: str) -> dict:
    return {
        "type": type(exc).__name__,
        "message": " ".join(str(exc).split()) or type(exc).__name__,
        "stage": stage,
        "plugin": method.plugin,
        "distribution": method.distribution,
        "version": method.version,
        "traceback": "".join(traceback.format_exception(exc)[-6:]),
    }


def _failed(run: Run, exc: BaseException, method: _Method, stage: str) -> Run:
    run.status = ERROR
    run.error = _error_record(exc, method, stage)
    run.reason = (
        f"{run.error['type']} in {stage}: {run.error['message']} "
        f"(plugin {method.plugin!r}, distribution {method.distribution} {method.version})"
    )
    return run


class _CompileSpans:
    """The outermost spans of numba's compiler lock inside a run (compiling kernels and
    loading them from the disk cache): their seconds, and ``tracemalloc`` paused across them
    when ``pause`` (compiling under tracing runs over twice as slow, and the compiler's own
    allocations are not the method's memory)."""

    def __init__(self, pause: bool) -> None:
        self.pause, self.seconds, self._depth, self._began = pause, 0.0, 0, 0.0
        self._paused, self._frames = False, 1
        self._carried = 0  # bytes traced before the pauses, counted as still held
        self._peak = 0  # the highest traced total before the last pause

    def enter(self) -> None:
        if self._depth == 0:
            self._began = time.perf_counter()
            if self.pause and tracemalloc.is_tracing():
                current, peak = tracemalloc.get_traced_memory()
                self._peak = max(self._peak, self._carried + peak)
                self._carried += current
                self._frames = tracemalloc.get_traceback_limit()
                tracemalloc.stop()
                self._paused = True
        self._depth += 1

    def leave(self) -> None:
        self._depth -= 1
        if self._depth == 0:
            self.seconds += time.perf_counter() - self._began
            if self._paused:
                tracemalloc.start(self._frames)
                self._paused = False

    def traced_peak(self) -> int:
        """Peak traced bytes since tracing started; across a pause the bytes traced before it
        count as held (frees of them are not seen after it): an upper bound."""
        peak = tracemalloc.get_traced_memory()[1] if tracemalloc.is_tracing() else 0
        return max(self._peak, self._carried + peak)


@contextmanager
def _compile_spans(pause_tracing: bool) -> Iterator[_CompileSpans]:
    """Yields a :class:`_CompileSpans` that follows numba's compiler lock inside the block."""
    spans = _CompileSpans(pause_tracing)
    try:
        from numba.core import event
    except ImportError:  # no numba: nothing is compiled
        yield spans
        return

    class Listener(event.Listener):
        def on_start(self, ev: object) -> None:
            spans.enter()

        def on_end(self, ev: object) -> None:
            spans.leave()

    with event.install_listener("numba:compiler_lock", Listener()):
        yield spans


def _run_one(case: Case, cname: str, method: _Method, params: dict) -> Run:
    run = Run(
        cname,
        method.name,
        OK,
        plugin=method.plugin,
        distribution=method.distribution,
        version=method.version,
    )
    try:
        reason = method.cls.why_not(case.source, case.target)
    except (Exception, SystemExit) as exc:  # a plugin's own applicability check may be broken too
        return _failed(run, exc, method, "why_not")
    if reason:
        run.status, run.reason = NOT_APPLICABLE, reason
        return run
    stage = "construct"
    started_tracing = not tracemalloc.is_tracing()
    if started_tracing:
        tracemalloc.start()
    tracemalloc.reset_peak()
    base = tracemalloc.get_traced_memory()[0]
    try:
        retargeter = method.cls(**params)
        run.parameters = retargeter.get_params()
        # tracing paused while numba compiles, only if this run started it (stopping
        # would drop a caller's own traces)
        with _compile_spans(pause_tracing=started_tracing) as compiling:
            stage = "fit"
            t0 = time.perf_counter()
            retargeter.fit(case.source, case.target)
            t1 = time.perf_counter()
            stage = "retarget"
            animation = retargeter.retarget(case.source)
            t2 = time.perf_counter()
        run.fit_s, run.retarget_s, run.compile_s = t1 - t0, t2 - t1, compiling.seconds
        run.peak_memory_mib = max(0, compiling.traced_peak() - base) / 2**20
        run.animation = animation  # checked by Retargeter.check_output
    except CapabilityError as exc:
        run.status, run.reason = NOT_APPLICABLE, " ".join(str(exc).split())
    except Exception as exc:  # a failing plugin must not stop the others
        _failed(run, exc, method, stage)
    except (
        SystemExit,
        GeneratorExit,
    ) as exc:  # sys.exit in a plugin run in this process: a failure, not the end
        _failed(run, exc, method, stage)
    finally:
        if started_tracing:
            tracemalloc.stop()
    return run


def _metric_rows(run: Run, case: Case, metrics: Mapping[str, Metric]) -> list[dict]:
    rows = []

    def add(name: str, value: object, metric: Metric, status: str, reason: str = "") -> None:
        rows.append(
            {
                "case": run.case,
                "method": run.method,
                "metric": name,
                "value": value,
                "unit": metric.unit,
                "status": status,
                "reason": reason,
            }
        )

    if run.status != OK:
        for name, metric in metrics.items():
            add(name, None, metric, run.status, run.reason)
        return rows
    context: dict[str, Any] = {
        "fit_s": run.fit_s,
        "retarget_s": run.retarget_s,
        "total_s": (run.fit_s or 0.0) + (run.retarget_s or 0.0),
        "compile_s": run.compile_s,
        "peak_memory_mib": run.peak_memory_mib,
        "method": run.method,
        "cache": {},
        "reasons": {},
    }
    for name, metric in metrics.items():
        try:
            value = metric.compute(run.animation, case, context)
            if value is None:
                reason = context["reasons"].get(name) or (
                    metric.why_not(run.animation, case) if metric.why_not else None
                )
                add(
                    name,
                    None,
                    metric,
                    NOT_APPLICABLE,
                    reason or "the metric gave no value for this run",
                )
            elif isinstance(value, Mapping):
                for label, v in value.items():
                    ok = v is not None and math.isfinite(float(v))
                    add(
                        f"{name}[{label}]",
                        float(v) if ok else None,
                        metric,
                        OK if ok else NOT_APPLICABLE,
                        "" if ok else "no value for this region",
                    )
            else:
                value = float(value)
                if math.isfinite(value):
                    add(name, value, metric, OK)
                else:
                    add(name, None, metric, ERROR, f"the metric returned {value}")
        except Exception as exc:  # a failing metric plugin is reported, not fatal
            add(name, None, metric, ERROR, f"{type(exc).__name__}: {' '.join(str(exc).split())}")
    return rows


_CASE_CACHE: dict[str, Any] = {}


def cached_case(spec: str) -> Case:
    """:func:`resolve_case` with a small per-process cache (workers reuse built cases)."""
    if spec not in _CASE_CACHE:
        if len(_CASE_CACHE) >= 4:
            _CASE_CACHE.clear()
        _CASE_CACHE[spec] = resolve_case(spec)
    return _CASE_CACHE[spec]


#: Extras (method-specific outputs) smaller than this come back from worker processes;
#: bigger ones (e.g. a per-frame normal mesh) are dropped there.
LIGHT_EXTRAS_BYTES = 4 * 2**20


def _light_extras(extras: Mapping) -> dict:
    """The extras worth sending back from a worker: numbers, strings and arrays (or lists
    of numbers) up to :data:`LIGHT_EXTRAS_BYTES`."""
    kept = {}
    for key, value in extras.items():
        if value is None or isinstance(value, (bool, int, float, str, np.generic)):
            kept[key] = value
            continue
        try:
            size = (
                value.nbytes
                if isinstance(value, np.ndarray)
                else np.asarray(value, dtype=float).nbytes
            )
        except (TypeError, ValueError):
            continue
        if size <= LIGHT_EXTRAS_BYTES:
            kept[key] = value
    return kept


class _CaseByName:
    """A case sent to a worker by name: unpickling it there builds (or reuses) the case,
    so the building happens while the task loads, before the run's clock starts."""

    def __init__(self, spec: str) -> None:
        self.spec = spec

    def __reduce__(self) -> tuple[Callable[[str], Case], tuple[str]]:
        return (cached_case, (self.spec,))


def _run_item(method: _Method, params: dict, cname: str, case: Case) -> Run:
    """Worker side of an isolated compare: one method on one case (heavy extras dropped)."""
    run = _run_one(case, cname, method, params)
    if run.animation is not None and run.animation.extras:
        run.animation = run.animation.replace(extras=_light_extras(run.animation.extras))
    return run


@contextmanager
def single_threaded_children() -> Iterator[None]:
    """Within this block, spawned child processes use one BLAS / OpenMP / numba thread
    each (variables the user set are kept). It changes this process's environment: nothing
    in this process may compile a numba kernel inside it (see
    :func:`._workers.single_threaded_environ`, which our own workers get instead)."""
    from ._workers import THREAD_VARIABLES

    saved = {k: os.environ.get(k) for k in THREAD_VARIABLES}
    for k in THREAD_VARIABLES:
        os.environ.setdefault(k, "1")
    try:
        yield
    finally:
        for k, v in saved.items():
            if v is None:
                os.environ.pop(k, None)
            else:
                os.environ[k] = v


def _isolated(
    refs: dict,
    chosen: list[_Method],
    per_method: dict,
    n_jobs: int,
    timeout: float | None,
    on_run: Callable[[Run], None],
    reproductions: Sequence[tuple[Any, str]] = (),
    on_preset: Callable[[str, Any], None] | None = None,
    registry: Registry | None = None,
) -> None:
    """Every run in a supervised worker process (killed after ``timeout`` seconds); with
    ``reproductions`` (:func:`.presets.chosen_presets` from ``registry``) their presets too,
    each one task whose result goes to ``on_preset(name, result)``.

    The methods of one module (sharing numba kernels) form one group, so each worker
    compiles them once; a run that overruns or kills its worker is recorded as an error
    naming the plugin and its distribution, and the group goes on in a fresh worker.
    """
    from ._workers import DONE, Task, run_supervised, single_threaded_environ

    by_name = {m.name: m for m in chosen}
    groups: dict[str, list[Task]] = {}
    for m in chosen:
        tasks = groups.setdefault(m.cls.__module__, [])
        for cname, ref in refs.items():
            case = _CaseByName(ref) if isinstance(ref, str) else ref
            tasks.append(
                Task(
                    (cname, m.name),
                    _run_item,
                    (m, per_method[m.name], cname, case),
                    timeout,
                    owner=_owner(m),
                )
            )

    from .presets import PresetKey, isolated_groups, outcome_result

    preset_groups = isolated_groups(reproductions, refs, timeout, registry)

    def on_outcome(outcome: Outcome) -> None:
        if isinstance(outcome.key, PresetKey):
            assert on_preset is not None  # preset tasks come with their callback
            on_preset(*outcome_result(reproductions, outcome))
            return
        cname, name = cast("tuple[str, str]", outcome.key)  # the keys of the tasks above
        if outcome.status == DONE:
            on_run(outcome.value)
            return
        m = by_name[name]
        run = Run(
            cname, name, ERROR, plugin=m.plugin, distribution=m.distribution, version=m.version
        )
        _failed(run, outcome.error(), m, "run" if outcome.started else "hand-over to a worker")
        if isinstance(outcome.value, str):
            assert run.error is not None  # _failed recorded it
            run.error["traceback"] = outcome.value
        on_run(run)

    # the metrics of finished runs are computed here meanwhile: this process's environment
    # must not change (numba would see a new thread count)
    # presets first: each is one long task (many fits), and the runs fill the cores around them
    run_supervised(
        [*preset_groups, *groups.values()],
        workers=n_jobs,
        on_outcome=on_outcome,
        env=single_threaded_environ(),
    )


def compare(
    cases: Sequence[Case | str] | Mapping[str, Case | str] | None = None,
    methods: Sequence[str | type[Retargeter]] | None = None,
    params: Mapping[str, Mapping[str, Any]] | None = None,
    *,
    metrics: Sequence[str] | None = None,
    registry: Registry | None = None,
    keep_animations: bool = True,
    progress: bool = False,
    n_jobs: int = 1,
    timeout: float | None = None,
    presets: bool | Sequence[str] = False,
) -> ComparisonResult:
    """Run retargeters on cases and measure them.

    Parameters
    ----------
    cases : list of case objects or names (see :data:`CASE_NAMES`; ``"ict?n_frames=40"``
        passes keywords), or a mapping ``{display name: case or name}``; default the
        synthetic human and stylized cases and the ICT case.
    methods : list of retargeter names (aliases work) or :class:`~faceretarget.Retargeter`
        subclasses; default every registered retargeter.
    params : ``{method name: {parameter: value}}`` for the constructors.
    metrics : metric names to compute (default every registered metric).
    registry : a :class:`~faceretarget.registry.Registry` (default the process-wide one).
    keep_animations : keep each result in ``Run.animation`` (the report needs them).
    progress : show a tqdm progress bar on stderr.
    n_jobs : worker processes; > 1 runs the methods in parallel (the methods of one
        module form one task, so their numba kernels compile once), metrics are computed
        here as results arrive; the animations come back without ``extras``. Classes must
        be importable by the workers, and (as with any ``multiprocessing`` code) a script
        must call this under ``if __name__ == "__main__":``.
    timeout : seconds one run (fit + retarget) may take; given, every run happens in a
        worker process (``n_jobs`` of them) that is killed when it overruns, and the run is
        recorded as an error naming the plugin (:class:`~faceretarget.errors.PluginTimeoutError`).
        A worker that crashes is recorded the same way. None or 0: no limit.
    presets : also run the paper reproductions (True: every registered one; or a list of
        preset names) on these cases, attached to ``result.presets``; with worker processes
        each preset is one more task of the same pool (``timeout`` applies to a preset as a
        whole), so presets and runs share the cores. See
        :func:`faceretarget.evaluation.presets.run_presets`.

    Returns
    -------
    ComparisonResult
    """
    if registry is None:
        from ..registry import registry as _registry

        registry = _registry()
    chosen = _methods(methods, registry)
    if params:
        unknown = sorted(set(params) - {m.name for m in chosen})
        if unknown:
            named = ", ".join(f"{u!r}{did_you_mean(u, [m.name for m in chosen])}" for u in unknown)
            raise UnknownNameError(
                f"params given for {named}, which is not among the compared methods {[m.name for m in chosen]}"
            )
    all_metrics = {name: m for name, (m, _) in registry.metrics.items()}
    if metrics is not None:
        missing = [m for m in metrics if m not in all_metrics]
        if missing:
            named = ", ".join(f"{m!r}{did_you_mean(m, all_metrics)}" for m in missing)
            raise UnknownNameError(f"no metric(s) {named}; valid: {', '.join(all_metrics)}")
        all_metrics = {m: all_metrics[m] for m in metrics}
    from .. import config

    config.check_jobs(n_jobs)

    timeout = config.check_timeout(timeout, "compare: timeout")
    from .presets import chosen_presets

    reproductions = (
        chosen_presets(None if presets is True else presets, registry)
        if presets is not False
        else []
    )
    named_cases = (
        list(cases.items())
        if isinstance(cases, Mapping)
        else [(None, c) for c in (DEFAULT_CASES if cases is None else cases)]
    )
    if not named_cases:
        raise ConfigError("compare: no cases given")
    resolved: dict[str, Any] = {}
    refs: dict[str, Any] = {}
    for i, (given, spec) in enumerate(named_cases):
        case = resolve_case(spec)
        name = given or (spec if isinstance(spec, str) else case_name(case, i))
        base, k = name, 2
        while name in resolved:
            name, k = f"{base}#{k}", k + 1
        resolved[name], refs[name] = case, spec
    per_method = {m.name: _params_for(m, params) for m in chosen}
    from tqdm import tqdm

    bar = tqdm(
        total=len(resolved) * len(chosen) + len(reproductions),
        desc="compare",
        unit="run",
        disable=not progress,
        leave=False,
    )
    done: dict[tuple[str, str], tuple[Run, list[dict]]] = {}

    def on_run(run: Run) -> None:
        rows = _metric_rows(run, resolved[run.case], all_metrics)
        if not keep_animations:
            run.animation = None
        done[(run.case, run.method)] = (run, rows)
        bar.set_postfix_str(f"{run.case}: {run.method}")
        bar.update()

    reproduced: dict[str, Any] = {}

    def on_preset(name: str, res: Any) -> None:
        reproduced[name] = res
        bar.set_postfix_str(f"preset {name}")
        bar.update()

    tasks = len(chosen) + len(reproductions)
    if timeout is not None or (n_jobs > 1 and tasks > 1):
        _isolated(
            refs,
            chosen,
            per_method,
            max(1, min(n_jobs, tasks)),
            timeout,
            on_run,
            reproductions,
            on_preset,
            registry,
        )
    else:
        for cname, case in resolved.items():
            for method in chosen:
                on_run(_run_one(case, cname, method, per_method[method.name]))
        if reproductions:
            from .presets import Cases, run_preset

            pool = Cases(resolved)
            for preset, _ in reproductions:
                on_preset(preset.name, run_preset(preset, pool))
    bar.close()
    order = [(c, m.name) for c in resolved for m in chosen]
    runs = [done[key][0] for key in order]
    rows = [row for key in order for row in done[key][1]]
    return ComparisonResult(
        rows, runs, resolved, all_metrics, [reproduced[p.name] for p, _ in reproductions]
    )


def ranking_metric(result: ComparisonResult, name: str | None = None) -> str | None:
    """The metric to rank by: ``name`` (checked), else :data:`DEFAULT_RANKING_METRIC` when it was
    computed, else the first computed metric of ``RANKED_METRICS``; None when none was computed."""
    from .metrics import RANKED_METRICS

    if name is not None:
        if name not in result.metrics:
            raise UnknownNameError(
                f"cannot rank by {name!r}{did_you_mean(name, result.metrics)}: not among the computed metrics {', '.join(result.metrics)}"
            )
        if result.better(name) not in ("lower", "higher"):
            raise ConfigError(
                f"cannot rank by {name!r}: it is descriptive (neither lower nor higher is better)"
            )
        return name
    for candidate in (DEFAULT_RANKING_METRIC, *RANKED_METRICS):
        if candidate in result.metrics:
            return candidate
    return None
