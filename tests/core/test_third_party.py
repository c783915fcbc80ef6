"""The example third-party plugin installs through its entry point, is listed, and conforms."""
import json
import subprocess
import sys
from pathlib import Path

import pytest

from faceretarget.registry import reload

EXAMPLE = Path(__file__).resolve().parents[2] / "examples" / "third_party_plugin"


@pytest.fixture(scope="module")
def installed_example():
    """pip-install examples/third_party_plugin into this environment (idempotent)."""
    out = subprocess.run(
        [sys.executable, "-m", "pip", "install", "--no-deps", "--no-build-isolation", "--quiet", str(EXAMPLE)],
        capture_output=True, text=True,
    )
    assert out.returncode == 0, out.stderr[-2000:]
    import importlib

    importlib.invalidate_caches()
    yield
    reload()


def test_faceretarget_list_shows_the_plugin(installed_example):
    out = subprocess.run(["faceretarget", "list", "--json"], capture_output=True, text=True)
    assert out.returncode == 0, out.stderr
    rows = {r["name"]: r for r in json.loads(out.stdout)["retargeters"]}
    assert "displacement" in rows
    assert rows["displacement"]["origin"] == "faceretarget-displacement 0.1.0"
    assert rows["displacement"]["builtin"] is False
    text = subprocess.run(["faceretarget", "list"], capture_output=True, text=True).stdout
    assert "displacement" in text and "faceretarget-displacement" in text


def test_the_plugin_passes_the_conformance_kit(installed_example):
    from faceretarget.testing import check_retargeter

    reg = reload()
    cls = reg.retargeters["displacement"].cls
    check_retargeter(cls)
