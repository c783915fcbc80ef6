"""Every model constructor answers any input with a typed error or a valid, read-only object.

Each test draws inputs from two pools: anything at all (:func:`fuzzkit.junk`: None,
strings, complex, object and datetime arrays, ragged lists, dicts...) and near-valid
arrays with one thing wrong (NaN/inf, a wrong length, an index out of range...). A
constructor may reject an input only with a :class:`FaceRetargetError` subclass; when it
accepts one, the object must satisfy the model's invariants (checked here).
"""

import numpy as np
import pytest
from hypothesis import example, given
from hypothesis import strategies as st
from reliability.fuzzkit import (
    count,
    failed,
    float_array,
    fuzz,
    index_array,
    junk,
    names,
    ragged_frames,
    typed,
    unique_names,
)

import faceretarget as fr
from faceretarget import errors

AREA = "model constructors"


# ---------------------------------------------------------------------------------------
# invariants of accepted objects
# ---------------------------------------------------------------------------------------
def assert_readonly_finite(arr, allow_nan=False):
    assert isinstance(arr, np.ndarray) and not arr.flags.writeable, (
        "stored arrays must be read-only"
    )
    if arr.dtype.kind == "f":
        assert not np.isinf(arr).any()
        if not allow_nan:
            assert not np.isnan(arr).any()


def assert_mesh_ok(mesh, *, derived=True):
    v, t = mesh.vertices, mesh.triangles
    assert v.ndim == 2 and v.shape[1] == 3 and v.shape[0] >= 3 and v.dtype == np.float64
    assert t.ndim == 2 and t.shape[1] == 3 and t.shape[0] >= 1
    assert_readonly_finite(v)
    assert not t.flags.writeable and t.min() >= 0 and t.max() < len(v)
    assert (t[:, 0] != t[:, 1]).all() and (t[:, 1] != t[:, 2]).all() and (t[:, 0] != t[:, 2]).all()
    assert len(np.unique(np.sort(t, axis=1), axis=0)) == len(t), (
        "duplicate triangles must be rejected"
    )
    if not derived:
        return
    for name in ("face_normals", "face_areas", "vertex_normals", "edges", "boundary_vertices"):
        value = getattr(mesh, name)
        assert_readonly_finite(value)
    norms = np.linalg.norm(mesh.face_normals, axis=1)
    assert np.all((np.abs(norms - 1) < 1e-9) | (norms == 0)), "face normals are unit or zero"
    assert (mesh.face_areas >= 0).all()
    assert mesh.edges.min() >= 0 and mesh.edges.max() < len(v)
    adj = mesh.adjacency
    assert adj.shape == (len(v), len(v)) and (adj != adj.T).nnz == 0
    bad = mesh.degenerate_triangles()
    assert bad.dtype.kind in "iu" and (bad < len(t)).all()
    result = typed(AREA, mesh.check_nondegenerate)
    assert (result is None) == (bad.size == 0)
    if failed(result):
        assert isinstance(result, errors.DegenerateGeometryError)


def brute_force_boundary(triangles):
    """Vertices on edges used by exactly one triangle (the definition, by loops)."""
    count = {}
    for tri in triangles.tolist():
        for a, b in ((tri[0], tri[1]), (tri[1], tri[2]), (tri[2], tri[0])):
            key = (min(a, b), max(a, b))
            count[key] = count.get(key, 0) + 1
    return sorted({v for e, c in count.items() if c == 1 for v in e}), sorted(count)


# ---------------------------------------------------------------------------------------
# strategies for near-valid inputs
# ---------------------------------------------------------------------------------------
@st.composite
def mesh_arrays(draw, *, special=True, index_slack=2, min_vertices=0):
    n_vertices = draw(st.integers(min_vertices, 8))
    n_triangles = draw(st.integers(0, 6))
    vertices = draw(float_array((n_vertices, 3), special=special))
    triangles = draw(
        index_array((n_triangles, 3), -index_slack, max(0, n_vertices - 1) + index_slack)
    )
    return vertices, triangles


@st.composite
def valid_mesh(draw, max_vertices=8, bound=1e3):
    """A Mesh built from finite vertices and triangles without repeated corners or duplicates."""
    n = draw(st.integers(3, max_vertices))
    vertices = draw(float_array((n, 3), special=False, bound=bound))
    candidates = draw(
        st.lists(
            st.lists(st.integers(0, n - 1), min_size=3, max_size=3, unique=True),
            min_size=1,
            max_size=8,
        )
    )
    seen, tris = set(), []
    for tri in candidates:
        key = tuple(sorted(tri))
        if key not in seen:
            seen.add(key)
            tris.append(tri)
    return fr.Mesh(vertices, np.array(tris))


@given(
    data=st.one_of(
        mesh_arrays(), st.tuples(junk(), junk()), st.tuples(junk(), index_array((2, 3), 0, 2))
    )
)
@fuzz(60)
def test_mesh_any_input(data):
    vertices, triangles = data
    mesh = typed(AREA, fr.Mesh, vertices, triangles)
    if not failed(mesh):
        assert_mesh_ok(mesh)


@given(mesh=valid_mesh(), data=st.data())
@fuzz(40)
def test_mesh_topology_matches_definitions(mesh, data):
    """Duplicate vertices and non-manifold edges are accepted; edges/boundary follow the definitions."""
    if data.draw(st.booleans()):  # make every vertex a copy of vertex 0 or 1 (duplicate positions)
        picks = data.draw(index_array((mesh.n_vertices,), 0, 1))
        mesh = mesh.with_vertices(np.asarray(mesh.vertices)[picks])
    count(AREA)
    assert_mesh_ok(mesh)
    boundary, edges = brute_force_boundary(np.asarray(mesh.triangles))
    assert mesh.boundary_vertices.tolist() == boundary
    assert [tuple(e) for e in mesh.edges.tolist()] == edges


def test_non_manifold_edge_is_accepted_and_not_boundary():
    v = np.array([[0, 0, 0], [1, 0, 0], [0, 1, 0], [0, -1, 0], [0, 0, 1]], float)
    t = np.array([[0, 1, 2], [1, 0, 3], [0, 1, 4]])  # edge (0, 1) is shared by three triangles
    mesh = typed(AREA, fr.Mesh, v, t)
    assert not failed(mesh)
    assert_mesh_ok(mesh)
    assert 0 in mesh.boundary_vertices  # (0, 2), (0, 3), (0, 4) are boundary edges
    assert [0, 1] in mesh.edges.tolist()


@given(mesh=valid_mesh(), data=st.data())
@fuzz(40)
def test_mesh_degenerate_and_duplicate_triangles(mesh, data):
    t = np.asarray(mesh.triangles)
    kind = data.draw(
        st.sampled_from(["repeat_corner", "duplicate", "flipped_duplicate", "zero_area"])
    )
    i = data.draw(st.integers(0, len(t) - 1))
    v = np.array(mesh.vertices)
    if kind == "repeat_corner":
        bad = np.vstack([t, [t[i, 0], t[i, 0], t[i, 1]]])
    elif kind == "duplicate":
        bad = np.vstack([t, t[i]])
    elif kind == "flipped_duplicate":
        bad = np.vstack([t, t[i, ::-1]])
    else:  # distinct but collinear corners: accepted, found by degenerate_triangles()
        a, b, c = t[i]
        v[c] = 0.5 * (v[a] + v[b])
        bad = t
    result = typed(AREA, fr.Mesh, v, bad)
    if kind == "zero_area":
        assert not failed(result), f"zero-area triangles are documented as accepted: {result}"
        assert i in result.degenerate_triangles()
        with pytest.raises(errors.DegenerateGeometryError):
            result.check_nondegenerate()
    else:
        assert isinstance(result, errors.DegenerateGeometryError), (
            f"{kind} must raise DegenerateGeometryError, got {result!r}"
        )


@given(mesh=valid_mesh(bound=1e12))
@fuzz(30)
def test_mesh_derived_quantities_finite_for_large_and_tiny_coordinates(mesh):
    count(AREA, 2)
    assert_mesh_ok(mesh)
    tiny = mesh.with_vertices(np.asarray(mesh.vertices) * 1e-100)
    assert_mesh_ok(tiny)


# ---------------------------------------------------------------------------------------
@given(
    vertex_ids=st.one_of(junk(), index_array(st.integers(0, 5).map(lambda n: (n,)), -2, 9)),
    bary=st.one_of(st.none(), junk(), float_array(st.tuples(st.integers(0, 4), st.just(3)))),
    use_triangles=st.booleans(),
    label=st.one_of(st.none(), names(), junk()),
    mesh=valid_mesh(),
)
@fuzz(60)
def test_landmarks_any_input(vertex_ids, bary, use_triangles, label, mesh):
    kwargs = (
        dict(triangle_ids=vertex_ids, barycentric=bary)
        if use_triangles
        else dict(vertex_ids=vertex_ids)
    )
    lm = typed(AREA, fr.Landmarks, names=label, **kwargs)
    if failed(lm):
        return
    assert len(lm) >= 1 and len(set(lm.names)) == len(lm.names)
    checked = typed(AREA, lm.validate_for, mesh)
    if failed(checked):
        assert isinstance(checked, errors.IndexRangeError)
        return
    pos = lm.positions(mesh.vertices, mesh.triangles)
    assert pos.shape == (len(lm), 3) and np.isfinite(pos).all()


# ---------------------------------------------------------------------------------------
@st.composite
def marker_arrays(draw):
    f, n, d = draw(st.integers(0, 4)), draw(st.integers(0, 4)), draw(st.sampled_from([2, 3, 3, 4]))
    arr = draw(float_array((f, n, d)))
    if draw(st.booleans()) and arr.size:  # whole-marker gaps, the documented way to be missing
        gaps = draw(st.lists(st.tuples(st.integers(0, f - 1), st.integers(0, n - 1)), max_size=4))
        for i, j in gaps:
            arr[i, j] = np.nan
    return arr


@given(
    positions=st.one_of(marker_arrays(), junk(), ragged_frames()),
    label=st.one_of(st.none(), names(), junk()),
    fps=st.one_of(st.just(30.0), junk(), st.integers(-10, 10**400)),
    reference=st.one_of(
        st.none(),
        st.none(),
        junk(),
        float_array(st.tuples(st.integers(0, 4), st.sampled_from([2, 3]))),
    ),
)
@fuzz(80)
def test_marker_sequence_any_input(positions, label, fps, reference):
    seq = typed(AREA, fr.MarkerSequence, positions, names=label, fps=fps, reference=reference)
    if failed(seq):
        return
    assert_readonly_finite(seq.positions, allow_nan=True)
    nan = np.isnan(seq.positions)
    assert (nan.all(axis=-1) == nan.any(axis=-1)).all(), (
        "a missing sample is NaN in every coordinate"
    )
    assert_readonly_finite(seq.reference)
    assert seq.reference.shape == seq.positions.shape[1:]
    assert len(seq.names) == seq.n_markers and len(set(seq.names)) == seq.n_markers
    assert np.isfinite(seq.fps) and seq.fps > 0
    assert seq.missing.shape == seq.positions.shape[:2]


@given(
    frames=st.one_of(
        float_array(st.tuples(st.integers(0, 3), st.integers(0, 6), st.sampled_from([3, 3, 2]))),
        junk(),
        ragged_frames(),
    ),
    triangles=st.one_of(index_array((2, 3), -1, 6), junk(), st.just(np.array([[0, 1, 2]]))),
    reference=st.one_of(st.none(), junk(), float_array((4, 3))),
    fps=st.one_of(st.just(24), junk()),
)
@fuzz(80)
def test_mesh_sequence_any_input(frames, triangles, reference, fps):
    seq = typed(AREA, fr.MeshSequence, frames, triangles, reference=reference, fps=fps)
    if failed(seq):
        return
    assert seq.vertices.ndim == 3 and seq.vertices.shape[1:] == (seq.reference.n_vertices, 3)
    assert_readonly_finite(seq.vertices)
    assert_mesh_ok(seq.reference, derived=False)


def test_mesh_sequence_rejects_frames_of_different_vertex_counts():
    frames = [np.eye(3), np.eye(4, 3)]
    assert isinstance(typed(AREA, fr.MeshSequence, frames, [[0, 1, 2]]), errors.InputError)
    ref = fr.Mesh(np.eye(4, 3), [[0, 1, 2]])
    assert isinstance(
        typed(AREA, fr.MeshSequence, np.zeros((2, 3, 3)), [[0, 1, 2]], reference=ref),
        errors.TopologyMismatchError,
    )


@given(
    weights=st.one_of(float_array(st.tuples(st.integers(0, 4), st.integers(0, 4))), junk()),
    label=st.one_of(names(), junk()),
    fps=st.one_of(st.just(60.0), junk()),
)
@fuzz(60)
def test_weight_sequence_any_input(weights, label, fps):
    seq = typed(AREA, fr.WeightSequence, weights, label, fps=fps)
    if failed(seq):
        return
    assert_readonly_finite(seq.weights)
    assert seq.weights.ndim == 2 and len(seq.names) == seq.weights.shape[1]


# ---------------------------------------------------------------------------------------
NEUTRAL = fr.Mesh(
    np.array([[0, 0, 0], [1, 0, 0], [0, 1, 0], [1, 1, 0]], float), [[0, 1, 2], [1, 3, 2]]
)


@given(
    deltas=st.one_of(
        float_array(
            st.tuples(st.integers(0, 3), st.sampled_from([4, 4, 3, 5]), st.sampled_from([3, 3, 2]))
        ),
        junk(),
        st.builds(lambda fs: [f[:, :3] for f in fs], ragged_frames()),
    ),
    label=st.one_of(names(), junk()),
    bounds=st.one_of(st.none(), junk(), float_array(st.tuples(st.integers(0, 3), st.just(2)))),
    neutral=st.one_of(st.just(NEUTRAL), st.just(NEUTRAL), junk()),
)
@fuzz(80)
def test_blendshape_rig_any_input(deltas, label, bounds, neutral):
    rig = typed(AREA, fr.BlendshapeRig, neutral, deltas, label, bounds=bounds)
    if failed(rig):
        return
    assert rig.deltas.shape == (rig.n_shapes, NEUTRAL.n_vertices, 3) and rig.n_shapes >= 1
    assert_readonly_finite(rig.deltas)
    if rig.bounds is not None:
        assert_readonly_finite(rig.bounds)
        assert (rig.bounds[:, 0] <= rig.bounds[:, 1]).all()
    out = rig.evaluate(np.ones(rig.n_shapes))
    assert out.shape == (4, 3)
    bad = typed(AREA, rig.evaluate, np.ones(rig.n_shapes + 1))
    assert isinstance(bad, errors.ShapeError)


@given(
    layers=st.one_of(
        junk(),
        st.dictionaries(
            st.one_of(st.text(max_size=3), st.integers(0, 2)),
            st.one_of(
                float_array(
                    st.tuples(
                        st.integers(0, 3), st.sampled_from([4, 4, 3]), st.sampled_from([3, 3, 2])
                    )
                ),
                junk(),
            ),
            max_size=3,
        ),
    ),
    masks=st.one_of(float_array(st.tuples(st.integers(0, 3), st.sampled_from([4, 4, 3]))), junk()),
    pose_names=st.one_of(
        st.none(), junk(), st.dictionaries(st.text(max_size=2), names(), max_size=2)
    ),
    region_names=st.one_of(st.none(), names(), junk()),
)
@fuzz(80)
def test_layered_rig_any_input(layers, masks, pose_names, region_names):
    rig = typed(
        AREA, fr.LayeredRig, layers, masks, pose_names=pose_names, region_names=region_names
    )
    if failed(rig):
        return
    assert rig.layer_names and all(
        p.shape[1:] == (rig.n_points, rig.dim) for p in rig.layers.values()
    )
    for poses in rig.layers.values():
        assert_readonly_finite(poses)
    assert_readonly_finite(rig.masks)
    assert (rig.masks >= 0).all() and rig.masks.shape == (rig.n_regions, rig.n_points)
    assert set(rig.pose_names) == set(rig.layers)


# ---------------------------------------------------------------------------------------
# composites: any mix of valid and invalid parts
# ---------------------------------------------------------------------------------------
MARKERS = fr.MarkerSequence(np.random.default_rng(0).normal(size=(3, 4, 3)), fps=30)
MESHSEQ = fr.MeshSequence(
    np.repeat(np.asarray(NEUTRAL.vertices)[None], 3, axis=0), NEUTRAL.triangles
)
WEIGHTS = fr.WeightSequence(np.zeros((3, 2)), ["a", "b"])
RIG = fr.BlendshapeRig(NEUTRAL, np.ones((2, 4, 3)), ["a", "b"])
LAYERS4 = fr.LayeredRig({"emotion": np.zeros((2, 4, 3))}, np.ones((1, 4)))
TRACKS = fr.MarkerSequence(np.zeros((3, 5, 2)))
LANDMARKS = fr.Landmarks([0, 3])
EYE = np.eye(4)


def parts(*valid):
    return st.one_of(st.none(), st.sampled_from(valid), junk())


@given(
    performance=st.one_of(st.sampled_from([MARKERS, MESHSEQ, WEIGHTS]), junk()),
    head_motion=st.one_of(
        st.none(),
        st.just(np.repeat(EYE[None], 3, 0)),
        st.just(np.repeat(EYE[None], 2, 0)),
        float_array((3, 4, 4)),
        junk(),
    ),
    landmarks=parts(LANDMARKS, fr.Landmarks([7]), [0, 1]),
    feature_lines=parts(
        {"lip": [0, 1, 2]}, {"lip": [0]}, {"lip": [0, 9]}, {1: [0, 1], "1": [1, 2]}
    ),
    examples=st.one_of(
        st.none(),
        float_array(st.tuples(st.integers(0, 2), st.sampled_from([4, 5]), st.just(3))),
        junk(),
    ),
    example_names=st.one_of(st.none(), names()),
    rig=parts(RIG),
    actor_layers=parts(LAYERS4, fr.LayeredRig({"e": np.zeros((2, 5, 3))}, np.ones((1, 5)))),
    tracks2d=parts(TRACKS, MARKERS, fr.MarkerSequence(np.zeros((2, 5, 2)))),
    actor_layers_2d=parts(fr.LayeredRig({"e": np.zeros((2, 5, 2))}, np.ones((1, 5)))),
)
@fuzz(100)
def test_source_any_combination(
    performance,
    head_motion,
    landmarks,
    feature_lines,
    examples,
    example_names,
    rig,
    actor_layers,
    tracks2d,
    actor_layers_2d,
):
    src = typed(
        AREA,
        fr.Source,
        performance,
        head_motion=head_motion,
        landmarks=landmarks,
        feature_lines=feature_lines,
        examples=examples,
        example_names=example_names,
        rig=rig,
        actor_layers=actor_layers,
        tracks2d=tracks2d,
        actor_layers_2d=actor_layers_2d,
    )
    if failed(src):
        return
    assert src.kind in ("markers", "mesh", "weights")
    if src.head_motion is not None:
        assert src.head_motion.shape == (src.n_frames, 4, 4)
    for chain in src.feature_lines.values():
        assert chain.ndim == 1 and len(chain) >= 2
    if src.landmarks is not None:
        assert isinstance(src.landmarks, fr.Landmarks)
    for call in (src.marker_positions, src.marker_reference):
        out = typed(AREA, call)
        if not failed(out):
            assert out.shape[-1] in (2, 3)


@given(
    neutral=st.one_of(st.just(NEUTRAL), st.just(NEUTRAL), junk()),
    blendshapes=parts(
        RIG, fr.BlendshapeRig(fr.Mesh(np.eye(3), [[0, 1, 2]]), np.ones((1, 3, 3)), ["x"])
    ),
    layers=parts(
        LAYERS4,
        fr.LayeredRig({"e": np.zeros((2, 5, 3))}, np.ones((1, 5))),
        fr.LayeredRig({"e": np.zeros((1, 4, 2))}, np.ones((1, 4))),
    ),
    landmarks=parts(
        LANDMARKS, fr.Landmarks([4]), fr.Landmarks(triangle_ids=[2], barycentric=[[1, 0, 0]])
    ),
    feature_lines=parts({"eye": [0, 1]}, {"eye": [0, 4]}),
    examples=st.one_of(
        st.none(),
        float_array(st.tuples(st.integers(0, 2), st.sampled_from([4, 3]), st.just(3))),
        junk(),
    ),
    example_names=st.one_of(st.none(), names()),
)
@fuzz(80)
def test_target_rig_any_combination(
    neutral, blendshapes, layers, landmarks, feature_lines, examples, example_names
):
    target = typed(
        AREA,
        fr.TargetRig,
        neutral,
        blendshapes=blendshapes,
        layers=layers,
        landmarks=landmarks,
        feature_lines=feature_lines,
        examples=examples,
        example_names=example_names,
    )
    if failed(target):
        return
    for part in target.parts():
        assert target.has(part)
    if target.examples is not None:
        assert target.examples.shape[1:] == (target.neutral.n_vertices, 3)
        assert len(target.example_names) == target.examples.shape[0]


@given(
    vertices=st.one_of(
        st.none(),
        float_array(
            st.tuples(st.integers(0, 3), st.sampled_from([4, 4, 0, 3]), st.sampled_from([3, 3, 2]))
        ),
        junk(),
        ragged_frames(),
    ),
    weights=st.one_of(
        st.none(), float_array(st.tuples(st.integers(0, 3), st.sampled_from([2, 2, 3]))), junk()
    ),
    rig=parts(RIG),
    head_motion=st.one_of(st.none(), st.just(np.repeat(EYE[None], 2, 0)), junk()),
    triangles=st.one_of(st.none(), index_array((1, 3), -1, 4), junk()),
    fps=st.one_of(st.just(30), junk()),
    weight_names=st.one_of(st.none(), names()),
    provenance=st.one_of(st.none(), st.just({"method": "x"}), junk()),
    extras=st.one_of(st.none(), st.just({}), junk()),
)
@example(  # found by the random long mode: zero frames reached the chunked finiteness check
    vertices=np.zeros((0, 4, 3)),
    weights=None,
    rig=None,
    head_motion=None,
    triangles=None,
    fps=30,
    weight_names=None,
    provenance=None,
    extras=None,
)
@fuzz(100)
def test_animation_any_combination(
    vertices, weights, rig, head_motion, triangles, fps, weight_names, provenance, extras
):
    anim = typed(
        AREA,
        fr.Animation,
        vertices=vertices,
        weights=weights,
        rig=rig,
        head_motion=head_motion,
        triangles=triangles,
        fps=fps,
        weight_names=weight_names,
        provenance=provenance,
        extras=extras,
    )
    if failed(anim):
        return
    v = anim.vertices
    assert v.ndim == 3 and v.shape[0] == anim.n_frames and v.shape[2] == 3 and v.shape[1] >= 1
    assert np.isfinite(v).all() and not v.flags.writeable
    if anim.weights is not None:
        assert anim.weights.shape[0] == anim.n_frames and np.isfinite(anim.weights).all()
        if anim.rig is not None:
            assert v.shape[1] == anim.rig.neutral.n_vertices, (
                "vertices and rig must agree on the vertex count"
            )
    if anim.triangles is not None:
        assert anim.triangles.max() < v.shape[1]
    assert isinstance(anim.provenance, dict) and isinstance(anim.extras, dict)


# ---------------------------------------------------------------------------------------
# names and inputs that must not change
# ---------------------------------------------------------------------------------------
@given(label=names(3))
@fuzz(60)
def test_names_unicode_duplicates_and_blanks(label):
    seq = typed(AREA, fr.WeightSequence, np.zeros((1, 3)), label)
    not_text = any(not isinstance(n, str) for n in label)
    blank = any(not str(n).strip() for n in label)
    dup = len(set(map(repr, label))) != len(label)
    if len(label) != 3 or not_text or blank or dup:
        assert isinstance(seq, errors.InputError), f"names {label!r} must be rejected"
    else:
        assert seq.names == tuple(label), "valid unicode names are kept exactly"


@given(
    mesh=valid_mesh(),
    names_=unique_names(2),
    dtype=st.sampled_from([np.float32, np.float64]),
    data=st.data(),
)
@fuzz(30)
def test_constructors_leave_inputs_untouched(mesh, names_, dtype, data):
    v = np.asarray(mesh.vertices, dtype=dtype).copy()
    deltas = data.draw(float_array((2, mesh.n_vertices, 3), special=False, dtype=dtype))
    frames = np.stack([v, v + 1])
    readonly = data.draw(st.booleans())
    arrays = [v, deltas, frames]
    for a in arrays:
        a.flags.writeable = not readonly
    before = [(a.tobytes(), a.flags.writeable, a.dtype) for a in arrays]
    tris = np.array(mesh.triangles)
    typed(AREA, fr.Mesh, v, tris)
    rig = typed(AREA, fr.BlendshapeRig, fr.Mesh(v, tris), deltas, names_)
    seq = typed(AREA, fr.MeshSequence, frames, tris)
    anim = typed(AREA, fr.Animation, weights=np.ones((2, 2), dtype), rig=rig)
    assert not any(map(failed, (rig, seq, anim)))
    assert np.asarray(anim.vertices).shape == (2, mesh.n_vertices, 3)
    assert [(a.tobytes(), a.flags.writeable, a.dtype) for a in arrays] == before
