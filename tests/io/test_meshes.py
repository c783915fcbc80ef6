"""Static meshes: OBJ, PLY, OFF, STL (and glTF/npz as meshes): vertex order, round trips, errors."""

from __future__ import annotations

import struct

import numpy as np
import pytest

import faceretarget as fr
from faceretarget.errors import FileFormatError, ResourceLimitError
from faceretarget.io.meshes import fan_triangulate
from faceretarget.model import Mesh

OBJ_WITH_SEAMS = """# a quad and a triangle, UVs split along a seam (vertex 2 has two UVs)
mtllib x.mtl
o patch
v 0 0 0
v 1 0 0
v 1 1 0
v 0 1 0
v 2 1 0 1.0
vt 0 0
vt 1 0
vt 1 1
vt 0 1
vt 0.5 0.5
vn 0 0 1
g faces
usemtl skin
s 1
f 1/1/1 2/2/1 3/3/1 4/4/1
f 2/2 5/5 -3/5
"""


def test_obj_keeps_vertex_order_across_uv_seams_and_fans_quads(tmp_path):
    path = tmp_path / "seam.obj"
    path.write_text(OBJ_WITH_SEAMS)
    mesh = fr.load(path)
    assert mesh.n_vertices == 5  # no vertex split although vertex 3 carries two UVs
    np.testing.assert_array_equal(mesh.vertices[4], [2, 1, 0])
    np.testing.assert_array_equal(mesh.triangles, [[0, 1, 2], [0, 2, 3], [1, 4, 2]])


def test_obj_line_by_line_path_agrees_with_vectorized(tmp_path):
    """A statement the fast parser sends to the line parser (a vertex with a trailing comment)."""
    fast = tmp_path / "fast.obj"
    slow = tmp_path / "slow.obj"
    fast.write_text("v 0 0 0\nv 1 0 0\nv 0 1 0\nv 1 1 0\nf 1 2 4 3\n")
    slow.write_text("v 0 0 0 # origin\nv 1 0 0\nv 0 1 0\nv 1 1 0\nf 1 2 4 3\n")
    a, b = fr.load(fast), fr.load(slow)
    np.testing.assert_array_equal(a.vertices, b.vertices)
    np.testing.assert_array_equal(a.triangles, b.triangles)
    np.testing.assert_array_equal(a.triangles, [[0, 1, 3], [0, 3, 2]])


def test_fan_triangulation_of_mixed_polygons():
    tris = fan_triangulate([[0, 1, 2], [3, 4, 5, 6, 7]])
    np.testing.assert_array_equal(tris, [[0, 1, 2], [3, 4, 5], [3, 5, 6], [3, 6, 7]])


@pytest.mark.parametrize("ext", ["obj", "ply", "off", "npz"])
def test_exact_round_trip(tmp_path, mesh, ext):
    first = tmp_path / f"a.{ext}"
    fr.save(mesh, first)
    again = fr.load(first)
    np.testing.assert_array_equal(again.vertices, mesh.vertices)  # bit-exact float64
    np.testing.assert_array_equal(again.triangles, mesh.triangles)
    second = tmp_path / f"b.{ext}"
    fr.save(again, second)
    assert second.read_bytes() == first.read_bytes()


@pytest.mark.parametrize("ext", ["stl", "glb", "gltf"])
def test_float32_formats_round_trip_exactly_after_one_pass(tmp_path, mesh, ext):
    # STL numbers vertices by first use: give it a mesh already in that order
    order = np.unique(mesh.triangles.ravel(), return_index=True)[1]
    first_use = mesh.triangles.ravel()[np.sort(order)]
    remap = np.empty(mesh.n_vertices, dtype=int)
    remap[first_use] = np.arange(mesh.n_vertices)
    ordered = Mesh(mesh.vertices[first_use], remap[mesh.triangles])
    fr.save(ordered, tmp_path / f"a.{ext}")
    once = fr.load(tmp_path / f"a.{ext}", kind="mesh")
    np.testing.assert_allclose(once.vertices, ordered.vertices, atol=1e-6)
    np.testing.assert_array_equal(once.triangles, ordered.triangles)
    fr.save(once, tmp_path / f"b.{ext}")
    twice = fr.load(tmp_path / f"b.{ext}", kind="mesh")
    np.testing.assert_array_equal(twice.vertices, once.vertices)
    np.testing.assert_array_equal(twice.triangles, once.triangles)


def _ply_header(fmt: str, n_v: int, n_f: int, extra_vertex_prop: str = "") -> bytes:
    return (
        f"ply\nformat {fmt} 1.0\ncomment made by hand\nelement vertex {n_v}\nproperty float x\nproperty float y\n"
        f"property float z\n{extra_vertex_prop}element face {n_f}\nproperty list uchar int vertex_indices\n"
        "element material 1\nproperty list uchar float rgb\nend_header\n"
    ).encode()


@pytest.mark.parametrize("fmt", ["binary_little_endian", "binary_big_endian"])
def test_binary_ply_with_mixed_polygons_and_extra_elements(tmp_path, fmt):
    order = "<" if fmt.endswith("little_endian") else ">"
    verts = np.array([[0, 0, 0], [1, 0, 0], [1, 1, 0], [0, 1, 0], [2, 1, 0]], dtype=order + "f4")
    body = verts.tobytes()
    body += struct.pack(order + "B4i", 4, 0, 1, 2, 3) + struct.pack(order + "B3i", 3, 1, 4, 2)
    body += struct.pack(order + "B3f", 3, 0.1, 0.2, 0.3)
    path = tmp_path / "m.ply"
    path.write_bytes(_ply_header(fmt, 5, 2) + body)
    mesh = fr.load(path)
    np.testing.assert_array_equal(mesh.vertices, verts.astype(float))
    np.testing.assert_array_equal(mesh.triangles, [[0, 1, 2], [0, 2, 3], [1, 4, 2]])


def test_ascii_ply_and_off_variants(tmp_path):
    ply = tmp_path / "m.ply"
    ply.write_bytes(
        _ply_header("ascii", 4, 1, "property uchar red\n")
        + b"0 0 0 9\n1 0 0 9\n1 1 0 9\n0 1 0 9\n4 0 1 2 3\n3 0.1 0.2 0.3\n"
    )
    np.testing.assert_array_equal(fr.load(ply).triangles, [[0, 1, 2], [0, 2, 3]])
    off = tmp_path / "m.off"
    off.write_text(
        "COFF\n# colours per vertex\n4 1 0\n0 0 0 255 0 0 255\n1 0 0 255 0 0 255\n1 1 0 0 0 0 255\n0 1 0 1 1 1 1\n4 0 1 2 3\n"
    )
    np.testing.assert_array_equal(fr.load(off).vertices[:, :2], [[0, 0], [1, 0], [1, 1], [0, 1]])


def test_ascii_stl_joins_identical_corners_in_first_use_order(tmp_path):
    path = tmp_path / "m.stl"
    facet = "facet normal 0 0 1\n outer loop\n  vertex {} \n  vertex {} \n  vertex {} \n endloop\nendfacet\n"
    path.write_text(
        "solid x\n"
        + facet.format("1 0 0", "1 1 0", "0 0 0")
        + facet.format("0 0 0", "1 1 0", "0 1 0")
        + "endsolid x\n"
    )
    mesh = fr.load(path)
    np.testing.assert_array_equal(mesh.vertices, [[1, 0, 0], [1, 1, 0], [0, 0, 0], [0, 1, 0]])
    np.testing.assert_array_equal(mesh.triangles, [[0, 1, 2], [2, 1, 3]])


BAD_FILES = [
    ("obj", b"v 0 0 0\nv 1 0 0\nf 1 2 7\n", "vertex 7"),
    ("obj", b"v 0 0 0\nv 1 0 0\nv 0 1 nan\nf 1 2 3\n", "NaN"),
    ("obj", b"v 0 0 0\nv 1 0 0\nv 0 1 0\nf 1 2 2\n", "degenerate"),
    ("obj", b"v 0 0 0\nv 1 0 0\nv 0 1 0\nf 1 2 0\n", "index 0"),
    ("obj", b"v 0 0 0\nv 1 0 0\nv 0 1 0\nf 1 2 -9\n", "relative index"),
    ("obj", b"v 0 0 0\nv 1 0 0\nv 0 1 0\n", "no faces"),
    ("obj", b"v 0 0 0\nbogus 1 2 3\n", "unknown OBJ statement"),
    ("obj", b"v 0 0\nf 1 2 3\n", "3 coordinates"),
    ("off", b"OFF\n4 2 0\n0 0 0\n1 0 0\n0 1 0\n", "truncated"),
    ("off", b"OFF\n-3 1 0\n", ">= 0"),
    (
        "ply",
        b"ply\nformat binary_little_endian 1.0\nelement vertex 100\nproperty float x\nproperty float y\nproperty float z\n"
        b"element face 1\nproperty list uchar int vertex_indices\nend_header\n\x00\x00",
        "truncated",
    ),
    (
        "ply",
        b"ply\nformat ascii 1.0\nelement vertex 1\nproperty float x\nend_header\n0\n",
        "'vertex' and 'face'",
    ),
    ("stl", b"\x00" * 80 + struct.pack("<I", 1000) + b"\x00" * 50, "declares 1000 triangles"),
]


@pytest.mark.parametrize("ext,data,needle", BAD_FILES)
def test_malformed_meshes_raise_file_format_errors_naming_the_file(tmp_path, ext, data, needle):
    path = tmp_path / f"broken.{ext}"
    path.write_bytes(data)
    with pytest.raises(FileFormatError) as info:
        fr.load(path)
    assert str(path) in str(info.value)
    assert needle in str(info.value)


def test_declared_sizes_over_the_memory_budget_are_refused_before_reading(tmp_path, monkeypatch):
    path = tmp_path / "big.off"
    path.write_text("OFF\n100000000 200000000 0\n0 0 0\n")
    monkeypatch.setenv("FACERETARGET_MEMORY_BUDGET", "64M")
    with pytest.raises(ResourceLimitError, match="memory budget"):
        fr.load(path)
