"""Bad input gives a typed error naming the cause."""

import numpy as np
import pytest

import faceretarget as fr
from faceretarget.errors import (
    CapabilityError,
    DegenerateGeometryError,
    FaceRetargetError,
    IndexRangeError,
    InputError,
    NonFiniteError,
    ShapeError,
    TopologyMismatchError,
)
from faceretarget.model import Landmarks, MeshSequence, Source, TargetRig


def _source(case, **changes):
    src = case.source
    args = dict(landmarks=src.landmarks, examples=src.examples, example_names=src.example_names)
    args.update(changes)
    return Source(
        changes.pop("performance", src.performance),
        **{k: v for k, v in args.items() if k != "performance"},
    )


def _target(case, **changes):
    tgt = case.target
    args = dict(landmarks=tgt.landmarks, examples=tgt.examples, example_names=tgt.example_names)
    args.update(changes)
    return TargetRig(tgt.neutral, **args)


def _fit(case, source=None, target=None, **params):
    return fr.get("normalmesh", **params).fit(source or case.source, target or case.target)


def test_too_few_feature_points(human_case):
    few = Landmarks(human_case.source.landmarks.vertex_ids[:3])
    few_t = Landmarks(human_case.target.landmarks.vertex_ids[:3])
    with pytest.raises(ShapeError, match="at least 4"):
        _fit(human_case, _source(human_case, landmarks=few), _target(human_case, landmarks=few_t))


def test_feature_point_counts_must_match(human_case):
    with pytest.raises(TopologyMismatchError, match="feature point"):
        _fit(
            human_case,
            target=_target(
                human_case, landmarks=Landmarks(human_case.target.landmarks.vertex_ids[:-1])
            ),
        )


def test_flipped_base_triangles(human_case, fitted):
    reversed_tri = fitted.base_triangles_[:, ::-1]
    with pytest.raises(DegenerateGeometryError, match="flipped"):
        _fit(human_case, base_triangles=reversed_tri)


def test_mirrored_target_feature_points_flip_the_base(human_case):
    """Target landmarks listed with left and right swapped: base triangles flip on the target."""
    names = human_case.target.landmarks.names
    swap = {n: n.replace("_L", "_X").replace("_R", "_L").replace("_X", "_R") for n in names}
    ids = dict(zip(names, human_case.target.landmarks.vertex_ids))
    mirrored = Landmarks([ids[swap[n]] for n in names], names=names)
    with pytest.raises(DegenerateGeometryError, match="flipped on the target"):
        _fit(human_case, target=_target(human_case, landmarks=mirrored))


def test_degenerate_base_triangles(human_case, fitted):
    tri = fitted.base_triangles_.copy()
    lm = human_case.source.landmarks
    names = list(lm.names)
    with pytest.raises(DegenerateGeometryError, match="repeats"):
        _fit(human_case, base_triangles=np.vstack([tri, [[0, 0, 1]]]))
    ids = lm.vertex_ids.copy()
    ids[names.index("lip_upper_3")] = ids[
        names.index("lip_upper_2")
    ]  # two feature points on one vertex
    with pytest.raises(DegenerateGeometryError, match="degenerate"):
        _fit(
            human_case,
            _source(human_case, landmarks=Landmarks(ids, names=names)),
            base_triangles=tri,
        )


def test_base_triangle_indices_and_shape(human_case):
    with pytest.raises(IndexRangeError):
        _fit(human_case, base_triangles=np.array([[0, 1, 99]]))
    with pytest.raises(ShapeError):
        _fit(human_case, base_triangles=np.array([[0.0, 1.0, 2.0]]))
    with pytest.raises(ShapeError):
        _fit(human_case, base_triangles=np.zeros((0, 3), int))


def test_missing_examples_and_landmarks(human_case):
    with pytest.raises(CapabilityError, match="example"):
        _fit(
            human_case,
            target=TargetRig(human_case.target.neutral, landmarks=human_case.target.landmarks),
        )
    with pytest.raises(CapabilityError, match="example"):
        _fit(
            human_case,
            source=Source(human_case.source.performance, landmarks=human_case.source.landmarks),
        )
    with pytest.raises(CapabilityError, match="landmarks"):
        _fit(
            human_case,
            target=TargetRig(
                human_case.target.neutral,
                examples=human_case.target.examples,
                example_names=human_case.target.example_names,
            ),
        )


def test_mismatched_example_names(human_case):
    names = list(human_case.target.example_names)
    names[2] = "grimace"
    with pytest.raises(TopologyMismatchError, match="grimace"):
        _fit(human_case, target=_target(human_case, example_names=names))


def test_examples_are_paired_by_name_not_order(human_case):
    order = np.arange(len(human_case.target.example_names))[::-1]
    shuffled = _target(
        human_case,
        examples=human_case.target.examples[order],
        example_names=[human_case.target.example_names[i] for i in order],
    )
    a = _fit(human_case).base_map_
    b = _fit(human_case, target=shuffled).base_map_
    x = np.random.default_rng(0).normal(scale=0.1, size=(2, len(human_case.source.landmarks), 3))
    np.testing.assert_allclose(a(x), b(x), atol=1e-9)


def test_nan_is_rejected(human_case):
    v = np.array(human_case.source.performance.vertices)
    v[1, 5, 0] = np.nan
    with pytest.raises(NonFiniteError):
        MeshSequence(v, human_case.source.performance.triangles)
    for bad in (
        dict(rbf_c=float("nan")),
        dict(max_offset=0.0),
        dict(levels=9),
        dict(detail_levels=-2),
        dict(detail_scale="volume"),
        dict(head_motion="sometimes"),
        dict(backend="optix"),
        dict(rbf_smoothing=-1.0),
    ):
        with pytest.raises(InputError):
            _fit(human_case, **bad)


def test_other_source_topology_at_retarget(human_case, fitted):
    other = fr.cases.synthetic(seed=0, resolution=800, n_frames=3)
    with pytest.raises(TopologyMismatchError, match="topology"):
        fitted.retarget(other.source)


def test_every_error_is_a_faceretarget_error(human_case):
    with pytest.raises(FaceRetargetError):
        _fit(human_case, base_triangles=np.array([[0, 1, 99]]))
    with pytest.raises(fr.NotFittedError):
        fr.get("normalmesh").retarget(human_case.source)
