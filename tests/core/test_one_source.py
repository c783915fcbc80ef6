"""One of each (issue 18 item 4): the version in a leaf module, one --set parser, one JSON
conversion, one output check, one meaning of a timeout."""

import ast
import math
import re
from pathlib import Path

import numpy as np
import pytest

import faceretarget
from faceretarget import config
from faceretarget._args import parse_sets
from faceretarget._json import jsonable
from faceretarget.errors import ConfigError, ParameterError

CORE = Path(faceretarget.__file__).parent


def _core_sources():
    for path in sorted(CORE.rglob("*.py")):
        rel = path.relative_to(CORE).as_posix()
        yield rel, path.read_text(encoding="utf-8")


def test_the_version_lives_in_a_leaf_module():
    tree = ast.parse((CORE / "_version.py").read_text())
    assert not [n for n in ast.walk(tree) if isinstance(n, (ast.Import, ast.ImportFrom))]
    assert faceretarget.__version__ == faceretarget._version.__version__
    upward = [
        rel
        for rel, text in _core_sources()
        if re.search(r"from \.+ import [^\n]*__version__", text)
    ]
    assert not upward, (
        f"import __version__ from faceretarget._version, not from the package: {upward}"
    )


def test_one_json_conversion():
    others = [
        rel
        for rel, text in _core_sources()
        if re.search(r"def _?json(able|_number)\b", text) and rel != "_json.py"
    ]
    assert not others, f"JSON conversion outside faceretarget._json: {others}"
    assert jsonable({1: np.float32(0.5), "a": (np.arange(2), math.nan, math.inf), "b": object}) == {
        "1": 0.5,
        "a": [[0, 1], None, None],
        "b": repr(object),
    }


def test_one_set_parser():
    others = [
        rel
        for rel, text in _core_sources()
        if re.search(r"def _?parse_(sets|params)\b", text) and rel != "_args.py"
    ]
    assert not others, f"a --set parser outside faceretarget._args: {others}"
    assert parse_sets([" alpha = 0.5", "mode=range", "flag=TRUE"]) == {
        "alpha": 0.5,
        "mode": "range",
        "flag": True,
    }
    assert parse_sets(["m.a.b=1"], per_method=True) == {"m.a": {"b": 1}}
    for bad, per_method in (("alpha", False), ("=1", False), ("alpha=1", True), (".a=1", True)):
        with pytest.raises(ParameterError, match="expected"):
            parse_sets([bad], per_method=per_method)


def test_one_output_check():
    callers = [rel for rel, text in _core_sources() if "validate_output" in text]
    assert not callers, (
        f"results are checked by Retargeter.check_output (made by retarget): {callers}"
    )


def test_one_meaning_of_a_timeout():
    """Seconds; 0 or None: no limit. The same for compare, batch jobs and worker tasks."""
    from faceretarget.evaluation._workers import Task

    assert (
        config.check_timeout(0) is None
        and config.check_timeout(None) is None
        and config.check_timeout(5) == 5.0
    )
    assert (
        Task("t", print, timeout=0).timeout is None and Task("t", print, timeout=2).timeout == 2.0
    )
    for bad in (-1, math.inf, "10", True):
        with pytest.raises(ConfigError):
            config.check_timeout(bad)
        with pytest.raises(ConfigError):
            Task("t", print, timeout=bad)
