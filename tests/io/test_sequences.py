"""Mesh sequences: folders, npy, PC2, MDD (memory-mapped), round trips and bad files."""

from __future__ import annotations

import json
import struct

import numpy as np
import pytest

import faceretarget as fr
from faceretarget.errors import FileFormatError, ResourceLimitError
from faceretarget.model import MeshSequence


def test_folder_is_read_in_natural_order_with_sidecar_fps(tmp_path, seq):
    folder = tmp_path / "take"
    folder.mkdir()
    for k in range(seq.n_frames):  # frame2 must come before frame10
        fr.save(seq.frame(k), folder / f"frame{k * 4}.obj")
    read = fr.load(folder)
    assert isinstance(read, MeshSequence) and read.fps == 30.0
    np.testing.assert_array_equal(read.vertices, seq.vertices)
    (folder / "sequence.json").write_text(json.dumps({"fps": 12}))
    assert fr.load(folder).fps == 12


def test_folder_with_another_topology_names_the_frame(tmp_path, seq, mesh):
    folder = tmp_path / "take"
    folder.mkdir()
    fr.save(seq.frame(0), folder / "f1.obj")
    fr.save(mesh.with_vertices(mesh.vertices), folder / "f2.obj")
    other = folder / "f3.obj"
    other.write_text("v 0 0 0\nv 1 0 0\nv 0 1 0\nf 1 2 3\n")
    with pytest.raises(FileFormatError, match="f3.obj.*different topology"):
        fr.load(folder)


@pytest.mark.parametrize("ext", ["", ".npz"])
def test_exact_round_trips(tmp_path, seq, ext):
    fr.save(seq, tmp_path / f"a{ext}")
    once = fr.load(tmp_path / f"a{ext}", kind="mesh_sequence")
    np.testing.assert_array_equal(once.vertices, seq.vertices)
    np.testing.assert_array_equal(once.triangles, seq.triangles)
    assert once.fps == seq.fps
    fr.save(once, tmp_path / f"b{ext}")
    twice = fr.load(tmp_path / f"b{ext}", kind="mesh_sequence")
    np.testing.assert_array_equal(twice.vertices, once.vertices)


@pytest.mark.parametrize("ext", [".pc2", ".mdd", ".npy"])
def test_point_caches_are_memory_mapped_and_round_trip(tmp_path, seq, mesh, ext):
    fr.save(seq, tmp_path / f"a{ext}")
    once = fr.load(tmp_path / f"a{ext}", topology=mesh)
    if ext != ".mdd":  # MDD is big-endian: the model converts non-native arrays to float64
        assert isinstance(once.vertices, np.memmap)
    np.testing.assert_allclose(once.vertices, seq.vertices, atol=1e-6)
    fr.save(once, tmp_path / f"b{ext}")
    twice = fr.load(tmp_path / f"b{ext}", topology=mesh)
    np.testing.assert_array_equal(np.asarray(twice.vertices), np.asarray(once.vertices))
    if ext == ".mdd":
        assert once.fps == pytest.approx(seq.fps)  # MDD stores frame times


def test_mdd_is_big_endian_and_mapped(tmp_path, mesh):
    frames = np.arange(2 * mesh.n_vertices * 3, dtype=">f4").reshape(2, mesh.n_vertices, 3)
    path = tmp_path / "take.mdd"
    path.write_bytes(
        struct.pack(">ii", 2, mesh.n_vertices)
        + np.array([0, 0.04], ">f4").tobytes()
        + frames.tobytes()
    )
    fr.save(mesh, tmp_path / "take.obj")  # topology found beside the cache by stem
    read = fr.load(path)
    np.testing.assert_array_equal(np.asarray(read.vertices[1]), frames[1].astype(float))
    assert read.fps == 25.0


def test_point_cache_without_topology_says_how_to_fix(tmp_path, seq):
    fr.save(seq, tmp_path / "lonely.pc2")
    with pytest.raises(FileFormatError, match="topology"):
        fr.load(tmp_path / "lonely.pc2")


def _pc2(n_points, n_frames, payload_frames=None, magic=b"POINTCACHE2\0"):
    payload_frames = n_frames if payload_frames is None else payload_frames
    data = np.zeros((max(payload_frames, 0), max(n_points, 0), 3), "<f4").tobytes()
    return struct.pack("<12siiffi", magic, 1, n_points, 0.0, 1.0, n_frames) + data


@pytest.mark.parametrize(
    "data,needle",
    [
        (_pc2(16, 3, payload_frames=2), "truncated"),
        (_pc2(16, 3, magic=b"POINTCACHE3\0"), "wrong magic"),
        (_pc2(-16, 3), "positive"),
        (_pc2(16, 0), "positive"),
        (b"POINTCACHE2\0", "too short"),
    ],
)
def test_bad_pc2(tmp_path, mesh, data, needle):
    path = tmp_path / "bad.pc2"
    path.write_bytes(data)
    with pytest.raises(FileFormatError, match=needle):
        fr.load(path, topology=mesh)


def test_npy_with_nan_or_wrong_shape(tmp_path, mesh):
    frames = np.zeros((2, mesh.n_vertices, 3))
    frames[1, 3, 0] = np.nan
    np.save(tmp_path / "nan.npy", frames)
    with pytest.raises(FileFormatError, match="nan.npy.*NaN"):
        fr.load(tmp_path / "nan.npy", topology=mesh)
    np.save(tmp_path / "flat.npy", np.zeros((4, 3)))
    with pytest.raises(FileFormatError, match="F, V, 3"):
        fr.load(tmp_path / "flat.npy", topology=mesh)
    np.save(tmp_path / "count.npy", np.zeros((2, mesh.n_vertices + 1, 3)))
    with pytest.raises(FileFormatError, match="must match"):
        fr.load(tmp_path / "count.npy", topology=mesh)


def test_object_arrays_are_never_unpickled(tmp_path, mesh):
    np.save(tmp_path / "obj.npy", np.array([{"x": 1}], dtype=object), allow_pickle=True)
    with pytest.raises(FileFormatError, match="pickle"):
        fr.load(tmp_path / "obj.npy", topology=mesh)
    np.savez(tmp_path / "obj.npz", vertices=np.array([object()], dtype=object))
    with pytest.raises(FileFormatError, match="pickle"):
        fr.load(tmp_path / "obj.npz")


def test_huge_declared_cache_is_refused_before_mapping(tmp_path, mesh, monkeypatch):
    monkeypatch.setenv("FACERETARGET_MEMORY_BUDGET", "1M")
    path = tmp_path / "huge.pc2"
    path.write_bytes(_pc2(100000, 1000, payload_frames=0))
    with pytest.raises(ResourceLimitError, match="huge.pc2"):
        fr.load(path, topology=mesh)
