"""Every environment variable faceretarget reads is documented."""

from pathlib import Path

import pytest

from faceretarget import config

ROOT = Path(__file__).resolve().parents[2]
VARIABLES = sorted(value for name, value in vars(config).items() if name.startswith("ENV_"))


@pytest.mark.parametrize("variable", VARIABLES)
def test_environment_variable_is_documented(variable):
    docs = [ROOT / "README.md", *sorted((ROOT / "docs").glob("*.md"))]
    assert any(variable in path.read_text(encoding="utf-8") for path in docs), (
        f"{variable} is read by faceretarget but documented nowhere"
    )
