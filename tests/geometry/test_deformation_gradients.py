"""Deformation gradients and Sumner-Popovic deformation transfer (Schur-reduced solve)."""

import numpy as np
import pytest
from naive.coating import deformation_transfer as naive_transfer
from naive.coating import grid_mesh

from faceretarget.errors import DegenerateGeometryError, ShapeError, TopologyMismatchError
from faceretarget.geometry.deformation_gradients import (
    DeformationTransfer,
    deformation_gradients,
    deformation_transfer,
    feature_line_gradients,
    fourth_vertex,
    gradient_columns,
    gradient_operator,
    reference_inverse,
    triangle_frames,
)


def _rotation(axis, angle):
    axis = np.asarray(axis, float) / np.linalg.norm(axis)
    k = np.array([[0, -axis[2], axis[1]], [axis[2], 0, -axis[0]], [-axis[1], axis[0], 0]])
    return np.eye(3) + np.sin(angle) * k + (1 - np.cos(angle)) * k @ k


def _target(v):
    """Another face: stretched and bent version of ``v``."""
    w = v * [1.3, 0.9, 1.1]
    w[:, 2] += 0.2 * w[:, 0] ** 2
    return w


def test_fourth_vertex_and_frames():
    v, t = grid_mesh(4, seed=0)
    v4 = fourth_vertex(v, t)
    e1, e2 = v[t[:, 1]] - v[t[:, 0]], v[t[:, 2]] - v[t[:, 0]]
    n = np.cross(e1, e2)
    np.testing.assert_allclose(
        np.linalg.norm(v4 - v[t[:, 0]], axis=1), np.sqrt(np.linalg.norm(n, axis=1))
    )
    np.testing.assert_allclose(triangle_frames(v, t)[:, :, 2], v4 - v[t[:, 0]])


def test_gradients_of_similarity_are_the_similarity():
    v, t = grid_mesh(5, seed=1)
    r = _rotation([1, 2, 3], 0.7)
    q = deformation_gradients(v, 1.7 * v @ r.T + [1.0, -2.0, 0.5], t)
    np.testing.assert_allclose(q, np.broadcast_to(1.7 * r, q.shape), atol=1e-12)


def test_numba_gradient_columns_match_numpy():
    v, t = grid_mesh(6, seed=11)
    frames = v + 0.05 * np.random.default_rng(2).normal(size=(3,) + v.shape)
    cols = gradient_columns(reference_inverse(v, t), frames, t)
    want = deformation_gradients(v, frames, t)  # (F, T, 3, 3) [f, j, d, c]
    np.testing.assert_allclose(
        cols.reshape(len(t), 3, 3, 3), np.transpose(want, (1, 3, 0, 2)), atol=1e-12
    )
    bad = frames.copy()
    a, b, c = t[7]
    bad[2, c] = 0.5 * (bad[2, a] + bad[2, b])
    with pytest.raises(DegenerateGeometryError, match=r"mesh 2 \(ids \[7"):
        gradient_columns(reference_inverse(v, t), bad, t)


def test_gradient_operator_reproduces_gradients():
    v, t = grid_mesh(5, seed=2)
    moved = v + 0.05 * np.random.default_rng(0).normal(size=v.shape)
    a = gradient_operator(v, t)
    x = np.concatenate([moved, fourth_vertex(moved, t)])
    got = (a @ x).reshape(len(t), 3, 3).transpose(0, 2, 1)  # [j, d, c]
    np.testing.assert_allclose(got, deformation_gradients(v, moved, t), atol=1e-11)
    given = gradient_operator(v, t, inverse=reference_inverse(v, t))
    assert (given != a).nnz == 0
    with pytest.raises(ShapeError):
        gradient_operator(v, t, inverse=reference_inverse(v, t)[1:])


def test_identity_transfers_to_identity():
    v, t = grid_mesh(6, seed=3)
    target = _target(v)
    out = deformation_transfer(v, v, target, t)
    np.testing.assert_allclose(out, target, atol=1e-10)


def test_rigid_motion_transfers_to_the_same_rotation():
    v, t = grid_mesh(6, seed=4)
    target = _target(v)
    r = _rotation([0.3, 1.0, -0.2], 0.9)
    out = deformation_transfer(v, v @ r.T + [2.0, 0.0, 1.0], target, t)
    want = target @ r.T
    np.testing.assert_allclose(out - out.mean(0), want - want.mean(0), atol=1e-10)


def test_matches_full_system_with_fourth_vertex_unknowns():
    v, t = grid_mesh(5, seed=5)
    target = _target(v)
    rng = np.random.default_rng(1)
    deformed = v + 0.08 * rng.normal(size=v.shape)
    got = DeformationTransfer(target, t).transfer(
        v, deformed, mean_displacement=np.zeros((1, 1, 3))
    )
    want = naive_transfer(v, deformed, target, t)
    # same solution up to translation (the naive one pins vertex 0 at the origin)
    np.testing.assert_allclose(got - got.mean(0), want - want.mean(0), atol=1e-9)


def test_gauge_sets_weighted_mean_displacement():
    v, t = grid_mesh(6, seed=6)
    target = _target(v)
    gauge = np.zeros(len(v))
    gauge[:6] = 1.0
    dt = DeformationTransfer(target, t, gauge_weights=gauge)
    deformed = v.copy()
    deformed[:, 2] += 0.1 * v[:, 0]
    want = np.array([[[0.1, -0.2, 0.3]]])
    out = dt.transfer(v, deformed, mean_displacement=want)
    np.testing.assert_allclose((out - target)[:6].mean(axis=0), want[0, 0], atol=1e-12)


def test_feature_lines_identity_and_effect():
    v, t = grid_mesh(7, seed=7)
    target = _target(v)
    chain = np.arange(7 * 3, 7 * 3 + 7)  # a row of the grid
    lines = {"mouth": chain}
    dt = DeformationTransfer(target, t, feature_lines=lines, sigma=100.0)
    np.testing.assert_allclose(dt.transfer(v, v, source_feature_lines=lines), target, atol=1e-10)
    q = feature_line_gradients(v, v, t, [chain])
    np.testing.assert_allclose(q, np.broadcast_to(np.eye(3), q.shape), atol=1e-12)
    # stretching the source line: with the line term the target line stretches closer to it
    deformed = v.copy()
    deformed[chain, 0] = v[chain, 0].mean() + 1.5 * (v[chain, 0] - v[chain, 0].mean())
    with_lines = dt.transfer(v, deformed, source_feature_lines=lines)
    without = DeformationTransfer(target, t).transfer(v, deformed)
    ratio = np.linalg.norm(deformed[chain[-1]] - deformed[chain[0]]) / np.linalg.norm(
        v[chain[-1]] - v[chain[0]]
    )
    want = ratio * np.linalg.norm(target[chain[-1]] - target[chain[0]])

    def length(x):
        return np.linalg.norm(x[chain[-1]] - x[chain[0]])

    assert abs(length(with_lines) - want) < abs(length(without) - want)


def test_lines_with_other_sampling_and_direction_pair_by_position():
    v, t = grid_mesh(7, seed=8)
    target = _target(v)
    chain = np.arange(7 * 3, 7 * 3 + 7)
    deformed = v.copy()
    deformed[chain[:3], 1] += 0.1  # only the first half of the line moves
    dt = DeformationTransfer(target, t, feature_lines={"a": chain[::-1]})
    pairs = dt.line_targets(v, deformed[None], {"a": chain})
    direct = feature_line_gradients(v, deformed[None], t, [chain])
    # target segment k (reversed chain) is source segment 5 - k
    np.testing.assert_allclose(pairs[0], direct[0][::-1], atol=1e-12)
    with pytest.raises(TopologyMismatchError, match="a"):
        dt.line_targets(v, v[None], {"b": chain})


def test_zero_area_triangles_named():
    v, t = grid_mesh(5, seed=9)
    a, b, c = t[4]
    bad = v.copy()
    bad[c] = 0.5 * (bad[a] + bad[b])
    with pytest.raises(
        DegenerateGeometryError, match=r"frame of a zero-area triangle is undefined"
    ) as err:
        deformation_gradients(v, bad, t)
    assert "4" in str(err.value)
    with pytest.raises(DegenerateGeometryError):
        DeformationTransfer(bad, t)


def test_topology_mismatch():
    v, t = grid_mesh(5)
    dt = DeformationTransfer(v, t)
    with pytest.raises(TopologyMismatchError):
        dt.transfer(v[:-1], v[:-1])


def test_components_get_their_own_gauge():
    v, t = grid_mesh(4, seed=10)
    v2 = v + [3.0, 0.0, 0.0]
    verts = np.concatenate([v, v2])
    tris = np.concatenate([t, t + len(v)])
    dt = DeformationTransfer(verts, tris)
    assert dt.n_components == 2
    moved = verts.copy()
    moved[len(v) :] += [0.0, 1.0, 0.0]
    out = dt.transfer(verts, moved)
    np.testing.assert_allclose(out, moved, atol=1e-10)


def test_transfer_forms_the_gradient_columns_a_few_meshes_at_a_time(monkeypatch):
    """The transfer equals its steps done on all meshes at once; blocks of two meshes give
    the one-block answer bit for bit (lines included), and a
    degenerate mesh (the second of its block) is named by its place in the whole sequence."""
    from faceretarget.geometry import deformation_gradients as dg

    v, t = grid_mesh(7, seed=11)
    chain = np.arange(7 * 3, 7 * 3 + 7)
    dt = DeformationTransfer(_target(v), t, feature_lines={"mouth": chain}, sigma=10.0)
    rng = np.random.default_rng(11)
    meshes = v + 0.05 * rng.normal(size=(5,) + v.shape)
    whole = dt.transfer(v, meshes, source_feature_lines={"mouth": chain})
    # the same steps on all meshes at once, outside transfer's loop
    lines = dt.line_targets(v, meshes, {"mouth": chain})
    rhs = dt.rhs_columns(gradient_columns(reference_inverse(v, t), meshes, t), lines)
    np.testing.assert_array_equal(whole, dt.solve_rhs(rhs, dt.component_means(meshes - v)))
    rows = whole.reshape(len(meshes), -1)  # stored (V, 3, F): the meshes' rows are a view
    assert np.shares_memory(rows, whole) and rows.flags.f_contiguous
    calls = []
    columns = dg.gradient_columns
    monkeypatch.setattr(
        dg, "gradient_columns", lambda *a, **k: calls.append(a[1].shape[0]) or columns(*a, **k)
    )
    monkeypatch.setattr(dg.config, "SCRATCH_BLOCK_BYTES", 2 * 72 * t.shape[0])  # two meshes a block
    blocks = dt.transfer(v, meshes, source_feature_lines={"mouth": chain})
    assert calls == [2, 2, 1]
    np.testing.assert_array_equal(blocks, whole)
    a, b, c = t[4]
    meshes[3, c] = 0.5 * (meshes[3, a] + meshes[3, b])
    with pytest.raises(DegenerateGeometryError, match=r"in mesh 3 \(ids \[4\]"):
        dt.transfer(v, meshes, source_feature_lines={"mouth": chain})


def test_solve_rhs_in_its_right_hand_sides_or_a_copy():
    """``overwrite_rhs`` solves in the caller's array (the result a view of it) with the same
    numbers as the default, which leaves the right-hand sides as they were; the components'
    anchor vertices stay at the reference in both."""
    v, t = grid_mesh(6, seed=4)
    two = np.concatenate([t, t + v.shape[0]])  # two components: two anchors
    ref = np.concatenate([v, v + 3.0])
    dt = DeformationTransfer(_target(ref), two)
    rng = np.random.default_rng(4)
    meshes = ref + 0.05 * rng.normal(size=(3,) + ref.shape)
    rhs = dt.rhs_columns(gradient_columns(reference_inverse(ref, two), meshes, two))
    kept = rhs.copy()
    want = dt.solve_rhs(rhs)
    np.testing.assert_array_equal(rhs, kept)
    got = dt.solve_rhs(rhs, overwrite_rhs=True)
    np.testing.assert_array_equal(got, want)
    assert np.shares_memory(got, rhs)
    x = got.transpose(1, 0, 2).reshape(
        ref.shape[0], -1
    )  # (V, 3F): the gauge shift is in N's null space
    np.testing.assert_allclose(dt.normal_matrix[dt.free] @ x, kept[dt.free], atol=1e-9)
    with pytest.raises(ShapeError, match="solve_rhs"):
        dt.solve_rhs(rhs[:, :4])


@pytest.mark.parametrize("scale", [1e-3, 1.0, 1e3])
def test_reference_inverse_is_the_frames_inverse(scale):
    """The closed-form inverse frames are LAPACK's inverse of :func:`triangle_frames` to
    rounding, in any length unit and for thin triangles; a batch of meshes is refused."""
    v, t = grid_mesh(9, seed=3)
    v = v * scale
    v[5] += [0.3 * scale, 0.0, 0.0]  # stretched and thin triangles around vertex 5
    frames = triangle_frames(v, t)
    want = np.linalg.inv(frames)
    got = reference_inverse(v, t)
    np.testing.assert_allclose(got, want, rtol=1e-12, atol=1e-13 * np.abs(want).max())
    np.testing.assert_allclose(got @ frames, np.broadcast_to(np.eye(3), frames.shape), atol=1e-12)
    with pytest.raises(ShapeError, match=r"\(V, 3\)"):
        reference_inverse(np.stack([v, v]), t)
