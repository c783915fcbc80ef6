"""Errors a person can act on: a file of another kind says what it is, a typo gets a
"did you mean", a missing need names the Python argument that supplies it."""

import numpy as np
import pytest

import faceretarget as fr
from faceretarget.cases import get_case
from faceretarget.errors import (
    CapabilityError,
    FileFormatError,
    FormatMismatchError,
    UnknownNameError,
)
from faceretarget.evaluation.harness import parse_case_spec
from faceretarget.io._common import format_mismatch, sniff
from faceretarget.model import BlendshapeRig, Mesh, TargetRig

PNG = b"\x89PNG\r\n\x1a\n" + bytes(600)
HTML = b"<!DOCTYPE html>\n<html><head><title>404</title></head><body>Not Found</body></html>\n"


def _npz(path):
    np.savez(path, a=np.zeros(3))
    return path.read_bytes()


@pytest.mark.parametrize(
    "name, content, says",
    [
        ("take.c3d", PNG, "this looks like a PNG image, not a C3D file"),
        ("face.glb", HTML, "this looks like an HTML web page"),
        (
            "face.obj",
            None,
            "this looks like a NumPy .npz archive, not a Wavefront OBJ file; if that is what it is, give it the .npz extension",
        ),
        ("take.c3d", b"frame,time\n" * 80, "this looks like a CSV table, not a C3D file"),
        ("take.pc2", b'{"not": "a cache"}', "this looks like JSON text, not a PC2 point cache"),
        ("mesh.ply", b"PK\x03\x04" + bytes(100), "this looks like a ZIP archive, not a PLY file"),
    ],
    ids=["png-as-c3d", "html-as-glb", "npz-as-obj", "csv-as-c3d", "json-as-pc2", "zip-as-ply"],
)
def test_a_file_of_another_kind_says_what_it_is(tmp_path, name, content, says):
    path = tmp_path / name
    if content is None:
        content = _npz(tmp_path / "x.npz")
    path.write_bytes(content)
    with pytest.raises(FormatMismatchError) as caught:
        fr.load(path)
    assert str(caught.value).startswith(f"{path}: {says}")
    assert "AssertionError" not in str(caught.value) and isinstance(caught.value, FileFormatError)


def test_an_unreadable_extension_names_the_content(tmp_path):
    path = tmp_path / "photo.png"
    path.write_bytes(PNG)
    with pytest.raises(
        FileFormatError, match=r"no reader for '\.png' files \(it looks like a PNG image\)"
    ):
        fr.load(path)
    typo = tmp_path / "mesh.objj"
    typo.write_text("v 0 0 0\n")
    with pytest.raises(FileFormatError, match=r"did you mean '\.obj'"):
        fr.load(typo)


def test_files_that_fit_their_extension_are_not_mismatches(tmp_path):
    fr.save(Mesh([[0.0, 0, 0], [1, 0, 0], [0, 1, 0]], [[0, 1, 2]]), tmp_path / "m.obj")
    np.savez(tmp_path / "a.npz", a=np.zeros(2))
    (tmp_path / "broken.obj").write_text(
        "v 0 0\nf 1 2 3\n"
    )  # an OBJ with an error: its own message stands
    for name in ("m.obj", "a.npz", "broken.obj"):
        assert format_mismatch(tmp_path / name) is None, name
    assert sniff(tmp_path / "a.npz")[0] == "npz"
    with pytest.raises(FileFormatError) as caught:
        fr.load(tmp_path / "broken.obj")
    assert not isinstance(caught.value, FormatMismatchError)


def test_did_you_mean_for_methods_parameters_cases_kinds_and_formats(tmp_path):
    with pytest.raises(
        UnknownNameError, match=r"no retargeter named 'spacetme' \(did you mean 'spacetime'"
    ):
        fr.get("spacetme")
    with pytest.raises(UnknownNameError, match=r"no parameter 'alpah' \(did you mean 'alpha'\?\)"):
        fr.get("spacetime", alpah=1.0)
    with pytest.raises(UnknownNameError, match=r"no parameter 'alpah' \(did you mean 'alpha'\?\)"):
        fr.get("spacetime").set_params(alpah=1.0)
    with pytest.raises(UnknownNameError, match=r"did you mean 'synthetic'\?"):
        get_case("synthtic")
    with pytest.raises(UnknownNameError, match=r"did you mean 'cross_rig'"):
        parse_case_spec("cross-rig")
    (tmp_path / "m.obj").write_text("v 0 0 0\nv 1 0 0\nv 0 1 0\nf 1 2 3\n")
    with pytest.raises(UnknownNameError, match=r"did you mean 'mesh'"):
        fr.load(tmp_path / "m.obj", kind="mseh")
    with pytest.raises(UnknownNameError, match=r"did you mean 'obj'"):
        fr.load(tmp_path / "m.obj", format="ojb")


def test_did_you_mean_for_shape_names():
    neutral = Mesh([[0.0, 0, 0], [1, 0, 0], [0, 1, 0]], [[0, 1, 2]])
    rig = BlendshapeRig(neutral, np.zeros((3, 3, 3)), ["jawOpen", "eyeBlink_L", "eyeBlink_R"])
    with pytest.raises(
        UnknownNameError, match=r"no blendshape named 'JawOpen' \(did you mean 'jawOpen'\?\)"
    ):
        rig.index("JawOpen")
    with pytest.raises(UnknownNameError, match=r"did you mean 'eyeBlink_L'"):
        rig.index("eyeblink_l")
    case = get_case("cross_rig")
    target = case.target
    name = target.blendshapes.names[0]
    method = fr.get("spacetime", prior_shapes=[name[:-1] + name[-1].swapcase() + "x"])
    with pytest.raises(UnknownNameError, match=f"did you mean {name!r}"):
        method.fit(case.source, target)


def test_missing_needs_name_the_python_argument():
    case = get_case("synthetic")
    bare = TargetRig(case.target.neutral)
    with pytest.raises(CapabilityError) as caught:
        fr.get("coating").fit(case.source, bare)
    message = str(caught.value)
    assert "needs a TargetRig with feature lines" in message
    assert (
        "TargetRig(neutral, feature_lines=" in message
        and "load_target(path, feature_lines=JSON)" in message
    )
