"""The plugin hooks of faceretarget (pluggy project name ``"faceretarget"``).

A plugin is a module (or object) exposed through an entry point in the group
``faceretarget``; it implements any of these hooks with ``@faceretarget.hookimpl``.
Hooks are called with keyword arguments only (they take none) and each returns a
list. The built-in methods, formats and metrics use exactly these hooks.

Example::

    import faceretarget

    @faceretarget.hookimpl
    def faceretarget_retargeters():
        return [MyRetargeter]
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass
from typing import TYPE_CHECKING, Any

import pluggy

if TYPE_CHECKING:  # pragma: no cover
    from .retargeter import Retargeter

PROJECT = "faceretarget"
hookspec = pluggy.HookspecMarker(PROJECT)
hookimpl = pluggy.HookimplMarker(PROJECT)

#: The kinds of thing a reader produces / a writer consumes.
DATA_KINDS = ("mesh", "mesh_sequence", "rig", "markers", "weights", "animation")


@dataclass(frozen=True)
class Reader:
    """A file format a plugin can read.

    name : short unique name, e.g. ``"obj"``
    kind : what ``read`` returns: one of ``DATA_KINDS`` (``"mesh"`` -> Mesh,
        ``"mesh_sequence"`` -> MeshSequence, ``"rig"`` -> BlendshapeRig,
        ``"markers"`` -> MarkerSequence, ``"weights"`` -> WeightSequence)
    extensions : lower-case suffixes with the dot (``(".obj",)``); ``("/",)`` for a folder format
    read : ``read(path, **options)`` -> the model object; raises FileFormatError naming the
        file, or :class:`~faceretarget.errors.FormatMismatchError` to decline a file that is
        not of its format (the next reader for the extension is then tried)
    description : one line for ``faceretarget formats``
    priority : precedence among readers of one extension and kind: the highest is tried
        first; built-ins have 0; on a tie built-ins come first, then plugins in load order.
        A plugin reader for an extension the core reads needs ``priority > 0`` to win
        (``faceretarget formats`` lists the readers it shadows or is shadowed by)
    accepts : optional ``accepts(path) -> bool``, asked before ``read``: False declines the
        file (cheaply, e.g. by its first bytes) and the next reader is tried
    sniff : optional ``sniff(path) -> kind or None``: what the file holds (one of
        ``DATA_KINDS``), found by looking inside cheaply; None when it cannot tell. Where
        readers of several kinds share an extension (``.npz``, ``.glb``, ``.csv``,
        folders), ``load`` without ``kind=`` reads the file as the kind the sniffers name.
        Readers of one format family share one sniffer object (it is asked once per file)
    magic : byte strings a file of this format starts with (e.g. ``(b"ply",)``): a file
        with another extension that starts with one is named as this format in errors
        ("it starts like a PLY file"); files are never refused for lacking it
    """

    name: str
    kind: str
    extensions: tuple[str, ...]
    read: Callable[..., Any]
    description: str = ""
    priority: int = 0
    accepts: Callable[..., bool] | None = None
    sniff: Callable[..., str | None] | None = None
    magic: tuple[bytes, ...] = ()


@dataclass(frozen=True)
class Writer:
    """A file format a plugin can write (atomically; never over an input).

    kind : what ``write`` accepts: one of ``DATA_KINDS``
    write : ``write(obj, path, **options)`` -> None. :func:`faceretarget.io.save` hands it
        a *temporary* path beside the destination (same suffix; an empty file, or an empty
        folder for a ``"/"`` format) and moves the result into place itself, so a writer
        never needs to care about ``force`` or inputs (see :func:`faceretarget.io.atomic_path`)
    priority : precedence among writers of one extension and kind (highest first; built-ins 0)
    """

    name: str
    kind: str
    extensions: tuple[str, ...]
    write: Callable[..., Any]
    description: str = ""
    priority: int = 0


@dataclass(frozen=True)
class Metric:
    """An evaluation metric.

    compute : ``compute(animation, case, context)`` -> float, or None when it does not
        apply (then ``why_not(animation, case)`` says why); ``context`` is a dict with
        timings and memory measured by the harness
    better : "lower" or "higher"
    unit : e.g. "% face height", "s", "MiB"
    """

    name: str
    compute: Callable[..., Any]
    description: str
    better: str = "lower"
    unit: str = ""
    why_not: Callable[..., str | None] | None = None


@dataclass(frozen=True)
class Preset:
    """A paper reproduction shown in the report (``faceretarget compare --presets``, ``demo``).

    run : ``run(cases, result)``: ``cases(name)`` returns a case by name or case spec (the
        comparison's own, else built); ``result`` is the
        :class:`~faceretarget.evaluation.presets.PresetResult` to fill (``table``, ``plots``,
        ``agrees`` and ``evidence``). Helpers: :mod:`faceretarget.evaluation.reproduction`.
        A missing retargeter (``UnknownNameError``, ``CapabilityError``) makes the preset
        "not applicable", any other exception an "error"; neither stops the report
    title, paper : one line each; description : what is run and plotted
    claim : the paper's claim, one sentence; setting : the paper's setting as reproduced,
        and what differs
    """

    name: str
    title: str
    paper: str
    description: str
    run: Callable[..., Any]
    claim: str = ""
    setting: str = ""


class FaceRetargetSpec:
    """Hook specifications."""

    @hookspec
    def faceretarget_retargeters(self) -> list[type[Retargeter]]:
        """Return retargeter classes (subclasses of :class:`faceretarget.Retargeter`).

        Each class has a unique ``name``; names and aliases must not clash with any
        other plugin's.
        """

    @hookspec
    def faceretarget_readers(self) -> list[Reader]:
        """Return :class:`Reader` records for the file formats this plugin reads."""

    @hookspec
    def faceretarget_writers(self) -> list[Writer]:
        """Return :class:`Writer` records for the file formats this plugin writes."""

    @hookspec
    def faceretarget_metrics(self) -> list[Metric]:
        """Return :class:`Metric` records for the evaluation harness."""

    @hookspec
    def faceretarget_presets(self) -> list[Preset]:
        """Return :class:`Preset` records: paper reproductions for the report. Import heavy
        code inside ``run``, not when building the records."""


HOOK_NAMES = tuple(n for n in vars(FaceRetargetSpec) if n.startswith("faceretarget_"))
