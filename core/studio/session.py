"""The studio's state: the inputs, every method that applies, cached results, undo and redo.

Nothing here knows about HTTP: :mod:`.app` turns requests into calls of :class:`Session` and
its typed errors (:mod:`faceretarget.errors`) into JSON answers.

- :meth:`Session.methods` lists every registered method with whether it applies to the
  inputs (and why not), its parameters as the manifest declares them (default, valid
  values, meaning) and the edits it offers.
- :meth:`Session.run` checks the parameters against the manifest
  (:func:`faceretarget.validation.check_value`), fits and retargets, and caches the result
  by (method, parameters): switching back to a method costs nothing.
- :meth:`Session.edit` hands an edit to the method's own ``edit()``; what the studio offers
  is read from that signature (:data:`EDIT_KINDS`), so a plugin's method gets the same tools.
  Each result keeps its history: :meth:`Session.undo`, :meth:`Session.redo`.
- :meth:`Session.export` writes GLB, weight CSV or PC2 atomically into the output folder,
  under a new name (never over an existing file or an input).
"""

from __future__ import annotations

import hashlib
import inspect
import json
import threading
import time
from collections import OrderedDict
from collections.abc import Iterable
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from .._json import jsonable
from .._validate import did_you_mean
from ..errors import (
    CapabilityError,
    InputError,
    OutputError,
    UnknownNameError,
)
from ..model import Animation, BlendshapeRig, Source, TargetRig, apply_head_motion
from ..validation import Interval, Options, check_value, describe

__all__ = ["Session", "Result", "EDIT_KINDS", "EXPORT_FORMATS", "edit_kinds"]

#: Edits the studio offers, by the keywords a method's ``edit()`` takes:
#: ``weights``: new blendshape weights at a frame (sliders), propagated over a window;
#: ``points``: move a vertex at a frame (drag a point on the face);
#: ``detail``: scale or remove the fine detail (wrinkles) of a region at a frame.
EDIT_KINDS: dict[str, tuple[str, ...]] = {
    "weights": ("frame", "weights"),
    "points": ("points",),
    "detail": ("detail",),
}
#: Export format -> file extension.
EXPORT_FORMATS = {"glb": ".glb", "csv": ".csv", "pc2": ".pc2"}
#: Undo steps kept per result (each step holds one Animation).
HISTORY = 30
#: Results kept in the cache (least recently used dropped first).
CACHE = 8


def edit_kinds(cls: Any) -> list[str]:
    """The edits (:data:`EDIT_KINDS`) a retargeter class offers, read from its ``edit()``."""
    caps = getattr(cls, "capabilities", None)
    if caps is None or not caps.edit:
        return []
    params = inspect.signature(cls.edit).parameters
    return [kind for kind, needs in EDIT_KINDS.items() if all(n in params for n in needs)]


@dataclass
class Result:
    """One (method, parameters) run: the fitted retargeter and its animation's history."""

    id: str
    method: str
    params: dict[str, Any]
    retargeter: Any
    history: list[Animation]
    seconds: dict[str, float]
    position: int = 0
    version: int = 0
    edits: list[str] = field(default_factory=list)

    @property
    def animation(self) -> Animation:
        return self.history[self.position]

    @property
    def undo_steps(self) -> int:
        return self.position

    @property
    def redo_steps(self) -> int:
        return len(self.history) - 1 - self.position

    def push(self, animation: Animation) -> None:
        del self.history[self.position + 1 :]  # a new edit drops what could be redone
        self.history.append(animation)
        if len(self.history) > HISTORY + 1:
            del self.history[0]
        self.position = len(self.history) - 1
        self.version += 1


class Session:
    """The inputs of one studio and the results made from them.

    Parameters
    ----------
    source, target : the performance and the character
    truth : the right answer (an evaluation case's), for the error heat map; optional
    name : shown in the page and used for export file names
    files : the files named on the command line: the only files the page may read
    out_dir : where exports go (created if missing)
    face_height : error unit for the heat map (default: the target neutral's height)
    """

    def __init__(
        self,
        source: Source,
        target: TargetRig,
        *,
        truth: Animation | None = None,
        name: str = "studio",
        files: Iterable[Path | str] = (),
        out_dir: Path | str = ".",
        face_height: float | None = None,
    ) -> None:
        if not isinstance(source, Source) or not isinstance(target, TargetRig):
            raise InputError("studio: give a faceretarget.Source and a faceretarget.TargetRig")
        if truth is not None and (
            truth.n_frames != source.n_frames
            or truth.vertices.shape[1] != target.neutral.n_vertices
        ):
            truth = None  # not comparable frame by frame: no heat map
        self.source, self.target, self.truth, self.name = source, target, truth, name
        self.files = tuple(Path(f) for f in files)
        self.out_dir = Path(out_dir)
        self.face_height = float(face_height or target.neutral.height or 1.0)
        self.live: Any = None  # a live.LiveLink when the studio receives a stream
        #: what the page selects first: {"method": name, "params": {...}} (the command line's)
        self.defaults: dict[str, Any] = {}
        self._results: OrderedDict[str, Result] = OrderedDict()
        self._lock = threading.RLock()
        self._rigs: dict[int, tuple[str, Any]] = {}
        self._methods: list[dict[str, Any]] | None = None

    # -- what can be run ------------------------------------------------------------------
    def methods(self) -> list[dict[str, Any]]:
        """Every registered method: name, summary, paper, outputs, edits, stream, whether it
        applies (``why_not`` says why not), and its parameters from the manifest."""
        if self._methods is None:
            from ..registry import registry

            out = []
            for name, entry in sorted(registry().retargeters.items()):
                cls = entry.cls
                why = cls.why_not(self.source, self.target)
                out.append(
                    {
                        "name": name,
                        "summary": entry.summary,
                        "paper": entry.paper,
                        "builtin": entry.plugin.builtin,
                        "outputs": entry.capabilities.outputs,
                        "stream": entry.capabilities.stream,
                        "edit": edit_kinds(cls),
                        "edit_window": "window" in inspect.signature(cls.edit).parameters,
                        "applies": why is None,
                        "why_not": why or "",
                        "parameters": [parameter_widget(p) for p in entry.parameters.values()],
                    }
                )
            self._methods = out
        return self._methods

    def method(self, name: Any) -> dict[str, Any]:
        """One entry of :meth:`methods` by name or alias; it must apply to the inputs."""
        from ..registry import registry

        if not isinstance(name, str):
            raise InputError(f"studio: a method is a name, got {name!r}")
        canonical = registry().resolve(name).name  # UnknownNameError with "did you mean"
        entry = next(m for m in self.methods() if m["name"] == canonical)
        if not entry["applies"]:
            raise CapabilityError(f"{canonical} does not apply to these inputs: {entry['why_not']}")
        return entry

    def check_params(self, name: str, params: Any) -> dict[str, Any]:
        """``params`` checked against the manifest's declarations of method ``name``: unknown
        names and invalid values raise (:class:`UnknownNameError`, :class:`ParameterError`)."""
        from ..registry import registry

        entry = registry().resolve(name)
        if params is None:
            return {}
        if not isinstance(params, dict):
            raise InputError(
                f"studio: params must be an object {{name: value}}, got {type(params).__name__}"
            )
        declared = entry.parameters
        unknown = [k for k in params if k not in declared]
        if unknown:
            named = ", ".join(f"{k!r}{did_you_mean(k, declared)}" for k in unknown)
            raise UnknownNameError(
                f"{entry.name} has no parameter {named}; valid: {', '.join(declared)}"
            )
        return {
            k: check_value(v, declared[k].constraints, k, entry.name) for k, v in params.items()
        }

    # -- results ----------------------------------------------------------------------------
    def run(self, name: Any, params: Any = None) -> tuple[Result, bool]:
        """The result of method ``name`` with ``params`` (fitted and retargeted, or from the
        cache: the second item says which)."""
        from .. import get

        entry = self.method(name)
        checked = self.check_params(entry["name"], params)
        key = entry["name"] + json.dumps(jsonable(checked), sort_keys=True)
        rid = f"{entry['name']}-{hashlib.sha1(key.encode()).hexdigest()[:10]}"
        with self._lock:
            if rid in self._results:
                self._results.move_to_end(rid)
                return self._results[rid], True
            retargeter = get(entry["name"], **checked)
            t0 = time.perf_counter()
            retargeter.fit(self.source, self.target)
            t1 = time.perf_counter()
            animation = retargeter.retarget(self.source)
            t2 = time.perf_counter()
            result = Result(
                rid,
                entry["name"],
                jsonable(checked),
                retargeter,
                [animation],
                {"fit": t1 - t0, "retarget": t2 - t1},
            )
            self._results[rid] = result
            while len(self._results) > CACHE:
                self._results.popitem(last=False)
            return result, False

    def result(self, rid: Any) -> Result:
        if not isinstance(rid, str) or rid not in self._results:
            raise UnknownNameError(
                f"studio: no result {rid!r}; run a method first (POST /api/run) and use the id it returns"
            )
        return self._results[rid]

    def undo(self, rid: Any) -> Result:
        with self._lock:
            result = self.result(rid)
            if result.position == 0:
                raise InputError("studio: nothing to undo")
            result.position -= 1
            result.version += 1
            return result

    def redo(self, rid: Any) -> Result:
        with self._lock:
            result = self.result(rid)
            if result.redo_steps == 0:
                raise InputError("studio: nothing to redo")
            result.position += 1
            result.version += 1
            return result

    def edit(self, rid: Any, request: Any) -> tuple[Result, list[int] | None]:
        """Apply one edit (a dict: ``kind``, ``frame``, optional ``window`` and the kind's
        fields, see :data:`EDIT_KINDS`) with the method's ``edit()``. Returns the result and
        the first and last frames that changed (None if none did)."""
        with self._lock:
            result = self.result(rid)
            if not isinstance(request, dict):
                raise InputError("studio edit: send an object with kind, frame and the edit")
            kinds = edit_kinds(type(result.retargeter))
            kind = check_value(
                request.get("kind"), [Options(kinds or ["(none)"])], "kind", "studio edit"
            )
            before = result.animation
            n = before.n_frames
            frame = check_value(request.get("frame"), [Interval(int, 0, n - 1)], "frame", "edit")
            window = request.get("window")
            if window is not None:
                if not isinstance(window, (list, tuple)) or len(window) != 2:
                    raise InputError(f"studio edit: window must be [first, last], got {window!r}")
                window = tuple(
                    check_value(w, [Interval(int, 0, n - 1)], "window", "studio edit")
                    for w in window
                )
                if not window[0] <= frame <= window[1]:
                    raise InputError(
                        f"studio edit: frame {frame} lies outside the window {list(window)}; widen the window"
                    )
            options = {} if window is None else {"window": window}
            if kind == "weights":
                after = result.retargeter.edit(
                    before, frame=frame, weights=self._weights(before, request), **options
                )
            elif kind == "points":
                vertex, position = self._point(before, request)
                after = result.retargeter.edit(
                    before, points=[(frame, vertex, position)], **options
                )
            else:
                after = result.retargeter.edit(
                    before, detail=self._detail(before, frame, request, window)
                )
            result.push(after)
            result.edits.append(kind)
            return result, changed_frames(before, after)

    def _weights(self, animation: Animation, request: dict) -> dict[str, float]:
        weights = request.get("weights")
        names = list(animation.weight_names)
        if not isinstance(weights, dict) or not weights:
            raise InputError(
                'studio edit: weights must be an object {shape name: new weight}, e.g. {"jawOpen": 0.8}'
            )
        out = {}
        for k, v in weights.items():
            if k not in names:
                raise UnknownNameError(
                    f"studio edit: no blendshape {k!r}{did_you_mean(k, names)} in this result"
                )
            out[k] = check_value(v, [Interval(float, -1e3, 1e3)], k, "studio edit")
        return out

    def _point(self, animation: Animation, request: dict) -> tuple[int, tuple[float, ...]]:
        n_vertices = animation.vertices.shape[1]
        vertex = check_value(
            request.get("vertex"), [Interval(int, 0, n_vertices - 1)], "vertex", "studio edit"
        )
        position = request.get("position")
        if not isinstance(position, (list, tuple)) or len(position) != 3:
            raise InputError(f"studio edit: position must be [x, y, z], got {position!r}")
        xyz = tuple(check_value(c, [Interval(float)], "position", "studio edit") for c in position)
        return vertex, xyz

    def _detail(
        self, animation: Animation, frame: int, request: dict, window: tuple[int, int] | None
    ) -> dict:
        vertices = np.asarray(self.frames(animation, frame, frame + 1)[0], dtype=np.float64)
        vertex = check_value(
            request.get("vertex"), [Interval(int, 0, len(vertices) - 1)], "vertex", "studio edit"
        )
        radius = check_value(
            request.get("radius"), [Interval(float, 0, None, "neither")], "radius", "studio edit"
        )
        operation = check_value(
            request.get("operation", "scale"), [Options(["scale", "remove"])], "operation", "edit"
        )
        factor = check_value(
            request.get("factor", 1.0), [Interval(float, 0, 100)], "factor", "studio edit"
        )
        region = np.flatnonzero(np.linalg.norm(vertices - vertices[vertex], axis=1) <= radius)
        detail = {"frame": frame, "vertices": region, "operation": operation, "factor": factor}
        if window is not None:
            detail["window"] = window
        return detail

    # -- geometry for the page ----------------------------------------------------------------
    def frames(self, animation: Animation, start: int, stop: int) -> np.ndarray:
        """(stop - start, V, 3) vertices of ``animation`` (a blendshape result's computed
        for these frames only)."""
        if animation.is_blendshape_based:
            assert animation.rig is not None and animation.weights is not None
            local = animation.rig.evaluate(animation.weights[start:stop])
            motion = None if animation.head_motion is None else animation.head_motion[start:stop]
            return apply_head_motion(motion, local)
        return np.asarray(animation.vertices[start:stop])

    def source_frames(self, start: int, stop: int) -> np.ndarray:
        """(stop - start, P, 3) points of the performance: mesh vertices, markers (NaN where
        missing), or a weight-curve source's rig evaluated."""
        from ..model import MarkerSequence, MeshSequence

        perf = self.source.performance
        if isinstance(perf, MarkerSequence):
            return np.asarray(perf.positions)[start:stop]
        if isinstance(perf, MeshSequence):
            return np.asarray(perf.vertices[start:stop])
        if self.source.rig is None:
            raise CapabilityError("studio: a weight-curve source without its rig cannot be shown")
        return self.source.rig.evaluate(np.asarray(perf.weights)[start:stop])

    def error_frames(self, animation: Animation, start: int, stop: int) -> np.ndarray:
        """(stop - start, V) distance of every vertex to the truth, in % of the face height."""
        if self.truth is None:
            raise CapabilityError(
                "studio: these inputs have no ground truth (use an evaluation case)"
            )
        mine = self.frames(animation, start, stop)
        right = self.frames(self.truth, start, stop)
        return np.linalg.norm(mine - right, axis=2) * (100.0 / self.face_height)

    def rig_key(self, animation: Animation) -> str | None:
        """A name for ``animation``'s rig, so the page loads each rig's deltas once."""
        rig = animation.rig if animation.is_blendshape_based else None
        if rig is None:
            return None
        with self._lock:
            if id(rig) not in self._rigs:
                self._rigs[id(rig)] = (f"rig{len(self._rigs)}", rig)
            return self._rigs[id(rig)][0]

    def rig(self, key: Any) -> BlendshapeRig:
        for name, rig in self._rigs.values():
            if name == key:
                return rig
        raise UnknownNameError(f"studio: no rig {key!r}; its key comes with a result")

    # -- export --------------------------------------------------------------------------------
    def export(self, rid: Any, fmt: Any) -> Path:
        """Write the current animation of result ``rid`` as ``fmt`` (:data:`EXPORT_FORMATS`)
        into :attr:`out_dir`, under a name no file has yet; returns the path."""
        from .. import io

        fmt = check_value(fmt, [Options(list(EXPORT_FORMATS))], "format", "studio export")
        result = self.result(rid)
        animation = result.animation
        if fmt == "csv" and animation.weights is None:
            raise CapabilityError(
                f"studio export: {result.method} gives vertices, not weight curves; export glb or pc2"
            )
        self.out_dir.mkdir(parents=True, exist_ok=True)
        stem = "".join(c if c.isalnum() or c in "-_" else "_" for c in self.name) or "studio"
        base = f"{stem}-{result.method}" + (f"-{result.undo_steps}edits" if result.position else "")
        for i in range(1, 10_000):
            path = self.out_dir / f"{base}{'' if i == 1 else f'-{i}'}{EXPORT_FORMATS[fmt]}"
            if not path.exists():
                break
        else:  # pragma: no cover - ten thousand exports of one result
            raise OutputError(f"studio export: no free file name for {base} in {self.out_dir}")
        return io.save(animation, path, inputs=[str(f) for f in self.files])


def changed_frames(before: Animation, after: Animation) -> list[int] | None:
    """First and last frame where ``after`` differs from ``before`` (None if nowhere)."""
    if before.weights is not None and after.weights is not None:
        a, b = before.weights, after.weights
        moved = np.any(a != b, axis=1)
    else:
        a3, b3 = np.asarray(before.vertices), np.asarray(after.vertices)
        moved = np.any(a3 != b3, axis=(1, 2))
    if before.head_motion is not None and after.head_motion is not None:
        moved |= np.any(before.head_motion != after.head_motion, axis=(1, 2))
    frames = np.flatnonzero(moved)
    return [int(frames[0]), int(frames[-1])] if len(frames) else None


def parameter_widget(param: Any) -> dict[str, Any]:
    """How the page shows one manifest parameter: ``name``, ``default``, ``valid`` (in words),
    ``doc``, and ``widget``: ``checkbox``, ``select`` (``choices``), ``number`` (``min``,
    ``max``, ``step``), ``text`` (strings, or a choice or a number: ``choices`` are
    suggestions) or ``json`` (arrays, mappings, anything the method checks itself);
    ``nullable`` when None is valid (an empty field)."""
    names = [getattr(c, "name", "") for c in param.constraints]
    options = [o for c in param.constraints if isinstance(c, Options) for o in c.options]
    numbers = [c for c in param.constraints if isinstance(c, Interval)]
    out: dict[str, Any] = {
        "name": param.name,
        "default": jsonable(param.default),
        "valid": describe(param.constraints),
        "doc": param.doc,
        "nullable": "none" in names,
    }
    plain = [n for n in names if n not in ("none", "")]
    if plain == ["boolean"] and not options and not numbers:
        out["widget"] = "checkbox"
    elif options and not numbers and not plain:
        out.update(widget="select", choices=options)
    elif numbers and len(numbers) == 1 and not options and not plain:
        c = numbers[0]
        out.update(
            widget="number",
            min=c.left,
            max=c.right,
            step=1 if c.kind is int else "any",
        )
    elif (options or numbers or "type" in plain) and not ({"array-like", "mapping"} & set(plain)):
        out.update(widget="text", choices=options)
    else:
        out["widget"] = "json"
    return out
