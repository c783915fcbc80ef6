"""Values typed on the command line: Python literals and ``--set`` pairs (every command alike)."""

from __future__ import annotations

import ast
from typing import Any

from .errors import ParameterError

__all__ = ["literal", "parse_sets"]


def literal(text: str) -> Any:
    """A Python literal (number, bool, None, string, tuple ...) from ``text``, else the text itself
    (``true``/``false``/``none`` in any case are the constants)."""
    try:
        return ast.literal_eval(text.strip())
    except (ValueError, SyntaxError):
        return {"true": True, "false": False, "none": None}.get(text.strip().lower(), text.strip())


def parse_sets(pairs: list[str] | None, *, per_method: bool = False) -> dict[str, Any]:
    """``--set`` values: ``["alpha=0.1", "mode=range"]`` -> ``{"alpha": 0.1, "mode": "range"}``;
    with ``per_method``, ``["m.alpha=0.1"]`` -> ``{"m": {"alpha": 0.1}}`` (values: :func:`literal`).
    Raises :class:`~faceretarget.errors.ParameterError` for a malformed pair."""
    out: dict[str, Any] = {}
    for pair in pairs or []:
        key, sep, value = pair.partition("=")
        key = key.strip()
        if per_method:
            method, dot, param = key.rpartition(".")
            if not sep or not dot or not method or not param:
                raise ParameterError(
                    f"--set {pair!r}: expected METHOD.PARAM=VALUE, e.g. --set METHOD.alpha=0.05"
                )
            out.setdefault(method, {})[param] = literal(value)
        else:
            if not sep or not key:
                raise ParameterError(f"--set {pair!r}: expected KEY=VALUE, e.g. --set alpha=0.05")
            out[key] = literal(value)
    return out
