"""Expression recipes: ARKit name normalization, resolution onto rigs, reporting of unmapped names."""

import itertools
import warnings

import numpy as np
import pytest

from faceretarget import recipes
from faceretarget.errors import UnknownNameError


@pytest.mark.parametrize(
    "raw, canonical",
    [
        ("eyeBlinkLeft", "eyeBlinkLeft"),
        ("eyeBlink_L", "eyeBlinkLeft"),
        ("EyeBlinkLeft", "eyeBlinkLeft"),
        ("eye_blink_left", "eyeBlinkLeft"),
        ("EYE-BLINK-RIGHT", "eyeBlinkRight"),
        ("eyeBlinkR", "eyeBlinkRight"),
        ("blendShape1.mouthSmile_L", "mouthSmileLeft"),
        ("face:jawOpen", "jawOpen"),
        ("browInnerUp_R", "browInnerUpRight"),
        ("cheekPuff", "cheekPuff"),
        ("JawOpen", "jawOpen"),
        ("nose_sneer_l", "noseSneerLeft"),
        ("smile", None),
        ("eyeBlink_X", None),
    ],
)
def test_normalize_shape_name(raw, canonical):
    assert recipes.normalize_shape_name(raw) == canonical


def test_recipes_use_arkit_names_and_stay_in_range():
    tables = {**recipes.EMOTIONS, **recipes.VISEMES, **recipes.BLINKS}
    for name, recipe in tables.items():
        for shape, w in recipe.items():
            assert shape in recipes.ARKIT_NAMES and shape in recipes.RECIPE_SHAPES, (name, shape)
            assert 0.0 < w <= 1.0
    # an emotion, a viseme and a blink together never push a shape past 1
    for e, v, b in itertools.product(
        recipes.EMOTIONS.values(), recipes.VISEMES.values(), recipes.BLINKS.values()
    ):
        total = {}
        for r in (e, v, b):
            for k, w in r.items():
                total[k] = total.get(k, 0.0) + w
        assert max(total.values(), default=0.0) <= 1.0 + 1e-12
    assert list(recipes.VISEMES)[0] == "MBP" and len(recipes.VISEMES) >= 10
    assert {
        "happiness",
        "sadness",
        "anger",
        "surprise",
        "fear",
        "disgust",
        "contempt",
        "neutral",
    } <= set(recipes.EMOTIONS)
    assert recipes.EMOTIONS["neutral"] == {} and recipes.BLINKS["open"] == {}
    # FACS: happiness = cheek raiser (AU6) + lip corner puller (AU12)
    assert {"cheekSquintLeft", "mouthSmileLeft"} <= set(recipes.EMOTIONS["happiness"])


def test_resolve_on_ict_style_names():
    names = [
        "browInnerUp_L",
        "browInnerUp_R",
        "mouthSmile_L",
        "mouthSmile_R",
        "jawOpen",
        "eyeBlink_L",
        "eyeBlink_R",
    ]
    w = recipes.resolve({"browInnerUp": 0.7, "mouthSmileLeft": 0.8, "jawOpen": 0.3}, names)
    np.testing.assert_allclose(w, [0.7, 0.7, 0.8, 0.0, 0.3, 0.0, 0.0])
    closed = recipes.resolve(recipes.BLINKS["closed"], names)
    np.testing.assert_allclose(closed, [0, 0, 0, 0, 0, 1, 1])


def test_resolve_onto_merged_shapes_and_case_variants():
    w = recipes.resolve(
        {"mouthSmileLeft": 0.8, "mouthSmileRight": 0.6, "EyeBlinkLeft": 1.0},
        ["mouthSmile", "eye_blink_left"],
    )
    np.testing.assert_allclose(w, [0.7, 1.0])


def test_unmapped_names_are_reported_not_dropped():
    names = ["jawOpen", "eyeBlinkLeft"]
    recipe = recipes.EMOTIONS["surprise"]
    with pytest.warns(recipes.RecipeWarning, match="browOuterUpLeft"):
        w = recipes.resolve(recipe, names)
    np.testing.assert_allclose(w, [0.3, 0.0])
    with pytest.raises(UnknownNameError, match="eyeWideLeft"):
        recipes.resolve(recipe, names, on_unmapped="raise")
    assert "browInnerUp" in recipes.unmapped_names(recipe, names)
    assert recipes.unmapped_names({"jawOpen": 1.0}, names) == []
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        recipes.resolve(recipe, names, on_unmapped="ignore")
    with pytest.raises(UnknownNameError):
        recipes.resolve(recipe, names, on_unmapped="maybe")


def test_resolve_all_stacks_in_the_asked_order():
    m = recipes.resolve_all(recipes.VISEMES, list(recipes.RECIPE_SHAPES), names=["AA", "MBP"])
    assert m.shape == (2, len(recipes.RECIPE_SHAPES))
    assert m[0, recipes.RECIPE_SHAPES.index("jawOpen")] == 0.6
    with pytest.raises(UnknownNameError):
        recipes.resolve_all(recipes.VISEMES, ["jawOpen"], names=["ZZ"])
