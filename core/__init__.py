"""faceretarget: facial animation retargeting behind one plugin interface.

    import faceretarget as fr
    case = fr.cases.synthetic(seed=0)
    name = fr.available()[0]["name"]      # any name `faceretarget list` shows
    anim = fr.get(name).fit(case.source, case.target).retarget(case.source)

Public API: :func:`available`, :func:`get`, the model types, :class:`Retargeter`,
:class:`Capabilities`, :data:`hookimpl`, the error types (``faceretarget.errors``)
and the readers/writers (``faceretarget.load``, ``faceretarget.save``).
"""

from __future__ import annotations

from importlib import import_module
from pathlib import Path
from types import ModuleType
from typing import TYPE_CHECKING, Any

from . import _numba_cache  # noqa: E402
from ._types import PathLike
from ._version import __version__

if TYPE_CHECKING:
    from .registry import RetargeterInfo

_numba_cache.install()  # concurrent processes sharing numba's cache never fail a call (numba is not imported here)

from .errors import CapabilityError, FaceRetargetError, NotFittedError, UnknownNameError  # noqa: E402
from .hookspecs import Metric, Preset, Reader, Writer, hookimpl, hookspec  # noqa: E402
from .model import (  # noqa: E402
    Animation,
    BlendshapeRig,
    Landmarks,
    LayeredRig,
    MarkerSequence,
    Mesh,
    MeshSequence,
    Source,
    TargetRig,
    WeightSequence,
)
from .retargeter import Capabilities, Retargeter, clone  # noqa: E402

__all__ = [
    "__version__",
    "available",
    "get",
    "info",
    "load",
    "save",
    "Animation",
    "BlendshapeRig",
    "Capabilities",
    "CapabilityError",
    "FaceRetargetError",
    "Landmarks",
    "LayeredRig",
    "MarkerSequence",
    "Mesh",
    "MeshSequence",
    "Metric",
    "NotFittedError",
    "Preset",
    "Reader",
    "Retargeter",
    "Source",
    "TargetRig",
    "UnknownNameError",
    "WeightSequence",
    "Writer",
    "clone",
    "hookimpl",
    "hookspec",
]


def available() -> list[dict[str, Any]]:
    """Every registered retargeter: name, aliases, summary, paper, capabilities, origin.

    Read from the manifests (``registry.toml``, a plugin's ``faceretarget.toml``) without
    importing plugin code; see :func:`faceretarget.registry.catalogue`.
    """
    from .registry import catalogue

    return [entry.as_dict() for _, entry in sorted(catalogue().retargeters.items())]


def get(name: str, **params: Any) -> Retargeter:
    """An unfitted retargeter by name or alias, with ``params`` set.

    Raises :class:`UnknownNameError` listing the valid names (or parameters).
    """
    from .registry import registry

    entry = registry().resolve(name)
    entry.cls.check_params(params, who=entry.name)
    return entry.cls(**params)


def info(name: str) -> RetargeterInfo:
    """The :class:`~faceretarget.registry.RetargeterInfo` of a retargeter (parameters, docs, origin)."""
    from .registry import registry

    return registry().resolve(name)


def load(path: PathLike, kind: str | None = None, **options: Any) -> Any:
    """Read a file with the registered reader for its extension (see ``faceretarget.io``)."""
    from .io import load as _load

    return _load(path, kind=kind, **options)


def save(obj: Any, path: PathLike, **options: Any) -> Path:
    """Write ``obj`` atomically with the registered writer for the path's extension."""
    from .io import save as _save

    return _save(obj, path, **options)


_LAZY = {
    "cases": ".cases",
    "testing": ".testing",
    "evaluation": ".evaluation",
    "correspond": ".correspond",
    "io": ".io",
    "geometry": ".geometry",
    "registry": ".registry",
    "validation": ".validation",
    "manifest": ".manifest",
    "errors": ".errors",
    "model": ".model",
    "naming": ".naming",
}


def __getattr__(name: str) -> ModuleType:
    if name in _LAZY:
        module = import_module(_LAZY[name], __name__)
        globals()[name] = module
        return module
    raise AttributeError(f"module 'faceretarget' has no attribute {name!r}")
