"""Conformance kit for retargeter authors (built-in and third-party).

Run every check on your class::

    from faceretarget.testing import check_retargeter
    check_retargeter(MyRetargeter)            # raises AssertionError naming the failed invariant

or one pytest test per check::

    from faceretarget.testing import parametrize_with_checks

    @parametrize_with_checks([MyRetargeter()])
    def test_conformance(retargeter, check):
        check(retargeter)

Each check tests one invariant on a tiny synthetic parallel-rig case
(:func:`tiny_case`) and fails with a message saying what broke:

- ``check_params``: ``__init__`` stores keyword parameters unchanged; get/set_params round trip
- ``check_not_fitted``: ``retarget`` before ``fit`` raises :class:`NotFittedError`
- ``check_output``: the result has the target's vertex count, every frame, finite values
- ``check_rest_pose``: a source that stays at its neutral gives the target's neutral
- ``check_rigid_motion``: rigid head motion alone is carried to the target, not turned into expression
- ``check_inputs_unchanged``: neither source nor target arrays change
- ``check_float32_readonly``: float32, read-only inputs work and agree with float64
- ``check_deterministic``: two fits give the same result
- ``check_clone_pickle``: ``clone`` gives equal parameters; a fitted retargeter survives pickling
- ``check_stream``: ``stream`` agrees with ``retarget`` (where offered)
- ``check_capabilities``: declared capabilities are honest (unsupported sources and missing
  rig parts raise :class:`CapabilityError`; "weights" outputs carry weights)
- ``check_unit_invariance``: scaling the source or the target by 0.01, 100 and 1000, or moving
  either rigidly, changes the result (expressed in the target's units and frame) by less
  than ``UNIT_TOLERANCE`` of the face height
- ``check_cross_topology_neutral``: on a source of another topology (:func:`tiny_cross_topology_case`:
  closed eyes, a mouth bag, another outline) resting at its neutral, the result is the
  target's neutral within ``CROSS_NEUTRAL_TOLERANCE`` (0.01%) of the face height
- ``check_declared_needs``: wherever ``why_not(source, target)`` is None (parts stripped one at a
  time, same and other topology, with and without landmarks) ``fit`` raises no
  :class:`CapabilityError`: declared needs are the real needs

The module is also a pytest plugin (entry point ``pytest11``) giving the fixture
``faceretarget_case`` (the tiny case).
"""

from __future__ import annotations

import copy
import functools
import hashlib
import pickle
from collections.abc import Callable, Iterable, Iterator, Sequence
from typing import TYPE_CHECKING, Any, TypeAlias, overload

import numpy as np
import numpy.typing as npt

from .errors import CapabilityError, FaceRetargetError, NotFittedError
from .model import (
    BlendshapeRig,
    LayeredRig,
    MarkerSequence,
    Mesh,
    MeshSequence,
    Source,
    TargetRig,
    WeightSequence,
)
from .retargeter import Retargeter, clone

if TYPE_CHECKING:
    import pytest

    from ._types import Performance
    from .cases import Case

#: A retargeter class or instance (the checks take either).
RetargeterLike: TypeAlias = Retargeter | type[Retargeter]

__all__ = [
    "check_retargeter",
    "parametrize_with_checks",
    "tiny_case",
    "CHECKS",
    "REST_TOLERANCE",
    "RIGID_TOLERANCE",
    "UNIT_TOLERANCE",
    "CROSS_NEUTRAL_TOLERANCE",
    "tiny_cross_topology_case",
]

#: RMS error allowed for the rest-pose and rigid checks, as a fraction of the target face height.
REST_TOLERANCE = 2e-3
RIGID_TOLERANCE = 5e-3
#: Agreement required between float32 and float64 inputs (fraction of face height).
FLOAT32_TOLERANCE = 1e-3
#: Largest change (RMS, fraction of the target's face height) allowed when the source or the
#: target is rescaled (x0.01, x100, x1000) or moved rigidly, the result mapped back.
UNIT_TOLERANCE = 1e-6
#: Scales and rigid moves tried by check_unit_invariance.
UNIT_SCALES = (0.01, 100.0, 1000.0)
#: RMS error allowed for a cross-topology source resting at its neutral (fraction of face height: 0.01%).
CROSS_NEUTRAL_TOLERANCE = 1e-4


@functools.lru_cache(maxsize=4)
def _build_tiny_case(seed: int) -> Case:
    from . import cases

    return cases.synthetic(seed=seed, resolution=600, n_frames=16)


def tiny_case(seed: int = 0) -> Case:
    """A small synthetic parallel-rig case carrying every rig part.

    Built once per seed; each call returns a deep copy, so a retargeter that mutates
    its inputs cannot spoil the case for the checks that follow.
    """
    return copy.deepcopy(_build_tiny_case(seed))


@functools.lru_cache(maxsize=2)
def _build_tiny_cross_topology_case(seed: int) -> Case:
    from . import cases

    return cases.cross_topology(seed=seed, n_frames=6)


def tiny_cross_topology_case(seed: int = 0) -> Case:
    """A short case whose source is of another topology than the target: the closed-eye head
    with a mouth bag and another outline of :func:`faceretarget.cases.cross_topology` (2,357
    vertices) onto the open-eye ICT face (9,409 vertices), 6 frames. A deep copy per call."""
    return copy.deepcopy(_build_tiny_cross_topology_case(seed))


# ------------------------------------------------------------------------------------
# helpers
# ------------------------------------------------------------------------------------
class _Affine:
    """``x -> scale * R x + t`` on points, ``scale * R d`` on displacements."""

    def __init__(
        self,
        scale: float = 1.0,
        rotation: npt.ArrayLike | None = None,
        translation: npt.ArrayLike | None = None,
    ) -> None:
        self.scale = float(scale)
        self.rotation = np.eye(3) if rotation is None else np.asarray(rotation, dtype=np.float64)
        self.translation = (
            np.zeros(3) if translation is None else np.asarray(translation, dtype=np.float64)
        )

    @overload
    def points(self, x: None) -> None: ...
    @overload
    def points(self, x: npt.ArrayLike) -> np.ndarray: ...
    def points(self, x: npt.ArrayLike | None) -> np.ndarray | None:
        return (
            None
            if x is None
            else self.scale * (np.asarray(x, dtype=np.float64) @ self.rotation.T) + self.translation
        )

    @overload
    def vectors(self, d: None) -> None: ...
    @overload
    def vectors(self, d: npt.ArrayLike) -> np.ndarray: ...
    def vectors(self, d: npt.ArrayLike | None) -> np.ndarray | None:
        return (
            None if d is None else self.scale * (np.asarray(d, dtype=np.float64) @ self.rotation.T)
        )

    def inverse_points(self, y: npt.ArrayLike) -> np.ndarray:
        return ((np.asarray(y, dtype=np.float64) - self.translation) @ self.rotation) / self.scale

    def matrix(self) -> np.ndarray:
        m = np.eye(4)
        m[:3, :3] = self.scale * self.rotation
        m[:3, 3] = self.translation
        return m

    def conjugate(self, motion: npt.ArrayLike | None) -> np.ndarray | None:
        """Rigid motions ``(F, 4, 4)`` seen in the moved frame: ``A M A^-1``."""
        if motion is None:
            return None
        a = self.matrix()
        return a @ np.asarray(motion, dtype=np.float64) @ np.linalg.inv(a)

    def mesh(self, mesh: Mesh) -> Mesh:
        return Mesh(self.points(mesh.vertices), mesh.triangles, name=mesh.name)

    def rig(self, rig: BlendshapeRig | None) -> BlendshapeRig | None:
        if rig is None:
            return None
        return BlendshapeRig(
            self.mesh(rig.neutral), self.vectors(rig.deltas), rig.names, bounds=rig.bounds
        )

    def layers(self, layers: LayeredRig | None) -> LayeredRig | None:
        if layers is None:
            return None
        return LayeredRig(
            {k: self.points(v) for k, v in layers.layers.items()},
            np.asarray(layers.masks),
            pose_names=layers.pose_names,
            region_names=layers.region_names,
        )


def _rotation(axis: Sequence[float] | np.ndarray, degrees: float) -> np.ndarray:
    axis = np.asarray(axis, dtype=np.float64)
    axis = axis / np.linalg.norm(axis)
    k = np.array([[0.0, -axis[2], axis[1]], [axis[2], 0.0, -axis[0]], [-axis[1], axis[0], 0.0]])
    a = np.deg2rad(degrees)
    return np.eye(3) + np.sin(a) * k + (1.0 - np.cos(a)) * (k @ k)


def _moved_source(source: Source, a: _Affine) -> Source:
    """The same performance with every 3D position moved by ``a`` (2D tracks stay in the image)."""
    perf = source.performance
    moved: MeshSequence | MarkerSequence | WeightSequence
    if isinstance(perf, MeshSequence):
        moved = MeshSequence(
            a.points(perf.vertices),
            perf.triangles,
            fps=perf.fps,
            reference=a.mesh(perf.reference),
            name=perf.name,
        )
    elif isinstance(perf, MarkerSequence):
        moved = MarkerSequence(
            a.points(perf.positions),
            names=perf.names,
            fps=perf.fps,
            reference=a.points(perf.reference),
        )
    else:
        moved = perf
    return source.replace(
        performance=moved,
        examples=a.points(source.examples),
        rig=a.rig(source.rig),
        actor_layers=a.layers(source.actor_layers),
        head_motion=a.conjugate(source.head_motion),
    )


def _moved_target(target: TargetRig, a: _Affine) -> TargetRig:
    neutral = a.mesh(target.neutral)
    rig = None
    if target.blendshapes is not None:
        rig = BlendshapeRig(
            neutral,
            a.vectors(target.blendshapes.deltas),
            target.blendshapes.names,
            bounds=target.blendshapes.bounds,
        )
    return target.replace(
        neutral=neutral,
        blendshapes=rig,
        layers=a.layers(target.layers),
        examples=a.points(target.examples),
    )


def _instance(obj: RetargeterLike) -> Retargeter:
    if isinstance(obj, Retargeter):
        return clone(obj)
    if isinstance(obj, type) and issubclass(obj, Retargeter):
        return obj()
    raise TypeError(f"expected a Retargeter subclass or instance, got {obj!r}")


def _label(r: RetargeterLike) -> str:
    return r.name or type(r).__name__


def _replace_performance(source: Source, performance: Performance) -> Source:
    """``source`` with another performance, keeping every extra that still fits."""
    keep_landmarks = isinstance(performance, MeshSequence)
    same_frames = source.tracks2d is not None and source.tracks2d.n_frames == performance.n_frames
    return source.replace(
        performance=performance,
        head_motion=None,
        landmarks=source.landmarks if keep_landmarks else None,
        feature_lines=source.feature_lines if keep_landmarks else None,
        examples=source.examples
        if (keep_landmarks or source.examples is None)
        else _examples_at_markers(source),
        example_names=source.example_names or None,
        tracks2d=source.tracks2d if same_frames else None,
        actor_layers_2d=source.actor_layers_2d if same_frames else None,
    )


def _examples_at_markers(source: Source) -> np.ndarray | None:
    if source.landmarks is None:
        return None
    assert isinstance(source.performance, MeshSequence)  # Source: only a mesh takes landmarks
    assert source.examples is not None  # _replace_performance calls this only with examples
    return source.landmarks.positions(source.examples, source.performance.triangles)


def _source_of_kind(case: Case, kind: str) -> Source:
    src = case.source
    if src.kind == kind:
        return src
    if kind == "markers":
        positions = src.marker_positions()
        assert src.landmarks is not None  # else marker_positions() raised CapabilityError
        markers = MarkerSequence(
            positions,
            names=src.landmarks.names,
            fps=src.fps,
            reference=src.marker_reference(),
        )
        return _replace_performance(src, markers)
    if kind == "weights":
        weights = case.meta.get("weights")
        rig = case.meta.get("source_rig") or src.rig
        if weights is None or rig is None:
            raise AssertionError(
                "the tiny case has no source weight curves and rig to test a weights-only retargeter"
            )
        ws = WeightSequence(weights, rig.names, fps=src.fps)
        return Source(ws, rig=rig)
    raise AssertionError(f"cannot build a {kind!r} source from the tiny case")


def _preferred_source(r: Retargeter, case: Case) -> Source:
    kinds = r.capabilities.sources
    for kind in ("mesh", "markers", "weights"):
        if kind in kinds:
            return _source_of_kind(case, kind)
    raise AssertionError(f"{_label(r)} declares no known source kind: {kinds}")


def _static_source(source: Source, transforms: np.ndarray | None = None) -> Source:
    """Every frame at the source's neutral, optionally moved rigidly by ``transforms (F, 4, 4)``."""
    perf = source.performance
    n_frames = perf.n_frames
    if isinstance(perf, MeshSequence):
        ref = np.asarray(perf.reference.vertices)
        frames = np.repeat(ref[None], n_frames, axis=0)
        if transforms is not None:
            frames = (
                np.einsum("fij,fpj->fpi", transforms[:, :3, :3], frames)
                + transforms[:, None, :3, 3]
            )
        return _replace_performance(
            source, MeshSequence(frames, perf.triangles, fps=perf.fps, reference=perf.reference)
        )
    if isinstance(perf, MarkerSequence):
        ref = np.asarray(perf.reference)
        frames = np.repeat(ref[None], n_frames, axis=0)
        if transforms is not None:
            frames = (
                np.einsum("fij,fpj->fpi", transforms[:, :3, :3], frames)
                + transforms[:, None, :3, 3]
            )
        return _replace_performance(
            source, MarkerSequence(frames, names=perf.names, fps=perf.fps, reference=ref)
        )
    if isinstance(perf, WeightSequence):
        return Source(
            WeightSequence(np.zeros_like(perf.weights), perf.names, fps=perf.fps), rig=source.rig
        )
    raise AssertionError("unknown performance type")


def _rigid_transforms(n_frames: int, size: float) -> np.ndarray:
    """Smooth rigid head motion: up to ~8 degrees of rotation and 5% of ``size`` translation."""
    t = np.linspace(0.0, 1.0, n_frames)
    out = np.zeros((n_frames, 4, 4))
    for f, s in enumerate(t):
        ax, ay = 0.14 * np.sin(2 * np.pi * s), 0.10 * np.sin(np.pi * s)
        cx, sx, cy, sy = np.cos(ax), np.sin(ax), np.cos(ay), np.sin(ay)
        rx = np.array([[1, 0, 0], [0, cx, -sx], [0, sx, cx]])
        ry = np.array([[cy, 0, sy], [0, 1, 0], [-sy, 0, cy]])
        out[f, :3, :3] = ry @ rx
        out[f, :3, 3] = size * 0.05 * np.array([np.sin(np.pi * s), 0.5 * s, -0.3 * s])
        out[f, 3, 3] = 1.0
    return out


def _rms(a: np.ndarray, b: np.ndarray) -> float:
    return float(
        np.sqrt(np.mean(np.sum((np.asarray(a, float) - np.asarray(b, float)) ** 2, axis=-1)))
    )


def _fingerprint(obj: object) -> str:
    """Hash of every numpy array reachable from a model object (to detect mutation).

    Cached derived operators (``functools.cached_property``) are skipped: they are
    not inputs and may be filled in by use.
    """
    h = hashlib.sha256()
    seen: dict[int, object] = {}  # id -> object, kept alive so ids are not reused

    def visit(x: object) -> None:
        if isinstance(x, (str, bytes, int, float, bool, type(None))):
            h.update(repr(x).encode())
            return
        if id(x) in seen:
            return
        seen[id(x)] = x
        if isinstance(x, np.ndarray):
            h.update(str((x.shape, x.dtype)).encode())
            h.update(np.ascontiguousarray(x).tobytes())
        elif isinstance(x, dict):
            for k in sorted(x, key=str):
                h.update(str(k).encode())
                visit(x[k])
        elif isinstance(x, (list, tuple)):
            for v in x:
                visit(v)
        elif type(x).__module__.startswith("faceretarget"):
            cls = type(x)
            fields = {}
            for klass in cls.__mro__:
                for slot in getattr(klass, "__slots__", ()):
                    if slot != "__dict__" and hasattr(x, slot):
                        fields[slot] = getattr(x, slot)
            for k, v in getattr(x, "__dict__", {}).items():
                if not k.startswith("_") and not isinstance(
                    getattr(cls, k, None), functools.cached_property
                ):
                    fields[k] = v
            visit(fields)

    visit(obj)
    return h.hexdigest()


@overload
def _f32(x: None) -> None: ...
@overload
def _f32(x: npt.ArrayLike) -> np.ndarray: ...
def _f32(x: npt.ArrayLike | None) -> np.ndarray | None:
    """A float32, read-only copy of ``x`` (None stays None)."""
    if x is None:
        return None
    y = np.array(x, dtype=np.float32)
    y.flags.writeable = False
    return y


def _layers32(layers: LayeredRig | None) -> LayeredRig | None:
    if layers is None:
        return None
    return LayeredRig(
        {k: _f32(v) for k, v in layers.layers.items()},
        _f32(layers.masks),
        pose_names=layers.pose_names,
        region_names=layers.region_names,
    )


def _performance32(perf: Performance) -> Performance:
    if isinstance(perf, MeshSequence):
        return MeshSequence(
            _f32(perf.vertices),
            perf.triangles,
            fps=perf.fps,
            reference=_f32(perf.reference.vertices),
        )
    if isinstance(perf, MarkerSequence):
        return MarkerSequence(
            _f32(perf.positions), names=perf.names, fps=perf.fps, reference=_f32(perf.reference)
        )
    return WeightSequence(_f32(perf.weights), perf.names, fps=perf.fps)


def _rig32(rig: BlendshapeRig | None) -> BlendshapeRig | None:
    if rig is None:
        return None
    return BlendshapeRig(
        Mesh(_f32(rig.neutral.vertices), rig.neutral.triangles),
        _f32(rig.deltas),
        rig.names,
        bounds=rig.bounds,
    )


def _source32(source: Source) -> Source:
    """The same source rebuilt from float32, read-only arrays."""
    return source.replace(
        performance=_performance32(source.performance),
        examples=_f32(source.examples),
        rig=_rig32(source.rig),
        actor_layers=_layers32(source.actor_layers),
        tracks2d=None if source.tracks2d is None else _performance32(source.tracks2d),
        actor_layers_2d=_layers32(source.actor_layers_2d),
    )


def _target32(target: TargetRig) -> TargetRig:
    """The same target rebuilt from float32, read-only arrays."""
    neutral = Mesh(
        _f32(target.neutral.vertices), target.neutral.triangles, name=target.neutral.name
    )
    rig = None
    if target.blendshapes is not None:
        rig = BlendshapeRig(
            neutral,
            _f32(target.blendshapes.deltas),
            target.blendshapes.names,
            bounds=target.blendshapes.bounds,
        )
    return target.replace(
        neutral=neutral,
        blendshapes=rig,
        layers=_layers32(target.layers),
        examples=_f32(target.examples),
    )


# ------------------------------------------------------------------------------------
# the checks
# ------------------------------------------------------------------------------------
def check_params(r: RetargeterLike, case: Case | None = None) -> None:
    r = _instance(r)
    params = r.get_params()
    fresh = type(r)(**params)
    assert fresh.get_params().keys() == params.keys(), (
        f"{_label(r)}: get_params() keys change after reconstruction"
    )
    for k, v in params.items():
        same = fresh.get_params()[k]
        assert same is v or _equal(same, v), (
            f"{_label(r)}: __init__ must store parameter {k!r} unchanged (got {same!r} for {v!r})"
        )
    r.set_params(**params)
    assert _equal(r.get_params(), params), (
        f"{_label(r)}: set_params(**get_params()) changed the parameters"
    )


def check_not_fitted(r: RetargeterLike, case: Case | None = None) -> None:
    case = case or tiny_case()
    r = _instance(r)
    source = _preferred_source(r, case)
    try:
        r.retarget(source)
    except NotFittedError:
        return
    raise AssertionError(
        f"{_label(r)}: retarget() before fit() must raise faceretarget.NotFittedError"
    )


def check_output(r: RetargeterLike, case: Case | None = None) -> None:
    case = case or tiny_case()
    r = _instance(r)
    source = _preferred_source(r, case)
    anim = r.fit(source, case.target).retarget(source)
    v = np.asarray(anim.vertices)
    want = (source.n_frames, case.target.neutral.n_vertices, 3)
    assert v.shape == want, f"{_label(r)}: Animation.vertices has shape {v.shape}, expected {want}"
    assert np.isfinite(v).all(), f"{_label(r)}: Animation.vertices holds NaN or inf"
    assert anim.provenance.get("method") == r.name, f"{_label(r)}: provenance lacks the method name"


def check_rest_pose(r: RetargeterLike, case: Case | None = None) -> None:
    case = case or tiny_case()
    r = _instance(r)
    source = _static_source(_preferred_source(r, case))
    anim = r.fit(source, case.target).retarget(source)
    height = case.target.neutral.height
    want = np.repeat(np.asarray(case.target.neutral.vertices)[None], source.n_frames, axis=0)
    err = _rms(anim.vertices, want) / height
    assert err <= REST_TOLERANCE, (
        f"{_label(r)}: a source resting at its neutral must give the target's neutral; RMS error is "
        f"{100 * err:.3f}% of face height (allowed {100 * REST_TOLERANCE:.2f}%)"
    )


def check_rigid_motion(r: RetargeterLike, case: Case | None = None) -> None:
    case = case or tiny_case()
    r = _instance(r)
    base = _preferred_source(r, case)
    if base.kind == "weights":
        return  # weight curves carry no head motion
    transforms = _rigid_transforms(base.n_frames, case.target.neutral.height)
    source = _static_source(base, transforms)
    anim = r.fit(source, case.target).retarget(source)
    neutral = np.asarray(case.target.neutral.vertices)
    want = np.einsum("fij,pj->fpi", transforms[:, :3, :3], neutral) + transforms[:, None, :3, 3]
    height = case.target.neutral.height
    err = _rms(anim.vertices, want) / height
    assert err <= RIGID_TOLERANCE, (
        f"{_label(r)}: rigid head motion with no expression must move the target rigidly; RMS error is "
        f"{100 * err:.3f}% of face height (allowed {100 * RIGID_TOLERANCE:.2f}%): head motion turned into expression?"
    )
    if anim.weights is not None:
        assert np.abs(anim.weights).max() < 0.05, (
            f"{_label(r)}: rigid motion alone produced blendshape weights up to {np.abs(anim.weights).max():.3f}"
        )


def check_inputs_unchanged(r: RetargeterLike, case: Case | None = None) -> None:
    case = case or tiny_case()
    r = _instance(r)
    source = _preferred_source(r, case)
    before = (_fingerprint(source), _fingerprint(case.target))
    r.fit(source, case.target).retarget(source)
    after = (_fingerprint(source), _fingerprint(case.target))
    assert before[0] == after[0], f"{_label(r)}: fit/retarget modified the source"
    assert before[1] == after[1], f"{_label(r)}: fit/retarget modified the target rig"


def check_float32_readonly(r: RetargeterLike, case: Case | None = None) -> None:
    case = case or tiny_case()
    source = _preferred_source(_instance(r), case)
    ref = _instance(r).fit(source, case.target).retarget(source).vertices
    source32 = _source32(source)
    target32 = _target32(case.target)
    try:
        got = _instance(r).fit(source32, target32).retarget(source32).vertices
    except ValueError as exc:
        if "read-only" in str(exc) or "readonly" in str(exc):
            raise AssertionError(
                f"{_label(r)}: writes into a read-only input array ({exc})"
            ) from exc
        raise
    err = _rms(got, ref) / case.target.neutral.height
    assert err <= FLOAT32_TOLERANCE, (
        f"{_label(r)}: float32 inputs differ from float64 by {100 * err:.4f}% of face height"
    )


def check_deterministic(r: RetargeterLike, case: Case | None = None) -> None:
    case = case or tiny_case()
    source = _preferred_source(_instance(r), case)
    a = _instance(r).fit(source, case.target).retarget(source)
    b = _instance(r).fit(source, case.target).retarget(source)
    assert np.array_equal(np.asarray(a.vertices), np.asarray(b.vertices)), (
        f"{_label(r)}: two fits on the same input differ"
    )


def check_clone_pickle(r: RetargeterLike, case: Case | None = None) -> None:
    case = case or tiny_case()
    r = _instance(r)
    twin = clone(r)
    assert type(twin) is type(r) and _equal(twin.get_params(), r.get_params()), (
        f"{_label(r)}: clone() changed the parameters"
    )
    assert not getattr(twin, "fitted_", False), (
        f"{_label(r)}: clone() must return an unfitted retargeter"
    )
    source = _preferred_source(r, case)
    r.fit(source, case.target)
    want = np.asarray(r.retarget(source).vertices)
    again = pickle.loads(pickle.dumps(r))
    got = np.asarray(again.retarget(source).vertices)
    assert np.allclose(got, want, rtol=0, atol=1e-9 * max(1.0, case.target.neutral.height)), (
        f"{_label(r)}: a pickled and restored retargeter gives a different result"
    )


def check_stream(r: RetargeterLike, case: Case | None = None) -> None:
    r = _instance(r)
    if not r.capabilities.stream:
        try:
            list(r.stream([]))
        except CapabilityError:
            return
        raise AssertionError(
            f"{_label(r)}: declares stream=False but stream() does not raise CapabilityError"
        )
    case = case or tiny_case()
    source = _preferred_source(r, case)
    r.fit(source, case.target)
    batch = np.asarray(r.retarget(source).vertices)
    perf = source.performance
    if isinstance(perf, MarkerSequence):
        frames = list(np.asarray(perf.positions))
    elif isinstance(perf, MeshSequence):
        frames = list(np.asarray(perf.vertices))
    else:
        frames = list(np.asarray(perf.weights))
    streamed = np.stack([np.asarray(f) for f in r.stream(iter(frames))])
    assert streamed.shape == batch.shape, (
        f"{_label(r)}: stream() gave {streamed.shape}, retarget() gave {batch.shape}"
    )
    err = _rms(streamed, batch) / case.target.neutral.height
    assert err <= 1e-6, (
        f"{_label(r)}: stream() differs from retarget() by {100 * err:.5f}% of face height"
    )


def check_capabilities(r: RetargeterLike, case: Case | None = None) -> None:
    case = case or tiny_case()
    r = _instance(r)
    caps = r.capabilities
    for kind in ("markers", "mesh"):
        if kind in caps.sources:
            continue
        try:
            source = _source_of_kind(case, kind)
        except AssertionError:
            continue
        try:
            _instance(r).fit(source, case.target)
        except CapabilityError:
            continue
        raise AssertionError(
            f"{_label(r)}: does not declare {kind!r} sources but fit() accepted one without CapabilityError"
        )
    source = _preferred_source(r, case)
    for need in caps.needs:
        options = need if isinstance(need, tuple) else (need,)
        if not all(n in TargetRig.PARTS for n in options):
            continue
        stripped = _target_without(case.target, options)
        try:
            _instance(r).fit(source, stripped)
        except CapabilityError as exc:
            assert str(exc), f"{_label(r)}: CapabilityError without a message"
            continue
        raise AssertionError(
            f"{_label(r)}: declares it needs {' or '.join(options)} but fit() worked without it"
        )
    declared = {n for need in caps.needs for n in (need if isinstance(need, tuple) else (need,))}
    for part in TargetRig.PARTS:
        if part in declared or not case.target.has(part):
            continue
        stripped = _target_without(case.target, (part,))
        try:
            _instance(r).fit(source, stripped).retarget(source)
        except CapabilityError:
            continue  # a conditional need, stated clearly
        except Exception as exc:
            raise AssertionError(
                f"{_label(r)}: fails without the target's {part} ({type(exc).__name__}: {exc}) but does not declare it in capabilities.needs"
            ) from exc
    if caps.outputs == "weights":
        anim = _instance(r).fit(source, case.target).retarget(source)
        assert anim.weights is not None, (
            f"{_label(r)}: declares outputs='weights' but the Animation has no weights"
        )
    if not caps.edit:
        fitted = _instance(r).fit(source, case.target)
        try:
            fitted.edit(fitted.retarget(source))
        except CapabilityError:
            pass
        else:
            raise AssertionError(
                f"{_label(r)}: declares edit=False but edit() does not raise CapabilityError"
            )


def check_unit_invariance(r: RetargeterLike, case: Case | None = None) -> None:
    """Rescaling (x0.01, x100, x1000) or rigidly moving the source or the target changes
    nothing but the units and frame of the result.

    Run on the case's expressions without head motion (see :func:`_without_head_motion`).
    """
    case = _without_head_motion(case or tiny_case())
    source = _preferred_source(_instance(r), case)
    target = case.target
    height = target.neutral.height
    base = np.asarray(_instance(r).fit(source, target).retarget(source).vertices, dtype=np.float64)
    centre = np.asarray(target.neutral.vertices).mean(axis=0)
    rigid = _Affine(1.0, _rotation([0.3, 1.0, 0.2], 25.0), np.array([1.0, -2.0, 0.5]) * height)
    moves: list[tuple[str, _Affine | None, _Affine | None]] = [
        (f"source x{s:g}", _Affine(s), None) for s in UNIT_SCALES
    ]
    moves += [(f"target x{s:g}", None, _Affine(s, None, centre * (1.0 - s))) for s in UNIT_SCALES]
    moves += [("source moved rigidly", rigid, None), ("target moved rigidly", None, rigid)]
    failures = []
    for label, on_source, on_target in moves:
        if on_source is not None and source.kind == "weights":
            continue  # weight curves have no units
        src = _moved_source(source, on_source) if on_source is not None else source
        tgt = _moved_target(target, on_target) if on_target is not None else target
        try:
            got = np.asarray(_instance(r).fit(src, tgt).retarget(src).vertices, dtype=np.float64)
        except FaceRetargetError as exc:
            failures.append(f"{label}: {type(exc).__name__}: {exc}")
            continue
        if on_target is not None:
            got = on_target.inverse_points(got)
        err = _rms(got, base) / height
        if not err <= UNIT_TOLERANCE:
            failures.append(f"{label}: result differs by {err:.3g} of the face height")
    assert not failures, (
        f"{_label(r)}: the result must not depend on units or placement (allowed {UNIT_TOLERANCE:g} of the face height, "
        f"RMS, in the target's units): " + "; ".join(failures)
    )


def _without_head_motion(case: Case) -> Case:
    """The case with its mesh performance rebuilt from the source rig and true weights
    (expressions only): head motion is applied in world coordinates, so moving the target
    would rightly change where a head turn takes it (check_rigid_motion covers head motion)."""
    import dataclasses

    src = case.source
    weights = case.meta.get("weights") if isinstance(getattr(case, "meta", None), dict) else None
    if src.kind != "mesh" or src.rig is None or weights is None:
        return case
    perf = src.performance
    assert isinstance(perf, MeshSequence)  # src.kind == "mesh"
    local = MeshSequence(
        src.rig.evaluate(weights),
        perf.triangles,
        fps=perf.fps,
        reference=perf.reference,
        name=perf.name,
    )
    return dataclasses.replace(case, source=src.replace(performance=local, head_motion=None))


def check_cross_topology_neutral(r: RetargeterLike, case: Case | None = None) -> None:
    """A source of another topology resting at its neutral gives the target's neutral.

    Uses :func:`tiny_cross_topology_case` (``case`` is ignored: the check needs a pair of
    different topologies). Not applicable (returns) to weight-only retargeters, and where
    ``why_not`` rules the pair out.
    """
    r = _instance(r)
    kinds = [k for k in ("mesh", "markers") if k in r.capabilities.sources]
    if not kinds:
        return  # weight curves have no topology
    xcase = tiny_cross_topology_case()
    assert isinstance(xcase.source.performance, MeshSequence)  # cross_topology: a mesh source
    source = _static_source(_source_of_kind(xcase, kinds[0]))
    if type(r).why_not(source, xcase.target) is not None:
        return
    anim = r.fit(source, xcase.target).retarget(source)
    want = np.repeat(np.asarray(xcase.target.neutral.vertices)[None], source.n_frames, axis=0)
    got = np.asarray(anim.vertices, dtype=np.float64)
    err = _rms(got, want) / xcase.target.neutral.height
    per_vertex = np.linalg.norm(got - want, axis=-1).max(axis=0) / xcase.target.neutral.height
    assert err <= CROSS_NEUTRAL_TOLERANCE, (
        f"{_label(r)}: a {source.kind} source of another topology ({xcase.source.performance.reference.n_vertices} vertices, "
        f"closed eyes, mouth bag) resting at its neutral must give the target's neutral; RMS error is {100 * err:.4f}% of "
        f"face height (allowed {100 * CROSS_NEUTRAL_TOLERANCE:.2f}%), {100 * np.mean(per_vertex > 0.01):.1f}% of the "
        f"vertices off by more than 1%"
    )


def _stripped_variants(
    source: Source, target: TargetRig
) -> Iterator[tuple[str, Source, TargetRig]]:
    """(label, source, target): the pair as given, then with one part removed at a time."""
    yield "as given", source, target
    for part in TargetRig.PARTS:
        if target.has(part):
            yield f"target without {part}", source, _target_without(target, (part,))
    extras = {
        "landmarks": dict(landmarks=None),
        "examples": dict(examples=None, example_names=None),
        "feature_lines": dict(feature_lines=None),
        "actor_layers": dict(actor_layers=None),
        "rig": dict(rig=None),
    }
    for part, change in extras.items():
        if getattr(source, part, None) is not None and not (
            part == "feature_lines" and not source.feature_lines
        ):
            if part == "landmarks" and source.kind != "mesh":
                continue
            yield f"source without {part}", source.replace(**change), target
    if source.kind == "mesh" and source.landmarks is not None and target.landmarks is not None:
        yield (
            "neither with landmarks",
            source.replace(landmarks=None),
            _target_without(target, ("landmarks",)),
        )


def check_declared_needs(r: RetargeterLike, case: Case | None = None) -> None:
    """Where ``why_not(source, target)`` is None, ``fit`` must not raise CapabilityError.

    Tried on the given (or tiny) case and on :func:`tiny_cross_topology_case`, each as given
    and with one rig part or source extra removed at a time (and landmarks removed from
    both): a need that ``fit`` enforces must be declared (``capabilities.needs``, or a
    ``why_not`` override for a conditional need such as "landmarks when the topologies differ").
    """
    cls = type(_instance(r))
    pairs = [("same topology", case or tiny_case())]
    kinds = [k for k in ("mesh", "markers") if k in cls.capabilities.sources]
    if kinds:
        pairs.append(("other topology", tiny_cross_topology_case()))
    failures = []
    for pair_label, c in pairs:
        base = _preferred_source(_instance(r), c)
        for label, source, target in _stripped_variants(base, c.target):
            if cls.why_not(source, target) is not None:
                continue
            try:
                _instance(r).fit(source, target)
            except CapabilityError as exc:
                failures.append(f"{pair_label}, {label}: {exc}")
    assert not failures, (
        f"{_label(r)}: why_not() said it applies but fit() raised CapabilityError; declare the need "
        "(capabilities.needs, or override why_not for a conditional need): " + "; ".join(failures)
    )


def _target_without(target: TargetRig, parts: Iterable[str]) -> TargetRig:
    return target.replace(**{p: None for p in parts})


def _equal(a: Any, b: Any) -> bool:
    if isinstance(a, dict) and isinstance(b, dict):
        return a.keys() == b.keys() and all(_equal(a[k], b[k]) for k in a)
    if isinstance(a, np.ndarray) or isinstance(b, np.ndarray):
        return np.array_equal(np.asarray(a), np.asarray(b))
    if isinstance(a, float) and isinstance(b, float) and np.isnan(a) and np.isnan(b):
        return True
    return a == b


CHECKS: tuple[Callable, ...] = (
    check_params,
    check_not_fitted,
    check_output,
    check_rest_pose,
    check_rigid_motion,
    check_inputs_unchanged,
    check_float32_readonly,
    check_deterministic,
    check_clone_pickle,
    check_stream,
    check_capabilities,
    check_unit_invariance,
    check_cross_topology_neutral,
    check_declared_needs,
)


def check_retargeter(retargeter: RetargeterLike, case: Case | None = None) -> None:
    """Run every conformance check on a Retargeter class or instance.

    Raises AssertionError (the first failed invariant, by name). ``case`` defaults to
    :func:`tiny_case`.
    """
    for check in CHECKS:
        try:
            check(retargeter, case)
        except AssertionError as exc:
            raise AssertionError(f"[{check.__name__}] {exc}") from exc
        except FaceRetargetError as exc:
            name = getattr(retargeter, "name", None) or getattr(retargeter, "__name__", retargeter)
            raise AssertionError(
                f"[{check.__name__}] {name} raised {type(exc).__name__}: {exc}"
            ) from exc


def parametrize_with_checks(retargeters: Iterable[RetargeterLike]) -> pytest.MarkDecorator:
    """A pytest decorator: one test per (retargeter, check), ids like ``spacetime-check_rest_pose``.

    The decorated test takes the arguments ``retargeter`` and ``check``.
    """
    import pytest

    items = list(retargeters)
    params = []
    for r in items:
        label = getattr(r, "name", None) or getattr(r, "__name__", type(r).__name__)
        for check in CHECKS:
            params.append(pytest.param(r, check, id=f"{label}-{check.__name__}"))
    return pytest.mark.parametrize("retargeter, check", params)


# ------------------------------------------------------------------------------------
# pytest plugin (entry point pytest11 = faceretarget.testing)
# ------------------------------------------------------------------------------------
try:  # pragma: no cover - only when pytest is importable
    import pytest as _pytest

    @_pytest.fixture(scope="session")
    def faceretarget_case() -> Case:
        """A tiny synthetic parallel-rig case with every rig part (see ``tiny_case``)."""
        return tiny_case()

except ImportError:  # pragma: no cover
    pass
