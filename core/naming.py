"""Blendshape name mapping between naming conventions.

Rigs and capture tools name the same shape differently: ARKit ``eyeBlinkLeft``, Live
Link Face ``EyeBlinkLeft``, ICT-FaceKit ``eyeBlink_L``, Blender ``eyeBlink.L``, others
``L_eyeBlink`` or ``eyeblink_left``. :func:`map_names` pairs two name lists, first by an
explicit user mapping, then by rules of increasing looseness (the ``preset``):

``exact``  identical names;
``case``   + equal ignoring case;
``sides``  + equal after reading the side marker (``Left``/``Right``, ``_L``/``_R``,
           ``.L``, ``L_`` prefixes, trailing ``L``/``R``) and ignoring case and separators;
``auto``   (default) + *split/merge*: an unsided name maps to both sides when the other
           list only has sided versions (ARKit ``browInnerUp`` -> ICT ``browInnerUp_L``
           and ``browInnerUp_R``), and the two sides merge (averaged) into an unsided
           name the other way.

Nothing is dropped silently: the :class:`Mapping` result lists the names it could not
map (``unmapped``), the target names nothing maps to (``missing``) and the names a user
mapping explicitly ignores, and :meth:`Mapping.require_complete` raises
:class:`~faceretarget.errors.UnknownNameError` naming them.

``to_names`` may also be the name of a known set: ``"arkit"`` (the 52 ARKit shapes),
``"livelink"`` (the 61 Live Link Face CSV columns) or ``"ict"`` (the 53 ICT-FaceKit
expressions). :func:`rename` rewrites names into a convention's style.

User mapping files (:func:`load_mapping`): TOML or JSON objects ``{from = "to"}`` (a list
of targets for one-to-many, ``""`` to ignore a name), or a two-column CSV ``from,to``
(optional header, repeated rows for one-to-many).
"""

from __future__ import annotations

import csv
import io
import json
import re
import tomllib
from collections.abc import Iterable, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import TYPE_CHECKING, Any, overload

import numpy as np
import numpy.typing as npt

from ._types import PathLike
from .errors import ConfigError, InputError, UnknownNameError

if TYPE_CHECKING:
    from .model import WeightSequence

__all__ = [
    "ARKIT_NAMES",
    "ICT_NAMES",
    "LIVE_LINK_NAMES",
    "PRESETS",
    "Mapping",
    "map_names",
    "load_mapping",
    "canonical",
    "rename",
    "name_set",
]

#: the 52 ARKit blendshape locations, in Apple's documentation order
ARKIT_NAMES = (
    "eyeBlinkLeft",
    "eyeLookDownLeft",
    "eyeLookInLeft",
    "eyeLookOutLeft",
    "eyeLookUpLeft",
    "eyeSquintLeft",
    "eyeWideLeft",
    "eyeBlinkRight",
    "eyeLookDownRight",
    "eyeLookInRight",
    "eyeLookOutRight",
    "eyeLookUpRight",
    "eyeSquintRight",
    "eyeWideRight",
    "jawForward",
    "jawLeft",
    "jawRight",
    "jawOpen",
    "mouthClose",
    "mouthFunnel",
    "mouthPucker",
    "mouthLeft",
    "mouthRight",
    "mouthSmileLeft",
    "mouthSmileRight",
    "mouthFrownLeft",
    "mouthFrownRight",
    "mouthDimpleLeft",
    "mouthDimpleRight",
    "mouthStretchLeft",
    "mouthStretchRight",
    "mouthRollLower",
    "mouthRollUpper",
    "mouthShrugLower",
    "mouthShrugUpper",
    "mouthPressLeft",
    "mouthPressRight",
    "mouthLowerDownLeft",
    "mouthLowerDownRight",
    "mouthUpperUpLeft",
    "mouthUpperUpRight",
    "browDownLeft",
    "browDownRight",
    "browInnerUp",
    "browOuterUpLeft",
    "browOuterUpRight",
    "cheekPuff",
    "cheekSquintLeft",
    "cheekSquintRight",
    "noseSneerLeft",
    "noseSneerRight",
    "tongueOut",
)

#: Live Link Face CSV columns after Timecode and BlendShapeCount
LIVE_LINK_NAMES = (
    tuple(n[0].upper() + n[1:] for n in ARKIT_NAMES if not n.startswith("tongue"))
    + ("TongueOut",)
    + (
        "HeadYaw",
        "HeadPitch",
        "HeadRoll",
        "LeftEyeYaw",
        "LeftEyePitch",
        "LeftEyeRoll",
        "RightEyeYaw",
        "RightEyePitch",
        "RightEyeRoll",
    )
)


def _ict_names() -> tuple[str, ...]:
    out = []
    for n in ARKIT_NAMES:
        if n == "tongueOut":
            continue
        base, side = _split(n)
        if n in ("browInnerUp", "cheekPuff"):
            out += [f"{n}_L", f"{n}_R"]
        elif side is not None and not n.startswith(("jaw", "mouthLeft", "mouthRight")):
            out.append(f"{base}_{side}")
        else:
            out.append(n)
    return tuple(sorted(out, key=str.lower))


#: rules applied by each preset, in order
PRESETS = {
    "exact": ("exact",),
    "case": ("exact", "case"),
    "sides": ("exact", "case", "sides"),
    "auto": ("exact", "case", "sides", "split"),
}

_SIDE_WORD = {"left": "L", "right": "R", "l": "L", "r": "R"}
_SUFFIX_SEPARATED = re.compile(r"^(?P<stem>.+?)[_.\-\s](?P<side>left|right|l|r)$", re.IGNORECASE)
_SUFFIX_CAMEL = re.compile(r"^(?P<stem>.*[a-z0-9])(?P<side>Left|Right|LEFT|RIGHT|L|R)$")
_PREFIX = re.compile(r"^(?P<side>left|right|l|r)[_.\-\s](?P<stem>.+)$", re.IGNORECASE)
_PREFIX_CAMEL = re.compile(r"^(?P<side>Left|Right|left|right)(?P<stem>[A-Z].*)$")
_NON_ALNUM = re.compile(r"[^0-9a-z]+")


def _split(name: str) -> tuple[str, str | None]:
    """(stem, side 'L'/'R'/None) of a shape name, side markers removed."""
    n = name.strip()
    for pattern in (_SUFFIX_SEPARATED, _SUFFIX_CAMEL, _PREFIX, _PREFIX_CAMEL):
        m = pattern.match(n)
        if m and m.group("stem").strip("_.- "):
            return m.group("stem").strip("_.- "), _SIDE_WORD[m.group("side").lower()]
    return n, None


def canonical(name: str) -> tuple[str, str | None]:
    """Convention-free key of a shape name: (lower-case alphanumeric stem, side).

    ``eyeBlinkLeft``, ``EyeBlinkLeft``, ``eyeBlink_L``, ``eyeBlink.L`` and ``L_eyeBlink``
    all give ``("eyeblink", "L")``.
    """
    stem, side = _split(name)
    return _NON_ALNUM.sub("", stem.lower()), side


ICT_NAMES = _ict_names()

_SETS = {"arkit": ARKIT_NAMES, "livelink": LIVE_LINK_NAMES, "ict": ICT_NAMES}


def name_set(name: str) -> tuple[str, ...]:
    """A known name set: ``"arkit"``, ``"livelink"`` or ``"ict"``."""
    try:
        return _SETS[name.lower()]
    except (KeyError, AttributeError):
        raise UnknownNameError(f"no name set {name!r}; known sets: {', '.join(_SETS)}") from None


def rename(names: Iterable[str], style: str) -> tuple[str, ...]:
    """Rewrite names in a convention's style: ``"arkit"`` (eyeBlinkLeft), ``"livelink"``
    (EyeBlinkLeft), ``"ict"`` (eyeBlink_L) or ``"blender"`` (eyeBlink.L).

    ``jawLeft``/``mouthRight``-style direction names of ARKit keep their word form.
    """
    styles = ("arkit", "livelink", "ict", "blender")
    if style not in styles:
        raise UnknownNameError(f"no naming style {style!r}; styles: {', '.join(styles)}")
    out = []
    for name in names:
        stem, side = _split(name)
        directional = stem.lower() in ("jaw", "mouth")
        stem = stem[0].lower() + stem[1:] if stem else stem
        if side is None:
            new = stem
        elif style in ("arkit", "livelink") or directional:
            new = stem + ("Left" if side == "L" else "Right")
        elif style == "ict":
            new = f"{stem}_{side}"
        else:
            new = f"{stem}.{side}"
        if style == "livelink":
            new = new[0].upper() + new[1:]
        out.append(new)
    return tuple(out)


@dataclass(frozen=True)
class Mapping:
    """The result of :func:`map_names`.

    Attributes
    ----------
    from_names, to_names : tuple of str
    targets : dict from-name -> tuple of to-names (empty when unmapped or ignored)
    rules : dict from-name -> the rule that mapped it ("mapping", "exact", "case",
        "sides", "split", "merge")
    ignored : from-names a user mapping maps to nothing on purpose
    unused_rules : user-mapping entries whose from-name is not in ``from_names``
    """

    from_names: tuple[str, ...]
    to_names: tuple[str, ...]
    targets: dict[str, tuple[str, ...]]
    rules: dict[str, str] = field(default_factory=dict)
    ignored: tuple[str, ...] = ()
    unused_rules: tuple[str, ...] = ()

    @property
    def unmapped(self) -> tuple[str, ...]:
        """From-names that map to nothing (and are not explicitly ignored)."""
        return tuple(
            n for n in self.from_names if not self.targets.get(n) and n not in self.ignored
        )

    @property
    def missing(self) -> tuple[str, ...]:
        """To-names no from-name maps to."""
        hit = {t for ts in self.targets.values() for t in ts}
        return tuple(n for n in self.to_names if n not in hit)

    @property
    def pairs(self) -> tuple[tuple[str, str], ...]:
        return tuple((f, t) for f in self.from_names for t in self.targets.get(f, ()))

    @property
    def complete(self) -> bool:
        return not self.unmapped

    def __getitem__(self, name: str) -> tuple[str, ...]:
        if name not in self.targets:
            from ._validate import did_you_mean

            raise UnknownNameError(
                f"{name!r} is not one of the mapped names{did_you_mean(name, self.targets)}"
            )
        return self.targets[name]

    def matrix(self) -> np.ndarray:
        """``(len(to_names), len(from_names))`` float64: ``w_to = A @ w_from``.

        Each target is the average of the sources mapped to it (1 for one source,
        1/2 each when two sides merge); a source mapped to several targets (split)
        drives each fully.
        """
        col = {n: j for j, n in enumerate(self.from_names)}
        row = {n: i for i, n in enumerate(self.to_names)}
        a = np.zeros((len(self.to_names), len(self.from_names)))
        for f, t in self.pairs:
            a[row[t], col[f]] = 1.0
        counts = a.sum(axis=1, keepdims=True)
        return np.divide(a, counts, out=np.zeros_like(a), where=counts > 0)

    @overload
    def apply(self, weights: WeightSequence) -> WeightSequence: ...
    @overload
    def apply(self, weights: npt.ArrayLike) -> np.ndarray: ...
    def apply(self, weights: WeightSequence | npt.ArrayLike) -> WeightSequence | np.ndarray:
        """Weights over ``from_names`` -> weights over ``to_names``.

        ``weights``: ``(F, M_from)`` or ``(M_from,)`` array, or a
        :class:`~faceretarget.model.WeightSequence` (returns one over ``to_names``; its
        names must be ``from_names``). Targets nothing maps to get 0.
        """
        from .model import WeightSequence

        if isinstance(weights, WeightSequence):
            if tuple(weights.names) != self.from_names:
                raise InputError(
                    "Mapping.apply: the weight curves' names differ from the mapping's from_names"
                )
            return WeightSequence(self.apply(weights.weights), self.to_names, fps=weights.fps)
        w = np.asarray(weights, dtype=np.float64)
        if w.shape[-1] != len(self.from_names) or w.ndim not in (1, 2):
            raise InputError(
                f"Mapping.apply: expected (F, {len(self.from_names)}) weights, got {w.shape}"
            )
        return w @ self.matrix().T

    def report(self) -> str:
        """A readable summary: how many mapped, by which rule, and every unmapped name."""
        lines = [
            f"{len(self.from_names) - len(self.unmapped) - len(self.ignored)} of {len(self.from_names)} names mapped onto {len(self.to_names)}"
        ]
        by_rule: dict[str, int] = {}
        for r in self.rules.values():
            by_rule[r] = by_rule.get(r, 0) + 1
        if by_rule:
            lines.append("rules: " + ", ".join(f"{k} {v}" for k, v in sorted(by_rule.items())))
        if self.unmapped:
            lines.append("unmapped: " + ", ".join(self.unmapped))
        if self.missing:
            lines.append("targets without a source: " + ", ".join(self.missing))
        if self.ignored:
            lines.append("ignored by the mapping: " + ", ".join(self.ignored))
        if self.unused_rules:
            lines.append("mapping entries for absent names: " + ", ".join(self.unused_rules))
        return "\n".join(lines)

    def require_complete(self, what: str = "names") -> Mapping:
        """Raise :class:`UnknownNameError` unless every from-name is mapped (or ignored)."""
        if self.unmapped:
            raise UnknownNameError(
                f"{what}: {len(self.unmapped)} name(s) have no counterpart: {', '.join(self.unmapped[:20])}"
                f"{' ...' if len(self.unmapped) > 20 else ''}; available: {', '.join(self.to_names[:60])}. "
                "Pass a mapping file (from,to rows) or mapping={from: to}"
            )
        return self


def _as_names(names: str | Iterable[str], what: str) -> tuple[str, ...]:
    if isinstance(names, str):
        return name_set(names)
    try:
        out = tuple(names)
    except TypeError:
        raise InputError(
            f"{what}: expected a sequence of names or a set name ('arkit', 'livelink', 'ict')"
        ) from None
    if not all(isinstance(n, str) and n.strip() for n in out):
        raise InputError(f"{what}: every name must be a non-empty string")
    if len(set(out)) != len(out):
        dup = next(n for n in out if out.count(n) > 1)
        raise InputError(f"{what}: duplicate name {dup!r}")
    return out


def map_names(
    from_names: str | Iterable[str],
    to_names: str | Iterable[str],
    preset: str = "auto",
    mapping: dict[str, Any] | PathLike | None = None,
) -> Mapping:
    """Pair ``from_names`` with ``to_names``; see the module docstring for the rules.

    Parameters
    ----------
    from_names, to_names : sequence of str, or a known set name ("arkit", "livelink", "ict")
    preset : "exact", "case", "sides" or "auto"
    mapping : dict {from: to | [to, ...] | "" (ignore)}, or a path to a mapping file;
        applied first. Its to-names must exist in ``to_names``.

    Returns
    -------
    Mapping
        Never drops a name silently: see ``unmapped``, ``missing``, ``report()``.
    """
    src = _as_names(from_names, "map_names from_names")
    dst = _as_names(to_names, "map_names to_names")
    if preset not in PRESETS:
        raise UnknownNameError(f"no name-mapping preset {preset!r}; presets: {', '.join(PRESETS)}")
    explicit = (
        load_mapping(mapping)
        if isinstance(mapping, (str, Path))
        else _normalize_mapping(mapping or {}, "mapping")
    )
    dst_set = set(dst)
    for f, ts in explicit.items():
        unknown = [t for t in ts if t not in dst_set]
        if unknown:
            from ._validate import did_you_mean

            hints = "".join(did_you_mean(t, dst) for t in unknown)
            raise UnknownNameError(
                f"mapping: {f!r} -> {unknown} names no target shape{hints}; targets are: {', '.join(dst[:60])}"
            )
    targets: dict[str, tuple[str, ...]] = {}
    rules: dict[str, str] = {}
    ignored = []
    for f in src:
        if f in explicit:
            targets[f] = explicit[f]
            if explicit[f]:
                rules[f] = "mapping"
            else:
                ignored.append(f)
    unused = tuple(f for f in explicit if f not in set(src))
    steps = PRESETS[preset]
    by_case: dict[str, list[str]] = {}
    by_key: dict[tuple[str, str | None], list[str]] = {}
    for t in dst:
        by_case.setdefault(t.casefold(), []).append(t)
        by_key.setdefault(canonical(t), []).append(t)
    for f in src:
        if f in targets:
            continue
        found: tuple[str, ...] = ()
        rule: str | None = None
        if f in dst_set:
            found, rule = (f,), "exact"
        elif "case" in steps and len(by_case.get(f.casefold(), [])) == 1:
            found, rule = tuple(by_case[f.casefold()]), "case"
        elif "sides" in steps and len(by_key.get(canonical(f), [])) == 1:
            found, rule = tuple(by_key[canonical(f)]), "sides"
        elif "split" in steps:
            stem, side = canonical(f)
            if side is None and (stem, None) not in by_key:
                left, right = by_key.get((stem, "L"), []), by_key.get((stem, "R"), [])
                if len(left) == 1 and len(right) == 1:
                    found, rule = (left[0], right[0]), "split"
            elif (
                side is not None
                and len(by_key.get((stem, None), [])) == 1
                and not by_key.get((stem, side))
            ):
                found, rule = tuple(by_key[(stem, None)]), "merge"
        targets[f] = found
        if rule:
            rules[f] = rule
    return Mapping(src, dst, targets, rules, tuple(ignored), unused)


def _normalize_mapping(data: object, origin: str) -> dict[str, tuple[str, ...]]:
    if not isinstance(data, dict):
        raise ConfigError(
            f"{origin}: a name mapping must be a table/object of from-name -> to-name(s)"
        )
    out: dict[str, tuple[str, ...]] = {}
    for key, value in data.items():
        if not isinstance(key, str) or not key.strip():
            raise ConfigError(f"{origin}: every from-name must be a non-empty string, got {key!r}")
        if value is None or value == "":
            out[key] = ()
        elif isinstance(value, str):
            out[key] = (value,)
        elif isinstance(value, (list, tuple)) and all(isinstance(v, str) and v for v in value):
            out[key] = tuple(value)
        else:
            raise ConfigError(
                f'{origin}: {key!r} must map to a name, a list of names or "" (ignore), got {value!r}'
            )
    return out


def load_mapping(path: PathLike) -> dict[str, tuple[str, ...]]:
    """Read a user name-mapping file (``.toml``, ``.json`` or two-column ``.csv``).

    Returns from-name -> tuple of to-names (empty: ignore that name). Raises
    :class:`ConfigError` naming the file on any malformation.
    """
    p = Path(path)
    try:
        text = p.read_text(encoding="utf-8-sig")
    except FileNotFoundError:
        raise ConfigError(f"{p}: mapping file not found") from None
    except (OSError, UnicodeDecodeError) as exc:
        raise ConfigError(f"{p}: cannot read the mapping file ({exc})") from None
    suffix = p.suffix.lower()
    if suffix == ".toml":
        try:
            data = tomllib.loads(text)
        except tomllib.TOMLDecodeError as exc:
            raise ConfigError(f"{p}: not valid TOML ({exc})") from None
        if set(data) == {"mapping"} and isinstance(data["mapping"], dict):
            data = data["mapping"]
        return _normalize_mapping(data, str(p))
    if suffix == ".json":
        try:
            data = json.loads(text)
        except ValueError as exc:
            raise ConfigError(f"{p}: not valid JSON ({exc})") from None
        if isinstance(data, list):
            return _pairs_to_mapping(data, str(p))
        return _normalize_mapping(data, str(p))
    if suffix in (".csv", ".txt", ".tsv"):
        delimiter = "\t" if suffix == ".tsv" or ("\t" in text and "," not in text) else ","
        rows = [
            [c.strip() for c in r]
            for r in csv.reader(io.StringIO(text), delimiter=delimiter)
            if any(c.strip() for c in r)
        ]
        if rows and [c.lower() for c in rows[0][:2]] in (["from", "to"], ["source", "target"]):
            rows = rows[1:]
        return _pairs_to_mapping(rows, str(p))
    raise ConfigError(f"{p}: unknown mapping file type {suffix!r}; use .toml, .json or .csv")


def _pairs_to_mapping(rows: Sequence, origin: str) -> dict[str, tuple[str, ...]]:
    out: dict[str, list[str]] = {}
    for i, row in enumerate(rows, 1):
        if (
            not isinstance(row, (list, tuple))
            or len(row) not in (1, 2)
            or not all(isinstance(c, str) for c in row)
        ):
            raise ConfigError(f"{origin}: entry {i} must be two names (from, to); got {row!r:.60}")
        src = row[0].strip()
        if not src:
            raise ConfigError(f"{origin}: entry {i} has an empty from-name")
        dst = row[1].strip() if len(row) == 2 else ""
        targets = out.setdefault(src, [])
        if dst and dst not in targets:
            targets.append(dst)
    return {k: tuple(v) for k, v in out.items()}


#: A rig whose shape names are mostly (this fraction or more) ARKit / ICT / Live Link names
#: follows their convention of weights in [0, 1].
BOUNDED_CONVENTION_FRACTION = 0.5


def conventionally_bounded(names: Iterable[str]) -> bool:
    """True when ``names`` follow a naming convention whose weights are in [0, 1] (ARKit,
    ICT-FaceKit, Live Link Face), whatever the spelling (``eyeBlink_L``, ``EyeBlinkLeft``...)."""
    keys = {canonical(n) for names_ in _SETS.values() for n in names_}
    given = [canonical(str(n)) for n in names]
    if not given:
        return False
    return sum(k in keys for k in given) >= BOUNDED_CONVENTION_FRACTION * len(given)
