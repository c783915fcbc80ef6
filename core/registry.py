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

Manifest first (:mod:`faceretarget.manifest`): ``registry.toml`` (shipped inside the
package) describes every built-in retargeter (aliases, paper, summary, capabilities,
parameters), and a third-party package may ship the same as ``faceretarget.toml``.
:func:`catalogue` reads them without importing plugin code (``faceretarget list``/``info``,
:func:`faceretarget.available`); :func:`registry` imports the plugins and checks each class
against its manifest (capabilities, parameter names, defaults, constraints): a mismatch
is a :class:`PluginLoadError` naming the plugin, the hook and the difference.
``FACERETARGET_TRACE=1`` prints every hook call.
"""

from __future__ import annotations

import importlib.metadata as md
import inspect
import sys
from collections.abc import Sequence
from contextlib import nullcontext
from dataclasses import dataclass, field
from typing import Any

import pluggy

from . import config
from ._deadline import DeadlineExpired, deadline, grace_for, watchdog_process
from ._validate import did_you_mean
from .errors import (
    ConfigError,
    DuplicatePluginError,
    PluginError,
    PluginLoadError,
    PluginTimeoutError,
    UnknownNameError,
)
from .hookspecs import DATA_KINDS, PROJECT, FaceRetargetSpec, Metric, Preset, Reader, Writer
from .manifest import (
    PACKAGE_MANIFEST,
    Manifest,
    builtin_text,
    disagreements,
    find_package_manifest,
    from_class,
)
from .manifest import parse as parse_manifest
from .retargeter import Capabilities, Retargeter
from .validation import constraints_of, describe

__all__ = [
    "Registry",
    "PluginInfo",
    "RetargeterInfo",
    "registry",
    "catalogue",
    "reload",
    "read_catalogue",
]

DISTRIBUTION = "faceretarget"


@dataclass
class PluginInfo:
    """One loaded (or failed) plugin."""

    name: str
    distribution: str
    version: str
    builtin: bool
    error: str | None = None
    #: The retargeters its package manifest (faceretarget.toml) declares, by name.
    manifests: dict[str, Manifest] = field(default_factory=dict)

    @property
    def origin(self) -> str:
        return f"{self.distribution} {self.version}"


class RetargeterInfo:
    """A registered retargeter: its manifest (what ``list`` and ``info`` show) and its class,
    imported on first use of :attr:`cls` when the entry came from a manifest alone."""

    def __init__(
        self, manifest: Manifest, plugin: PluginInfo, cls: type[Retargeter] | None = None
    ) -> None:
        self.manifest = manifest
        self.plugin = plugin
        self._cls = cls

    name = property(lambda self: self.manifest.name)
    aliases = property(lambda self: self.manifest.aliases)
    summary = property(lambda self: self.manifest.summary)
    paper = property(lambda self: self.manifest.paper)
    baseline_of = property(lambda self: self.manifest.baseline_of)
    capabilities = property(lambda self: self.manifest.capabilities)
    parameters = property(
        lambda self: self.manifest.parameters, doc="name -> Parameter (default, constraints, doc)"
    )
    defaults = property(lambda self: self.manifest.defaults)
    parameter_docs = property(
        lambda self: {p: spec.doc for p, spec in self.manifest.parameters.items()}
    )

    @property
    def cls(self) -> type[Retargeter]:
        """The Retargeter class (loads every plugin the first time, for an entry read from a manifest)."""
        if self._cls is None:
            self._cls = registry().resolve(self.name).cls
        return self._cls

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

    def __repr__(self) -> str:
        return f"<RetargeterInfo {self.name!r} from {self.plugin.name!r} ({self.plugin.origin})>"


def read_catalogue(
    text: str | None = None, origin: str = "registry.toml"
) -> dict[str, dict[str, Any]]:
    """Parse ``registry.toml`` (the packaged copy unless ``text`` is given): see
    :func:`faceretarget.manifest.parse`. Raises :class:`ConfigError` on any malformation."""
    return parse_manifest(builtin_text() if text is None else text, origin)


class Registry:
    """Everything the installed plugins provide. Build with :func:`registry`."""

    def __init__(self) -> None:
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
        self.presets: dict[str, tuple[Preset, PluginInfo]] = {}
        self.catalogue = read_catalogue()
        self.manifests = {
            name: Manifest.from_entry(name, entry, "registry.toml")
            for name, entry in self.catalogue.items()
        }

    # -- loading ---------------------------------------------------------------------
    def index(self) -> Registry:
        """The retargeters as their manifests describe them, importing no plugin that has one
        (``faceretarget list`` / ``info``, :func:`faceretarget.available`): the built-ins from
        ``registry.toml``, third-party plugins from their package's ``faceretarget.toml``.
        A third-party plugin without a manifest is loaded as :meth:`load` does. Readers,
        writers and metrics are not indexed (use :meth:`load`)."""
        eps = sorted(md.entry_points(group=PROJECT), key=lambda ep: ep.name)
        builtin = {ep.name: ep for ep in eps if _dist_name(ep) == DISTRIBUTION}
        for name, manifest in self.manifests.items():
            ep = builtin.get(manifest.entry_point)
            if ep is None:
                raise ConfigError(
                    f"registry.toml lists retargeter {name!r} (entry point {manifest.entry_point!r}) but no built-in plugin provides it"
                )
            self._add(
                [
                    RetargeterInfo(
                        manifest, PluginInfo(ep.name, DISTRIBUTION, _dist_version(ep), builtin=True)
                    )
                ]
            )
        if config.env_flag(config.ENV_DISABLE_PLUGINS):
            return self
        allow = {a.strip() for a in _env(config.ENV_PLUGIN_ALLOWLIST).split(",") if a.strip()}
        unindexed = []
        for ep in (ep for ep in eps if _dist_name(ep) != DISTRIBUTION):
            info = PluginInfo(
                ep.name, _dist_name(ep) or "unknown", _dist_version(ep), builtin=False
            )
            if allow and ep.name not in allow and info.distribution not in allow:
                continue
            try:
                found = self._package_manifests(ep, info)
            except ConfigError as exc:
                self._fail(info, str(exc), fatal=False)
                continue
            if not found:
                unindexed.append(ep)
                continue
            entries = [RetargeterInfo(m, info) for m in found.values()]
            try:
                self._check_duplicates(entries, [], info)
            except PluginError as exc:
                self._fail(info, str(exc), fatal=False)
                continue
            self._add(entries)
            self.plugins.append(info)
        if unindexed:
            limit = config.seconds_setting(config.ENV_IMPORT_TIMEOUT, config.DEFAULT_IMPORT_TIMEOUT)
            with watchdog_process() if limit else nullcontext():
                self._load_external(unindexed, set(), limit)
        return self

    @staticmethod
    def _package_manifests(ep: md.EntryPoint, info: PluginInfo) -> dict[str, Manifest]:
        """The manifests of ``faceretarget.toml`` in ``ep``'s package (kept on ``info``), or {}."""
        path = find_package_manifest(ep.value)
        if path is None:
            return {}
        origin = f"plugin {info.name!r} ({info.origin}): {path}"
        try:
            text = path.read_text(encoding="utf-8")
        except (OSError, UnicodeError) as exc:
            raise ConfigError(f"{origin}: cannot be read ({exc})") from None
        entries = parse_manifest(text, origin, defaults={"entry_point": ep.name, "paper": ""})
        info.manifests = {
            name: Manifest.from_entry(name, entry, origin) for name, entry in entries.items()
        }
        return info.manifests

    def _add(self, entries: list[RetargeterInfo]) -> None:
        for entry in entries:
            self.retargeters[entry.name] = entry
            for alias in entry.aliases:
                self.aliases[alias.lower()] = entry.name

    def load(self, extra: list[tuple[str, Any]] | None = None) -> Registry:
        """Load built-in then third-party entry points (and ``extra`` (name, module) pairs)."""
        eps = sorted(md.entry_points(group=PROJECT), key=lambda ep: ep.name)
        builtin = [ep for ep in eps if _dist_name(ep) == DISTRIBUTION]
        external = [ep for ep in eps if _dist_name(ep) != DISTRIBUTION]
        for ep in builtin:
            info = PluginInfo(ep.name, DISTRIBUTION, _dist_version(ep), builtin=True)
            try:
                module = ep.load()
            except Exception as exc:
                raise PluginLoadError(
                    f"built-in plugin {ep.name!r} ({ep.value}) failed to import: {exc!r}"
                ) from exc
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

    def _load_external(
        self, external: list[md.EntryPoint], allow: set[str], limit: float | None
    ) -> None:
        """Import and register third-party entry points, each under :func:`deadline`: one
        that overruns ``limit`` is skipped, one that cannot even be interrupted ends the
        program with a message naming it (:mod:`faceretarget._deadline`, layers 3-4)."""
        for ep in external:
            info = PluginInfo(
                ep.name, _dist_name(ep) or "unknown", _dist_version(ep), builtin=False
            )
            if allow and ep.name not in allow and info.distribution not in allow:
                continue
            try:  # read before importing: the class is checked against it at registration
                self._package_manifests(ep, info)
            except ConfigError as exc:
                self._fail(info, str(exc), fatal=False)
                continue
            try:
                with deadline(limit, hard=_stuck(info, limit, "importing") if limit else None):
                    module = ep.load()
            except DeadlineExpired:
                assert limit is not None  # deadline(None) never expires
                self._fail(info, _too_slow(info, limit, "importing"), fatal=False)
                continue
            except BaseException as exc:  # a plugin may even call sys.exit on import
                if isinstance(exc, KeyboardInterrupt):
                    raise
                info.error = f"failed to import {ep.value!r}: {type(exc).__name__}: {exc}"
                self.failures.append(info)
                continue
            before = self._snapshot()
            registering = "calling its registration hooks"
            try:
                with deadline(limit, hard=_stuck(info, limit, registering) if limit else None):
                    self._register(module, info, fatal=False)
            except DeadlineExpired:  # roll back whatever it had registered
                assert limit is not None  # deadline(None) never expires
                self._restore(before)
                if self.pm.is_registered(module):
                    self.pm.unregister(module)
                self._fail(info, _too_slow(info, limit, registering), fatal=False)

    def _snapshot(self) -> tuple:
        return (
            dict(self.retargeters),
            dict(self.aliases),
            len(self.readers),
            len(self.writers),
            dict(self.metrics),
            dict(self.presets),
            len(self.plugins),
            len(self.failures),
        )

    def _restore(self, snapshot: tuple) -> None:
        retargeters, aliases, n_readers, n_writers, metrics, presets, n_plugins, n_failures = (
            snapshot
        )
        self.retargeters, self.aliases, self.metrics, self.presets = (
            retargeters,
            aliases,
            metrics,
            presets,
        )
        del (
            self.readers[n_readers:],
            self.writers[n_writers:],
            self.plugins[n_plugins:],
            self.failures[n_failures:],
        )

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
        for hook in (
            "faceretarget_retargeters",
            "faceretarget_readers",
            "faceretarget_writers",
            "faceretarget_metrics",
            "faceretarget_presets",
        ):
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
                error = PluginLoadError(
                    f"plugin {info.name!r} ({info.origin}), hook {hook}: its result cannot be read: {type(exc).__name__}: {exc}"
                )
                self._fail(info, str(error), fatal, error)
                return
        try:
            entries = [
                self._validate_retargeter(cls, info) for cls in staged["faceretarget_retargeters"]
            ]
            readers = [
                self._validate_record(r, Reader, "faceretarget_readers", info)
                for r in staged["faceretarget_readers"]
            ]
            writers = [
                self._validate_record(w, Writer, "faceretarget_writers", info)
                for w in staged["faceretarget_writers"]
            ]
            metrics = [
                self._validate_record(m, Metric, "faceretarget_metrics", info)
                for m in staged["faceretarget_metrics"]
            ]
            presets = [
                self._validate_record(p, Preset, "faceretarget_presets", info)
                for p in staged["faceretarget_presets"]
            ]
            self._check_duplicates(entries, metrics, info, presets)
            unprovided = sorted(set(info.manifests) - {e.name for e in entries})
            if unprovided:
                raise PluginLoadError(
                    f"plugin {info.name!r} ({info.origin}): its {PACKAGE_MANIFEST} declares {', '.join(map(repr, unprovided))} "
                    f"but hook faceretarget_retargeters returned no such class"
                )
        except PluginError as exc:
            self.pm.unregister(module)
            self._fail(info, str(exc), fatal, exc)
            return
        except (KeyboardInterrupt, DeadlineExpired):
            raise
        except (
            BaseException
        ) as exc:  # a class attribute of the plugin's that raises or has the wrong type
            self.pm.unregister(module)
            error = PluginLoadError(
                f"plugin {info.name!r} ({info.origin}): what its hooks returned is invalid: {type(exc).__name__}: {exc}"
            )
            self._fail(info, str(error), fatal, error)
            return
        self._add(entries)
        self.readers.extend((r, info) for r in readers)
        self.writers.extend((w, info) for w in writers)
        for m in metrics:
            self.metrics[m.name] = (m, info)
        for p in presets:
            self.presets[p.name] = (p, info)
        self.plugins.append(info)

    def _fail(
        self, info: PluginInfo, message: str, fatal: bool, exc: Exception | None = None
    ) -> None:
        info.error = message
        if fatal:
            if isinstance(exc, PluginError):
                raise exc
            raise PluginLoadError(f"built-in plugin {info.name!r}: {message}")
        self.failures.append(info)

    def _validate_retargeter(self, cls: Any, info: PluginInfo) -> RetargeterInfo:
        where = f"plugin {info.name!r} ({info.origin}), hook faceretarget_retargeters"
        if not (inspect.isclass(cls) and issubclass(cls, Retargeter)):
            raise PluginLoadError(
                f"{where}: returned {cls!r}, which is not a faceretarget.Retargeter subclass"
            )
        if not isinstance(cls.name, str) or not cls.name.strip() or cls.name != cls.name.strip():
            raise PluginLoadError(f"{where}: {cls.__name__} has no valid `name` class attribute")
        if not isinstance(cls.capabilities, Capabilities):
            raise PluginLoadError(
                f"{where}: {cls.__name__}.capabilities must be a faceretarget.Capabilities"
            )
        init = cls.__init__
        sig = inspect.signature(init) if init is not object.__init__ else inspect.Signature()
        for param in sig.parameters.values():
            if param.name == "self" or param.kind == param.VAR_KEYWORD:
                continue
            if param.kind != param.KEYWORD_ONLY or param.default is param.empty:
                raise PluginLoadError(
                    f"{where}: {cls.__name__}.__init__ parameter {param.name!r} must be keyword-only with a default"
                )
        try:
            constraints = constraints_of(cls)
        except (TypeError, ValueError) as exc:
            raise PluginLoadError(f"{where}: {cls.__name__}.parameter_constraints: {exc}") from None
        defaults = cls.default_params()
        for p, allowed in constraints.items():
            if p not in defaults:
                raise PluginLoadError(
                    f"{where}: {cls.__name__}.parameter_constraints names {p!r}, which __init__ does not take"
                )
            if allowed and not any(c.accepts(defaults[p]) for c in allowed):
                raise PluginLoadError(
                    f"{where}: {cls.__name__}: the default {p}={defaults[p]!r} is not {describe(allowed)}"
                )
        declared = self.manifests.get(cls.name) if info.builtin else info.manifests.get(cls.name)
        if declared is None:
            return RetargeterInfo(from_class(cls, info.name), info, cls)
        mismatches = disagreements(cls, declared)
        if mismatches:
            raise PluginLoadError(
                f"{where}: {cls.__name__} ({cls.name!r}) and its manifest {declared.origin} disagree: "
                + "; ".join(mismatches)
            )
        return RetargeterInfo(declared, info, cls)

    @staticmethod
    def _validate_record(record: Any, kind: type[Any], hook: str, info: PluginInfo) -> Any:
        where = f"plugin {info.name!r} ({info.origin}), hook {hook}"
        if not isinstance(record, kind):
            raise PluginLoadError(
                f"{where}: returned {record!r}, not a faceretarget.{kind.__name__}"
            )
        if not isinstance(record.name, str) or not record.name.strip():
            raise PluginLoadError(
                f"{where}: a {kind.__name__} needs a non-empty string name, got {record.name!r}"
            )
        call = {Reader: "read", Writer: "write", Metric: "compute", Preset: "run"}[kind]
        if not callable(getattr(record, call, None)):
            raise PluginLoadError(f"{where}: {record.name!r} has no callable {call}")
        if not isinstance(record.description, str):
            raise PluginLoadError(
                f"{where}: {record.name!r}: description must be a string, got {record.description!r}"
            )
        if kind is Metric:
            if record.better not in ("lower", "higher", "none") or not isinstance(record.unit, str):
                raise PluginLoadError(
                    f'{where}: metric {record.name!r}: better must be "lower", "higher" or "none" and unit a string'
                )
            if record.why_not is not None and not callable(record.why_not):
                raise PluginLoadError(
                    f"{where}: metric {record.name!r}: why_not must be callable or None"
                )
        elif kind is Preset:
            texts = {k: getattr(record, k) for k in ("title", "paper", "claim", "setting")}
            wrong = [k for k, v in texts.items() if not isinstance(v, str)]
            if wrong:
                raise PluginLoadError(
                    f"{where}: preset {record.name!r}: {', '.join(wrong)} must be strings"
                )
        else:
            if record.kind not in DATA_KINDS:
                raise PluginLoadError(
                    f"{where}: {record.name!r}: kind must be one of {', '.join(DATA_KINDS)}, got {record.kind!r}"
                )
            exts = record.extensions
            if (
                not isinstance(exts, (tuple, list))
                or not exts
                or not all(isinstance(e, str) and e for e in exts)
            ):
                raise PluginLoadError(
                    f'{where}: {record.name!r}: extensions must be a non-empty tuple of strings like (".obj",), got {exts!r}'
                )
            priority = getattr(record, "priority", 0)
            if (
                isinstance(priority, bool)
                or not isinstance(priority, (int, float))
                or priority != priority
            ):
                raise PluginLoadError(
                    f"{where}: {record.name!r}: priority must be a number (higher wins; built-ins have 0), got {priority!r}"
                )
            accepts = getattr(record, "accepts", None)
            if accepts is not None and not callable(accepts):
                raise PluginLoadError(
                    f"{where}: {record.name!r}: accepts must be a callable accepts(path) -> bool or None, got {accepts!r}"
                )
            sniff = getattr(record, "sniff", None)
            if sniff is not None and not callable(sniff):
                raise PluginLoadError(
                    f"{where}: {record.name!r}: sniff must be a callable sniff(path) -> kind or None, got {sniff!r}"
                )
            magic = getattr(record, "magic", ())
            if not isinstance(magic, (tuple, list)) or not all(
                isinstance(m, bytes) and m for m in magic
            ):
                raise PluginLoadError(
                    f'{where}: {record.name!r}: magic must be a tuple of non-empty byte strings like (b"ply",), got {magic!r}'
                )
        return record

    def _check_duplicates(
        self,
        entries: list[RetargeterInfo],
        metrics: Sequence[Metric],
        info: PluginInfo,
        presets: Sequence[Preset] = (),
    ) -> None:
        seen: dict[str, RetargeterInfo] = {}
        for entry in entries:
            for key in (entry.name, *entry.aliases):
                k = key.lower()
                owner = self.retargeters.get(self.aliases.get(k, key)) or self.retargeters.get(key)
                if owner is None:
                    owner = next(
                        (e for e in self.retargeters.values() if e.name.lower() == k), None
                    )
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
        for p in presets:
            if p.name in self.presets:
                other = self.presets[p.name][1]
                raise DuplicatePluginError(
                    f"preset {p.name!r} from plugin {info.name!r} ({info.origin}) is already registered by "
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
                note = "; plugins that failed to load: " + ", ".join(
                    f"{f.name} ({f.distribution})" for f in self.failures
                )
            hint = did_you_mean(name, [*self.retargeters, *self.aliases])
            raise UnknownNameError(
                f"no retargeter named {name!r}{hint}; valid choices: {valid}{note}"
            )
        return self.retargeters[key]


_REGISTRY: Registry | None = None


def registry() -> Registry:
    """The process-wide registry, loaded on first use."""
    global _REGISTRY
    if _REGISTRY is None:
        _REGISTRY = Registry().load()
    return _REGISTRY


_CATALOGUE: Registry | None = None


def catalogue() -> Registry:
    """The process-wide index of retargeters read from manifests (:meth:`Registry.index`):
    what ``faceretarget list`` / ``info`` and :func:`faceretarget.available` show, without
    importing plugin code. Use :func:`registry` for the classes, readers, writers, metrics."""
    global _CATALOGUE
    if _REGISTRY is not None:  # plugins already loaded: their classes and failures are the truth
        return _REGISTRY
    if _CATALOGUE is None:
        _CATALOGUE = Registry().index()
    return _CATALOGUE


def reload() -> Registry:
    """Forget and reload every plugin (after installing one, or changing the environment)."""
    global _REGISTRY, _CATALOGUE
    _REGISTRY = _CATALOGUE = None
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
