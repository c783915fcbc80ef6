"""Helpers that keep the tests out of the user's environment and the checkout.

Import as ``from envtools import ...`` (``tests/`` is on the test path).
"""

from __future__ import annotations

import shutil
import subprocess
import sys
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
#: What a copy of a source tree leaves out: build output, caches, installed metadata.
BUILD_LITTER = (
    "build",
    "dist",
    "*.egg-info",
    "__pycache__",
    ".hypothesis",
    ".pytest_cache",
    ".numba_cache",
)


def copy_sources(src: Path, dest: Path) -> Path:
    """A copy of the source tree ``src`` at ``dest`` without build output, caches, version
    control or demo output."""
    shutil.copytree(
        src,
        dest,
        ignore=shutil.ignore_patterns(*BUILD_LITTER, ".git", "faceretarget-demo*", "out"),
        symlinks=True,
    )
    return dest


def pip_install_target(project: Path, target: Path, workdir: Path) -> subprocess.CompletedProcess:
    """``pip install --target target`` of a copy of ``project`` (no dependencies, no build
    isolation: offline): the environment running the tests and the checkout stay as they are."""
    copy = copy_sources(project, workdir / f"src-{project.name}")
    return subprocess.run(
        [
            sys.executable,
            "-m",
            "pip",
            "install",
            "--no-deps",
            "--no-build-isolation",
            "--no-compile",
            "--quiet",
            "--disable-pip-version-check",
            "--target",
            str(target),
            str(copy),
        ],
        capture_output=True,
        text=True,
        cwd=workdir,
    )
