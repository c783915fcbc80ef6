"""Numerical edge cases in every registered method: regularized, or a typed error naming the cause.

Each scenario changes one thing in a small synthetic case: duplicate, linearly
dependent or zero blendshapes (rank-deficient systems), a target with a single shape /
pose / example, a one-frame sequence, markers missing for most frames, coincident
landmarks and duplicate example pairs (coincident RBF centres), zero-area triangles.
A method must either return a finite result of the right shape, or raise a
FaceRetargetError subclass with a message; never NaN, another exception or a hang.
The outcome of every (method, scenario) is printed in the session summary.
"""

import numpy as np
import pytest
from hypothesis import given
from hypothesis import strategies as st
from hypothesis.extra import numpy as hnp
from reliability import fuzzkit
from reliability.fuzzkit import failed, fuzz, index_array, typed

import faceretarget as fr
from faceretarget import errors
from faceretarget.geometry.rbf import KERNELS, fit_rbf

AREA = "numerical edge cases"
METHODS = [a["name"] for a in fr.available()]


@pytest.fixture(scope="module")
def case():
    return fr.cases.synthetic(resolution=200, n_frames=5)


# ---------------------------------------------------------------------------------------
# rebuilding model objects with one part changed
# ---------------------------------------------------------------------------------------
def target_with(target, **changes):
    parts = dict(
        blendshapes=target.blendshapes,
        layers=target.layers,
        landmarks=target.landmarks,
        feature_lines=target.feature_lines,
        examples=target.examples,
        example_names=target.example_names or None,
    )
    parts.update(changes)
    neutral = parts.pop("neutral", target.neutral)
    return fr.TargetRig(neutral, **parts)


def source_with(source, **changes):
    parts = dict(
        head_motion=source.head_motion,
        landmarks=source.landmarks,
        feature_lines=source.feature_lines,
        examples=source.examples,
        example_names=source.example_names or None,
        rig=source.rig,
        actor_layers=source.actor_layers,
        tracks2d=source.tracks2d,
        actor_layers_2d=source.actor_layers_2d,
    )
    parts.update(changes)
    performance = parts.pop("performance", source.performance)
    return fr.Source(performance, **parts)


def with_extra_shape(target, delta, name):
    rig = target.blendshapes
    deltas = np.concatenate([np.asarray(rig.deltas), delta[None]])
    bounds = None if rig.bounds is None else np.vstack([rig.bounds, rig.bounds[:1]])
    return target_with(
        target,
        blendshapes=fr.BlendshapeRig(rig.neutral, deltas, list(rig.names) + [name], bounds=bounds),
    )


def first_only(layers):
    if layers is None:
        return None
    return fr.LayeredRig(
        {k: np.asarray(v)[:1] for k, v in layers.layers.items()},
        layers.masks,
        pose_names={k: list(v)[:1] for k, v in layers.pose_names.items()},
        region_names=layers.region_names,
    )


def collapse_triangle(vertices, triangles, t=0):
    """Move corner c of triangle t onto the midpoint of edge (a, b): zero area, distinct ids."""
    v = np.array(vertices, dtype=float)
    a, b, c = np.asarray(triangles)[t]
    v[..., c, :] = 0.5 * (v[..., a, :] + v[..., b, :])
    return v


def markers_of(source):
    perf = source.performance
    if isinstance(perf, fr.MarkerSequence):
        return perf
    names = source.landmarks.names if source.landmarks is not None else None
    return fr.MarkerSequence(
        source.marker_positions(), names=names, fps=perf.fps, reference=source.marker_reference()
    )


# ---------------------------------------------------------------------------------------
# scenarios: (source, target) or None when the method cannot take that input at all
# ---------------------------------------------------------------------------------------
def duplicate_shapes(case, cls):
    rig = case.target.blendshapes
    return case.source, with_extra_shape(
        case.target, np.asarray(rig.deltas[0]), rig.names[0] + "_copy"
    )


def dependent_shape(case, cls):
    rig = case.target.blendshapes
    return case.source, with_extra_shape(
        case.target, np.asarray(rig.deltas[0] + rig.deltas[1]), "sum_of_two"
    )


def zero_shape(case, cls):
    return case.source, with_extra_shape(
        case.target, np.zeros_like(case.target.blendshapes.deltas[0]), "does_nothing"
    )


def single_shape(case, cls):
    rig, src = case.target.blendshapes, case.source
    target = target_with(
        case.target,
        blendshapes=fr.BlendshapeRig(rig.neutral, np.asarray(rig.deltas)[:1], rig.names[:1]),
        layers=first_only(case.target.layers),
        examples=np.asarray(case.target.examples)[:1],
        example_names=case.target.example_names[:1],
    )
    source = source_with(
        src,
        actor_layers=first_only(src.actor_layers),
        actor_layers_2d=first_only(src.actor_layers_2d),
        examples=np.asarray(src.examples)[:1],
        example_names=src.example_names[:1],
    )
    return source, target


def one_frame(case, cls):
    src = case.source
    perf = src.performance
    frames = np.asarray(perf.vertices)[2:3]
    hm = None if src.head_motion is None else np.asarray(src.head_motion)[2:3]
    tracks = (
        None
        if src.tracks2d is None
        else fr.MarkerSequence(
            np.asarray(src.tracks2d.positions)[2:3],
            names=src.tracks2d.names,
            reference=src.tracks2d.reference,
        )
    )
    return source_with(
        src,
        performance=fr.MeshSequence(frames, perf.triangles, fps=perf.fps, reference=perf.reference),
        head_motion=hm,
        tracks2d=tracks,
    ), case.target


def missing_markers(case, cls):
    if "markers" not in cls.capabilities.sources:
        return None
    markers = markers_of(case.source)
    pos = np.array(markers.positions)
    rng = np.random.default_rng(3)
    n = pos.shape[1]
    gappy = rng.choice(n, size=n // 3, replace=False)
    pos[1:, gappy] = np.where(
        rng.random((pos.shape[0] - 1, gappy.size, 1)) < 0.8, np.nan, pos[1:, gappy]
    )
    return marker_source(case, pos, markers)


def empty_frame(case, cls):
    if "markers" not in cls.capabilities.sources:
        return None
    markers = markers_of(case.source)
    pos = np.array(markers.positions)
    pos[-2] = np.nan  # one frame with every marker missing
    return marker_source(case, pos, markers)


def marker_source(case, pos, markers):
    """The case's source as markers at ``pos`` (NaN = missing), keeping every extra that fits."""
    seq = fr.MarkerSequence(pos, names=markers.names, fps=markers.fps, reference=markers.reference)
    src = case.source
    examples = (
        None
        if src.examples is None or src.landmarks is None
        else src.landmarks.positions(src.examples, src.performance.triangles)
    )
    return fr.Source(
        seq,
        head_motion=src.head_motion,
        examples=examples,
        example_names=src.example_names or None,
        rig=src.rig,
        actor_layers=src.actor_layers,
        tracks2d=src.tracks2d,
        actor_layers_2d=src.actor_layers_2d,
    ), case.target


def coincident_landmarks(case, cls):
    src, tgt = case.source, case.target
    ids_t = np.array(tgt.landmarks.vertex_ids)
    ids_t[1] = ids_t[0]
    ids_s = np.array(src.landmarks.vertex_ids)
    ids_s[1] = ids_s[0]
    target = target_with(tgt, landmarks=fr.Landmarks(ids_t, names=tgt.landmarks.names))
    return source_with(src, landmarks=fr.Landmarks(ids_s, names=src.landmarks.names)), target


def duplicate_examples(case, cls):
    src, tgt = case.source, case.target
    ex_s = np.concatenate([np.asarray(src.examples), np.asarray(src.examples)[-1:]])
    ex_t = np.concatenate([np.asarray(tgt.examples), np.asarray(tgt.examples)[-1:]])
    return (
        source_with(src, examples=ex_s, example_names=list(src.example_names) + ["again"]),
        target_with(tgt, examples=ex_t, example_names=list(tgt.example_names) + ["again"]),
    )


def zero_area_triangles(case, cls):
    src, tgt = case.source, case.target
    neutral = fr.Mesh(
        collapse_triangle(tgt.neutral.vertices, tgt.neutral.triangles),
        tgt.neutral.triangles,
        name=tgt.neutral.name,
    )
    rig = tgt.blendshapes
    target = target_with(
        tgt,
        neutral=neutral,
        blendshapes=fr.BlendshapeRig(neutral, rig.deltas, rig.names, bounds=rig.bounds),
    )
    perf = src.performance
    frames = collapse_triangle(perf.vertices, perf.triangles)
    ref = collapse_triangle(perf.reference.vertices, perf.triangles)
    return source_with(
        src, performance=fr.MeshSequence(frames, perf.triangles, fps=perf.fps, reference=ref)
    ), target


SCENARIOS = [
    duplicate_shapes,
    dependent_shape,
    zero_shape,
    single_shape,
    one_frame,
    missing_markers,
    empty_frame,
    coincident_landmarks,
    duplicate_examples,
    zero_area_triangles,
]


#: scenarios that add only redundant information (the span of the rig / examples is unchanged)
SAME_SPAN = (duplicate_shapes, dependent_shape, zero_shape, duplicate_examples)
#: RMS change they may cause, as a fraction of the face height (a prior may weigh shapes anew)
SAME_SPAN_TOLERANCE = 0.02


@pytest.mark.parametrize("scenario", SCENARIOS, ids=[s.__name__ for s in SCENARIOS])
@pytest.mark.parametrize("method", METHODS)
def test_edge_case(method, scenario, case):
    cls = fr.info(method).cls
    made = scenario(case, cls)
    if made is None:
        pytest.skip(f"{method} takes no marker input")
    source, target = made

    def run():
        return fr.get(method).fit(source, target).retarget(source)

    result = typed(AREA, run)
    key = (method, scenario.__name__)
    if failed(result):
        fuzzkit.OUTCOMES[key] = f"{type(result).__name__}: {' '.join(str(result).split())[:110]}"
        assert type(result) is not errors.FaceRetargetError, (
            "use the subclass that names the kind of failure"
        )
        return
    v = np.asarray(result.vertices)
    assert v.shape == (source.n_frames, target.neutral.n_vertices, 3), (
        f"{method}/{scenario.__name__}: shape {v.shape}"
    )
    assert np.isfinite(v).all(), f"{method}/{scenario.__name__}: NaN or inf in the result"
    if result.weights is not None:
        assert np.isfinite(result.weights).all()
    fuzzkit.OUTCOMES[key] = "finite result"
    if scenario in SAME_SPAN:
        # the rig (or example set) spans the same space as before: the answer must not move
        base = fr.get(method).fit(case.source, case.target).retarget(case.source)
        change = (
            np.sqrt(np.mean(np.sum((v - np.asarray(base.vertices)) ** 2, axis=-1)))
            / case.target.neutral.height
        )
        fuzzkit.OUTCOMES[key] = (
            f"finite result, {100 * change:.3f}% of face height from the unchanged case"
        )
        assert change < SAME_SPAN_TOLERANCE, (
            f"{method}/{scenario.__name__}: a redundant shape moved the result by {100 * change:.2f}% of face height"
        )


# ---------------------------------------------------------------------------------------
# the shared RBF fit on its own: coincident, collinear and clustered centres
# ---------------------------------------------------------------------------------------
@given(data=st.data(), kernel=st.sampled_from(KERNELS), dim=st.sampled_from([2, 3]))
@fuzz(60)
def test_rbf_coincident_and_degenerate_centres(data, kernel, dim):
    n = data.draw(st.integers(1, 7))
    coords = st.floats(
        -10.0, 10.0, allow_subnormal=False
    )  # subnormal spacings: see the xfail below
    base = data.draw(hnp.arrays(np.float64, (n, dim), elements=coords))
    if data.draw(st.booleans()):
        base[:, 1:] = 0.0  # all centres on one line
    centres = base[
        data.draw(index_array((data.draw(st.integers(1, 12)),), 0, n - 1))
    ]  # with repeats
    values = np.stack(
        [np.sin(centres).sum(axis=1), centres[:, 0] ** 2], axis=1
    )  # one value per position
    interp = typed(AREA, fit_rbf, centres, values, kernel=kernel)
    if failed(interp):
        assert isinstance(interp, (errors.DegenerateGeometryError, errors.NumericalError)), interp
        return
    got = interp(centres)
    assert np.isfinite(got).all(), f"{kernel}: NaN or inf from coincident centres"
    distinct = np.unique(centres, axis=0)
    gaps = np.linalg.norm(distinct[:, None] - distinct[None], axis=-1)[
        np.triu_indices(len(distinct), 1)
    ]
    extent = max(float(np.ptp(centres)), 1.0)
    if gaps.size == 0 or gaps.min() > 1e-2 * extent:  # well separated: must interpolate
        np.testing.assert_allclose(got, values, atol=1e-5 * (1 + np.abs(values).max()))


def test_rbf_centres_a_subnormal_distance_apart():
    result = typed(
        AREA,
        fit_rbf,
        np.array([[2.2250738585e-309, 0.0], [0.0, 0.0]]),
        np.array([[1.0], [2.0]]),
        kernel="gaussian",
    )
    assert failed(result) or np.isfinite(result(np.zeros((1, 2)))).all()
