"""Name mapping between ARKit, Live Link Face, ICT and other conventions."""

from __future__ import annotations

import json

import numpy as np
import pytest

from faceretarget.errors import ConfigError, InputError, UnknownNameError
from faceretarget.model import WeightSequence
from faceretarget.naming import (
    ARKIT_NAMES,
    ICT_NAMES,
    LIVE_LINK_NAMES,
    canonical,
    load_mapping,
    map_names,
    rename,
)


@pytest.mark.parametrize(
    "name,key",
    [
        ("eyeBlinkLeft", ("eyeblink", "L")),
        ("EyeBlinkLeft", ("eyeblink", "L")),
        ("eyeBlink_L", ("eyeblink", "L")),
        ("eyeBlink.L", ("eyeblink", "L")),
        ("L_eyeBlink", ("eyeblink", "L")),
        ("eyeBlinkL", ("eyeblink", "L")),
        ("EYE_BLINK_RIGHT", ("eyeblink", "R")),
        ("eyeblink_r", ("eyeblink", "R")),
        ("LeftEyeYaw", ("eyeyaw", "L")),
        ("jawOpen", ("jawopen", None)),
        ("Cleft", ("cleft", None)),
        ("eyeBright", ("eyebright", None)),
    ],
)
def test_canonical_keys(name, key):
    assert canonical(name) == key


def test_known_sets():
    assert len(ARKIT_NAMES) == 52 and len(set(ARKIT_NAMES)) == 52
    assert (
        len(LIVE_LINK_NAMES) == 61
        and LIVE_LINK_NAMES[0] == "EyeBlinkLeft"
        and LIVE_LINK_NAMES[-1] == "RightEyeRoll"
    )
    assert (
        len(ICT_NAMES) == 53
        and "browInnerUp_L" in ICT_NAMES
        and "jawLeft" in ICT_NAMES
        and "tongueOut" not in ICT_NAMES
    )


def test_arkit_to_ict_splits_and_reports_what_is_left():
    m = map_names("arkit", "ict")
    assert m["eyeBlinkLeft"] == ("eyeBlink_L",)
    assert m["jawLeft"] == ("jawLeft",) and m["mouthRight"] == ("mouthRight",)
    assert (
        m["browInnerUp"] == ("browInnerUp_L", "browInnerUp_R") and m.rules["browInnerUp"] == "split"
    )
    assert m.unmapped == ("tongueOut",) and m.missing == ()
    assert not m.complete
    with pytest.raises(UnknownNameError, match="tongueOut"):
        m.require_complete("ARKit curves")
    assert "unmapped: tongueOut" in m.report()


def test_ict_to_arkit_merges_sides_by_averaging():
    m = map_names(ICT_NAMES, ARKIT_NAMES)
    assert m.complete and m.missing == ("tongueOut",)
    a = m.matrix()
    row = ARKIT_NAMES.index("browInnerUp")
    cols = [ICT_NAMES.index("browInnerUp_L"), ICT_NAMES.index("browInnerUp_R")]
    np.testing.assert_array_equal(a[row, cols], [0.5, 0.5])
    assert a[row].sum() == 1.0
    w = np.random.default_rng(0).random((3, len(ICT_NAMES)))
    out = m.apply(w)
    np.testing.assert_allclose(out[:, row], w[:, cols].mean(axis=1))
    np.testing.assert_array_equal(
        out[:, ARKIT_NAMES.index("eyeBlinkLeft")], w[:, ICT_NAMES.index("eyeBlink_L")]
    )
    np.testing.assert_array_equal(out[:, ARKIT_NAMES.index("tongueOut")], 0)


def test_live_link_to_arkit_is_case_only_with_rotations_unmapped():
    m = map_names("livelink", "arkit")
    assert set(m.rules.values()) == {"case"}
    assert m.unmapped == LIVE_LINK_NAMES[52:]


def test_presets_differ():
    src, dst = ["EyeBlinkLeft", "browInnerUp"], ["eyeBlink_L", "browInnerUp_L", "browInnerUp_R"]
    assert map_names(src, dst, preset="exact").unmapped == tuple(src)
    assert map_names(src, dst, preset="case").unmapped == tuple(src)
    assert map_names(src, dst, preset="sides").unmapped == ("browInnerUp",)
    assert map_names(src, dst, preset="auto").complete
    with pytest.raises(UnknownNameError, match="presets"):
        map_names(src, dst, preset="fuzzy")


def test_ambiguous_loose_matches_are_not_guessed():
    m = map_names(["eyeblink_l"], ["eyeBlinkLeft", "eye_blink_L"])
    assert m.unmapped == ("eyeblink_l",)  # two candidates with the same key: reported, not picked


def test_explicit_mapping_wins_and_may_ignore_names():
    m = map_names(
        ["jawOpen", "HeadYaw", "smile"],
        ["JawOpen", "mouthSmile_L", "mouthSmile_R"],
        mapping={"smile": ["mouthSmile_L", "mouthSmile_R"], "HeadYaw": "", "notInTake": "JawOpen"},
    )
    assert m["smile"] == ("mouthSmile_L", "mouthSmile_R") and m.rules["smile"] == "mapping"
    assert m.ignored == ("HeadYaw",) and m.complete and m.unused_rules == ("notInTake",)
    with pytest.raises(UnknownNameError, match="nosuch"):
        map_names(["a"], ["b"], mapping={"a": "nosuch"})


def test_apply_to_weight_sequences():
    curves = WeightSequence(np.array([[0.2, 0.4]]), ["eyeBlinkLeft", "jawOpen"], fps=60)
    mapped = map_names(curves.names, ["eyeBlink_L", "jawOpen", "extra"]).apply(curves)
    assert mapped.names == ("eyeBlink_L", "jawOpen", "extra") and mapped.fps == 60
    np.testing.assert_array_equal(mapped.weights, [[0.2, 0.4, 0.0]])
    with pytest.raises(InputError, match="expected"):
        map_names(["a"], ["a"]).apply(np.zeros((2, 3)))


@pytest.mark.parametrize(
    "suffix,text",
    [
        (
            ".toml",
            'smile = ["mouthSmile_L", "mouthSmile_R"]\nHeadYaw = ""\n"Jaw Open" = "jawOpen"\n',
        ),
        (
            ".toml",
            '[mapping]\nsmile = ["mouthSmile_L", "mouthSmile_R"]\nHeadYaw = ""\n"Jaw Open" = "jawOpen"\n',
        ),
        (
            ".json",
            json.dumps(
                {"smile": ["mouthSmile_L", "mouthSmile_R"], "HeadYaw": None, "Jaw Open": "jawOpen"}
            ),
        ),
        (
            ".json",
            json.dumps(
                [
                    ["smile", "mouthSmile_L"],
                    ["smile", "mouthSmile_R"],
                    ["HeadYaw", ""],
                    ["Jaw Open", "jawOpen"],
                ]
            ),
        ),
        (".csv", "from,to\nsmile,mouthSmile_L\nsmile,mouthSmile_R\nHeadYaw,\nJaw Open,jawOpen\n"),
    ],
)
def test_mapping_files(tmp_path, suffix, text):
    path = tmp_path / f"map{suffix}"
    path.write_text(text)
    assert load_mapping(path) == {
        "smile": ("mouthSmile_L", "mouthSmile_R"),
        "HeadYaw": (),
        "Jaw Open": ("jawOpen",),
    }
    m = map_names(
        ["smile", "HeadYaw", "Jaw Open"], ["mouthSmile_L", "mouthSmile_R", "jawOpen"], mapping=path
    )
    assert m.complete and m.ignored == ("HeadYaw",)


@pytest.mark.parametrize(
    "suffix,text,needle",
    [
        (".toml", "a = [1, 2]\n", "must map to"),
        (".toml", "a = \n", "not valid TOML"),
        (".json", "{", "not valid JSON"),
        (".json", json.dumps([["a", "b", "c"]]), "two names"),
        (".csv", ",b\n", "empty from-name"),
        (".yaml", "a: b\n", "unknown mapping file type"),
    ],
)
def test_bad_mapping_files(tmp_path, suffix, text, needle):
    path = tmp_path / f"map{suffix}"
    path.write_text(text)
    with pytest.raises(ConfigError, match=needle):
        load_mapping(path)


def test_rename_styles():
    names = ["eyeBlink_L", "jawLeft", "browInnerUp", "mouthSmileRight"]
    assert rename(names, "arkit") == ("eyeBlinkLeft", "jawLeft", "browInnerUp", "mouthSmileRight")
    assert rename(names, "ict") == ("eyeBlink_L", "jawLeft", "browInnerUp", "mouthSmile_R")
    assert rename(names, "livelink") == (
        "EyeBlinkLeft",
        "JawLeft",
        "BrowInnerUp",
        "MouthSmileRight",
    )
    assert rename(names, "blender") == ("eyeBlink.L", "jawLeft", "browInnerUp", "mouthSmile.R")
    assert rename(ARKIT_NAMES, "livelink") == LIVE_LINK_NAMES[:52]
    with pytest.raises(UnknownNameError):
        rename(names, "maya")


def test_bad_name_lists():
    with pytest.raises(InputError, match="duplicate"):
        map_names(["a", "a"], ["b"])
    with pytest.raises(UnknownNameError, match="known sets"):
        map_names("metahuman", ["b"])
