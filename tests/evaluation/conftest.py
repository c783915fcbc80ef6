"""Fixtures of the evaluation tests: the tiny case and a registry with fake retargeters."""

import sys
from pathlib import Path

import pytest

sys.path.insert(0, str(Path(__file__).parent))

import fake_retargeters  # noqa: E402


@pytest.fixture(scope="session")
def tiny():
    return fake_retargeters.tiny_case()


@pytest.fixture(scope="session")
def fake_registry():
    return fake_retargeters.fake_registry()
