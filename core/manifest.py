"""Retargeter manifests: what a method is, read without importing its code (like napari's npe2).

A manifest is TOML with one table per retargeter::

    [retargeters.NAME]
    entry_point = "..."            the entry point (group "faceretarget") whose plugin provides it
    aliases = ["..."]              other names accepted by faceretarget.get()
    paper = "..."                  citation
    summary = "..."                one line for `faceretarget list`
    baseline_of = ["..."]          optional: the methods this one is the papers' baseline of
    [retargeters.NAME.capabilities] sources, needs, outputs, stream, edit, same_topology
    [retargeters.NAME.parameters]  PARAM = { default = ..., type = ..., range = ..., choices = [...], doc = "..." }

The built-ins' manifest is ``registry.toml``, shipped inside the package. A third-party
plugin may ship one as ``faceretarget.toml`` in the package its entry point names
(:func:`find_package_manifest` finds it without importing anything; ``entry_point`` may be
left out there); one that does not is described by its class (:func:`from_class`). The
registry checks that a class and its manifest agree (:func:`disagreements`).
"""

from __future__ import annotations

import importlib.util
import tomllib
from dataclasses import dataclass, field
from functools import lru_cache
from importlib import resources
from pathlib import Path
from typing import Any

from . import validation
from .capabilities import RIG_PARTS, SOURCE_EXTRAS, SOURCE_KINDS, Capabilities
from .errors import ConfigError

__all__ = [
    "Manifest",
    "Parameter",
    "parse",
    "builtin",
    "builtin_text",
    "constraints",
    "find_package_manifest",
    "from_class",
    "disagreements",
]

#: File name of a third-party plugin's manifest, next to its package's ``__init__.py``.
PACKAGE_MANIFEST = "faceretarget.toml"


@dataclass(frozen=True)
class Parameter:
    """One constructor parameter: its default, constraints and one-line meaning."""

    name: str
    default: Any = None
    constraints: tuple = ()
    doc: str = ""

    @property
    def valid(self) -> str:
        """The valid values in words (empty when the method checks them itself)."""
        return validation.describe(self.constraints)


@dataclass(frozen=True)
class Manifest:
    """One retargeter's manifest entry."""

    name: str
    entry_point: str
    summary: str
    paper: str = ""
    aliases: tuple[str, ...] = ()
    capabilities: Capabilities = Capabilities()
    parameters: dict[str, Parameter] = field(default_factory=dict)
    origin: str = ""
    #: The (paper) methods this one is a baseline of, as in their papers' comparisons.
    baseline_of: tuple[str, ...] = ()

    @property
    def defaults(self) -> dict[str, Any]:
        return {name: p.default for name, p in self.parameters.items()}

    @classmethod
    def from_entry(cls, name: str, entry: dict[str, Any], origin: str) -> Manifest:
        """From one table of :func:`parse`'s result."""
        params = {
            p: Parameter(
                p,
                spec.get("default"),
                tuple(validation.from_manifest(spec, f"{origin}: {name}.{p}")),
                spec["doc"],
            )
            for p, spec in entry["parameters"].items()
        }
        return cls(
            name,
            entry["entry_point"],
            entry["summary"],
            entry["paper"],
            tuple(entry["aliases"]),
            Capabilities.from_dict(entry["capabilities"]),
            params,
            origin,
            tuple(entry["baseline_of"]),
        )


def parse(
    text: str, origin: str, defaults: dict[str, Any] | None = None
) -> dict[str, dict[str, Any]]:
    """Parse manifest TOML: name -> entry with keys ``entry_point``, ``aliases``, ``paper``,
    ``summary``, ``capabilities``, ``parameters``. ``defaults`` fills missing top-level keys
    (a package manifest's ``entry_point``). Raises :class:`ConfigError` naming ``origin``."""
    if not isinstance(text, str):
        raise ConfigError(f"{origin}: expected TOML text, got {type(text).__name__}")
    try:
        data = tomllib.loads(text)
    except (tomllib.TOMLDecodeError, UnicodeError, TypeError) as exc:
        raise ConfigError(f"{origin}: not valid TOML ({exc})") from None
    entries = data.get("retargeters")
    if not isinstance(entries, dict):
        raise ConfigError(f"{origin}: needs a [retargeters.NAME] table per retargeter")
    out = {}
    for name, entry in entries.items():
        if not isinstance(entry, dict):
            raise ConfigError(f"{origin}: [retargeters.{name}] must be a table")
        entry = {**(defaults or {}), **entry}
        for key in ("entry_point", "summary", "paper"):
            if not isinstance(entry.get(key), str):
                raise ConfigError(f"{origin}: [retargeters.{name}] needs a string {key!r}")
        aliases, baseline_of = entry.get("aliases", []), entry.get("baseline_of", [])
        for key, value in (("aliases", aliases), ("baseline_of", baseline_of)):
            if not isinstance(value, list) or not all(isinstance(a, str) for a in value):
                raise ConfigError(f"{origin}: [retargeters.{name}].{key} must be a list of strings")
        params = entry.get("parameters", {})
        if not isinstance(params, dict) or not all(
            isinstance(v, dict) and isinstance(v.get("doc"), str) for v in params.values()
        ):
            raise ConfigError(
                f"{origin}: [retargeters.{name}.parameters] entries must be tables with a 'doc' string (and 'default')"
            )
        for p, spec in params.items():
            validation.from_manifest(spec, f"{origin}: [retargeters.{name}.parameters] {p}")
        caps = entry.get("capabilities", {})
        if not isinstance(caps, dict):
            raise ConfigError(f"{origin}: [retargeters.{name}.capabilities] must be a table")
        _check_capabilities(caps, f"{origin}: [retargeters.{name}.capabilities]")
        out[name] = {
            **entry,
            "aliases": aliases,
            "baseline_of": baseline_of,
            "parameters": params,
            "capabilities": caps,
        }
    return out


def _check_capabilities(caps: dict, where: str) -> None:
    """Raise ConfigError unless ``caps`` is a valid ``Capabilities.as_dict()`` table."""
    unknown = sorted(set(caps) - {"sources", "needs", "outputs", "stream", "edit", "same_topology"})
    if unknown:
        raise ConfigError(f"{where}: unknown key(s) {', '.join(map(repr, unknown))}")
    sources = caps.get("sources", ["markers"])
    if not isinstance(sources, list) or not all(
        isinstance(s, str) and s in SOURCE_KINDS for s in sources
    ):
        raise ConfigError(f"{where}: sources must be a list of {', '.join(SOURCE_KINDS)}")
    needs = caps.get("needs", [])
    valid = RIG_PARTS + SOURCE_EXTRAS
    if not isinstance(needs, list) or not all(
        (isinstance(n, str) and n in valid)
        or (isinstance(n, list) and n and all(isinstance(o, str) and o in valid for o in n))
        for n in needs
    ):
        raise ConfigError(
            f"{where}: needs must be a list of {', '.join(valid)} (or lists of alternatives)"
        )
    if caps.get("outputs", "vertices") not in ("weights", "vertices"):
        raise ConfigError(f'{where}: outputs must be "weights" or "vertices"')
    for key in ("stream", "edit", "same_topology"):
        if not isinstance(caps.get(key, False), bool):
            raise ConfigError(f"{where}: {key} must be true or false")


# -- the built-ins: registry.toml ----------------------------------------------------------
def builtin_text() -> str:
    """The text of the packaged ``registry.toml``."""
    try:
        return resources.files("faceretarget").joinpath("registry.toml").read_text(encoding="utf-8")
    except (FileNotFoundError, OSError) as exc:
        raise ConfigError(
            f"registry.toml: not found inside the installed package ({exc}); reinstall faceretarget"
        ) from None


@lru_cache(maxsize=1)
def builtin() -> dict[str, Manifest]:
    """The built-in retargeters' manifests (``registry.toml``), by name."""
    return {
        name: Manifest.from_entry(name, entry, "registry.toml")
        for name, entry in parse(builtin_text(), "registry.toml").items()
    }


def constraints(name: str) -> dict[str, list]:
    """``parameter_constraints`` of the built-in retargeter ``name``, from ``registry.toml``
    (a built-in class sets ``parameter_constraints = manifest.constraints("its name")``)."""
    return {p: list(spec.constraints) for p, spec in builtin()[name].parameters.items()}


# -- third-party plugins -------------------------------------------------------------------
def find_package_manifest(module: str) -> Path | None:
    """``faceretarget.toml`` in the package (or next to the module) an entry point names,
    found through the import system's finders without importing anything; None if absent."""
    top, *rest = module.split(":")[0].strip().split(".")
    try:
        spec = importlib.util.find_spec(top)
    except (ImportError, ValueError):
        return None
    if spec is None:
        return None
    if spec.submodule_search_locations:
        folders = [Path(p) for p in spec.submodule_search_locations]
    elif spec.origin and spec.has_location:
        folders = [Path(spec.origin).parent]
    else:
        return None
    for part in rest:  # walk down sub-packages by path, never importing the parent
        folders = [f / part for f in folders if (f / part).is_dir()] or folders
    for folder in folders:
        path = folder / PACKAGE_MANIFEST
        if path.is_file():
            return path
    return None


def from_class(cls: Any, entry_point: str = "") -> Manifest:
    """The manifest a class (a :class:`~faceretarget.retargeter.Retargeter` subclass, typed
    ``Any`` so that this module stays below the retargeter's) declares on itself: ``name``, ``summary`` (else its docstring's
    first line), ``paper``, ``aliases``, ``baseline_of``, ``capabilities``, ``parameter_docs``,
    ``parameter_constraints`` and its ``__init__`` defaults."""
    declared = validation.constraints_of(cls)
    docs = dict(getattr(cls, "parameter_docs", {}) or {})
    params = {
        p: Parameter(p, default, tuple(declared.get(p, ())), docs.get(p, ""))
        for p, default in cls.default_params().items()
    }
    summary = getattr(cls, "summary", "") or (cls.__doc__ or "").strip().split("\n")[0]
    return Manifest(
        cls.name,
        entry_point,
        summary,
        getattr(cls, "paper", "") or "",
        tuple(getattr(cls, "aliases", ()) or ()),
        cls.capabilities,
        params,
        f"class {cls.__module__}.{cls.__qualname__}",
        tuple(getattr(cls, "baseline_of", ()) or ()),
    )


def disagreements(cls: Any, manifest: Manifest) -> list[str]:
    """Where ``cls`` and its ``manifest`` differ: capabilities, parameter names, defaults and
    (when the class declares them) constraints. Empty when they agree."""
    out = []
    if cls.capabilities != manifest.capabilities:
        out.append(
            f"capabilities: class {cls.capabilities.as_dict()}, manifest {manifest.capabilities.as_dict()}"
        )
    defaults = cls.default_params()
    only_class = sorted(set(defaults) - set(manifest.parameters))
    only_manifest = sorted(set(manifest.parameters) - set(defaults))
    if only_class:
        out.append(f"parameter(s) {', '.join(only_class)} in __init__ but not in the manifest")
    if only_manifest:
        out.append(f"parameter(s) {', '.join(only_manifest)} in the manifest but not in __init__")
    declared = validation.constraints_of(cls)
    for p in sorted(set(defaults) & set(manifest.parameters)):
        spec = manifest.parameters[p]
        if not _same_default(defaults[p], spec.default):
            out.append(
                f"parameter {p!r}: default {defaults[p]!r} in __init__, {spec.default!r} in the manifest"
            )
        if p in declared and set(declared[p]) != set(spec.constraints):
            out.append(
                f"parameter {p!r}: class accepts {validation.describe(declared[p]) or 'anything'}, "
                f"the manifest {spec.valid or 'anything'}"
            )
    return out


def _same_default(a: object, b: object) -> bool:
    numbers = (
        isinstance(a, (int, float))
        and isinstance(b, (int, float))
        and isinstance(a, bool) == isinstance(b, bool)
    )
    if type(a) is not type(b) and not numbers:
        return False
    try:
        return bool(a == b)
    except Exception:
        return a is b
