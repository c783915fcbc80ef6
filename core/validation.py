"""Declarative parameter constraints, in the style of scikit-learn's ``_param_validation``.

A retargeter (built-in or third-party) declares, for each constructor parameter, a list of
constraints; a value is valid when it satisfies *any* of them::

    from faceretarget.validation import Interval, Options, validate_params

    class MyRetargeter(fr.Retargeter):
        parameter_constraints = {
            "alpha": [Interval(float, 0, None, closed="left")],   # a finite number >= 0
            "mode": [Options({"fast", "exact"})],                  # one of these strings
            "levels": [Options({"auto"}), Interval(int, 0, 7)],    # "auto" or a whole number
            "flip": ["boolean"],                                   # True / False (or 0 / 1)
            "weights": [None, "array-like"],                       # shape checked in fit
        }

        def _fit(self, source, target):
            params = validate_params(self)   # {name: checked value}, or ParameterError

Constraints: :class:`Interval`, :class:`Options`, ``"boolean"``, ``"array-like"`` (numpy's
sense: anything but a string or None; the method checks its shape), ``"mapping"``,
``"callable"`` (or the builtin :func:`callable`), ``None``, a type such as ``str``, and
``"no_validation"``. Numbers are never judged by truthiness: ``True`` is not ``1`` for a
number, and NaN or infinity are never valid.

The built-in methods declare theirs in ``registry.toml`` (``type``, ``range``, ``choices``,
``none``: see :func:`from_manifest`), so ``faceretarget info`` and the README tables show
the same text (:func:`describe`) the errors use. Checks that involve several parameters,
or the data's shapes, stay in the method.
"""

from __future__ import annotations

import inspect
import math
from collections.abc import Iterable, Mapping
from dataclasses import dataclass
from typing import Any

import numpy as np

from ._validate import did_you_mean, short_repr
from .errors import ConfigError, ParameterError

__all__ = [
    "Interval",
    "Options",
    "ParameterError",
    "check_value",
    "constraints_of",
    "describe",
    "did_you_mean",
    "from_manifest",
    "make_constraint",
    "validate_params",
]


# -- the constraints -----------------------------------------------------------------------
@dataclass(frozen=True)
class Interval:
    """A finite number of ``kind`` (``float`` or ``int``) between ``left`` and ``right``
    (``None`` = unbounded on that side); ``closed`` is ``"both"``, ``"left"``, ``"right"`` or
    ``"neither"``. ``int`` accepts whole floats (``3.0``) and gives ``3``; ``bool`` is never
    a number."""

    #: ``float`` or ``int`` (also given as ``"float"``, ``"int"``, ``numbers.Real`` or
    #: ``numbers.Integral``; stored as ``float`` or ``int``)
    kind: type | str
    left: float | None = None
    right: float | None = None
    closed: str = "both"

    def __post_init__(self) -> None:
        kind: object = (
            {"float": float, "int": int}.get(self.kind, self.kind)
            if isinstance(self.kind, str)
            else self.kind
        )
        if kind not in (float, int):
            import numbers

            aliases: dict[object, type] = {numbers.Real: float, numbers.Integral: int}
            kind = aliases.get(kind)
        if kind is None:
            raise TypeError(f"Interval: kind must be float or int, got {self.kind!r}")
        object.__setattr__(self, "kind", kind)
        if self.closed not in ("both", "left", "right", "neither"):
            raise ValueError(
                f"Interval: closed must be 'both', 'left', 'right' or 'neither', got {self.closed!r}"
            )
        if self.left is not None and self.right is not None and self.left > self.right:
            raise ValueError(f"Interval: left {self.left} > right {self.right}")
        # an unbounded side is open: Interval(float, 0, None) == Interval(float, 0, None, closed="left")
        left_in = self.left is not None and self.closed in ("both", "left")
        right_in = self.right is not None and self.closed in ("both", "right")
        object.__setattr__(
            self,
            "closed",
            {(True, True): "both", (True, False): "left", (False, True): "right"}.get(
                (left_in, right_in), "neither"
            ),
        )

    def accepts(self, value: object) -> bool:
        if isinstance(value, (bool, np.bool_)) or not isinstance(
            value, (int, float, np.integer, np.floating)
        ):
            return False
        try:
            number = float(value)
        except OverflowError:
            return False
        if not math.isfinite(number) or (self.kind is int and not number.is_integer()):
            return False
        low_ok = (
            self.left is None
            or number > self.left
            or (number == self.left and self.closed in ("both", "left"))
        )
        high_ok = (
            self.right is None
            or number < self.right
            or (number == self.right and self.closed in ("both", "right"))
        )
        return low_ok and high_ok

    def convert(self, value: Any) -> int | float:
        return int(value) if self.kind is int else float(value)

    def __str__(self) -> str:
        what = "a whole number" if self.kind is int else "a finite number"
        lo, hi = self.left, self.right
        left_in, right_in = self.closed in ("both", "left"), self.closed in ("both", "right")
        if lo is not None and hi is not None:
            return f"{what} in {'[' if left_in else '('}{_num(lo)}, {_num(hi)}{']' if right_in else ')'}"
        if lo is not None:
            return f"{what} {'>=' if left_in else '>'} {_num(lo)}"
        if hi is not None:
            return f"{what} {'<=' if right_in else '<'} {_num(hi)}"
        return what


@dataclass(frozen=True)
class Options:
    """One of a fixed set of strings (case matters; a near miss gets "did you mean")."""

    options: tuple[str, ...]

    def __init__(self, options: Iterable[str]) -> None:
        items = sorted(options) if isinstance(options, (set, frozenset)) else list(options)
        if not items or not all(isinstance(o, str) for o in items):
            raise TypeError(f"Options: expected a non-empty collection of strings, got {options!r}")
        object.__setattr__(self, "options", tuple(dict.fromkeys(items)))

    def __eq__(self, other: object) -> bool:
        return isinstance(other, Options) and set(self.options) == set(other.options)

    def __hash__(self) -> int:
        return hash(frozenset(self.options))

    def accepts(self, value: object) -> bool:
        return isinstance(value, str) and value in self.options

    def convert(self, value: Any) -> Any:
        return value

    def __str__(self) -> str:
        return _either([repr(o) for o in self.options])


@dataclass(frozen=True)
class _Kind:
    """The named constraints (``"boolean"``, ``"array-like"``...), ``None`` and plain types."""

    name: str
    type: type | None = None

    def accepts(self, value: object) -> bool:
        if self.name == "none":
            return value is None
        if self.name == "boolean":
            return isinstance(value, (bool, np.bool_)) or (
                isinstance(value, (int, np.integer)) and value in (0, 1)
            )
        if self.name == "array-like":
            return value is not None and not isinstance(value, (str, bytes))
        if self.name == "mapping":
            return isinstance(value, Mapping)
        if self.name == "callable":
            return callable(value)
        if self.name == "no_validation":
            return True
        assert self.type is not None  # a "type" kind carries its type (make_constraint)
        return isinstance(value, self.type) and not (
            self.type is not bool and isinstance(value, bool)
        )

    def convert(self, value: Any) -> Any:
        return bool(value) if self.name == "boolean" else value

    def __str__(self) -> str:
        if self.type is not None:
            return "a string" if self.type is str else f"a {self.type.__name__}"
        return {
            "none": "None",
            "boolean": "True or False",
            "array-like": "an array",
            "mapping": "a mapping",
            "callable": "a callable",
            "no_validation": "any value",
        }[self.name]


_NAMED = {"boolean", "array-like", "mapping", "callable", "no_validation"}


def make_constraint(spec: object) -> Interval | Options | _Kind:
    """One constraint from its declaration (see the module docstring)."""
    if isinstance(spec, (Interval, Options, _Kind)):
        return spec
    if spec is None:
        return _Kind("none")
    if spec is callable:
        return _Kind("callable")
    if isinstance(spec, str) and spec in _NAMED:
        return _Kind(spec)
    if isinstance(spec, type):
        return _Kind("type", spec)
    raise TypeError(
        f"unknown parameter constraint {spec!r}; use Interval(...), Options(...), None, a type, or one of "
        f"{', '.join(map(repr, sorted(_NAMED)))}"
    )


def describe(constraints: Iterable[object]) -> str:
    """The valid values in words, as errors and ``faceretarget info`` show them
    (``"'auto' or a whole number in [0, 7]"``); ``""`` when anything goes."""
    parts: list[str] = []
    for c in map(make_constraint, constraints):
        if isinstance(c, Options):
            parts.extend(repr(o) for o in c.options)
        elif c != _Kind("no_validation"):
            parts.append(str(c))
    return _either(parts)


# -- checking ------------------------------------------------------------------------------
def check_value(value: Any, constraints: Iterable[object], name: str, who: str = "") -> Any:
    """``value`` converted by the first constraint it satisfies (``int``/``float``/``bool``);
    a :class:`ParameterError` naming ``who``, ``name``, the valid values and the value given
    (with "did you mean" for a near-miss string) otherwise. No constraints: anything goes."""
    items = [make_constraint(c) for c in constraints]
    if not items:
        return value
    for c in items:
        if c.accepts(value):
            return c.convert(value)
    options = [o for c in items if isinstance(c, Options) for o in c.options]
    where = f"{who}: " if who else ""
    raise ParameterError(
        f"{where}parameter {name!r}: expected {describe(items)}, got {short_repr(value)}{did_you_mean(value, options)}"
    )


def constraints_of(cls: type) -> dict[str, list]:
    """``cls.parameter_constraints`` (name -> list of constraints), ``{}`` if it declares none."""
    declared = getattr(cls, "parameter_constraints", None) or {}
    if not isinstance(declared, Mapping):
        raise ConfigError(
            f"{cls.__name__}.parameter_constraints must be a dict {{name: [constraints]}}, got {declared!r}"
        )
    return {
        k: [make_constraint(c) for c in (v if isinstance(v, (list, tuple)) else [v])]
        for k, v in declared.items()
    }


def validate_params(
    estimator: Any, params: Mapping[str, Any] | None = None, *, who: str | None = None
) -> dict[str, Any]:
    """Every constructor parameter of ``estimator`` (or the given ``params``) checked against
    its class's ``parameter_constraints``: ``{name: value}`` with numbers and flags converted
    (``3.0`` -> ``3`` for an ``int`` interval, ``np.True_`` -> ``True``). The first invalid one
    raises :class:`ParameterError` naming the method and the parameter."""
    cls = estimator if inspect.isclass(estimator) else type(estimator)
    if params is None:
        params = estimator.get_params()
    who = who or getattr(cls, "name", "") or cls.__name__
    constraints = constraints_of(cls)
    return {k: check_value(v, constraints.get(k, ()), k, who) for k, v in params.items()}


# -- the manifest form (registry.toml, a plugin's faceretarget.toml) ------------------------
#: ``type = ...`` in a manifest -> the constraint it stands for.
MANIFEST_TYPES = {
    "float": None,
    "int": None,
    "bool": "boolean",
    "str": str,
    "array": "array-like",
    "mapping": "mapping",
    "callable": "callable",
    "any": "no_validation",
}
_SPEC_KEYS = {"default", "doc", "type", "range", "choices", "none"}


def from_manifest(spec: Mapping[str, Any], where: str) -> list:
    """The constraints of one manifest parameter table, e.g.
    ``{ type = "float", range = "[0, inf)" }``, ``{ choices = ["a", "b"] }``,
    ``{ choices = ["auto"], type = "int", range = "[0, 7]" }``, ``{ type = "array", none = true }``.

    ``type``: one name or a list of ``float int bool str array mapping callable any``;
    ``range``: an interval for ``float``/``int`` (``"(0, 1]"``, ``"[0, inf)"``); ``choices``:
    strings; ``none = true``: None is valid. A table with none of these is not checked.
    Raises :class:`ConfigError` naming ``where``.
    """
    unknown = sorted(set(spec) - _SPEC_KEYS)
    if unknown:
        raise ConfigError(
            f"{where}: unknown key(s) {', '.join(map(repr, unknown))}; valid: {', '.join(sorted(_SPEC_KEYS))}"
        )
    out: list = []
    none = spec.get("none", False)
    if not isinstance(none, bool):
        raise ConfigError(f"{where}: none must be true or false")
    if none:
        out.append(_Kind("none"))
    choices = spec.get("choices")
    if choices is not None:
        if (
            not isinstance(choices, list)
            or not choices
            or not all(isinstance(c, str) for c in choices)
        ):
            raise ConfigError(f"{where}: choices must be a non-empty list of strings")
        out.append(Options(choices))
    kinds = spec.get("type", [])
    kinds = [kinds] if isinstance(kinds, str) else kinds
    if not isinstance(kinds, list) or not all(
        isinstance(k, str) and k in MANIFEST_TYPES for k in kinds
    ):
        raise ConfigError(
            f"{where}: type must be one of {', '.join(MANIFEST_TYPES)} (or a list of them), got {spec.get('type')!r}"
        )
    numeric = [k for k in kinds if k in ("float", "int")]
    if "range" in spec and len(numeric) != 1:
        raise ConfigError(
            f'{where}: range needs exactly one numeric type (type = "float" or "int")'
        )
    for kind in kinds:
        if kind in ("float", "int"):
            out.append(_interval(kind, spec.get("range", "(-inf, inf)"), where))
        else:
            out.append(make_constraint(MANIFEST_TYPES[kind]))
    if "default" in spec and out and not any(c.accepts(spec["default"]) for c in out):
        raise ConfigError(f"{where}: default {spec['default']!r} is not {describe(out)}")
    return out


def _interval(kind: str, text: object, where: str) -> Interval:
    """``"[0, 1e12]"``, ``"(0, inf)"``... -> :class:`Interval`."""
    bad = ConfigError(
        f'{where}: range must be an interval such as "[0, 1]", "(0, inf)" or "[-1, 1e6]", got {text!r}'
    )
    if (
        not isinstance(text, str)
        or len(text) < 5
        or text[0] not in "[("
        or text[-1] not in "])"
        or text.count(",") != 1
    ):
        raise bad
    try:
        lo, hi = (float(part) for part in text[1:-1].split(","))
    except ValueError:
        raise bad from None
    if math.isnan(lo) or math.isnan(hi) or lo > hi:
        raise bad
    closed = {
        (True, True): "both",
        (True, False): "left",
        (False, True): "right",
        (False, False): "neither",
    }[(text[0] == "[", text[-1] == "]")]
    try:
        return Interval(
            kind, None if lo == -math.inf else lo, None if hi == math.inf else hi, closed
        )
    except ValueError:
        raise bad from None


def _num(x: float) -> str:
    """``0``, ``0.5``, ``1000``, ``1e12``, ``1e-4``: short, and exact for the bounds in use."""
    text = f"{x:.6g}"
    if "e" in text:
        mantissa, exponent = text.split("e")
        text = f"{mantissa}e{int(exponent)}"
    return text


def _either(parts: list[str]) -> str:
    parts = list(dict.fromkeys(parts))
    return (
        parts[0] if len(parts) == 1 else ", ".join(parts[:-1]) + " or " + parts[-1] if parts else ""
    )
