"""The example third-party plugin installs through its entry point, is listed, and conforms.

It is installed with ``pip install --target`` into a temporary folder (from a copy of its
sources), put on ``sys.path`` here and on ``PYTHONPATH`` of the subprocesses: the
environment running the tests and the checkout are left as they were
(``tests/test_clean_environment.py``).
"""

import importlib
import json
import os
import subprocess
import sys
from pathlib import Path

import pytest
from envtools import pip_install_target

from faceretarget.registry import reload

EXAMPLE = Path(__file__).resolve().parents[2] / "examples" / "third_party_plugin"


@pytest.fixture(scope="module")
def installed_example(tmp_path_factory):
    """The example plugin installed into a temporary ``--target`` folder: ``(folder, env)``."""
    work = tmp_path_factory.mktemp("third_party")
    site = work / "site"
    out = pip_install_target(EXAMPLE, site, work)
    assert out.returncode == 0, out.stderr[-2000:]
    env = dict(
        os.environ,
        PYTHONPATH=os.pathsep.join(filter(None, [str(site), os.environ.get("PYTHONPATH")])),
    )
    saved = _forget_plugin_modules()  # a copy the user installed stays what other tests hold
    with pytest.MonkeyPatch.context() as mp:
        mp.syspath_prepend(str(site))
        importlib.invalidate_caches()
        yield site, env
    _forget_plugin_modules()
    sys.modules.update(saved)
    importlib.invalidate_caches()
    reload()


def _forget_plugin_modules() -> dict:
    """Remove the plugin's modules from ``sys.modules``; returns them."""
    names = [
        m
        for m in sys.modules
        if m == "faceretarget_displacement" or m.startswith("faceretarget_displacement.")
    ]
    return {name: sys.modules.pop(name) for name in names}


def test_faceretarget_list_shows_the_plugin(installed_example):
    site, env = installed_example
    cmd = [sys.executable, "-m", "faceretarget.cli", "list"]
    out = subprocess.run([*cmd, "--json"], capture_output=True, text=True, env=env)
    assert out.returncode == 0, out.stderr
    rows = {r["name"]: r for r in json.loads(out.stdout)["retargeters"]}
    assert "displacement" in rows
    assert rows["displacement"]["origin"] == "faceretarget-displacement 0.1.0"
    assert rows["displacement"]["builtin"] is False
    text = subprocess.run(cmd, capture_output=True, text=True, env=env).stdout
    assert "displacement" in text and "faceretarget-displacement" in text


def test_the_plugin_is_loaded_from_the_temporary_folder(installed_example):
    site, _ = installed_example
    import faceretarget_displacement

    assert Path(faceretarget_displacement.__file__).resolve().is_relative_to(site.resolve())


def test_the_plugin_passes_the_conformance_kit(installed_example):
    from faceretarget.testing import check_retargeter

    reg = reload()
    cls = reg.retargeters["displacement"].cls
    check_retargeter(cls)


def test_list_and_info_read_the_plugin_manifest_without_importing_it(installed_example):
    site, env = installed_example
    code = (
        "import sys, contextlib, io; from faceretarget import cli\n"
        "with contextlib.redirect_stdout(io.StringIO()) as out:\n"
        "    cli.main(['list']); cli.main(['info', 'displacement'])\n"
        "print('faceretarget_displacement' in sys.modules); print(out.getvalue())"
    )
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, env=env)
    assert out.returncode == 0, out.stderr
    imported, text = out.stdout.split("\n", 1)
    assert imported == "False", (
        "faceretarget list/info imported the plugin instead of reading its faceretarget.toml"
    )
    assert "jacobian = True    (True or False)" in text


def test_the_plugin_checks_its_parameters_with_the_public_module(installed_example):
    import faceretarget as fr
    from faceretarget.errors import ParameterError

    reload()
    case = fr.cases.synthetic(resolution=200, n_frames=2)
    with pytest.raises(
        ParameterError, match="displacement: parameter 'jacobian': expected True or False, got 'no'"
    ):
        fr.get("displacement", jacobian="no").fit(case.source, case.target)
