"""Bundles and the user-file entry points load_source / load_target."""

from __future__ import annotations

import json

import numpy as np
import pytest

import faceretarget as fr
from faceretarget.errors import FileFormatError, UnknownNameError
from faceretarget.io import load_bundle, load_source, load_target, read_landmarks, save_bundle
from faceretarget.model import (
    Landmarks,
    LayeredRig,
    MarkerSequence,
    Source,
    TargetRig,
    WeightSequence,
)


def _same(a, b, path="obj"):
    """Recursively compare two model objects attribute by attribute (arrays exactly)."""
    if isinstance(a, np.ndarray) or isinstance(b, np.ndarray):
        np.testing.assert_array_equal(np.asarray(a), np.asarray(b), err_msg=path)
        return
    if isinstance(a, dict):
        assert set(a) == set(b), path
        for k in a:
            _same(a[k], b[k], f"{path}[{k!r}]")
        return
    if isinstance(a, (list, tuple)):
        assert len(a) == len(b), path
        for i, (x, y) in enumerate(zip(a, b)):
            _same(x, y, f"{path}[{i}]")
        return
    if hasattr(a, "__dict__") and not isinstance(a, type):
        assert type(a) is type(b), path
        keys = {k for k in vars(a) if not k.startswith("_")} | {"vertices"} & set(dir(a))
        for k in sorted(keys):
            if k in ("adjacency",):
                continue
            _same(getattr(a, k), getattr(b, k), f"{path}.{k}")
        return
    assert a == b, f"{path}: {a!r} != {b!r}"


def _full_source(seq, rig, mesh):
    layers = LayeredRig(
        {"emotion": np.random.default_rng(0).normal(size=(3, 4, 3)), "blink": np.zeros((2, 4, 3))},
        np.ones((2, 4)),
        pose_names={"emotion": ["a", "b", "c"]},
        region_names=["upper", "lower"],
    )
    tracks = MarkerSequence(np.random.default_rng(1).normal(size=(seq.n_frames, 3, 2)), fps=seq.fps)
    layers2d = LayeredRig(
        {"emotion": np.zeros((3, 3, 2)), "blink": np.zeros((2, 3, 2))}, np.ones((1, 3))
    )
    return Source(
        seq,
        head_motion=np.tile(np.eye(4), (seq.n_frames, 1, 1)),
        landmarks=Landmarks(
            triangle_ids=[0, 3, 5, 7],
            barycentric=np.full((4, 3), 1 / 3),
            names=["a", "b", "c", "d"],
        ),
        feature_lines={"mouth": [0, 1, 2], "eye_L": [4, 5]},
        examples=seq.vertices[:2],
        example_names=["smile", "blink"],
        rig=rig,
        actor_layers=layers,
        tracks2d=tracks,
        actor_layers_2d=layers2d,
        name="take 1",
    )


def test_source_bundle_keeps_every_part(tmp_path, seq, rig, mesh):
    src = _full_source(seq, rig, mesh)
    save_bundle(src, tmp_path / "src.npz")
    back = load_bundle(tmp_path / "src.npz")
    _same(src, back)
    assert load_source(tmp_path / "src.npz").name == "take 1"


def test_target_and_case_bundles(tmp_path):
    from faceretarget import cases

    case = cases.synthetic(seed=1, resolution=200, n_frames=6)
    save_bundle(case.target, tmp_path / "tgt.npz")
    _same(case.target, load_target(tmp_path / "tgt.npz"))
    save_bundle(case, tmp_path / "case.npz")
    back = fr.load(tmp_path / "case.npz")
    _same(case.source, back.source)
    _same(case.target, back.target)
    _same(case.truth, back.truth)
    _same(case.meta["layer_coefficients"], back.meta["layer_coefficients"])
    assert back.name == case.name
    _same(case.source, load_source(tmp_path / "case.npz"))
    assert isinstance(load_target(tmp_path / "case.npz"), TargetRig)


def test_newer_or_foreign_npz_versions(tmp_path, mesh):
    np.savez(
        tmp_path / "future.npz",
        format=np.array("faceretarget.mesh"),
        version=np.array(99),
        vertices=mesh.vertices,
        triangles=mesh.triangles,
    )
    with pytest.raises(FileFormatError, match="newer faceretarget"):
        fr.load(tmp_path / "future.npz")
    np.savez(tmp_path / "what.npz", stuff=np.zeros(3))
    with pytest.raises(FileFormatError, match="cannot tell"):
        fr.load(tmp_path / "what.npz")


def test_ict_style_npz_reads_as_a_rig(tmp_path, rig):
    np.savez(
        tmp_path / "ict.npz",
        neutral=rig.neutral.vertices.astype(np.float32),
        faces=rig.neutral.triangles.astype(np.int32),
        expression_names=np.array(rig.names),
        expression_deltas=rig.deltas.astype(np.float32),
        landmarks68=np.array([0, 3, 5]),
    )
    target = load_target(tmp_path / "ict.npz", landmarks=f"{tmp_path / 'ict.npz'}:landmarks68")
    assert target.blendshapes.names == rig.names
    np.testing.assert_array_equal(target.landmarks.vertex_ids, [0, 3, 5])


def test_landmark_files(tmp_path):
    (tmp_path / "a.json").write_text(json.dumps({"noseTip": 4, "chin": 2}))
    assert read_landmarks(tmp_path / "a.json").names == ("noseTip", "chin")
    (tmp_path / "b.txt").write_text("# id name\n4 noseTip\n2 chin\n")
    np.testing.assert_array_equal(read_landmarks(tmp_path / "b.txt").vertex_ids, [4, 2])
    (tmp_path / "c.txt").write_text("4\n2\n")
    assert read_landmarks(tmp_path / "c.txt").names == ("landmark0", "landmark1")
    (tmp_path / "d.json").write_text(
        json.dumps({"triangle_ids": [1], "barycentric": [[0.2, 0.3, 0.5]], "names": ["x"]})
    )
    assert read_landmarks(tmp_path / "d.json").triangle_ids.tolist() == [1]
    (tmp_path / "e.txt").write_text("4 noseTip\n2\n")
    with pytest.raises(FileFormatError, match="every landmark line has a name"):
        read_landmarks(tmp_path / "e.txt")
    (tmp_path / "f.json").write_text(json.dumps([1, -2]))
    with pytest.raises(FileFormatError, match="f.json.*negative"):
        read_landmarks(tmp_path / "f.json")


def test_target_from_rig_file_with_landmarks_out_of_range(tmp_path, rig):
    fr.save(rig, tmp_path / "rig.glb")
    (tmp_path / "lm.json").write_text(json.dumps([0, 1, 999]))
    with pytest.raises(Exception) as info:
        load_target(tmp_path / "rig.glb", landmarks=tmp_path / "lm.json")
    assert "999" in str(info.value)
    (tmp_path / "lm.json").write_text(json.dumps([0, 1, 5]))
    target = load_target(
        tmp_path / "rig.glb", landmarks=tmp_path / "lm.json", feature_lines={"mouth": [0, 1]}
    )
    assert target.parts() == ("blendshapes", "landmarks", "feature_lines")


def test_weight_source_is_mapped_onto_the_rig_names(tmp_path, rig):
    values = np.random.default_rng(0).random((5, 5))
    values[:, 3:] = 0.0  # no pitch or roll
    curves = WeightSequence(
        values, ["JawOpen", "eyeBlinkLeft", "HeadYaw", "HeadPitch", "HeadRoll"], fps=60
    )
    fr.save(curves, tmp_path / "take.csv")
    src = load_source(tmp_path / "take.csv", rig=rig, mapping={"eyeBlinkLeft": "eyeBlink_L"})
    # a Live Link head rotation column is the head motion, not a weight
    yaw = curves.weights[:, 2]
    np.testing.assert_allclose(src.head_motion[:, 0, 2], np.sin(yaw), atol=1e-6)
    assert src.performance.names == rig.names and src.rig is rig
    np.testing.assert_array_equal(src.performance.weights[:, 0], curves.weights[:, 0])
    np.testing.assert_array_equal(src.performance.weights[:, 2], 0)  # brow/up has no curve
    bad = WeightSequence(np.zeros((2, 2)), ["jawOpen", "tongueOut"], fps=60)
    fr.save(bad, tmp_path / "bad.csv")
    with pytest.raises(UnknownNameError, match="tongueOut"):
        load_source(tmp_path / "bad.csv", rig=rig)


def test_mesh_sequence_source_with_landmarks_and_head_motion(tmp_path, seq):
    fr.save(seq, tmp_path / "take.pc2")
    fr.save(seq.frame(0), tmp_path / "take.obj")
    np.save(tmp_path / "head.npy", np.tile(np.eye(4), (seq.n_frames, 1, 1)))
    (tmp_path / "lm.txt").write_text("0\n5\n9\n")
    src = load_source(
        tmp_path / "take.pc2",
        landmarks=tmp_path / "lm.txt",
        head_motion=tmp_path / "head.npy",
        fps=24,
    )
    assert (
        src.kind == "mesh"
        and src.fps == 24
        and src.marker_positions().shape == (seq.n_frames, 3, 3)
    )
    np.save(tmp_path / "head.npy", np.zeros((2, 4, 4)))
    with pytest.raises(Exception, match="head_motion"):
        load_source(tmp_path / "take.pc2", head_motion=tmp_path / "head.npy")
