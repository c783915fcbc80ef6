"""Files that travel: names from the final path, C3D read the way ezc3d reads it,
Live Link Face round trips, glTF scenes and compact vertex animations."""

from __future__ import annotations

import io
import struct
import warnings

import numpy as np
import pytest
from naive.io import split_glb

import faceretarget as fr
from faceretarget.errors import FaceRetargetWarning, FileFormatError


# ---------------------------------------------------------------------------------------
# a. output names come from the final destination, never the temporary
# ---------------------------------------------------------------------------------------
def _names(doc) -> list[str]:
    return [
        x.get("name", "") for key in ("nodes", "meshes", "animations") for x in doc.get(key, [])
    ]


@pytest.mark.parametrize("obj", ["animation", "seq", "rig", "mesh"])
def test_gltf_names_come_from_the_final_path_not_the_temporary(tmp_path, obj, request):
    """The demo and batch write through a temporary (``.NAME.PID.TOKEN.frtmp.glb``): no
    node, mesh or animation may carry that name (Blender objects, three.js tracks)."""
    from faceretarget.evaluation.batch import write_animation
    from faceretarget.io.gltf import write_gltf

    value = request.getfixturevalue(obj)
    out = tmp_path / "ict-spacetime.glb"
    write_animation(value, out, write_gltf)
    doc, _ = split_glb(out.read_bytes())
    names = _names(doc)
    assert names and not any("frtmp" in n or "frbatch" in n or n.startswith(".") for n in names), (
        names
    )
    if obj in ("animation", "seq"):  # the character/root node is named after the shot file
        root = doc["nodes"][doc["scenes"][0]["nodes"][0]]
        assert root["name"] == "ict-spacetime"


def test_gltf_names_from_a_legacy_batch_temporary(tmp_path, animation):
    from faceretarget.io.gltf import write_gltf

    write_gltf(animation, tmp_path / ".ict-spacetime.glb.frbatch-13430-89abcdef.glb")
    doc, _ = split_glb((tmp_path / ".ict-spacetime.glb.frbatch-13430-89abcdef.glb").read_bytes())
    assert (
        doc["nodes"][0]["name"] == "ict-spacetime" and doc["meshes"][0]["name"] == "ict-spacetime"
    )


def test_trc_header_names_the_final_file(tmp_path, markers):
    from faceretarget.io._atomic import atomic_path
    from faceretarget.io.markers import write_trc

    with atomic_path(tmp_path / "shot.trc") as tmp:
        assert tmp.name != "shot.trc"
        write_trc(markers, tmp)
    assert (tmp_path / "shot.trc").read_text().splitlines()[
        0
    ] == "PathFileType\t4\t(X/Y/Z)\tshot.trc"


# ---------------------------------------------------------------------------------------
# b. C3D: POINT:FRAMES and the data actually present, not the header's last frame
# ---------------------------------------------------------------------------------------
def _c3d_bytes(n_frames: int = 29, rate: float = 100.0) -> bytes:
    import c3d

    writer = c3d.Writer(point_rate=rate, point_scale=-1.0)
    writer.set_point_labels(["A", "B"])
    frames = []
    for f in range(n_frames):
        pts = np.zeros((2, 5), np.float32)
        pts[:, :3] = [[f, 1, 2], [3, 4, f]]
        frames.append((pts, np.zeros((0, 0), np.float32)))
    writer.add_frames(frames)
    buf = io.BytesIO()
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        writer.write(buf)
    return buf.getvalue()


@pytest.mark.parametrize("header_last", [40, 10, 65535])
def test_c3d_header_last_frame_disagreeing_with_point_frames(tmp_path, header_last):
    """An Optotrak-style file: the header's last-frame word disagrees with POINT:FRAMES
    (29, all present); the 29 frames are read, with a warning naming both."""
    data = bytearray(_c3d_bytes(29))
    assert struct.unpack_from("<H", data, 8)[0] == 29  # header word 5: last frame
    data[8:10] = struct.pack("<H", header_last)
    path = tmp_path / "optotrak.c3d"
    path.write_bytes(bytes(data))
    with pytest.warns(FaceRetargetWarning, match="POINT:FRAMES"):
        m = fr.load(path)
    assert m.n_frames == 29 and m.fps == 100.0
    np.testing.assert_array_equal(m.positions[:, 0, 0], np.arange(29))
    np.testing.assert_array_equal(m.positions[28, 1], [3, 4, 28])


def test_c3d_agreeing_header_reads_without_warning(tmp_path):
    (tmp_path / "ok.c3d").write_bytes(_c3d_bytes(5))
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        assert fr.load(tmp_path / "ok.c3d").n_frames == 5


def test_c3d_shorter_than_declared_reads_what_is_there(tmp_path):
    data = _c3d_bytes(29)
    per_frame = 2 * 4 * 4
    path = tmp_path / "cut.c3d"
    path.write_bytes(data[: _data_start(data) + 20 * per_frame])
    with pytest.warns(FaceRetargetWarning, match="holds 20 complete"):
        m = fr.load(path)
    assert m.n_frames == 20
    np.testing.assert_array_equal(m.positions[:, 0, 0], np.arange(20))


def _data_start(data: bytes) -> int:
    return (struct.unpack_from("<H", data, 16)[0] - 1) * 512  # header word 9: first data block


@pytest.mark.parametrize(
    "content",
    [b"hello, this is not a C3D file\n" * 40, b'{"asset": {}}' + b" " * 600, bytes(range(256)) * 3],
    ids=["text", "json", "binary"],
)
def test_a_non_c3d_file_named_c3d_is_a_typed_error_saying_so(tmp_path, content):
    path = tmp_path / "shot.c3d"
    path.write_bytes(content)
    with pytest.raises(FileFormatError) as info:
        fr.load(path)
    text = str(info.value)
    assert "not a C3D file" in text and str(path) in text and "AssertionError" not in text


# ---------------------------------------------------------------------------------------
# c. Live Link Face: timecode, rate and the head/eye rotation columns round trip exactly
# ---------------------------------------------------------------------------------------
def _live_link_take(n: int = 90, fps: float = 59.96) -> str:
    from faceretarget.io.weights import timecode
    from faceretarget.naming import LIVE_LINK_NAMES

    rng = np.random.default_rng(7)
    start = (32 * 60 + 9) * 60 + 7.867  # 00:32:09:07.867 in frames of the nominal 60
    lines = ["Timecode,BlendShapeCount," + ",".join(LIVE_LINK_NAMES)]
    for k in range(n):
        shapes = [repr(float(v)) for v in np.round(rng.random(52), 8)]
        rot = [repr(float(v)) for v in np.round(rng.normal(0, 0.2, 9), 8)]
        lines.append(f"{timecode(start + k * 60 / fps, 60)},61," + ",".join(shapes + rot))
    return "\n".join(lines) + "\n"


def test_live_link_face_round_trip_keeps_timecode_rate_and_rotations(tmp_path):
    from faceretarget.naming import LIVE_LINK_NAMES

    text = _live_link_take()
    assert text.splitlines()[1].startswith("00:32:09:07.867,61,")
    (tmp_path / "take.csv").write_text(text)
    w = fr.load(tmp_path / "take.csv")
    assert w.names == LIVE_LINK_NAMES[:52], "rotation columns are not blendshape weights"
    assert w.fps == pytest.approx(59.96, abs=1e-3)
    channels = w.extras["channels"]
    assert tuple(channels) == LIVE_LINK_NAMES[52:]
    # head rotation is head_motion: rigid, and yaw turns about +Y
    head = w.head_motion
    assert head.shape == (90, 4, 4)
    np.testing.assert_allclose(
        head[:, :3, :3] @ head[:, :3, :3].transpose(0, 2, 1),
        np.broadcast_to(np.eye(3), (90, 3, 3)),
        atol=1e-12,
    )
    from faceretarget.io.weights import _rotation

    only_yaw = _rotation(np.array([0.3]), np.zeros(1), np.zeros(1))[0]
    np.testing.assert_allclose(only_yaw[:3, 1], [0, 1, 0], atol=1e-15)
    fr.save(w, tmp_path / "out.csv")
    assert (tmp_path / "out.csv").read_text() == text  # byte for byte: timecodes, columns, values
    again = fr.load(tmp_path / "out.csv")
    assert again.fps == w.fps and again.names == w.names
    np.testing.assert_array_equal(again.head_motion, w.head_motion)


def test_live_link_head_motion_written_from_a_changed_head(tmp_path):
    """A head_motion set after reading (or on a new sequence) is what is written."""
    from faceretarget.io.weights import _rotation
    from faceretarget.model import WeightSequence

    (tmp_path / "take.csv").write_text(_live_link_take(90))
    w = fr.load(tmp_path / "take.csv")
    ypr = np.array([[0.1, -0.2, 0.05]] * 90)
    fresh = WeightSequence(w.weights, w.names, fps=w.fps)
    fresh.head_motion = _rotation(*ypr.T)
    fr.save(fresh, tmp_path / "fresh.csv")
    back = fr.load(tmp_path / "fresh.csv")
    np.testing.assert_allclose(back.head_motion, fresh.head_motion, atol=1e-12)
    assert back.fps == pytest.approx(59.96, abs=1e-3)  # generated timecodes keep a non-integer rate
    np.testing.assert_array_equal(back.extras["channels"]["LeftEyeYaw"], np.zeros(90))


@pytest.mark.parametrize("fps", [59.96, 29.97, 24.0])
def test_generated_timecodes_keep_the_rate(tmp_path, weights, fps):
    from faceretarget.model import WeightSequence

    seq = WeightSequence(weights.weights[:40], weights.names, fps=fps)
    fr.save(seq, tmp_path / "w.csv")
    back = fr.load(tmp_path / "w.csv")
    assert back.fps == pytest.approx(fps, abs=2e-3)
    np.testing.assert_array_equal(back.weights, seq.weights)


# ---------------------------------------------------------------------------------------
# d. glTF scenes: node transforms, several meshes, a rig from an animated file
# ---------------------------------------------------------------------------------------
def _tri_glb(path, nodes, scene_roots, n_meshes=1, targets=False):
    """A GLB made with pygltflib (not our writer): ``n_meshes`` copies of one triangle
    (mesh k shifted by k along z), shown by ``nodes``."""
    import pygltflib as g

    base = np.array([[0, 0, 0], [1, 0, 0], [0, 1, 0]], np.float32)
    idx = np.array([0, 1, 2], np.uint32)
    delta = np.array([[0, 0, 1], [0, 0, 0], [0, 0, 0]], np.float32)
    blob, views, accs, meshes = b"", [], [], []

    def add(arr, atype, ctype):
        nonlocal blob
        views.append(g.BufferView(buffer=0, byteOffset=len(blob), byteLength=arr.nbytes))
        extra = {"min": arr.min(0).tolist(), "max": arr.max(0).tolist()} if atype == "VEC3" else {}
        accs.append(
            g.Accessor(
                bufferView=len(views) - 1,
                componentType=ctype,
                count=len(arr) if arr.ndim > 1 else arr.size,
                type=atype,
                **extra,
            )
        )
        blob += arr.tobytes()
        return len(accs) - 1

    ind = add(idx, "SCALAR", g.UNSIGNED_INT)
    for k in range(n_meshes):
        pos = add(
            (base + np.float32(k) * np.float32([0, 0, 1])).astype(np.float32), "VEC3", g.FLOAT
        )
        prim = g.Primitive(attributes=g.Attributes(POSITION=pos), indices=ind)
        extras = {}
        if targets:
            prim.targets = [{"POSITION": add(delta, "VEC3", g.FLOAT)}]
            extras = {"targetNames": ["lift"]}
        meshes.append(g.Mesh(name=f"mesh{k}", primitives=[prim], extras=extras))
    doc = g.GLTF2(
        scene=0,
        scenes=[g.Scene(nodes=scene_roots)],
        nodes=[g.Node(**n) for n in nodes],
        meshes=meshes,
        accessors=accs,
        bufferViews=views,
        buffers=[g.Buffer(byteLength=len(blob))],
    )
    doc.set_binary_blob(blob)
    doc.save_binary(str(path))
    return base


def _quat_z(angle):
    return [0.0, 0.0, float(np.sin(angle / 2)), float(np.cos(angle / 2))]


def test_gltf_node_transforms_are_applied(tmp_path):
    """translation, rotation (90 deg about z) and scale of the node, and of its parent."""
    nodes = [
        {"name": "root", "translation": [100.0, 0.0, 0.0], "children": [1]},
        {
            "name": "duck",
            "mesh": 0,
            "translation": [0.0, 62.0, 0.0],
            "rotation": _quat_z(np.pi / 2),
            "scale": [2.0, 2.0, 2.0],
        },
    ]
    base = _tri_glb(tmp_path / "duck.glb", nodes, [0])
    m = fr.load(tmp_path / "duck.glb", kind="mesh")
    rot = np.array([[0, -1, 0], [1, 0, 0], [0, 0, 1]])
    expected = (2.0 * base.astype(float)) @ rot.T + [100.0, 62.0, 0.0]
    np.testing.assert_allclose(m.vertices, expected, atol=1e-6)


def test_gltf_node_matrix_is_applied(tmp_path):
    mat = np.eye(4)
    mat[:3, 3] = [0, 0, -162.0]
    _tri_glb(tmp_path / "m.glb", [{"mesh": 0, "matrix": mat.T.ravel().tolist()}], [0])
    np.testing.assert_allclose(
        fr.load(tmp_path / "m.glb", kind="mesh").vertices[:, 2], [-162.0] * 3
    )


def test_gltf_several_meshes_merge_or_select(tmp_path):
    nodes = [
        {"name": "face", "mesh": 0},
        {"name": "eyes", "mesh": 1, "translation": [5.0, 0.0, 0.0]},
    ]
    _tri_glb(tmp_path / "s.glb", nodes, [0, 1], n_meshes=2)
    merged = fr.load(tmp_path / "s.glb", kind="mesh")
    assert merged.n_vertices == 6 and merged.triangles.tolist() == [[0, 1, 2], [3, 4, 5]]
    np.testing.assert_allclose(merged.vertices[3:], [[5, 0, 1], [6, 0, 1], [5, 1, 1]])
    by_node = fr.load(tmp_path / "s.glb", kind="mesh", mesh="eyes")
    np.testing.assert_allclose(by_node.vertices, merged.vertices[3:])
    by_mesh = fr.load(tmp_path / "s.glb", kind="mesh", mesh="mesh0")
    np.testing.assert_allclose(by_mesh.vertices, merged.vertices[:3])
    assert fr.load(tmp_path / "s.glb", kind="mesh", merge=False).n_vertices == 3
    with pytest.raises(FileFormatError, match="has no mesh 'nose'"):
        fr.load(tmp_path / "s.glb", kind="mesh", mesh="nose")


def test_gltf_rig_in_scene_space_deltas_rotated(tmp_path):
    nodes = [
        {
            "name": "head",
            "mesh": 0,
            "translation": [0.0, 10.0, 0.0],
            "rotation": [float(np.sin(np.pi / 4)), 0.0, 0.0, float(np.cos(np.pi / 4))],
        }
    ]
    _tri_glb(tmp_path / "r.glb", nodes, [0], targets=True)
    rig = fr.load(tmp_path / "r.glb", kind="rig")
    np.testing.assert_allclose(
        rig.deltas[0, 0], [0, -1, 0], atol=1e-12
    )  # +z rotated 90 deg about x
    np.testing.assert_allclose(rig.neutral.vertices[2], [0, 10, 1], atol=1e-12)


def test_rig_from_a_file_that_also_holds_an_animation(tmp_path, animation):
    """A character glTF that also holds an animation is a target through kind='rig'."""
    fr.save(animation, tmp_path / "hero.glb")
    assert isinstance(fr.load(tmp_path / "hero.glb"), type(animation))
    rig = fr.load(tmp_path / "hero.glb", kind="rig")
    assert rig.names == animation.rig.names
    np.testing.assert_allclose(rig.deltas, animation.rig.deltas, atol=1e-7)
    target = fr.io.load_target(tmp_path / "hero.glb", kind="rig")
    assert target.blendshapes.names == animation.rig.names
