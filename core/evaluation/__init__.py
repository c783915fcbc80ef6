"""Evaluation: metrics, the comparison harness, its report, batch runs and paper presets.

    import faceretarget.evaluation as ev
    result = ev.compare(["synthetic-human", "ict"])      # every applicable registered method
    result.to_csv("results.csv")
    ev.write_report(result, "report/")                   # report.html + results.csv + results.json

See ``docs/evaluation.md`` for the metric definitions, the report and the batch manifest.
"""

from __future__ import annotations

from importlib import import_module
from typing import Any

__all__ = [
    "compare",
    "ComparisonResult",
    "Run",
    "write_report",
    "run_presets",
    "run_preset",
    "PRESETS",
    "run_batch",
    "load_manifest",
    "METRICS",
]

_EXPORTS = {
    "compare": ".harness",
    "ComparisonResult": ".harness",
    "Run": ".harness",
    "write_report": ".report",
    "run_presets": ".presets",
    "run_preset": ".presets",
    "PRESETS": ".presets",
    "run_batch": ".batch",
    "load_manifest": ".batch",
    "METRICS": ".metrics",
}


def __getattr__(name: str) -> Any:
    if name in _EXPORTS:
        value = getattr(import_module(_EXPORTS[name], __name__), name)
        globals()[name] = value
        return value
    raise AttributeError(f"module 'faceretarget.evaluation' has no attribute {name!r}")


def __dir__() -> list[str]:
    return sorted(set(globals()) | set(__all__))
