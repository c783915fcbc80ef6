"""Units and placement: the result, in the target's units and frame, does not depend on them."""

import numpy as np
import pytest

import faceretarget as fr
from faceretarget.model import Mesh, MeshSequence, Source, TargetRig

#: Largest change allowed, RMS over vertices and frames, as a fraction of the face height.
TOLERANCE = 1e-6


@pytest.fixture(scope="module")
def still_case():
    """A synthetic case without head motion (head turns act in world coordinates, so moving
    the target rightly changes where a turn takes it)."""
    return fr.cases.synthetic(seed=2, resolution=1500, n_frames=6, head_motion=False)


def _rotation(axis, degrees):
    axis = np.asarray(axis, float) / np.linalg.norm(axis)
    k = np.array([[0, -axis[2], axis[1]], [axis[2], 0, -axis[0]], [-axis[1], axis[0], 0]])
    a = np.radians(degrees)
    return np.eye(3) + np.sin(a) * k + (1 - np.cos(a)) * k @ k


def _source(case, move, head_motion=None):
    s, p = case.source, case.source.performance
    perf = MeshSequence(
        move(np.asarray(p.vertices)),
        p.triangles,
        fps=p.fps,
        reference=move(np.asarray(p.reference.vertices)),
    )
    return Source(
        perf,
        landmarks=s.landmarks,
        examples=move(np.asarray(s.examples)),
        example_names=s.example_names,
        head_motion=head_motion,
    )


def _target(case, move):
    t = case.target
    return TargetRig(
        Mesh(move(np.asarray(t.neutral.vertices)), t.neutral.triangles),
        landmarks=t.landmarks,
        examples=move(np.asarray(t.examples)),
        example_names=t.example_names,
    )


def _run(source, target, **params):
    return np.asarray(fr.get("normalmesh", **params).fit(source, target).retarget(source).vertices)


def _change(a, b, height):
    return float(np.sqrt(np.mean(np.sum((a - b) ** 2, axis=-1)))) / height


def _moves():
    rot, shift = _rotation([0.3, 1.0, 0.2], 25.0), np.array([1.0, -2.0, 0.5])
    out = [
        (f"x{k:g}", (lambda k: lambda x, k=k: k * x)(k), (lambda k: lambda y, k=k: y / k)(k))
        for k in (0.01, 100.0, 1000.0)
    ]
    out.append(("rigid", lambda x: x @ rot.T + 30.0 * shift, lambda y: (y - 30.0 * shift) @ rot))
    return out


@pytest.mark.parametrize("side", ["source", "target"])
def test_scaling_or_moving_either_face_changes_nothing(still_case, side):
    base = _run(_source(still_case, lambda x: x), _target(still_case, lambda x: x))
    height = still_case.target.neutral.height
    failures = {}
    for label, move, back in _moves():
        if side == "source":
            got = _run(_source(still_case, move), _target(still_case, lambda x: x))
        else:
            got = back(_run(_source(still_case, lambda x: x), _target(still_case, move)))
        failures[label] = _change(got, base, height)
    assert max(failures.values()) < TOLERANCE, failures  # measured ~1e-16


def test_the_papers_area_ratio_is_not_unit_free(still_case):
    """Eq. 9 as printed scales lengths by an area ratio: a source in metres onto a target in
    centimetres would get details 100x too large. ``detail_scale="area"`` keeps it, documented."""
    height = still_case.target.neutral.height
    target = _target(still_case, lambda x: x)
    base = _run(_source(still_case, lambda x: x), target, detail_scale="area")
    metres = _run(_source(still_case, lambda x: 0.01 * x), target, detail_scale="area")
    assert _change(metres, base, height) > 1e-3


def test_head_motion_is_carried_in_the_targets_units():
    """A source in metres with its head motion onto a target in centimetres: the head turns and
    moves as it would in centimetres (translations x100), given or estimated."""
    case = fr.cases.synthetic(seed=4, resolution=1500, n_frames=6)
    target = _target(case, lambda x: x)
    height = case.target.neutral.height
    motion = np.asarray(case.meta["head_motion"])
    in_metres = motion.copy()
    in_metres[:, :3, 3] *= 0.01
    for given in (True, False):
        base = _run(_source(case, lambda x: x, motion if given else None), target)
        metres = _run(_source(case, lambda x: 0.01 * x, in_metres if given else None), target)
        assert _change(metres, base, height) < TOLERANCE, given


def test_points_on_edges_and_corners_attach_the_same_wherever_the_mesh_is():
    """A closest point on an edge or a corner lies on several triangles; the one the query
    returns depends on rounding, so on placement. The attachment takes the lowest-numbered."""
    from faceretarget.plugins.normalmesh.attach import attach

    n = 6
    g = np.stack(
        np.meshgrid(np.arange(n, dtype=float), np.arange(n, dtype=float), indexing="ij"), axis=-1
    ).reshape(-1, 2)
    vertices = np.column_stack([g, 0.05 * np.sin(g[:, 0]) * np.cos(g[:, 1])])
    quads = np.array(
        [
            [i * n + j, (i + 1) * n + j, (i + 1) * n + j + 1, i * n + j + 1]
            for i in range(n - 1)
            for j in range(n - 1)
        ]
    )
    triangles = np.concatenate([quads[:, [0, 1, 2]], quads[:, [0, 2, 3]]])
    edges = np.concatenate([triangles[:, [0, 1]], triangles[:, [1, 2]]])
    points = np.concatenate([vertices, 0.5 * (vertices[edges[:, 0]] + vertices[edges[:, 1]])])
    want = attach(points, vertices, triangles)
    # on a corner or an edge: the lowest-numbered triangle sharing it
    lowest = np.array(
        [np.flatnonzero((triangles == v).any(axis=1)).min() for v in range(len(vertices))]
    )
    np.testing.assert_array_equal(want.triangle[: len(vertices)], lowest)
    for scale, rot, shift in [
        (1e-2, _rotation([1, 2, 3], 40.0), np.array([3.0, 1.0, -2.0])),
        (1e3, _rotation([0, 1, 0], 90.0), np.zeros(3)),
    ]:

        def move(x, rot=rot, scale=scale, shift=shift):
            return scale * x @ rot.T + shift

        got = attach(move(points), move(vertices), triangles)
        np.testing.assert_array_equal(got.triangle, want.triangle)
        np.testing.assert_allclose(got.barycentric, want.barycentric, atol=1e-9)
