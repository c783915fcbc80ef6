"""glTF/GLB: written structure (what Blender and three.js need), round trips, foreign files, errors."""

from __future__ import annotations

import base64
import json
import struct

import numpy as np
import pytest
from naive.io import GLB, read_accessor, split_glb, validate_gltf

import faceretarget as fr
from faceretarget.errors import FileFormatError
from faceretarget.model import Animation, BlendshapeRig, MeshSequence


def _written(obj, path):
    fr.save(obj, path)
    return split_glb(path.read_bytes())


def test_rig_glb_structure_and_round_trip(tmp_path, rig):
    doc, blob = _written(rig, tmp_path / "rig.glb")
    checked = validate_gltf(doc, blob)
    assert checked["targets"] == rig.n_shapes
    assert doc["meshes"][0]["extras"]["targetNames"] == list(rig.names)
    once = fr.load(tmp_path / "rig.glb")
    assert isinstance(once, BlendshapeRig) and once.names == rig.names
    np.testing.assert_allclose(once.deltas, rig.deltas, atol=1e-7)
    np.testing.assert_array_equal(once.bounds, rig.bounds)
    fr.save(once, tmp_path / "again.glb")
    twice = fr.load(tmp_path / "again.glb")
    np.testing.assert_array_equal(twice.deltas, once.deltas)
    np.testing.assert_array_equal(twice.neutral.vertices, once.neutral.vertices)


def test_blendshape_animation_glb(tmp_path, animation):
    doc, blob = _written(animation, tmp_path / "anim.glb")
    checked = validate_gltf(doc, blob)
    assert checked["samplers"] == 3  # weights, translation, rotation
    info = doc["asset"]["extras"]["faceretarget"]
    assert info["provenance"]["method"] == "test" and info["fps"] == 30.0
    channel_paths = {c["target"]["path"] for c in doc["animations"][0]["channels"]}
    assert channel_paths == {"weights", "translation", "rotation"}
    # the standard channels alone (what a viewer plays) reproduce the motion
    anim = doc["animations"][0]
    sampler = {c["target"]["path"]: anim["samplers"][c["sampler"]] for c in anim["channels"]}
    w = read_accessor(doc, blob, sampler["weights"]["output"]).reshape(animation.n_frames, -1)
    np.testing.assert_allclose(w, animation.weights, atol=1e-7)
    t = read_accessor(doc, blob, sampler["translation"]["output"])
    np.testing.assert_allclose(t, animation.head_motion[:, :3, 3], atol=1e-6)
    back = fr.load(tmp_path / "anim.glb")
    assert isinstance(back, Animation) and back.is_blendshape_based
    np.testing.assert_array_equal(back.weights, animation.weights)  # exact copy in extras
    np.testing.assert_array_equal(back.head_motion, animation.head_motion)
    assert back.provenance == {"method": "test", "parameters": {"alpha": 0.5}, "timings": [1.5, 2]}
    np.testing.assert_allclose(back.vertices, animation.vertices, atol=1e-5)


def test_ict_result_loads_back_with_names_and_animation(tmp_path):
    """The ICT-FaceKit case's ground truth (a blendshape result) through a GLB and back."""
    from faceretarget import cases

    truth = cases.ict(n_frames=4).truth
    fr.save(truth, tmp_path / "ict.glb")
    doc, blob = split_glb((tmp_path / "ict.glb").read_bytes())
    validate_gltf(doc, blob)
    back = fr.load(tmp_path / "ict.glb")
    assert back.rig.names == truth.rig.names and back.weight_names == truth.weight_names
    np.testing.assert_array_equal(back.weights, truth.weights)
    assert back.n_frames == 4 and back.fps == truth.fps
    np.testing.assert_allclose(back.vertices, truth.vertices, atol=1e-4)  # cm, float32 geometry


def test_vertex_animation_is_one_node_per_frame(tmp_path, seq):
    anim = Animation(
        vertices=seq.vertices, triangles=seq.triangles, fps=seq.fps, provenance={"method": "m"}
    )
    doc, blob = _written(anim, tmp_path / "frames.glb")
    validate_gltf(doc, blob)
    n = seq.n_frames
    assert len(doc["meshes"]) == n and len(doc["nodes"]) == n + 1
    # node k is shown (scale 1) exactly during frame k: sample every STEP channel
    chans = doc["animations"][0]["channels"]
    samplers = doc["animations"][0]["samplers"]
    for frame in range(n):
        time = frame / seq.fps
        visible = []
        for c in chans:
            s = samplers[c["sampler"]]
            keys = read_accessor(doc, blob, s["input"]).ravel()
            vals = read_accessor(doc, blob, s["output"])
            k = np.searchsorted(keys, np.float32(time), side="right") - 1
            if vals[k][0] == 1.0:
                visible.append(c["target"]["node"])
        assert visible == [frame]
    back = fr.load(tmp_path / "frames.glb", kind="mesh_sequence")
    np.testing.assert_allclose(back.vertices, seq.vertices, atol=1e-6)
    again = tmp_path / "again.glb"
    fr.save(back, again)
    np.testing.assert_array_equal(fr.load(again, kind="mesh_sequence").vertices, back.vertices)


def test_third_party_readers_open_our_files(tmp_path, animation, seq):
    import pygltflib
    import trimesh

    fr.save(animation, tmp_path / "anim.glb")
    g = pygltflib.GLTF2().load(str(tmp_path / "anim.glb"))
    assert len(g.meshes[0].primitives[0].targets) == animation.rig.n_shapes
    assert g.meshes[0].extras["targetNames"] == list(animation.rig.names)
    assert len(g.animations[0].channels) == 3
    scene = trimesh.load(tmp_path / "anim.glb", process=False)
    (geom,) = scene.geometry.values()
    np.testing.assert_allclose(geom.vertices, animation.rig.neutral.vertices, atol=1e-6)
    fr.save(
        Animation(vertices=seq.vertices, triangles=seq.triangles, fps=seq.fps),
        tmp_path / "frames.gltf",
    )
    assert len(trimesh.load(tmp_path / "frames.gltf", process=False).geometry) == seq.n_frames


def _foreign_rig(n_keys_uneven: bool = False, interpolation: str = "LINEAR") -> bytes:
    """Two primitives, interleaved positions + normals, uint16 indices, a triangle strip,
    a sparse morph target, normalized-ubyte weights keyed at uneven times."""
    b = GLB()
    quad = np.array([[0, 0, 0], [1, 0, 0], [1, 1, 0], [0, 1, 0]], "<f4")
    normals = np.tile(np.array([0, 0, 1], "<f4"), (4, 1))
    inter = np.hstack([quad, normals]).astype("<f4")
    view = b.view(inter.tobytes(), stride=24)
    pos0 = b.accessor(view, 5126, 4, "VEC3", min=[0, 0, 0], max=[1, 1, 0])
    nrm0 = b.accessor(view, 5126, 4, "VEC3", offset=12)
    idx0 = b.array(np.array([0, 1, 2, 0, 2, 3], "<u2"), 5123, "SCALAR")
    pos1 = b.array(quad + [2, 0, 0], 5126, "VEC3", min=[2, 0, 0], max=[3, 1, 0])
    strip = b.array(np.array([0, 1, 3, 2], "<u4"), 5125, "SCALAR")
    d0 = b.array(np.full((4, 3), 0.5, "<f4"), 5126, "VEC3")
    d1 = b.array(np.zeros((4, 3), "<f4"), 5126, "VEC3")
    sparse_idx = b.view(np.array([2], "<u1").tobytes())
    sparse_val = b.view(np.array([[0, 0, 1]], "<f4").tobytes())
    sparse = b.accessor(sparse_val, 5126, 4, "VEC3")  # values view reused as a dummy dense base
    b.doc["accessors"][sparse] = {
        "componentType": 5126,
        "count": 4,
        "type": "VEC3",
        "sparse": {
            "count": 1,
            "indices": {"bufferView": sparse_idx, "componentType": 5121},
            "values": {"bufferView": sparse_val},
        },
    }
    b.doc["meshes"].append(
        {
            "name": "face",
            "primitives": [
                {
                    "attributes": {"POSITION": pos0, "NORMAL": nrm0},
                    "indices": idx0,
                    "targets": [{"POSITION": d0}, {"POSITION": d1}],
                },
                {
                    "attributes": {"POSITION": pos1},
                    "indices": strip,
                    "mode": 5,
                    "targets": [{"POSITION": d1}, {"POSITION": sparse}],
                },
            ],
            "extras": {"targetNames": ["jawOpen", "smile"]},
        }
    )
    b.doc["nodes"].append({"mesh": 0})
    b.doc["scenes"] = [{"nodes": [0]}]
    times = np.array([0, 0.1, 0.3] if n_keys_uneven else [0, 0.1, 0.2], "<f4")
    per_key = 3 if interpolation == "CUBICSPLINE" else 1
    w = np.array([[0, 255], [128, 0], [255, 255]], "u1")
    if per_key == 3:
        w = np.stack([np.zeros_like(w), w, np.zeros_like(w)], axis=1).reshape(-1, 2)
    t_acc = b.array(times, 5126, "SCALAR", min=[float(times[0])], max=[float(times[-1])])
    w_acc = b.array(w.ravel(), 5121, "SCALAR", normalized=True)
    b.doc["animations"] = [
        {
            "samplers": [{"input": t_acc, "output": w_acc, "interpolation": interpolation}],
            "channels": [{"sampler": 0, "target": {"node": 0, "path": "weights"}}],
        }
    ]
    return b.bytes()


def test_foreign_glb_features(tmp_path):
    path = tmp_path / "foreign.glb"
    path.write_bytes(_foreign_rig())
    rig = fr.load(path, kind="rig")
    assert rig.names == ("jawOpen", "smile") and rig.neutral.n_vertices == 8
    np.testing.assert_array_equal(
        rig.neutral.triangles, [[0, 1, 2], [0, 2, 3], [4, 5, 7], [5, 6, 7]]
    )
    np.testing.assert_array_equal(rig.deltas[0, :4], np.full((4, 3), 0.5))
    np.testing.assert_array_equal(rig.deltas[1, 6], [0, 0, 1])  # sparse target on the 2nd primitive
    assert np.count_nonzero(rig.deltas[1]) == 1
    anim = fr.load(path)
    assert anim.fps == pytest.approx(10.0)
    np.testing.assert_allclose(anim.weights, [[0, 1], [128 / 255, 0], [1, 1]])


@pytest.mark.parametrize("interpolation", ["LINEAR", "STEP", "CUBICSPLINE"])
def test_uneven_keys_are_resampled(tmp_path, interpolation):
    path = tmp_path / "uneven.glb"
    path.write_bytes(_foreign_rig(n_keys_uneven=True, interpolation=interpolation))
    anim = fr.load(path, kind="animation", fps=10)
    assert anim.n_frames == 4  # t = 0, 0.1, 0.2, 0.3
    expected_mid = [128 / 255, 0] if interpolation == "STEP" else [(128 / 255 + 1) / 2, 0.5]
    np.testing.assert_allclose(anim.weights[2], expected_mid)


def _patched(path, tmp_path, edit):
    doc, blob = split_glb(path.read_bytes())
    edit(doc)
    raw = json.dumps(doc).encode()
    raw += b" " * ((-len(raw)) % 4)
    out = tmp_path / "patched.glb"
    total = 12 + 8 + len(raw) + 8 + len(blob)
    out.write_bytes(
        struct.pack("<4sII", b"glTF", 2, total)
        + struct.pack("<II", len(raw), 0x4E4F534A)
        + raw
        + struct.pack("<II", len(blob), 0x004E4942)
        + blob
    )
    return out


@pytest.mark.parametrize(
    "edit,needle",
    [
        (lambda d: d["meshes"][0]["extras"].update(targetNames=["a"]), "targetNames lists 1 names"),
        (lambda d: d["accessors"][1].update(count=10**6), "need"),
        (lambda d: d["bufferViews"][0].update(byteOffset=10**9), "outside buffer"),
        (lambda d: d["accessors"][0].update(componentType=1234), "componentType"),
        (lambda d: d["meshes"][0]["primitives"][0].update(indices=99), "accessors\\[99\\]"),
        (lambda d: d["meshes"][0]["primitives"][0].update(mode=1), "not a surface"),
        (lambda d: d["asset"].update(version="1.0"), "glTF 2"),
    ],
)
def test_malformed_glb_names_what_is_wrong(tmp_path, rig, edit, needle):
    fr.save(rig, tmp_path / "rig.glb")
    bad = _patched(tmp_path / "rig.glb", tmp_path, edit)
    with pytest.raises(FileFormatError, match=needle):
        fr.load(bad, kind="rig")


def test_key_times_must_increase(tmp_path, animation):
    fr.save(animation, tmp_path / "anim.glb")
    doc, blob = split_glb((tmp_path / "anim.glb").read_bytes())
    acc = doc["accessors"][doc["animations"][0]["samplers"][0]["input"]]
    view = doc["bufferViews"][acc["bufferView"]]
    blob = bytearray(blob)
    struct.pack_into("<f", blob, view["byteOffset"] + 4, 99.0)  # key 1 after key 2
    del doc["asset"]["extras"]["faceretarget"]["arrays"]
    raw = json.dumps(doc).encode()
    raw += b" " * ((-len(raw)) % 4)
    total = 12 + 8 + len(raw) + 8 + len(blob)
    path = tmp_path / "bad.glb"
    path.write_bytes(
        struct.pack("<4sII", b"glTF", 2, total)
        + struct.pack("<II", len(raw), 0x4E4F534A)
        + raw
        + struct.pack("<II", len(blob), 0x004E4942)
        + bytes(blob)
    )
    with pytest.raises(FileFormatError, match="strictly increasing"):
        fr.load(path)


def test_gltf_external_buffers_stay_beside_the_file(tmp_path, mesh):
    fr.save(mesh, tmp_path / "m.gltf")
    doc = json.loads((tmp_path / "m.gltf").read_text())
    blob = base64.b64decode(doc["buffers"][0]["uri"].split(",", 1)[1])
    (tmp_path / "m.bin").write_bytes(blob)
    doc["buffers"][0]["uri"] = "m.bin"
    (tmp_path / "ext.gltf").write_text(json.dumps(doc))
    np.testing.assert_allclose(fr.load(tmp_path / "ext.gltf").vertices, mesh.vertices, atol=1e-6)
    doc["buffers"][0]["uri"] = "../../etc/passwd"
    (tmp_path / "escape.gltf").write_text(json.dumps(doc))
    with pytest.raises(FileFormatError, match="outside"):
        fr.load(tmp_path / "escape.gltf")


def test_sequence_saved_as_glb_is_an_animation(tmp_path, seq):
    fr.save(seq, tmp_path / "s.glb")
    back = fr.load(tmp_path / "s.glb")
    assert isinstance(back, Animation) and not back.is_blendshape_based
    assert isinstance(fr.load(tmp_path / "s.glb", kind="mesh_sequence"), MeshSequence)


def test_uneven_keys_without_fps_resample_at_the_default_rate(tmp_path):
    path = tmp_path / "uneven.glb"
    path.write_bytes(_foreign_rig(n_keys_uneven=True))
    anim = fr.load(path)
    assert anim.fps == 30.0 and anim.n_frames == 10  # 0 .. 0.3 s at 30 fps
    np.testing.assert_allclose(anim.weights[-1], [1, 1])


def test_empty_arrays_in_extras_round_trip_without_an_empty_buffer_view(tmp_path):
    """A spacetime animation with no fixed frames stores known_frames of shape (0,): glTF
    buffer views must hold at least one byte, so the empty array is stored by its shape."""
    import faceretarget as fr

    rig = fr.BlendshapeRig(fr.Mesh(np.eye(3), [[0, 1, 2]]), np.ones((1, 3, 3)), ["a"])
    anim = fr.Animation(
        weights=np.zeros((2, 1)), rig=rig, fps=30.0, extras={"empty": np.zeros(0, dtype=np.int64)}
    )
    path = tmp_path / "a.glb"
    fr.save(anim, path)
    back = fr.load(path)
    assert back.extras["empty"].shape == (0,)
