"""The plugin manager: built-ins and third-party plugins through one entry-point group.

Loading order (as in pluggy's own ``load_setuptools_entrypoints``, with error isolation):

1. Entry points of the ``faceretarget`` group that belong to the faceretarget
   distribution itself (the built-ins): any error is fatal, it is our bug.
2. Every other distribution's entry points (third-party): an import error or an
   invalid hook is *recorded* (``Registry.failures``) and shown by ``faceretarget
   list``; it never stops the others. ``FACERETARGET_DISABLE_PLUGINS=1`` skips them,
   ``FACERETARGET_PLUGINS=name,dist`` allows only those. A third-party plugin whose
   import or registration hooks take longer than ``FACERETARGET_IMPORT_TIMEOUT``
   seconds (default 60) is interrupted and recorded the same way.
3. ``check_pending()`` after each plugin: a hook implementation whose name matches no
   hookspec is reported against the plugin that brought it.

``registry.toml`` (shipped inside the package) adds the catalogue data of the
built-in retargeters: aliases, paper, summary and parameter documentation.
``FACERETARGET_TRACE=1`` prints every hook call.
"""
from __future__ import annotations

import importlib.metadata as md
import inspect
import sys
import tomllib
from contextlib import nullcontext
from dataclasses import dataclass, field
from importlib import resources
from typing import Any

import pluggy

from . import config
from ._validate import did_you_mean
from ._deadline import DeadlineExpired, deadline, grace_for, watchdog_process
from .errors import ConfigError, DuplicatePluginError, PluginError, PluginLoadError, PluginTimeoutError, UnknownNameError
from .hookspecs import DATA_KINDS, PROJECT, FaceRetargetSpec, Metric, Reader, Writer
from .retargeter import RIG_PARTS, SOURCE_EXTRAS, SOURCE_KINDS, Capabilities, Retargeter

__all__ = ["Registry", "PluginInfo", "RetargeterInfo", "registry", "reload", "read_catalogue"]

DISTRIBUTION = "faceretarget"


@dataclass
class PluginInfo:
    """One loaded (or failed) plugin."""

    name: str
    distribution: str
    version: str
    builtin: bool
    error: str | None = None

    @property
    def origin(self) -> str:
        return f"{self.distribution} {self.version}"


@dataclass
class RetargeterInfo:
    """A registered retargeter class with its catalogue data."""

    name: str
    cls: type
    plugin: PluginInfo
    aliases: tuple[str, ...] = ()
    summary: str = ""
    paper: str = ""
    parameter_docs: dict[str, str] = field(default_factory=dict)

    @property
    def capabilities(self) -> Capabilities:
        return self.cls.capabilities

    @property
    def defaults(self) -> dict[str, Any]:
        return self.cls.default_params()

    def as_dict(self) -> dict[str, Any]:
        return {
            "name": self.name,
            "aliases": list(self.aliases),
            "summary": self.summary,
            "paper": self.paper,
            "builtin": self.plugin.builtin,
            "origin": self.plugin.origin,
            "plugin": self.plugin.name,
            "capabilities": self.capabilities.as_dict(),
        }


def read_catalogue(text: str | None = None, origin: str = "registry.toml") -> dict[str, dict[str, Any]]:
    """Parse ``registry.toml`` (the packaged copy unless ``text`` is given).

    Returns name -> entry with keys ``entry_point``, ``aliases``, ``paper``, ``summary``,
    ``capabilities``, ``parameters``. Raises :class:`ConfigError` on any malformation.
    """
    if text is None:
        try:
            text = resources.files("faceretarget").joinpath("registry.toml").read_text(encoding="utf-8")
        except (FileNotFoundError, OSError) as exc:
            raise ConfigError(f"{origin}: not found inside the installed package ({exc}); reinstall faceretarget") from None
    if not isinstance(text, str):
        raise ConfigError(f"{origin}: expected TOML text, got {type(text).__name__}")
    try:
        data = tomllib.loads(text)
    except (tomllib.TOMLDecodeError, UnicodeError, TypeError) as exc:
        raise ConfigError(f"{origin}: not valid TOML ({exc})") from None
    entries = data.get("retargeters")
    if not isinstance(entries, dict):
        raise ConfigError(f"{origin}: needs a [retargeters.NAME] table per built-in retargeter")
    out = {}
    for name, entry in entries.items():
        if not isinstance(entry, dict):
            raise ConfigError(f"{origin}: [retargeters.{name}] must be a table")
        for key, kind in (("entry_point", str), ("summary", str), ("paper", str)):
            if not isinstance(entry.get(key), kind):
                raise ConfigError(f"{origin}: [retargeters.{name}] needs a string {key!r}")
        aliases = entry.get("aliases", [])
        if not isinstance(aliases, list) or not all(isinstance(a, str) for a in aliases):
            raise ConfigError(f"{origin}: [retargeters.{name}].aliases must be a list of strings")
        params = entry.get("parameters", {})
        if not isinstance(params, dict) or not all(isinstance(v, dict) and isinstance(v.get("doc"), str) for v in params.values()):
            raise ConfigError(f"{origin}: [retargeters.{name}.parameters] entries must be tables with a 'doc' string (and 'default')")
        caps = entry.get("capabilities", {})
        if not isinstance(caps, dict):
            raise ConfigError(f"{origin}: [retargeters.{name}.capabilities] must be a table")
        _check_capabilities(caps, f"{origin}: [retargeters.{name}.capabilities]")
        out[name] = {**entry, "aliases": aliases, "parameters": params, "capabilities": caps}
    return out


def _check_capabilities(caps: dict, where: str) -> None:
    """Raise ConfigError unless ``caps`` is a valid ``Capabilities.as_dict()`` table."""
    unknown = sorted(set(caps) - {"sources", "needs", "outputs", "stream", "edit", "same_topology"})
    if unknown:
        raise ConfigError(f"{where}: unknown key(s) {', '.join(map(repr, unknown))}")
    sources = caps.get("sources", ["markers"])
    if not isinstance(sources, list) or not all(isinstance(s, str) and s in SOURCE_KINDS for s in sources):
        raise ConfigError(f"{where}: sources must be a list of {', '.join(SOURCE_KINDS)}")
    needs = caps.get("needs", [])
    valid = RIG_PARTS + SOURCE_EXTRAS
    if not isinstance(needs, list) or not all(
        (isinstance(n, str) and n in valid) or (isinstance(n, list) and n and all(isinstance(o, str) and o in valid for o in n))
        for n in needs
    ):
        raise ConfigError(f"{where}: needs must be a list of {', '.join(valid)} (or lists of alternatives)")
    if caps.get("outputs", "vertices") not in ("weights", "vertices"):
        raise ConfigError(f"{where}: outputs must be \"weights\" or \"vertices\"")
    for key in ("stream", "edit", "same_topology"):
        if not isinstance(caps.get(key, False), bool):
            raise ConfigError(f"{where}: {key} must be true or false")


class Registry:
    """Everything the installed plugins provide. Build with :func:`registry`."""

    def __init__(self):
        self.pm = pluggy.PluginManager(PROJECT)
        self.pm.add_hookspecs(FaceRetargetSpec)
        if config.env_flag(config.ENV_TRACE):
            self.pm.trace.root.setwriter(lambda s: sys.stderr.write(s))
            self.pm.enable_tracing()
        self.plugins: list[PluginInfo] = []
        self.failures: list[PluginInfo] = []
        self.retargeters: dict[str, RetargeterInfo] = {}
        self.aliases: dict[str, str] = {}
        self.readers: list[tuple[Reader, PluginInfo]] = []
        self.writers: list[tuple[Writer, PluginInfo]] = []
        self.metrics: dict[str, tuple[Metric, PluginInfo]] = {}
        self.catalogue = read_catalogue()

    # -- loading ---------------------------------------------------------------------
    def load(self, extra: list[tuple[str, Any]] | None = None) -> "Registry":
        """Load built-in then third-party entry points (and ``extra`` (name, module) pairs)."""
        eps = sorted(md.entry_points(group=PROJECT), key=lambda ep: ep.name)
        builtin = [ep for ep in eps if _dist_name(ep) == DISTRIBUTION]
        external = [ep for ep in eps if _dist_name(ep) != DISTRIBUTION]
        for ep in builtin:
            info = PluginInfo(ep.name, DISTRIBUTION, _dist_version(ep), builtin=True)
            try:
                module = ep.load()
            except Exception as exc:
                raise PluginLoadError(f"built-in plugin {ep.name!r} ({ep.value}) failed to import: {exc!r}") from exc
            self._register(module, info, fatal=True)
        if not config.env_flag(config.ENV_DISABLE_PLUGINS):
            allow = {a.strip() for a in _env(config.ENV_PLUGIN_ALLOWLIST).split(",") if a.strip()}
            limit = config.seconds_setting(config.ENV_IMPORT_TIMEOUT, config.DEFAULT_IMPORT_TIMEOUT)
            with watchdog_process() if (limit and external) else nullcontext():
                self._load_external(external, allow, limit)
        for name, module in extra or []:
            self._register(module, PluginInfo(name, "local", "-", builtin=False), fatal=False)
        self._check_catalogue()
        return self

    def _load_external(self, external: list, allow: set, limit: float | None) -> None:
        """Import and register third-party entry points, each under :func:`deadline`: one
        that overruns ``limit`` is skipped, one that cannot even be interrupted ends the
        program with a message naming it (:mod:`faceretarget._deadline`, layers 3-4)."""
        for ep in external:
            info = PluginInfo(ep.name, _dist_name(ep) or "unknown", _dist_version(ep), builtin=False)
            if allow and ep.name not in allow and info.distribution not in allow:
                continue
            try:
                with deadline(limit, hard=_stuck(info, limit, "importing")):
                    module = ep.load()
            except DeadlineExpired:
                self._fail(info, _too_slow(info, limit, "importing"), fatal=False)
                continue
            except BaseException as exc:  # a plugin may even call sys.exit on import
                if isinstance(exc, KeyboardInterrupt):
                    raise
                info.error = f"failed to import {ep.value!r}: {type(exc).__name__}: {exc}"
                self.failures.append(info)
                continue
            before = self._snapshot()
            try:
                with deadline(limit, hard=_stuck(info, limit, "calling its registration hooks")):
                    self._register(module, info, fatal=False)
            except DeadlineExpired:  # roll back whatever it had registered
                self._restore(before)
                if self.pm.is_registered(module):
                    self.pm.unregister(module)
                self._fail(info, _too_slow(info, limit, "calling its registration hooks"), fatal=False)

    def _snapshot(self) -> tuple:
        return (dict(self.retargeters), dict(self.aliases), len(self.readers), len(self.writers), dict(self.metrics), len(self.plugins), len(self.failures))

    def _restore(self, snapshot: tuple) -> None:
        retargeters, aliases, n_readers, n_writers, metrics, n_plugins, n_failures = snapshot
        self.retargeters, self.aliases, self.metrics = retargeters, aliases, metrics
        del self.readers[n_readers:], self.writers[n_writers:], self.plugins[n_plugins:], self.failures[n_failures:]

    def _register(self, module: Any, info: PluginInfo, *, fatal: bool) -> None:
        try:
            self.pm.register(module, name=info.name)
            self.pm.check_pending()
        except (pluggy.PluginValidationError, ValueError) as exc:
            if self.pm.is_registered(module):
                self.pm.unregister(module)
            self._fail(info, f"invalid hook implementation: {exc}", fatal)
            return
        others = [p for p in self.pm.get_plugins() if p is not module]
        staged: dict[str, list] = {}
        for hook in ("faceretarget_retargeters", "faceretarget_readers", "faceretarget_writers", "faceretarget_metrics"):
            caller = self.pm.subset_hook_caller(hook, remove_plugins=others)
            try:
                results = caller()
            except (KeyboardInterrupt, DeadlineExpired):
                raise
            except BaseException as exc:  # incl. SystemExit from a plugin's hook
                self.pm.unregister(module)
                self._fail(info, f"hook {hook} raised {type(exc).__name__}: {exc}", fatal)
                return
            try:  # a hook returns a list (or None); anything else is the plugin's bug, not ours
                staged[hook] = _hook_items(results, hook, info)
            except PluginError as exc:
                self.pm.unregister(module)
                self._fail(info, str(exc), fatal, exc)
                return
            except (KeyboardInterrupt, DeadlineExpired):
                raise
            except BaseException as exc:  # a result whose iteration or repr raises
                self.pm.unregister(module)
                error = PluginLoadError(f"plugin {info.name!r} ({info.origin}), hook {hook}: its result cannot be read: {type(exc).__name__}: {exc}")
                self._fail(info, str(error), fatal, error)
                return
        try:
            entries = [self._validate_retargeter(cls, info) for cls in staged["faceretarget_retargeters"]]
            readers = [self._validate_record(r, Reader, "faceretarget_readers", info) for r in staged["faceretarget_readers"]]
            writers = [self._validate_record(w, Writer, "faceretarget_writers", info) for w in staged["faceretarget_writers"]]
            metrics = [self._validate_record(m, Metric, "faceretarget_metrics", info) for m in staged["faceretarget_metrics"]]
            self._check_duplicates(entries, metrics, info)
        except PluginError as exc:
            self.pm.unregister(module)
            self._fail(info, str(exc), fatal, exc)
            return
        except (KeyboardInterrupt, DeadlineExpired):
            raise
        except BaseException as exc:  # a class attribute of the plugin's that raises or has the wrong type
            self.pm.unregister(module)
            error = PluginLoadError(f"plugin {info.name!r} ({info.origin}): what its hooks returned is invalid: {type(exc).__name__}: {exc}")
            self._fail(info, str(error), fatal, error)
            return
        for entry in entries:
            self.retargeters[entry.name] = entry
            for alias in entry.aliases:
                self.aliases[alias.lower()] = entry.name
        self.readers.extend((r, info) for r in readers)
        self.writers.extend((w, info) for w in writers)
        for m in metrics:
            self.metrics[m.name] = (m, info)
        self.plugins.append(info)

    def _fail(self, info: PluginInfo, message: str, fatal: bool, exc: Exception | None = None) -> None:
        info.error = message
        if fatal:
            if isinstance(exc, PluginError):
                raise exc
            raise PluginLoadError(f"built-in plugin {info.name!r}: {message}")
        self.failures.append(info)

    def _validate_retargeter(self, cls: Any, info: PluginInfo) -> RetargeterInfo:
        where = f"plugin {info.name!r} ({info.origin}), hook faceretarget_retargeters"
        if not (inspect.isclass(cls) and issubclass(cls, Retargeter)):
            raise PluginLoadError(f"{where}: returned {cls!r}, which is not a faceretarget.Retargeter subclass")
        if not isinstance(cls.name, str) or not cls.name.strip() or cls.name != cls.name.strip():
            raise PluginLoadError(f"{where}: {cls.__name__} has no valid `name` class attribute")
        if not isinstance(cls.capabilities, Capabilities):
            raise PluginLoadError(f"{where}: {cls.__name__}.capabilities must be a faceretarget.Capabilities")
        init = cls.__init__
        sig = inspect.signature(init) if init is not object.__init__ else inspect.Signature()
        for p in sig.parameters.values():
            if p.name == "self" or p.kind == p.VAR_KEYWORD:
                continue
            if p.kind != p.KEYWORD_ONLY or p.default is p.empty:
                raise PluginLoadError(
                    f"{where}: {cls.__name__}.__init__ parameter {p.name!r} must be keyword-only with a default"
                )
        entry = self.catalogue.get(cls.name) if info.builtin else None
        if entry is not None:
            docs = {k: v.get("doc", "") for k, v in entry["parameters"].items()}
            return RetargeterInfo(cls.name, cls, info, tuple(entry["aliases"]), entry["summary"], entry["paper"], docs)
        return RetargeterInfo(cls.name, cls, info, tuple(getattr(cls, "aliases", ())), cls.summary or (cls.__doc__ or "").strip().split("\n")[0], getattr(cls, "paper", ""), dict(cls.parameter_docs))

    @staticmethod
    def _validate_record(record: Any, kind: type, hook: str, info: PluginInfo):
        where = f"plugin {info.name!r} ({info.origin}), hook {hook}"
        if not isinstance(record, kind):
            raise PluginLoadError(f"{where}: returned {record!r}, not a faceretarget.{kind.__name__}")
        if not isinstance(record.name, str) or not record.name.strip():
            raise PluginLoadError(f"{where}: a {kind.__name__} needs a non-empty string name, got {record.name!r}")
        call = {Reader: "read", Writer: "write", Metric: "compute"}[kind]
        if not callable(getattr(record, call, None)):
            raise PluginLoadError(f"{where}: {record.name!r} has no callable {call}")
        if not isinstance(record.description, str):
            raise PluginLoadError(f"{where}: {record.name!r}: description must be a string, got {record.description!r}")
        if kind is Metric:
            if record.better not in ("lower", "higher", "none") or not isinstance(record.unit, str):
                raise PluginLoadError(f"{where}: metric {record.name!r}: better must be \"lower\", \"higher\" or \"none\" and unit a string")
            if record.why_not is not None and not callable(record.why_not):
                raise PluginLoadError(f"{where}: metric {record.name!r}: why_not must be callable or None")
        else:
            if record.kind not in DATA_KINDS:
                raise PluginLoadError(f"{where}: {record.name!r}: kind must be one of {', '.join(DATA_KINDS)}, got {record.kind!r}")
            exts = record.extensions
            if not isinstance(exts, (tuple, list)) or not exts or not all(isinstance(e, str) and e for e in exts):
                raise PluginLoadError(f"{where}: {record.name!r}: extensions must be a non-empty tuple of strings like (\".obj\",), got {exts!r}")
            priority = getattr(record, "priority", 0)
            if isinstance(priority, bool) or not isinstance(priority, (int, float)) or priority != priority:
                raise PluginLoadError(f"{where}: {record.name!r}: priority must be a number (higher wins; built-ins have 0), got {priority!r}")
            accepts = getattr(record, "accepts", None)
            if accepts is not None and not callable(accepts):
                raise PluginLoadError(f"{where}: {record.name!r}: accepts must be a callable accepts(path) -> bool or None, got {accepts!r}")
        return record

    def _check_duplicates(self, entries: list[RetargeterInfo], metrics: list[Metric], info: PluginInfo) -> None:
        seen = {}
        for entry in entries:
            for key in (entry.name, *entry.aliases):
                k = key.lower()
                owner = self.retargeters.get(self.aliases.get(k, key)) or self.retargeters.get(key)
                if owner is None:
                    owner = next((e for e in self.retargeters.values() if e.name.lower() == k), None)
                if owner is not None or k in seen:
                    other = owner.plugin if owner else info
                    raise DuplicatePluginError(
                        f"retargeter name {key!r} from plugin {info.name!r} ({info.origin}) is already registered by "
                        f"plugin {other.name!r} ({other.origin}); rename one of them"
                    )
                seen[k] = entry
        for m in metrics:
            if m.name in self.metrics:
                other = self.metrics[m.name][1]
                raise DuplicatePluginError(
                    f"metric {m.name!r} from plugin {info.name!r} ({info.origin}) is already registered by "
                    f"plugin {other.name!r} ({other.origin})"
                )

    def _check_catalogue(self) -> None:
        for name, entry in self.catalogue.items():
            if name not in self.retargeters:
                raise ConfigError(
                    f"registry.toml lists retargeter {name!r} (entry point {entry['entry_point']!r}) but no built-in plugin provides it"
                )

    # -- queries ---------------------------------------------------------------------
    def resolve(self, name: str) -> RetargeterInfo:
        """The retargeter called ``name`` (or one of its aliases, case-insensitively)."""
        if not isinstance(name, str):
            raise UnknownNameError(f"retargeter names are strings, got {name!r}")
        key = name if name in self.retargeters else self.aliases.get(name.lower())
        if key is None:
            key = next((n for n in self.retargeters if n.lower() == name.lower()), None)
        if key is None:
            valid = ", ".join(sorted(self.retargeters))
            note = ""
            if self.failures:
                note = "; plugins that failed to load: " + ", ".join(f"{f.name} ({f.distribution})" for f in self.failures)
            hint = did_you_mean(name, [*self.retargeters, *self.aliases])
            raise UnknownNameError(f"no retargeter named {name!r}{hint}; valid choices: {valid}{note}")
        return self.retargeters[key]


_REGISTRY: Registry | None = None


def registry() -> Registry:
    """The process-wide registry, loaded on first use."""
    global _REGISTRY
    if _REGISTRY is None:
        _REGISTRY = Registry().load()
    return _REGISTRY


def reload() -> Registry:
    """Forget and reload every plugin (after installing one, or changing the environment)."""
    global _REGISTRY
    _REGISTRY = None
    return registry()


def _hook_items(results: Any, hook: str, info: PluginInfo) -> list:
    """The items of one plugin's ``hook`` results (pluggy gives one result per implementation,
    None ones left out): each must be a list or tuple, else :class:`PluginLoadError` naming
    the plugin and the hook."""
    items: list = []
    for result in results if isinstance(results, list) else [results]:
        if result is None:
            continue
        if not isinstance(result, (list, tuple)):
            shown = repr(result)
            shown = shown if len(shown) <= 80 else shown[:77] + "..."
            raise PluginLoadError(
                f"plugin {info.name!r} ({info.origin}), hook {hook}: returned {shown} ({type(result).__name__}), "
                f"expected a list; the plugin was skipped (fix the hook, or leave the plugin out with "
                f"{config.ENV_PLUGIN_ALLOWLIST} or {config.ENV_DISABLE_PLUGINS}=1)"
            )
        items.extend(result)
    return items


def _too_slow(info: PluginInfo, seconds: float, doing: str) -> str:
    return (
        f"{PluginTimeoutError.__name__}: plugin {info.name!r} ({info.origin}) took longer than {seconds:g} s {doing}; "
        f"it was skipped (raise {config.ENV_IMPORT_TIMEOUT} to allow more time)"
    )


def _stuck(info: PluginInfo, seconds: float, doing: str) -> str:
    others = f"{config.ENV_PLUGIN_ALLOWLIST}=<the plugins you need>"
    return (
        f"faceretarget: error: {PluginTimeoutError.__name__}: plugin {info.name!r} ({info.origin}) was still {doing} "
        f"{seconds + grace_for(seconds):g} s after it started and could not be interrupted (it ignores the time limit's "
        f"signals); the program was stopped. Leave the plugin out ({others}, or {config.ENV_DISABLE_PLUGINS}=1), "
        f"uninstall {info.distribution}, or raise {config.ENV_IMPORT_TIMEOUT}"
    )


def _dist_name(ep: md.EntryPoint) -> str | None:
    dist = getattr(ep, "dist", None)
    return dist.metadata["Name"] if dist is not None else None


def _dist_version(ep: md.EntryPoint) -> str:
    dist = getattr(ep, "dist", None)
    return dist.version if dist is not None else "-"


def _env(name: str) -> str:
    import os

    return os.environ.get(name, "")
