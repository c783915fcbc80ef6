"""The test suite leaves the user's environment and the checkout as they were.

The tests that install a plugin or build a wheel (``PLUGIN_TESTS``) run here in a pytest
subprocess; before and after, the installed distributions (``pip list``), the listing of
every site-packages folder and ``git status --porcelain --ignored`` of the checkout (new
untracked or ignored files such as ``build/``, ``*.egg-info``, ``.hypothesis/``) must be equal.
The tests that write temporary files outside pytest's ``tmp_path`` or kill writers half-way
(``SCRATCH_TESTS``) run in a subprocess with a temporary folder of their own, which must hold
nothing but pytest's ``pytest-of-*`` afterwards.
"""

from __future__ import annotations

import json
import os
import shutil
import site
import subprocess
import sys
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]
PLUGIN_TESTS = [
    "tests/core/test_third_party.py",
    "tests/core/test_registry.py::test_wheel_ships_registry_toml_and_reads_it_from_there",
]
SCRATCH_TESTS = [
    "tests/reliability/test_no_data_loss.py",  # SIGKILLed writers (meshio's scratch folders)
    "tests/reliability/test_resource_limits.py",  # seeds written by every writer
    "tests/reliability/test_plugin_isolation.py::test_dask_batch_stops_a_slow_job",  # dask
]


def installed() -> list[tuple[str, str]]:
    out = subprocess.run(
        [sys.executable, "-m", "pip", "list", "--format=json", "--disable-pip-version-check"],
        capture_output=True,
        text=True,
    )
    assert out.returncode == 0, out.stderr
    return sorted((d["name"].lower(), d["version"]) for d in json.loads(out.stdout))


def site_listing() -> dict[str, list[str]]:
    folders = [*site.getsitepackages(), site.getusersitepackages()]
    return {f: sorted(os.listdir(f)) for f in folders if os.path.isdir(f)}


def checkout_litter() -> list[str]:
    """Untracked and ignored entries of the checkout (tracked files are never written by tests)."""
    out = subprocess.run(
        ["git", "-C", str(ROOT), "status", "--porcelain", "--ignored"],
        capture_output=True,
        text=True,
    )
    assert out.returncode == 0, out.stderr
    return sorted(line for line in out.stdout.splitlines() if line.startswith(("??", "!!")))


@pytest.mark.skipif(
    shutil.which("git") is None or not (ROOT / ".git").exists(), reason="needs a git checkout"
)
def test_plugin_and_build_tests_leave_environment_and_checkout_alone(tmp_path):
    before = (installed(), site_listing(), checkout_litter())
    env = dict(os.environ, PYTHONDONTWRITEBYTECODE="1", NUMBA_CACHE_DIR=str(tmp_path / "numba"))
    out = subprocess.run(
        [sys.executable, "-m", "pytest", "-q", "-p", "no:cacheprovider", *PLUGIN_TESTS],
        cwd=ROOT,
        env=env,
        capture_output=True,
        text=True,
    )
    after = (installed(), site_listing(), checkout_litter())
    assert after[0] == before[0], (
        f"pip list changed: added {sorted(set(after[0]) - set(before[0]))}, removed {sorted(set(before[0]) - set(after[0]))}"
    )
    for folder in before[1]:
        added = sorted(set(after[1].get(folder, [])) - set(before[1][folder]))
        assert not added, f"{folder} gained {added}"
    assert after[2] == before[2], f"the checkout gained {sorted(set(after[2]) - set(before[2]))}"
    assert out.returncode == 0, out.stdout[-3000:] + out.stderr[-2000:]


def test_hypothesis_keeps_its_files_outside_the_checkout():
    from hypothesis.configuration import storage_directory

    folder = storage_directory("examples", intent_to_write=False).path.resolve()
    assert not folder.is_relative_to(ROOT), f"hypothesis would write into the checkout: {folder}"


def test_temporary_files_are_removed(tmp_path):
    scratch = tmp_path / "tmp"
    scratch.mkdir()
    env = dict(os.environ, PYTHONDONTWRITEBYTECODE="1", TMPDIR=str(scratch), TEMP=str(scratch))
    env.pop("DASK_TEMPORARY_DIRECTORY", None)  # the child's conftest chooses its own
    out = subprocess.run(
        [sys.executable, "-m", "pytest", "-q", "-rs", "-p", "no:cacheprovider", *SCRATCH_TESTS],
        cwd=ROOT,
        env=env,
        capture_output=True,
        text=True,
    )
    assert out.returncode == 0, out.stdout[-3000:] + out.stderr[-2000:]
    skipped = [line for line in out.stdout.splitlines() if line.startswith("SKIPPED")]
    assert not any("test_plugin_isolation" in line for line in skipped), skipped  # dask ran
    left = sorted(p.name for p in scratch.iterdir() if not p.name.startswith("pytest-of-"))
    assert not left, f"the tests left {left} in the temporary folder"
