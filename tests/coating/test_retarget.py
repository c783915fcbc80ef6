"""The coating and deformation_transfer retargeters on synthetic parallel rigs."""
import numpy as np
import pytest

import faceretarget as fr
from faceretarget.geometry.smoothing import TaubinSmoother
from faceretarget.errors import (
    CapabilityError,
    ConfigError,
    DegenerateGeometryError,
    NonFiniteError,
    OutputError,
    TopologyMismatchError,
)
from faceretarget.model import Mesh, MeshSequence, Source, TargetRig
from faceretarget.plugins.coating.retargeter import CoatingRetargeter, DeformationTransferRetargeter

RES, FRAMES = 1200, 30
#: Stated bounds on the low-resolution stylized case: RMS errors as fractions of the
#: target face height; correlation of the fine-scale wrinkle fields.
RMS_BOUND = 0.01
LARGE_SCALE_BOUND = 0.01
WRINKLE_CORRELATION = 0.98


def _rms(a, b, height):
    return float(np.sqrt(np.mean(np.sum((np.asarray(a) - np.asarray(b)) ** 2, axis=-1)))) / height


@pytest.fixture(scope="module")
def cases():
    return {w: fr.cases.synthetic(seed=1, resolution=RES, n_frames=FRAMES, target="stylized", wrinkles=w) for w in (True, False)}


@pytest.fixture(scope="module")
def results(cases):
    out = {}
    for cls in (CoatingRetargeter, DeformationTransferRetargeter):
        for wrinkles, case in cases.items():
            out[cls.name, wrinkles] = cls().fit(case.source, case.target).retarget(case.source)
    return out


@pytest.mark.parametrize("name", ["coating", "deformation_transfer"])
def test_close_to_ground_truth(cases, results, name):
    case = cases[True]
    height = case.target.neutral.height
    assert _rms(results[name, True].vertices, case.truth.vertices, height) < RMS_BOUND


def test_large_scale_and_wrinkles_against_ground_truth(cases, results):
    """Large scale: the case without wrinkles. Wrinkles: the fine-scale part (minus its
    Taubin-smoothed version) of (with wrinkles) - (without), for the truth and each method."""
    height = cases[True].target.neutral.height
    smoother = TaubinSmoother(cases[True].target.neutral.triangles, cases[True].target.neutral.n_vertices)

    def fine(x):
        return x - smoother(x)

    truth_w = fine(cases[True].truth.local_vertices - cases[False].truth.local_vertices)
    corr = {}
    for name in ("coating", "deformation_transfer"):
        large = _rms(results[name, False].vertices, cases[False].truth.vertices, height)
        assert large < LARGE_SCALE_BOUND, f"{name}: large-scale error {large:.4f}"
        got_w = fine(results[name, True].local_vertices - results[name, False].local_vertices)
        corr[name] = float(np.sum(got_w * truth_w) / np.linalg.norm(got_w) / np.linalg.norm(truth_w))
    assert corr["coating"] > WRINKLE_CORRELATION, corr
    assert corr["coating"] > corr["deformation_transfer"] + 0.01, corr


def test_diagnostics_and_weights(results):
    anim = results["coating", True]
    diag = anim.provenance["diagnostics"]
    assert diag["n_bases"] == len(diag["basis_frames"]) + 1
    assert diag["selection_rms"][-1] <= CoatingRetargeter().epsilon or diag["n_bases"] == CoatingRetargeter().max_bases
    w = anim.extras["weights"]
    assert w.shape == (FRAMES, diag["n_bases"]) and (w >= 0).all()


def test_reproduces_the_source_on_itself_exactly(cases):
    """Zero edits, every frame a basis, target = source: decomposition and reconstruction are exact."""
    case = cases[True]
    src = case.source
    perf = src.performance
    target = TargetRig(perf.reference, feature_lines=src.feature_lines)
    source = Source(perf, head_motion=case.meta["head_motion"], feature_lines=src.feature_lines)
    r = CoatingRetargeter(epsilon=1e-12, max_bases=FRAMES + 1).fit(source, target)
    anim = r.retarget(source)
    height = perf.reference.height
    assert _rms(anim.vertices, perf.vertices, height) < 1e-7


def test_rigid_motion_is_carried_exactly(cases):
    case = cases[True]
    perf = case.source.performance
    motion = case.meta["head_motion"]
    ref = np.asarray(perf.reference.vertices)
    frames = np.einsum("fij,vj->fvi", motion[:, :3, :3], ref) + motion[:, None, :3, 3]
    source = Source(MeshSequence(frames, perf.triangles, reference=perf.reference), feature_lines=case.source.feature_lines)
    for cls in (CoatingRetargeter, DeformationTransferRetargeter):
        anim = cls().fit(source, case.target).retarget(source)
        want = np.einsum("fij,vj->fvi", motion[:, :3, :3], case.target.neutral.vertices) + motion[:, None, :3, 3]
        assert _rms(anim.vertices, want, case.target.neutral.height) < 1e-6, cls.name


def test_chunks_stream_and_file_agree(cases, tmp_path):
    case = cases[True]
    r = CoatingRetargeter(chunk_frames=7).fit(case.source, case.target)
    full = r.retarget(case.source).vertices
    pieces = np.concatenate([v for _, v in r.iter_retarget(case.source)])
    np.testing.assert_array_equal(pieces, full)
    path = tmp_path / "out.npy"
    anim = r.retarget_to(case.source, path)
    np.testing.assert_allclose(np.load(path), full, atol=1e-4 * case.target.neutral.height)
    assert anim.vertices.shape == full.shape and anim.extras["coating"].details is None
    with pytest.raises(OutputError):
        r.retarget_to(case.source, tmp_path / "out.txt")


def test_memory_mapped_source(cases, tmp_path):
    case = cases[True]
    perf = case.source.performance
    path = tmp_path / "src.npy"
    np.save(path, np.asarray(perf.vertices, dtype=np.float32))
    mapped = Source(MeshSequence(np.load(path, mmap_mode="r"), perf.triangles, reference=perf.reference), feature_lines=case.source.feature_lines)
    r = CoatingRetargeter(chunk_frames=8).fit(mapped, case.target)
    anim = r.retarget(mapped)
    assert _rms(anim.vertices, case.truth.vertices, case.target.neutral.height) < RMS_BOUND


def test_one_frame_sequence(cases):
    case = cases[True]
    perf = case.source.performance
    one = Source(MeshSequence(perf.vertices[12:13], perf.triangles, reference=perf.reference), feature_lines=case.source.feature_lines)
    for cls in (CoatingRetargeter, DeformationTransferRetargeter):
        anim = cls().fit(one, case.target).retarget(one)
        assert anim.vertices.shape == (1, case.target.neutral.n_vertices, 3)
        assert _rms(anim.vertices, case.truth.vertices[12:13], case.target.neutral.height) < RMS_BOUND


def test_bad_inputs(cases):
    case = cases[True]
    src, tgt = case.source, case.target
    perf = src.performance
    # missing feature lines
    bare = TargetRig(tgt.neutral)
    with pytest.raises(CapabilityError, match="feature lines"):
        CoatingRetargeter().fit(src, bare)
    # feature lines named differently
    renamed = TargetRig(tgt.neutral, feature_lines={"lips": next(iter(tgt.feature_lines.values()))})
    with pytest.raises(TopologyMismatchError, match="lips"):
        CoatingRetargeter().fit(src, renamed)
    # zero-area triangle in the target: the triangles are named
    verts = np.array(tgt.neutral.vertices)
    a, b, c = tgt.neutral.triangles[5]
    verts[c] = 0.5 * (verts[a] + verts[b])
    flat = TargetRig(Mesh(verts, tgt.neutral.triangles), feature_lines=tgt.feature_lines)
    for cls in (CoatingRetargeter, DeformationTransferRetargeter):
        with pytest.raises(DegenerateGeometryError, match="zero-area"):
            cls().fit(src, flat)
    # a differently triangulated target without landmarks cannot be resampled
    other = fr.cases.synthetic(resolution=RES // 2, n_frames=2)
    with pytest.raises(CapabilityError, match="landmarks"):
        DeformationTransferRetargeter().fit(Source(perf), TargetRig(other.target.neutral))
    # retargeting a source of another topology than the fit
    r = DeformationTransferRetargeter().fit(src, tgt)
    with pytest.raises(TopologyMismatchError):
        r.retarget(other.source)
    # NaN never gets in
    bad = np.array(perf.vertices[:3])
    bad[1, 4, 0] = np.nan
    with pytest.raises(NonFiniteError):
        MeshSequence(bad, perf.triangles)
    # parameters
    with pytest.raises(ConfigError):
        CoatingRetargeter(laplacian="nope").fit(src, tgt)
    with pytest.raises(ConfigError):
        CoatingRetargeter(epsilon=-1.0).fit(src, tgt)
    with pytest.raises(ConfigError):
        DeformationTransferRetargeter(stable_fraction=2.0).fit(src, tgt)


def test_different_target_topology_is_resampled(cases):
    case = fr.cases.synthetic(seed=1, resolution=RES, target_resolution=RES // 2 + 200, n_frames=12)
    height = case.target.neutral.height
    for cls in (CoatingRetargeter, DeformationTransferRetargeter):
        r = cls().fit(case.source, case.target)
        anim = r.retarget(case.source)
        assert anim.vertices.shape == case.truth.vertices.shape
        assert _rms(anim.vertices, case.truth.vertices, height) < RMS_BOUND
        assert not r.topology_.same and r.topology_.report["landmark_error"] < 0.01
    # edits name the target's own vertices
    v = int(case.target.landmarks.vertex_ids[0])
    goal = anim.vertices[5, v] + [0.0, 0.01 * height, 0.0]
    coating = CoatingRetargeter().fit(case.source, case.target)
    base = coating.retarget(case.source)
    out = coating.edit(base, points=[(5, v, goal)], mode="bases")
    assert np.linalg.norm(out.vertices[5, v] - goal) < np.linalg.norm(base.vertices[5, v] - goal)


def test_registered():
    assert isinstance(fr.get("coating"), CoatingRetargeter)
    assert isinstance(fr.get("deformation_transfer"), DeformationTransferRetargeter)
    info = fr.info("coating")
    assert info.capabilities.edit and "Xu" in info.paper
