"""Procrustes fits and transforms (geometry.procrustes): the one kernel of each job against
brute force, frame by frame, with missing points, per-frame references and weights."""

import ast
from pathlib import Path

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

import faceretarget
import faceretarget.plugins
from faceretarget.errors import DegenerateGeometryError
from faceretarget.geometry import procrustes


def _umeyama(reference, frame, w, scale):
    """Brute force, one frame: weighted Kabsch / Umeyama on the rows without a NaN."""
    keep = ~np.isnan(frame).any(axis=1)
    ref, x, w = reference[keep], frame[keep], w[keep]
    wn = w / w.sum()
    mu_r, mu_x = wn @ ref, wn @ x
    cov = sum(wn[i] * np.outer(x[i] - mu_x, ref[i] - mu_r) for i in range(len(wn)))
    u, sig, vt = np.linalg.svd(cov)
    fix = np.ones(len(sig))
    fix[-1] = np.sign(np.linalg.det(u @ vt)) or 1.0
    rot = u @ np.diag(fix) @ vt
    s = (sig @ fix) / (wn @ np.sum((ref - mu_r) ** 2, axis=1)) if scale else 1.0
    return rot, mu_x - s * rot @ mu_r, s


def _case(dim, n_frames=6, n_points=9, seed=0):
    rng = np.random.default_rng(seed)
    reference = rng.normal(size=(n_frames, n_points, dim))  # one a frame
    rot = Rotation.random(n_frames, random_state=seed).as_matrix()[:, :dim, :dim]
    if dim == 2:
        angle = rng.uniform(-np.pi, np.pi, n_frames)
        rot = np.stack([[np.cos(angle), -np.sin(angle)], [np.sin(angle), np.cos(angle)]], -1)
        rot = rot.transpose(1, 0, 2)
    frames = 1.7 * np.einsum("fij,fpj->fpi", rot, reference) + rng.normal(size=(n_frames, 1, dim))
    frames += 0.05 * rng.normal(size=frames.shape)  # not exactly rigid
    frames[1, 3] = np.nan  # a missing point
    frames[2, 4, 1] = np.nan  # a point with one NaN coordinate is missing too
    weights = rng.uniform(0.2, 2.0, size=(n_frames, n_points))
    return reference, frames, weights


@pytest.mark.parametrize("dim", [2, 3])
@pytest.mark.parametrize("scale", [False, True])
def test_fit_rigid_matches_brute_force(dim, scale):
    """Per-frame references and weights, missing points; and a frame alone gives the same
    numbers as inside the batch."""
    reference, frames, weights = _case(dim)
    rot, trans, s = procrustes.fit_rigid(reference, frames, weights, scale=scale)
    for f in range(len(frames)):
        want = _umeyama(reference[f], frames[f], weights[f], scale)
        np.testing.assert_allclose(rot[f], want[0], atol=1e-12)
        np.testing.assert_allclose(trans[f], want[1], atol=1e-12)
        np.testing.assert_allclose(s[f], want[2], atol=1e-12)
        assert np.isclose(np.linalg.det(rot[f]), 1.0)
        alone = procrustes.fit_rigid(reference[f], frames[f], weights[f], scale=scale)
        np.testing.assert_array_equal(alone[0], rot[f])
        np.testing.assert_array_equal(alone[1], trans[f])
    shared = procrustes.fit_rigid(reference[0], frames, weights[0], scale=scale)  # one for all
    for f in range(len(frames)):
        want = _umeyama(reference[0], frames[f], weights[0], scale)
        np.testing.assert_allclose(shared[0][f], want[0], atol=1e-12)


def test_too_few_points_raise_or_give_the_identity():
    reference, frames, weights = _case(3)
    frames[4, 2:] = np.nan  # two points left
    weights[5, 3:] = 0.0  # three points of non-zero weight: enough
    with pytest.raises(DegenerateGeometryError, match="frame 4 has fewer than 3"):
        procrustes.fit_rigid(reference, frames, weights)
    rot, trans, s = procrustes.fit_rigid(reference, frames, weights, min_points=3, scale=True)
    np.testing.assert_array_equal(rot[4], np.eye(3))
    assert np.all(trans[4] == 0) and s[4] == 1.0
    want = _umeyama(reference[5], frames[5], weights[5], True)
    np.testing.assert_allclose(rot[5], want[0], atol=1e-12)
    weights[5, 2] = 0.0  # two of non-zero weight: the identity
    assert np.array_equal(
        procrustes.fit_rigid(reference, frames, weights, min_points=3)[0][5], np.eye(3)
    )


def test_apply_and_remove_match_the_matrices():
    """One kernel applies and undoes (affine) transforms: against numpy, float32 points
    read as they are, a reference subtracted, points shared by all frames broadcast."""
    rng = np.random.default_rng(5)
    m = np.tile(np.eye(4), (4, 1, 1))
    m[:, :3, :3] = rng.normal(size=(4, 3, 3)) + 3 * np.eye(3)
    m[:, :3, 3] = rng.normal(size=(4, 3))
    points = rng.normal(size=(4, 6, 3))
    points[1, 2] = np.nan
    ref = rng.normal(size=(6, 3))
    want = np.einsum("fij,fpj->fpi", m[:, :3, :3], points) + m[:, None, :3, 3]
    np.testing.assert_allclose(procrustes.apply(m, points), want, atol=1e-13)
    np.testing.assert_allclose(
        procrustes.apply(m, points[0]),
        np.einsum("fij,pj->fpi", m[:, :3, :3], points[0]) + m[:, None, :3, 3],
        atol=1e-13,
    )
    single = points.astype(np.float32)
    got = procrustes.apply(m, single)
    assert got.dtype == np.float64
    np.testing.assert_allclose(got, procrustes.apply(m, single.astype(np.float64)), atol=0)
    np.testing.assert_allclose(procrustes.remove(m, want), points, atol=1e-12)
    np.testing.assert_allclose(procrustes.remove(m, want, ref), points - ref, atol=1e-12)
    assert np.isnan(procrustes.remove(m, want)[1, 2]).all()


def test_no_plugin_kernel_repeats_a_shared_one():
    """One kernel per job: a plugin's numba kernels do not redefine one of
    faceretarget.geometry's (vertex normals, Procrustes fits, transforms, ...)."""
    root = Path(faceretarget.__file__).parent

    def kernels(paths):
        out = {}
        for path in paths:
            for node in ast.parse(path.read_text(encoding="utf-8")).body:
                if isinstance(node, ast.FunctionDef) and not node.name.startswith("_"):
                    out[node.name] = path
        return out

    shared = kernels(sorted((root / "geometry").glob("_*kernels.py")))
    plugins = Path(faceretarget.plugins.__file__).parent
    repeated = {
        name: str(path.relative_to(plugins))
        for name, path in kernels(sorted(plugins.glob("*/_*kernels.py"))).items()
        if name in shared
    }
    assert not repeated, f"use the kernels of faceretarget.geometry instead: {repeated}"
    assert {"vertex_normals", "kabsch", "transform_points"} <= set(shared)


@pytest.mark.parametrize("dim", [2, 3])
def test_rotations_match_the_svd_on_hard_configurations(dim):
    """The kernel's rotation (2-D closed form, 3-D Horn quaternion by Jacobi: no LAPACK
    compiled into it) against Kabsch's SVD with its reflection fix: exact rotations
    (180 degrees included, where the quaternion's scalar part is 0), mirrored data (the best
    orthogonal map is a reflection: the proper rotation must be returned), flat and many
    random noisy frames."""
    rng = np.random.default_rng(11)
    frames, refs = [], []
    for seed in range(40):
        ref = rng.normal(size=(7, dim))
        if seed % 5 == 1:
            ref[:, -1] = 0.0  # coplanar (3-D) / on a line (2-D)
        rot = Rotation.random(random_state=seed).as_matrix()[:dim, :dim]
        if dim == 2:
            a = rng.uniform(-np.pi, np.pi)
            rot = np.array([[np.cos(a), -np.sin(a)], [np.sin(a), np.cos(a)]])
        if seed % 5 == 2:
            rot = np.diag([-1.0, -1.0, 1.0][:dim]) if dim == 3 else -np.eye(2)  # 180 degrees
        if seed % 5 == 3:
            rot = rot @ np.diag([1.0] * (dim - 1) + [-1.0])  # a reflection
        x = ref @ rot.T * 1.3 + rng.normal(size=dim)
        if seed % 5 in (3, 4):
            x += 0.2 * rng.normal(size=x.shape)
        refs.append(ref)
        frames.append(x)
    refs, frames = np.array(refs), np.array(frames)
    w = np.ones((len(frames), 7))
    for scale in (False, True):
        rot, trans, s = procrustes.fit_rigid(refs, frames, w, scale=scale)
        for f in range(len(frames)):
            want = _umeyama(refs[f], frames[f], w[f], scale)
            np.testing.assert_allclose(rot[f], want[0], atol=1e-12, err_msg=f"frame {f}")
            np.testing.assert_allclose(trans[f], want[1], atol=1e-12, err_msg=f"frame {f}")
            np.testing.assert_allclose(s[f], want[2], rtol=1e-12, err_msg=f"frame {f}")
            assert np.isclose(np.linalg.det(rot[f]), 1.0)
