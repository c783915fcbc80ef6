"""load/save dispatch: extensions, kinds, looking inside ambiguous files, plugin formats."""

from __future__ import annotations

import types

import numpy as np
import pytest

import faceretarget as fr
import faceretarget.registry as registry_module
from faceretarget.errors import FileFormatError, UnknownNameError
from faceretarget.hookspecs import Reader, Writer, hookimpl
from faceretarget.io import formats, kind_of
from faceretarget.model import (
    Animation,
    BlendshapeRig,
    MarkerSequence,
    Mesh,
    MeshSequence,
    WeightSequence,
)


def test_ambiguous_extensions_are_resolved_by_content(
    tmp_path, mesh, rig, seq, animation, markers, weights
):
    cases = [
        (mesh, "m.glb", Mesh),
        (rig, "r.glb", BlendshapeRig),
        (animation, "a.glb", Animation),
        (mesh, "m.npz", Mesh),
        (rig, "r.npz", BlendshapeRig),
        (seq, "s.npz", MeshSequence),
        (animation, "a.npz", Animation),
        (markers, "k.npz", MarkerSequence),
        (weights, "w.npz", WeightSequence),
        (markers, "k.csv", MarkerSequence),
        (weights, "w.csv", WeightSequence),
        (rig, "rigdir", BlendshapeRig),
        (seq, "seqdir", MeshSequence),
    ]
    for obj, name, cls in cases:
        fr.save(obj, tmp_path / name)
        assert isinstance(fr.load(tmp_path / name), cls), name


def test_kind_converts_between_related_kinds(tmp_path, animation, rig):
    fr.save(animation, tmp_path / "a.npz")
    assert isinstance(fr.load(tmp_path / "a.npz", kind="weights"), WeightSequence)
    assert isinstance(fr.load(tmp_path / "a.npz", kind="mesh_sequence"), MeshSequence)
    fr.save(rig, tmp_path / "r.glb")
    neutral = fr.load(tmp_path / "r.glb", kind="mesh")
    np.testing.assert_allclose(neutral.vertices, rig.neutral.vertices, atol=1e-6)
    with pytest.raises(FileFormatError, match="cannot be read as markers"):
        fr.load(tmp_path / "r.glb", kind="markers")
    with pytest.raises(UnknownNameError, match="unknown kind"):
        fr.load(tmp_path / "r.glb", kind="nonsense")


def test_save_coerces_animation_to_sequences_and_weights(tmp_path, animation, mesh):
    fr.save(animation, tmp_path / "a.pc2")
    np.testing.assert_allclose(
        fr.load(tmp_path / "a.pc2", topology=mesh).vertices, animation.vertices, atol=1e-5
    )
    fr.save(animation, tmp_path / "w.csv")
    np.testing.assert_array_equal(fr.load(tmp_path / "w.csv").weights, animation.weights)
    fr.save(animation, tmp_path / "frames")
    assert fr.load(tmp_path / "frames").n_frames == animation.n_frames
    with pytest.raises(FileFormatError, match="cannot be written"):
        fr.save(mesh, tmp_path / "m.c3d")


def test_unknown_extensions_list_what_is_supported(tmp_path, mesh):
    (tmp_path / "x.abc").write_text("?")
    with pytest.raises(FileFormatError, match=r"no reader for '\.abc' files; readable: .*\.obj"):
        fr.load(tmp_path / "x.abc")
    with pytest.raises(FileFormatError, match="no writer for '.abc'"):
        fr.save(mesh, tmp_path / "y.abc")
    with pytest.raises(FileFormatError, match="no such file"):
        fr.load(tmp_path / "missing.obj")
    with pytest.raises(UnknownNameError, match="no reader named"):
        fr.load(tmp_path / "x.abc", format="nope")


def _xyz_plugin():
    """A third-party plugin adding a '.xyz' point-list mesh format."""

    def read(path, **options):
        return Mesh(np.loadtxt(path, ndmin=2), [[0, 1, 2]])

    def write(obj, path, *, force=False, inputs=(), **options):
        from faceretarget.io._atomic import write_bytes

        write_bytes(
            path,
            "\n".join(" ".join(map(repr, v)) for v in obj.vertices.tolist()).encode(),
            force=force,
            inputs=inputs,
        )

    module = types.ModuleType("xyzplug")
    module.faceretarget_readers = hookimpl(
        lambda: [Reader("xyz", "mesh", (".xyz",), read, "points")]
    )
    module.faceretarget_writers = hookimpl(
        lambda: [Writer("xyz", "mesh", (".xyz",), write, "points")]
    )
    return module


def test_plugin_formats_are_used_through_the_registry(tmp_path, monkeypatch):
    reg = registry_module.Registry().load(extra=[("xyzplug", _xyz_plugin())])
    monkeypatch.setattr(registry_module, "_REGISTRY", reg)
    tri = Mesh([[0, 0, 0], [1, 0, 0], [0, 1, 0]], [[0, 1, 2]])
    fr.save(tri, tmp_path / "t.xyz")
    back = fr.load(tmp_path / "t.xyz")
    np.testing.assert_array_equal(back.vertices, tri.vertices)
    rows = [r for r in formats() if r["name"] == "xyz"]
    assert {r["direction"] for r in rows} == {"read", "write"} and all(
        r["origin"] == "local -" for r in rows
    )
    # a folder of the plugin's meshes is a sequence too
    folder = tmp_path / "frames"
    folder.mkdir()
    for k in range(3):
        fr.save(tri.with_vertices(tri.vertices + k), folder / f"f{k}.xyz")
    assert fr.load(folder).n_frames == 3


def test_kind_of_rejects_other_objects():
    from faceretarget.errors import InputError

    with pytest.raises(InputError, match="cannot save a dict"):
        kind_of({})
