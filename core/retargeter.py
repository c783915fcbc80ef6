"""The Retargeter contract, in the style of scikit-learn estimators.

- ``__init__`` takes keyword-only parameters and stores them unchanged as attributes
  of the same name (no validation, no work); :meth:`get_params` reads them back
  from the signature.
- ``fit(source, target)`` validates, precomputes and returns ``self``; everything it
  learns is stored in attributes ending in ``_``.
- ``retarget(source)`` returns an :class:`~faceretarget.model.Animation` and never
  mutates its inputs.
- Optional protocols, declared in :attr:`Retargeter.capabilities`: ``stream(frames)``
  (online, frame by frame) and ``edit(animation, ...)`` (constraints on a result, over space and time).

A subclass implements ``_fit`` and ``_retarget``; the base class does the checks.
"""

from __future__ import annotations

import copy
import functools
import inspect
import time
from collections.abc import Callable, Iterable, Iterator
from typing import TYPE_CHECKING, Any, ClassVar

import numpy as np

from ._json import jsonable
from ._validate import all_finite
from .capabilities import RIG_PARTS, SOURCE_KINDS, Capabilities
from .errors import CapabilityError, InputError, NonFiniteError, NotFittedError, PluginOutputError
from .model import Animation, Source, TargetRig

if TYPE_CHECKING:
    from .manifest import Manifest

__all__ = ["Capabilities", "Retargeter", "clone", "SOURCE_KINDS", "RIG_PARTS"]

#: The package of the built-in plugins: a class defined under it takes its capabilities and
#: summary from the packaged ``registry.toml`` (:meth:`Retargeter.packaged_manifest`).
BUILTIN_PACKAGE = "faceretarget.plugins"


def _has(source: Source, target: TargetRig, need: str) -> bool:
    if need in RIG_PARTS:
        return target.has(need)
    if need == "source_landmarks":
        return source.kind == "markers" or source.landmarks is not None
    if need == "source_examples":
        return source.examples is not None
    if need == "source_feature_lines":
        return bool(source.feature_lines)
    if need == "actor_layers":
        return source.actor_layers is not None
    if need == "source_rig":
        return source.rig is not None
    return False


_NEED_TEXT = {
    "blendshapes": "a TargetRig with blendshapes",
    "layers": "a TargetRig with layered poses (TargetRig.layers)",
    "landmarks": "a TargetRig with landmarks",
    "feature_lines": "a TargetRig with feature lines",
    "examples": "a TargetRig with example poses",
    "source_landmarks": "a Source with landmarks (mesh sequence) or markers",
    "source_examples": "a Source with example poses",
    "source_feature_lines": "a Source with feature lines",
    "actor_layers": "a Source with actor layers (Source.actor_layers)",
    "source_rig": "a Source with its own blendshape rig",
}


#: Need -> the Python argument that supplies it (named by :class:`CapabilityError` from ``fit``;
#: the command line names its own options, see ``faceretarget run --help``).
PYTHON_ARGUMENTS = {
    "blendshapes": "TargetRig(neutral, blendshapes=BlendshapeRig(...)) or load_target(RIG_FILE)",
    "layers": "TargetRig(neutral, layers=LayeredRig(...))",
    "landmarks": "TargetRig(neutral, landmarks=Landmarks(ids)) or load_target(path, landmarks=FILE)",
    "feature_lines": "TargetRig(neutral, feature_lines={name: [vertex ids]}) or load_target(path, feature_lines=JSON)",
    "examples": "TargetRig(neutral, examples=..., example_names=...) or load_target(path, examples=FILE)",
    "source_landmarks": "Source(performance, landmarks=Landmarks(ids)) or load_source(path, landmarks=FILE)",
    "source_examples": "Source(performance, examples=..., example_names=...) or load_source(path, examples=FILE)",
    "source_feature_lines": "Source(performance, feature_lines={name: [vertex ids]}) or load_source(path, feature_lines=JSON)",
    "actor_layers": "Source(performance, actor_layers=LayeredRig(...))",
    "source_rig": "Source(weights, rig=BlendshapeRig(...)) or load_source(path, rig=RIG_FILE)",
}


def missing_needs(
    capabilities: Capabilities, source: Source, target: TargetRig
) -> list[tuple[str, ...]]:
    """The needs of ``capabilities`` that (source, target) lack, each as its tuple of alternatives."""
    out = []
    for need in capabilities.needs:
        options = need if isinstance(need, tuple) else (need,)
        if not any(_has(source, target, n) for n in options):
            out.append(options)
    return out


class Retargeter:
    """Base class of every retargeter, built-in or third-party.

    Subclasses set :attr:`name`, write an ``__init__`` with keyword-only parameters stored
    as-is, and implement ``_fit`` and ``_retarget``. A third-party class also sets
    :attr:`capabilities` (and :attr:`summary`); a built-in one (defined under
    :data:`BUILTIN_PACKAGE`) takes both from its ``registry.toml`` entry, by its name, when
    the class is created (:meth:`packaged_manifest`), so the manifest is their one source.
    """

    name: ClassVar[str] = ""
    capabilities: ClassVar[Capabilities] = Capabilities()
    #: One-line description shown by ``faceretarget list`` (registry.toml wins for built-ins).
    summary: ClassVar[str] = ""
    #: Parameter meanings shown by ``faceretarget info``: name -> text.
    parameter_docs: ClassVar[dict[str, str]] = {}

    def __init_subclass__(cls, **kwargs: Any) -> None:
        super().__init_subclass__(**kwargs)
        entry = cls.packaged_manifest()
        if entry is not None:  # what the class states itself stays (the registry compares)
            if "capabilities" not in vars(cls):
                cls.capabilities = entry.capabilities
            if "summary" not in vars(cls):
                cls.summary = entry.summary

    @classmethod
    def packaged_manifest(cls) -> Manifest | None:
        """This class's entry of the packaged ``registry.toml`` when it is a built-in: defined
        in a module under :data:`BUILTIN_PACKAGE` and setting its own :attr:`name`, which the
        manifest lists; else None. Reads the manifest only (no other plugin is imported)."""
        if "name" not in vars(cls) or not cls.__module__.startswith(BUILTIN_PACKAGE + "."):
            return None
        from . import manifest

        return manifest.builtin().get(cls.name)

    # -- parameters ------------------------------------------------------------------
    @classmethod
    def _param_names(cls) -> list[str]:
        init = cls.__init__
        if init is object.__init__:
            return []
        return list(_init_parameter_names(init))

    @classmethod
    def default_params(cls) -> dict[str, Any]:
        sig = inspect.signature(cls.__init__)
        return {n: sig.parameters[n].default for n in cls._param_names()}

    def get_params(self) -> dict[str, Any]:
        """The constructor parameters and their current values."""
        return {n: getattr(self, n) for n in self._param_names()}

    def set_params(self, **params: Any) -> Retargeter:
        """Set constructor parameters; unknown names raise. Returns self."""
        self.check_params(params, who=type(self).__name__)
        for k, v in params.items():
            setattr(self, k, v)
        return self

    @classmethod
    def check_params(cls, params: Iterable[str], who: str | None = None) -> None:
        """Raise :class:`~faceretarget.errors.UnknownNameError` for keyword names that are
        not constructor parameters of this retargeter, each with the closest valid name
        ("did you mean") and the full list of valid parameters."""
        from ._validate import did_you_mean
        from .errors import UnknownNameError

        valid = cls._param_names()
        unknown = [k for k in params if k not in valid]
        if not unknown:
            return
        who = who or cls.name or cls.__name__
        named = ", ".join(f"{k!r}{did_you_mean(k, valid)}" for k in unknown)
        raise UnknownNameError(
            f"{who} has no parameter{'s' if len(unknown) > 1 else ''} {named}; valid parameters: {', '.join(valid) or '(none)'}"
        )

    def clone(self) -> Retargeter:
        """A new unfitted retargeter with the same (deep-copied) parameters."""
        return clone(self)

    def __repr__(self) -> str:
        defaults = self.default_params()
        changed = {k: v for k, v in self.get_params().items() if not _same(v, defaults.get(k))}
        args = ", ".join(f"{k}={v!r}" for k, v in changed.items())
        return f"{type(self).__name__}({args})"

    # -- capability checks -----------------------------------------------------------
    @classmethod
    def why_not(cls, source: Source, target: TargetRig | None) -> str | None:
        """None if this retargeter applies to (source, target), else the reason."""
        caps = cls.capabilities
        if source.kind not in caps.sources:
            return f"{cls.name or cls.__name__} takes {' or '.join(caps.sources)} sources; this source is {source.kind}"
        if target is None:
            return None
        missing = [
            " or ".join(_NEED_TEXT.get(n, n) for n in options)
            for options in missing_needs(caps, source, target)
        ]
        if missing:
            return f"{cls.name or cls.__name__} needs {'; '.join(missing)}; this one lacks it"
        return None

    def _check_applicable(self, source: Source, target: TargetRig) -> None:
        if not isinstance(source, Source):
            raise InputError(
                f"{self.name}.fit: source must be a faceretarget.Source, got {type(source).__name__}"
            )
        if not isinstance(target, TargetRig):
            raise InputError(
                f"{self.name}.fit: target must be a faceretarget.TargetRig, got {type(target).__name__}"
            )
        reason = self.why_not(source, target)
        if reason:
            hints = [
                " or ".join(PYTHON_ARGUMENTS.get(n, n) for n in options)
                for options in missing_needs(self.capabilities, source, target)
            ]
            raise CapabilityError(f"{reason}; give {'; '.join(hints)}" if hints else reason)

    def _check_fitted(self) -> None:
        if not getattr(self, "fitted_", False):
            raise NotFittedError(
                f"this {type(self).__name__} is not fitted yet; call fit(source, target) before retarget()"
            )

    # -- public protocol ---------------------------------------------------------------
    def fit(self, source: Source, target: TargetRig) -> Retargeter:
        """Validate (source, target), precompute, and return self."""
        self._check_applicable(source, target)
        start = time.perf_counter()
        self._fit(source, target)
        self.target_ = target
        self.fit_seconds_ = time.perf_counter() - start
        self.fitted_ = True
        return self

    def retarget(self, source: Source) -> Animation:
        """Retarget ``source`` onto the fitted target; returns an :class:`Animation`."""
        self._check_fitted()
        if not isinstance(source, Source):
            raise InputError(
                f"{self.name}.retarget: expected a faceretarget.Source, got {type(source).__name__}"
            )
        reason = self.why_not(source, None)
        if reason:
            raise CapabilityError(reason)
        start = time.perf_counter()
        animation = self._retarget(source)
        seconds = time.perf_counter() - start
        return self._stamp(animation, seconds, source)

    def stream(self, frames: Iterable) -> Iterator[np.ndarray]:
        """Online retargeting, frame by frame (only where ``capabilities.stream``)."""
        raise CapabilityError(
            f"{self.name or type(self).__name__} does not stream; use retarget() on the whole sequence"
        )

    def edit(self, animation: Animation, **constraints: Any) -> Animation:
        """Spacetime editing (only where ``capabilities.edit``)."""
        raise CapabilityError(f"{self.name or type(self).__name__} does not support editing")

    # -- for subclasses --------------------------------------------------------------
    def _fit(self, source: Source, target: TargetRig) -> None:  # pragma: no cover - abstract
        raise CapabilityError(f"{type(self).__name__} must implement _fit(source, target)")

    def _retarget(self, source: Source) -> Animation:  # pragma: no cover - abstract
        raise CapabilityError(f"{type(self).__name__} must implement _retarget(source)")

    def check_output(self, animation: Any, source: Source | None = None) -> None:
        """The one check of a result (``retarget`` makes it before returning; the command line,
        the harness and batch rely on it): an :class:`Animation`, one frame per ``source``
        frame, the fitted target's vertex count, no NaN or infinite value. Raises
        :class:`PluginOutputError` naming the method."""
        who = self.name or type(self).__name__
        if not isinstance(animation, Animation):
            raise PluginOutputError(
                f"{who}: _retarget returned {type(animation).__name__}, not an Animation"
            )
        if source is not None and animation.n_frames != source.n_frames:
            raise PluginOutputError(
                f"{who}: returned {animation.n_frames} frames for a source of {source.n_frames}; expected one per source frame"
            )
        target = getattr(self, "target_", None)
        n_vertices = animation.n_vertices
        if isinstance(target, TargetRig) and n_vertices != target.neutral.n_vertices:
            raise PluginOutputError(
                f"{who}: returned {n_vertices} vertices per frame but the target has {target.neutral.n_vertices}; "
                "results must be on the target's own vertices"
            )
        for what, values in (
            ("weights", animation.weights),
            ("head motion", animation.head_motion),
        ):
            if values is not None and not all_finite(values):
                raise PluginOutputError(f"{who} returned NaN or infinite {what}")
        if not _finite_vertices(animation):
            raise PluginOutputError(f"{who} returned NaN or infinite vertex coordinates")

    def _stamp(
        self, animation: Animation, seconds: float, source: Source | None = None
    ) -> Animation:
        """:meth:`check_output`, then fill the provenance."""
        self.check_output(animation, source)
        from ._version import __version__

        prov = animation.provenance
        prov.setdefault("method", self.name)
        prov.setdefault("version", __version__)
        prov.setdefault("parameters", jsonable(self.get_params()))
        timings = prov.setdefault("timings", {})
        timings.setdefault("fit_s", getattr(self, "fit_seconds_", None))
        timings.setdefault("retarget_s", seconds)
        prov.setdefault("diagnostics", {})
        return animation


@functools.lru_cache(maxsize=256)
def _init_parameter_names(init: Callable[..., Any]) -> tuple[str, ...]:
    """Sorted keyword parameters of a constructor, once per function (``inspect.signature``
    took ~0.25 ms of every ``retarget()``, through the provenance's parameters)."""
    sig = inspect.signature(init)
    return tuple(
        sorted(
            p.name
            for p in sig.parameters.values()
            if p.name != "self" and p.kind not in (p.VAR_KEYWORD, p.VAR_POSITIONAL)
        )
    )


def clone(retargeter: Retargeter) -> Retargeter:
    """A new unfitted retargeter with the same parameters (deep-copied)."""
    return type(retargeter)(**copy.deepcopy(retargeter.get_params()))


def _same(a: Any, b: Any) -> bool:
    try:
        return bool(np.all(a == b)) if not isinstance(a, (dict, list)) else a == b
    except Exception:
        return a is b


def _finite_vertices(animation: Animation, chunk: int = 64) -> bool:
    """Whether every vertex coordinate is finite, frames a chunk at a time (a memory-mapped
    result is not loaded whole; vertices a rig computes from weights are not kept)."""
    from .model import apply_head_motion

    stored = animation._vertices
    if stored is not None:
        return all(all_finite(stored[i : i + chunk]) for i in range(0, stored.shape[0], chunk))
    if animation._lazy is not None:  # a frame source checks what it computes
        try:
            for i in range(0, animation.n_frames, chunk):
                animation.frames(slice(i, i + chunk))
        except NonFiniteError:
            return False
        return True
    rig, weights, motion = (
        animation.rig,
        np.asarray(animation.weights, dtype=np.float64),
        animation.head_motion,
    )
    assert rig is not None  # an Animation without vertices has a rig
    with np.errstate(over="ignore", invalid="ignore"):
        # weights and head motion are finite here: a bound on |vertex| far from overflow proves it
        largest = rig.delta_extent
        bound = np.abs(rig.neutral.vertices).max(initial=0.0) + (np.abs(weights) @ largest).max(
            initial=0.0
        )
        if motion is not None:
            bound = bound * 3.0 * np.abs(motion[:, :3, :3]).max(initial=0.0) + np.abs(
                motion[:, :3, 3]
            ).max(initial=0.0)
        if bound < 1e300:
            return True
        return all(
            np.isfinite(
                apply_head_motion(
                    None if motion is None else motion[i : i + chunk],
                    rig.evaluate(weights[i : i + chunk]),
                )
            ).all()
            for i in range(0, weights.shape[0], chunk)
        )
