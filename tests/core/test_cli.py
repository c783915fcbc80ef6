"""The command line: one-line errors, list/info, version."""
import json
import subprocess
import sys

import pytest

from faceretarget import __version__, errors
from faceretarget.cli import main, parse_params


def run(*args):
    return subprocess.run([sys.executable, "-m", "faceretarget.cli", *args], capture_output=True, text=True)


def test_version():
    out = run("--version")
    assert out.returncode == 0 and __version__ in out.stdout


def test_list_and_json(capsys):
    assert main(["list", "--json"]) == 0
    data = json.loads(capsys.readouterr().out)
    assert set(data) == {"retargeters", "failed_plugins"}
    assert main(["list"]) == 0
    assert "NAME" in capsys.readouterr().out


def test_unknown_name_is_one_line_error_without_traceback():
    out = run("info", "no-such-method")
    assert out.returncode == 2
    lines = out.stderr.strip().splitlines()
    assert len(lines) == 1 and lines[0].startswith("faceretarget: error:") and "no-such-method" in lines[0]
    assert "Traceback" not in out.stderr


def test_debug_shows_traceback():
    out = run("--debug", "info", "no-such-method")
    assert out.returncode != 0 and "Traceback" in out.stderr


def test_info_of_every_retargeter(capsys):
    assert main(["list", "--json"]) == 0
    names = [r["name"] for r in json.loads(capsys.readouterr().out)["retargeters"]]
    for name in names:
        assert main(["info", name]) == 0
        text = capsys.readouterr().out
        assert "parameters:" in text and name in text


def test_parse_params():
    assert parse_params(["alpha=0.5", "mode=range", "flag=true", "window=(1, 4)"]) == {
        "alpha": 0.5, "mode": "range", "flag": True, "window": (1, 4)
    }
    with pytest.raises(errors.InputError, match="KEY=VALUE"):
        parse_params(["alpha"])


def test_run_reports_missing_files_in_one_line(tmp_path):
    out = run("run", "spacetime", "--source", str(tmp_path / "nope.c3d"), "--target", str(tmp_path / "rig.glb"), "--out", str(tmp_path / "o.glb"))
    assert out.returncode != 0
    assert len(out.stderr.strip().splitlines()) == 1 and "Traceback" not in out.stderr
    assert not (tmp_path / "o.glb").exists()
