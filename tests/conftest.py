"""Shared pytest configuration: the suite leaves the checkout and the environment as it found them.

- Hypothesis keeps its example database and caches in a temporary folder (not ``.hypothesis/``
  in the checkout), removed at the end of the session (``FACERETARGET_HYPOTHESIS_DIR`` keeps
  them somewhere else on purpose); so does dask's scratch space (``dask-scratch-space`` in
  the user's temporary folder otherwise).
- Plugins are installed by the tests with ``pip install --target`` into temporary folders
  (fixture :func:`pip_target`), never into the environment running the tests; builds happen
  on copies of the sources in temporary folders (:func:`source_copy`), so no ``build/`` or
  ``*.egg-info`` appears in the checkout. ``tests/test_clean_environment.py`` checks both.
"""

from __future__ import annotations

import os
import shutil
import tempfile
from pathlib import Path

import pytest
from envtools import copy_sources


def _hypothesis_home() -> tuple[Path, bool]:
    given = os.environ.get("FACERETARGET_HYPOTHESIS_DIR")
    if given:
        return Path(given), False
    return Path(tempfile.mkdtemp(prefix="faceretarget-hypothesis-")), True


_HYPOTHESIS_HOME, _HYPOTHESIS_TEMPORARY = _hypothesis_home()
try:
    from hypothesis.configuration import set_hypothesis_home_dir
except ImportError:  # pragma: no cover - hypothesis is a test dependency
    pass
else:
    set_hypothesis_home_dir(_HYPOTHESIS_HOME)
os.environ.setdefault("HYPOTHESIS_STORAGE_DIRECTORY", str(_HYPOTHESIS_HOME))  # subprocesses too
# read by dask.config when dask is first imported (the batch tests' LocalCluster), subprocesses too
_DASK_SCRATCH = Path(tempfile.mkdtemp(prefix="faceretarget-dask-"))
os.environ.setdefault("DASK_TEMPORARY_DIRECTORY", str(_DASK_SCRATCH))


def pytest_sessionfinish(session, exitstatus):
    if _HYPOTHESIS_TEMPORARY:
        shutil.rmtree(_HYPOTHESIS_HOME, ignore_errors=True)
    shutil.rmtree(_DASK_SCRATCH, ignore_errors=True)


@pytest.fixture
def source_copy(tmp_path):
    """``source_copy(path)``: a copy of a source tree of the checkout in a temporary folder."""

    def make(src: Path) -> Path:
        return copy_sources(src, tmp_path / f"copy-{src.name}")

    return make
