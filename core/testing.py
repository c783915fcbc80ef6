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

The module is also a pytest plugin (entry point ``pytest11``) giving the fixture
``faceretarget_case`` (the tiny case).
"""
from __future__ import annotations

import copy
import functools
import hashlib
import pickle
from typing import Callable, Iterable

import numpy as np

from .errors import CapabilityError, FaceRetargetError, NotFittedError
from .model import BlendshapeRig, LayeredRig, MarkerSequence, Mesh, MeshSequence, Source, TargetRig, WeightSequence
from .retargeter import Retargeter, clone

__all__ = [
    "check_retargeter",
    "parametrize_with_checks",
    "tiny_case",
    "CHECKS",
    "REST_TOLERANCE",
    "RIGID_TOLERANCE",
]

#: RMS error allowed for the rest-pose and rigid checks, as a fraction of the target face height.
REST_TOLERANCE = 2e-3
RIGID_TOLERANCE = 5e-3
#: Agreement required between float32 and float64 inputs (fraction of face height).
FLOAT32_TOLERANCE = 1e-3


@functools.lru_cache(maxsize=4)
def _build_tiny_case(seed: int):
    from . import cases

    return cases.synthetic(seed=seed, resolution=600, n_frames=16)


def tiny_case(seed: int = 0):
    """A small synthetic parallel-rig case carrying every rig part.

    Built once per seed; each call returns a deep copy, so a retargeter that mutates
    its inputs cannot spoil the case for the checks that follow.
    """
    return copy.deepcopy(_build_tiny_case(seed))


# ------------------------------------------------------------------------------------
# helpers
# ------------------------------------------------------------------------------------
def _instance(obj) -> Retargeter:
    if isinstance(obj, Retargeter):
        return clone(obj)
    if isinstance(obj, type) and issubclass(obj, Retargeter):
        return obj()
    raise TypeError(f"expected a Retargeter subclass or instance, got {obj!r}")


def _label(r: Retargeter) -> str:
    return r.name or type(r).__name__


def _replace_performance(source: Source, performance) -> Source:
    """``source`` with another performance, keeping every extra that still fits."""
    keep_landmarks = isinstance(performance, MeshSequence)
    same_frames = source.tracks2d is not None and source.tracks2d.n_frames == performance.n_frames
    return source.replace(
        performance=performance,
        head_motion=None,
        landmarks=source.landmarks if keep_landmarks else None,
        feature_lines=source.feature_lines if keep_landmarks else None,
        examples=source.examples if (keep_landmarks or source.examples is None) else _examples_at_markers(source),
        example_names=source.example_names or None,
        tracks2d=source.tracks2d if same_frames else None,
        actor_layers_2d=source.actor_layers_2d if same_frames else None,
    )


def _examples_at_markers(source: Source):
    if source.landmarks is None:
        return None
    return source.landmarks.positions(source.examples, source.performance.triangles)


def _source_of_kind(case, kind: str) -> Source:
    src = case.source
    if src.kind == kind:
        return src
    if kind == "markers":
        markers = MarkerSequence(
            src.marker_positions(), names=src.landmarks.names, fps=src.fps, reference=src.marker_reference()
        )
        return _replace_performance(src, markers)
    if kind == "weights":
        weights = case.meta.get("weights")
        rig = case.meta.get("source_rig") or src.rig
        if weights is None or rig is None:
            raise AssertionError("the tiny case has no source weight curves and rig to test a weights-only retargeter")
        ws = WeightSequence(weights, rig.names, fps=src.fps)
        return Source(ws, rig=rig)
    raise AssertionError(f"cannot build a {kind!r} source from the tiny case")


def _preferred_source(r: Retargeter, case) -> Source:
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
            frames = np.einsum("fij,fpj->fpi", transforms[:, :3, :3], frames) + transforms[:, None, :3, 3]
        return _replace_performance(source, MeshSequence(frames, perf.triangles, fps=perf.fps, reference=perf.reference))
    if isinstance(perf, MarkerSequence):
        ref = np.asarray(perf.reference)
        frames = np.repeat(ref[None], n_frames, axis=0)
        if transforms is not None:
            frames = np.einsum("fij,fpj->fpi", transforms[:, :3, :3], frames) + transforms[:, None, :3, 3]
        return _replace_performance(source, MarkerSequence(frames, names=perf.names, fps=perf.fps, reference=ref))
    if isinstance(perf, WeightSequence):
        return Source(WeightSequence(np.zeros_like(perf.weights), perf.names, fps=perf.fps), rig=source.rig)
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
    return float(np.sqrt(np.mean(np.sum((np.asarray(a, float) - np.asarray(b, float)) ** 2, axis=-1))))


def _fingerprint(obj) -> str:
    """Hash of every numpy array reachable from a model object (to detect mutation).

    Cached derived operators (``functools.cached_property``) are skipped: they are
    not inputs and may be filled in by use.
    """
    h = hashlib.sha256()
    seen: dict[int, object] = {}  # id -> object, kept alive so ids are not reused

    def visit(x):
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
                if not k.startswith("_") and not isinstance(getattr(cls, k, None), functools.cached_property):
                    fields[k] = v
            visit(fields)

    visit(obj)
    return h.hexdigest()


def _f32(x):
    """A float32, read-only copy of ``x`` (None stays None)."""
    if x is None:
        return None
    y = np.array(x, dtype=np.float32)
    y.flags.writeable = False
    return y


def _layers32(layers):
    if layers is None:
        return None
    return LayeredRig(
        {k: _f32(v) for k, v in layers.layers.items()},
        _f32(layers.masks),
        pose_names=layers.pose_names,
        region_names=layers.region_names,
    )


def _performance32(perf):
    if isinstance(perf, MeshSequence):
        return MeshSequence(_f32(perf.vertices), perf.triangles, fps=perf.fps, reference=_f32(perf.reference.vertices))
    if isinstance(perf, MarkerSequence):
        return MarkerSequence(_f32(perf.positions), names=perf.names, fps=perf.fps, reference=_f32(perf.reference))
    return WeightSequence(_f32(perf.weights), perf.names, fps=perf.fps)


def _rig32(rig):
    if rig is None:
        return None
    return BlendshapeRig(Mesh(_f32(rig.neutral.vertices), rig.neutral.triangles), _f32(rig.deltas), rig.names, bounds=rig.bounds)


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
    neutral = Mesh(_f32(target.neutral.vertices), target.neutral.triangles, name=target.neutral.name)
    rig = None
    if target.blendshapes is not None:
        rig = BlendshapeRig(neutral, _f32(target.blendshapes.deltas), target.blendshapes.names, bounds=target.blendshapes.bounds)
    return target.replace(neutral=neutral, blendshapes=rig, layers=_layers32(target.layers), examples=_f32(target.examples))


# ------------------------------------------------------------------------------------
# the checks
# ------------------------------------------------------------------------------------
def check_params(r: Retargeter, case=None) -> None:
    r = _instance(r)
    params = r.get_params()
    fresh = type(r)(**params)
    assert fresh.get_params().keys() == params.keys(), f"{_label(r)}: get_params() keys change after reconstruction"
    for k, v in params.items():
        same = fresh.get_params()[k]
        assert same is v or _equal(same, v), f"{_label(r)}: __init__ must store parameter {k!r} unchanged (got {same!r} for {v!r})"
    r.set_params(**params)
    assert _equal(r.get_params(), params), f"{_label(r)}: set_params(**get_params()) changed the parameters"


def check_not_fitted(r: Retargeter, case=None) -> None:
    case = case or tiny_case()
    r = _instance(r)
    source = _preferred_source(r, case)
    try:
        r.retarget(source)
    except NotFittedError:
        return
    raise AssertionError(f"{_label(r)}: retarget() before fit() must raise faceretarget.NotFittedError")


def check_output(r: Retargeter, case=None) -> None:
    case = case or tiny_case()
    r = _instance(r)
    source = _preferred_source(r, case)
    anim = r.fit(source, case.target).retarget(source)
    v = np.asarray(anim.vertices)
    want = (source.n_frames, case.target.neutral.n_vertices, 3)
    assert v.shape == want, f"{_label(r)}: Animation.vertices has shape {v.shape}, expected {want}"
    assert np.isfinite(v).all(), f"{_label(r)}: Animation.vertices holds NaN or inf"
    assert anim.provenance.get("method") == r.name, f"{_label(r)}: provenance lacks the method name"


def check_rest_pose(r: Retargeter, case=None) -> None:
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


def check_rigid_motion(r: Retargeter, case=None) -> None:
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
        assert np.abs(anim.weights).max() < 0.05, f"{_label(r)}: rigid motion alone produced blendshape weights up to {np.abs(anim.weights).max():.3f}"


def check_inputs_unchanged(r: Retargeter, case=None) -> None:
    case = case or tiny_case()
    r = _instance(r)
    source = _preferred_source(r, case)
    before = (_fingerprint(source), _fingerprint(case.target))
    r.fit(source, case.target).retarget(source)
    after = (_fingerprint(source), _fingerprint(case.target))
    assert before[0] == after[0], f"{_label(r)}: fit/retarget modified the source"
    assert before[1] == after[1], f"{_label(r)}: fit/retarget modified the target rig"


def check_float32_readonly(r: Retargeter, case=None) -> None:
    case = case or tiny_case()
    source = _preferred_source(_instance(r), case)
    ref = _instance(r).fit(source, case.target).retarget(source).vertices
    source32 = _source32(source)
    target32 = _target32(case.target)
    try:
        got = _instance(r).fit(source32, target32).retarget(source32).vertices
    except ValueError as exc:
        if "read-only" in str(exc) or "readonly" in str(exc):
            raise AssertionError(f"{_label(r)}: writes into a read-only input array ({exc})") from exc
        raise
    err = _rms(got, ref) / case.target.neutral.height
    assert err <= FLOAT32_TOLERANCE, f"{_label(r)}: float32 inputs differ from float64 by {100 * err:.4f}% of face height"


def check_deterministic(r: Retargeter, case=None) -> None:
    case = case or tiny_case()
    source = _preferred_source(_instance(r), case)
    a = _instance(r).fit(source, case.target).retarget(source)
    b = _instance(r).fit(source, case.target).retarget(source)
    assert np.array_equal(np.asarray(a.vertices), np.asarray(b.vertices)), f"{_label(r)}: two fits on the same input differ"


def check_clone_pickle(r: Retargeter, case=None) -> None:
    case = case or tiny_case()
    r = _instance(r)
    twin = clone(r)
    assert type(twin) is type(r) and _equal(twin.get_params(), r.get_params()), f"{_label(r)}: clone() changed the parameters"
    assert not getattr(twin, "fitted_", False), f"{_label(r)}: clone() must return an unfitted retargeter"
    source = _preferred_source(r, case)
    r.fit(source, case.target)
    want = np.asarray(r.retarget(source).vertices)
    again = pickle.loads(pickle.dumps(r))
    got = np.asarray(again.retarget(source).vertices)
    assert np.allclose(got, want, rtol=0, atol=1e-9 * max(1.0, case.target.neutral.height)), f"{_label(r)}: a pickled and restored retargeter gives a different result"


def check_stream(r: Retargeter, case=None) -> None:
    r = _instance(r)
    if not r.capabilities.stream:
        try:
            list(r.stream([]))
        except CapabilityError:
            return
        raise AssertionError(f"{_label(r)}: declares stream=False but stream() does not raise CapabilityError")
    case = case or tiny_case()
    source = _preferred_source(r, case)
    r.fit(source, case.target)
    batch = np.asarray(r.retarget(source).vertices)
    if source.kind == "markers":
        frames = list(np.asarray(source.performance.positions))
    elif source.kind == "mesh":
        frames = list(np.asarray(source.performance.vertices))
    else:
        frames = list(np.asarray(source.performance.weights))
    streamed = np.stack([np.asarray(f) for f in r.stream(iter(frames))])
    assert streamed.shape == batch.shape, f"{_label(r)}: stream() gave {streamed.shape}, retarget() gave {batch.shape}"
    err = _rms(streamed, batch) / case.target.neutral.height
    assert err <= 1e-6, f"{_label(r)}: stream() differs from retarget() by {100 * err:.5f}% of face height"


def check_capabilities(r: Retargeter, case=None) -> None:
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
        raise AssertionError(f"{_label(r)}: does not declare {kind!r} sources but fit() accepted one without CapabilityError")
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
        raise AssertionError(f"{_label(r)}: declares it needs {' or '.join(options)} but fit() worked without it")
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
        assert anim.weights is not None, f"{_label(r)}: declares outputs='weights' but the Animation has no weights"
    if not caps.edit:
        fitted = _instance(r).fit(source, case.target)
        try:
            fitted.edit(fitted.retarget(source))
        except CapabilityError:
            pass
        else:
            raise AssertionError(f"{_label(r)}: declares edit=False but edit() does not raise CapabilityError")


def _target_without(target: TargetRig, parts: Iterable[str]) -> TargetRig:
    return target.replace(**{p: None for p in parts})


def _equal(a, b) -> bool:
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
)


def check_retargeter(retargeter, case=None) -> None:
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
            raise AssertionError(f"[{check.__name__}] {name} raised {type(exc).__name__}: {exc}") from exc


def parametrize_with_checks(retargeters: Iterable):
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
    def faceretarget_case():
        """A tiny synthetic parallel-rig case with every rig part (see ``tiny_case``)."""
        return tiny_case()

except ImportError:  # pragma: no cover
    pass
