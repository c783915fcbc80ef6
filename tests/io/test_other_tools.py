"""Files written by other tools (Blender 3.4.1's exporters, ezc3d 1.7.2, Gmsh 4.8.4) read to what those
tools say they hold. How the files were made: tests/io/data/other_tools/README.md."""

import json
import warnings
from pathlib import Path

import numpy as np
import pytest

from faceretarget import io

DATA = Path(__file__).parent / "data" / "other_tools"
FRAMES = range(1, 9)


def truth(name: str) -> dict:
    return json.loads((DATA / f"{name}.truth.json").read_text())


def world(t: dict, up: str = "y") -> np.ndarray:
    """(8, V, 3) Blender's evaluated world vertices per frame, in Y-up or Z-up coordinates."""
    return np.array([t[f"world_{up}_up"][str(f)] for f in FRAMES])


def matching(ours: np.ndarray, theirs: np.ndarray) -> np.ndarray:
    """Index into ``theirs`` of each of ``ours`` rows (exporters may split or reorder vertices)."""
    d = np.linalg.norm(ours[:, None] - theirs[None], axis=2)
    assert d.min(axis=1).max() < 1e-6, "a vertex with no counterpart in Blender's mesh"
    return d.argmin(axis=1)


FACE = truth("blender_face")


def test_blender_obj_is_frame_one_in_y_up():
    mesh = io.load(DATA / "blender_face.obj")
    np.testing.assert_allclose(mesh.vertices, world(FACE)[0], atol=1e-6)
    assert len(mesh.triangles) == len(FACE["triangles"])


def test_blender_ply_holds_the_same_points_and_faces():
    mesh = io.load(DATA / "blender_face.ply")
    assert (
        sorted(np.bincount(matching(np.asarray(mesh.vertices), world(FACE)[0])))
        == [1] * FACE["n_vertices"]
    )
    assert len(mesh.triangles) == len(FACE["triangles"])


def test_blender_pc2_frames_are_the_evaluated_world_vertices():
    seq = io.load(DATA / "blender_face.pc2", topology=DATA / "blender_face.obj")
    np.testing.assert_allclose(seq.vertices, world(FACE), atol=1e-6)


def test_blender_mdd_frames_and_rate():
    seq = io.load(DATA / "blender_face.mdd", topology=DATA / "blender_face.obj")
    np.testing.assert_allclose(
        seq.vertices, world(FACE, "z"), atol=1e-6
    )  # the MDD add-on keeps Blender's Z up
    assert seq.fps == pytest.approx(FACE["fps"])


def test_blender_glb_rig_and_weight_animation_in_scene_space():
    """The object is moved, rotated and scaled: the rig and every animated frame are in
    scene space, as Blender shows them, whether read as a rig or as an animation."""
    rig = io.load(DATA / "blender_face.glb", kind="rig")
    assert list(rig.names) == FACE["shape_names"]
    order = matching(np.asarray(rig.neutral.vertices), world(FACE)[0])
    anim = io.load(DATA / "blender_face.glb")
    assert anim.fps == FACE["fps"] and anim.head_motion is None
    np.testing.assert_allclose(anim.weights, FACE["weights"], atol=1e-6)
    np.testing.assert_allclose(anim.vertices, world(FACE)[:, order], atol=1e-6)
    seq = io.load(DATA / "blender_face.glb", kind="mesh_sequence")
    np.testing.assert_allclose(seq.vertices, world(FACE)[:, order], atol=1e-6)


def test_blender_glb_head_motion_under_a_parent_and_two_animations():
    """Blender writes the object's motion and its shape-key weights as two glTF animations
    that play together; the object has a scale and a moved, rotated parent."""
    head = truth("blender_head")
    anim = io.load(DATA / "blender_head.glb")
    assert anim.head_motion is not None and anim.fps == head["fps"]
    np.testing.assert_allclose(anim.weights, head["weights"], atol=1e-6)
    theirs = world(head)
    order = matching(np.asarray(anim.vertices)[0], theirs[0])
    np.testing.assert_allclose(anim.vertices, theirs[:, order], atol=1e-6)


def test_gmsh_msh41_plate_reads_as_its_triangles():
    with warnings.catch_warnings():
        warnings.simplefilter(
            "ignore"
        )  # the boundary's line and point elements are skipped, with a warning
        mesh = io.load(DATA / "gmsh_plate.msh")
    v, t = np.asarray(mesh.vertices), np.asarray(mesh.triangles)
    area = (
        0.5
        * np.linalg.norm(np.cross(v[t[:, 1]] - v[t[:, 0]], v[t[:, 2]] - v[t[:, 0]]), axis=1).sum()
    )
    assert area == pytest.approx(2.0) and np.all(v[:, 2] == 0.0) and len(t) > 20


def test_ezc3d_markers_names_rate_and_occlusions():
    t = json.loads((DATA / "ezc3d_face.truth.json").read_text())
    expected = np.array(
        [[[np.nan if c is None else c for c in m] for m in f] for f in t["points"]], dtype=float
    )
    markers = io.load(DATA / "ezc3d_face.c3d")
    assert list(markers.names) == t["labels"] and markers.fps == t["rate"]
    np.testing.assert_array_equal(
        np.isnan(markers.positions), np.isnan(expected)
    )  # residual < 0: missing
    np.testing.assert_allclose(markers.positions, expected, atol=1e-4, equal_nan=True)
