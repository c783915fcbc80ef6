"""faceretarget.validation: declarative parameter constraints, and every built-in method enforcing
the ones registry.toml declares for it."""

import numpy as np
import pytest

import faceretarget as fr
from faceretarget import errors, manifest
from faceretarget.validation import (
    Interval,
    Options,
    check_value,
    describe,
    from_manifest,
    make_constraint,
    validate_params,
)


@pytest.mark.parametrize(
    "constraints, good, bad",
    [
        (
            [Interval(float, 0, None, closed="left")],
            [0, 0.5, 1e300, np.float32(2)],
            [-1e-9, np.nan, np.inf, True, "1", None, [1]],
        ),
        ([Interval(float, 0, 1, closed="right")], [1, 0.5], [0, 1.5]),
        ([Interval(float, 0, 1, closed="neither")], [0.5], [0, 1]),
        ([Interval(int, 1, 10)], [1, 10, 3.0, np.int64(4)], [0, 11, 2.5, np.bool_(True), "3"]),
        ([Options({"a", "b"})], ["a", "b"], ["A", "c", None, 1]),
        ([Options(["auto"]), Interval(int, 0, 7)], ["auto", 0, 7], ["Auto", 8, -1]),
        (["boolean"], [True, False, 0, 1, np.bool_(False)], [2, "yes", None, np.array([True])]),
        ([None, "array-like"], [None, [1, 2], np.zeros(3), 5], ["abc", b"x"]),
        ([None, "mapping"], [None, {}, {"a": 1}], [[1], "a"]),
        ([callable], [len, lambda: 1], [1, "f"]),
        ([str], ["", "x"], [1, None]),
        ([], [object(), None, "x"], []),
    ],
)
def test_constraints_accept_and_reject(constraints, good, bad):
    for value in good:
        check_value(value, constraints, "p", "m")
    for value in bad:
        with pytest.raises(errors.ParameterError, match="m: parameter 'p': expected"):
            check_value(value, constraints, "p", "m")


def test_values_are_converted():
    assert (
        check_value(3.0, [Interval(int, 0, 7)], "p") == 3
        and type(check_value(3.0, [Interval(int, 0, 7)], "p")) is int
    )
    assert type(check_value(np.float32(0.5), [Interval(float)], "p")) is float
    assert (
        check_value(np.bool_(True), ["boolean"], "p") is True
        and check_value(0, ["boolean"], "p") is False
    )


def test_parameter_error_is_both_a_config_and_an_input_error():
    assert issubclass(errors.ParameterError, errors.ConfigError) and issubclass(
        errors.ParameterError, errors.InputError
    )


def test_a_near_miss_choice_gets_did_you_mean():
    with pytest.raises(errors.ParameterError, match=r"got 'Movment' \(did you mean 'movement'\?\)"):
        check_value("Movment", [Options(["movement", "noconst"])], "mode", "spacetime")


def test_descriptions():
    assert (
        describe([Options(["auto"]), Interval(int, 0, 7)]) == "'auto' or a whole number in [0, 7]"
    )
    assert describe([Interval(float, 0, None, closed="neither")]) == "a finite number > 0"
    assert describe([Interval(float, 1e-4, 1e12)]) == "a finite number in [0.0001, 1e12]"
    assert describe([None, Options(["rig"]), "array-like"]) == "None, 'rig' or an array"
    assert describe(["boolean"]) == "True or False"
    assert describe(["no_validation"]) == ""


def test_unknown_constraints_are_refused():
    for spec in ("bool", 3, "array"):
        with pytest.raises(TypeError):
            make_constraint(spec)
    with pytest.raises(ValueError):
        Interval(float, 2, 1)


@pytest.mark.parametrize(
    "spec, valid",
    [
        ({"type": "float", "range": "[0, 1e12]"}, "a finite number in [0, 1e12]"),
        ({"type": "int", "range": "[-1, inf)"}, "a whole number >= -1"),
        (
            {"choices": ["auto"], "type": "float", "range": "(0, 1]"},
            "'auto' or a finite number in (0, 1]",
        ),
        ({"type": ["str", "int"], "none": True}, "None, a string or a whole number"),
        ({"type": "bool", "default": True}, "True or False"),
        ({"doc": "anything"}, ""),
    ],
)
def test_manifest_form(spec, valid):
    assert describe(from_manifest(spec, "here")) == valid


@pytest.mark.parametrize(
    "spec",
    [
        {"type": "double"},
        {"type": "float", "range": "0..1"},
        {"type": "float", "range": "[1, 0]"},
        {"range": "[0, 1]"},
        {"choices": []},
        {"choices": "a"},
        {"none": "yes"},
        {"min": 0},
        {"type": "int", "range": "[0, 1]", "default": 2},
    ],
)
def test_malformed_manifest_form_is_a_config_error(spec):
    with pytest.raises(errors.ConfigError, match="here"):
        from_manifest(spec, "here")


class Plugin(fr.Retargeter):
    name = "plugin"
    parameter_constraints = {"gain": [Interval(float, 0, None)], "mode": [Options(["a", "b"])]}

    def __init__(self, *, gain=1.0, mode="a", extra=None):
        self.gain, self.mode, self.extra = gain, mode, extra


def test_validate_params_checks_every_declared_parameter():
    assert validate_params(Plugin(gain=2)) == {"gain": 2.0, "mode": "a", "extra": None}
    with pytest.raises(errors.ParameterError, match="plugin: parameter 'gain'"):
        validate_params(Plugin(gain=-1))
    with pytest.raises(errors.ParameterError, match="did you mean 'b'"):
        validate_params(Plugin(mode="B"))


def _bad_values(constraints):
    """Values each outside every one of ``constraints`` (an interval's neighbours, a wrong string)."""
    if not constraints or any(
        not isinstance(c, (Interval, Options)) and c.name in ("array-like", "no_validation")
        for c in constraints
    ):
        return []
    out = ["no-such-choice"] if not any(c == make_constraint(str) for c in constraints) else []
    for c in constraints:
        if isinstance(c, Interval):
            out += [
                v
                for v in (
                    c.left - 1 if c.left is not None else None,
                    c.right + 1 if c.right is not None else None,
                )
                if v is not None
            ]
            if c.kind is int:
                out.append(0.5 + (c.left or 0))
    return [v for v in out if not any(c.accepts(v) for c in constraints)]


def _check_stage(retargeter):
    """The method's own parameter check (what fit() runs first)."""
    check = getattr(retargeter, "_check_params", None) or retargeter._params
    return check()


CASES = [
    (name, p, spec.constraints)
    for name, m in manifest.builtin().items()
    for p, spec in m.parameters.items()
]


@pytest.mark.parametrize("name, param, constraints", CASES, ids=[f"{n}.{p}" for n, p, _ in CASES])
def test_every_builtin_method_enforces_its_declared_constraints(name, param, constraints):
    cls = fr.registry.registry().resolve(name).cls
    _check_stage(cls())  # the defaults pass
    for value in _bad_values(constraints):
        with pytest.raises(errors.ParameterError, match=f"parameter '{param}'"):
            _check_stage(cls(**{param: value}))


def test_every_builtin_parameter_declares_a_constraint_or_is_checked_by_hand():
    hand_checked = {
        "marker_weights",
        "prior_shapes",
        "prior_animations",
        "base_triangles",
        "source_feature_points",
        "target_feature_points",
    }
    for name, m in manifest.builtin().items():
        for p, spec in m.parameters.items():
            assert spec.valid or p in hand_checked, (
                f"{name}.{p} declares no type, range or choices in registry.toml"
            )
