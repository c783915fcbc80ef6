"""The benchmark scripts import, ``run_all.py --help`` works, and the documentation quotes no
timing figure that the generated ``docs/performance.md`` does not contain.

No timing is measured or asserted here: speed goals live in ``benchmarks/``.
"""

from __future__ import annotations

import importlib.util
import re
import subprocess
import sys
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]
BENCH = ROOT / "benchmarks"
SCRIPTS = sorted(p for p in BENCH.glob("*.py"))

#: Figures quoted from the papers (or otherwise not measurements of this project), each with
#: the text that must surround it.
ALLOW = (
    "47.38 s in Matlab",
    "~127 ms",
    "127 ms on 8 cores",
)

#: A timing figure: a number with ms / us, frames/s, "x faster|slower", "x spsolve", KB a frame.
FIGURE = re.compile(
    r"(?<![\w.])(~?\d[\d,]*(?:\.\d+)?)\s?"
    r"(ms|us|µs|frames/s|frames per second|x faster|x slower|x spsolve|x (?:the )?spsolve|KB a frame|KB/frame|KB per frame)\b",
    re.IGNORECASE,
)


def _docs():
    files = [ROOT / "README.md", *sorted((ROOT / "docs").rglob("*.md"))]
    return [f for f in files if f.name != "performance.md" and f.exists()]


@pytest.mark.parametrize("path", SCRIPTS, ids=[p.name for p in SCRIPTS])
def test_script_imports(path, monkeypatch):
    monkeypatch.syspath_prepend(str(BENCH))
    spec = importlib.util.spec_from_file_location(f"_bench_{path.stem}", path)
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)  # module level only: nothing runs without __main__
    if path.name.startswith("bench_") or path.name == "run_all.py":
        assert callable(getattr(module, "main", None)), f"{path.name} has no main()"


def test_run_all_help():
    proc = subprocess.run(
        [sys.executable, str(BENCH / "run_all.py"), "--help"],
        capture_output=True,
        text=True,
        timeout=120,
    )
    assert proc.returncode == 0, proc.stderr
    assert "--quick" in proc.stdout and "performance.md" in proc.stdout


def test_run_all_covers_every_timing_script():
    spec = importlib.util.spec_from_file_location("_bench_run_all", BENCH / "run_all.py")
    module = importlib.util.module_from_spec(spec)
    sys.path.insert(0, str(BENCH))
    try:
        spec.loader.exec_module(module)
    finally:
        sys.path.remove(str(BENCH))
    timing = {p.stem for p in SCRIPTS if p.stem.startswith("bench_")} - {"bench_dense_fidelity"}
    assert timing <= set(module.SCRIPTS)


def _figures(text: str):
    for m in FIGURE.finditer(text):
        line_start = text.rfind("\n", 0, m.start()) + 1
        line_end = text.find("\n", m.end())
        yield m.group(0), text[line_start : line_end if line_end >= 0 else len(text)]


def test_docs_quote_only_generated_figures():
    perf = ROOT / "docs" / "performance.md"
    generated = perf.read_text() if perf.exists() else ""
    flat = lambda s: re.sub(r"\s+", " ", s)  # noqa: E731
    bad = []
    for path in _docs():
        text = path.read_text()
        for figure, line in _figures(text):
            if any(a in flat(line) for a in ALLOW):
                continue
            if flat(figure) in flat(generated):
                continue
            bad.append(f"{path.relative_to(ROOT)}: {figure!r} in: {line.strip()[:160]}")
    assert not bad, (
        "timing figures not reproduced by benchmarks/run_all.py (docs/performance.md); quote that file "
        "or add a paper figure to ALLOW:\n" + "\n".join(bad)
    )


def test_figure_pattern():
    found = [
        f
        for f, _ in _figures(
            "solve 2.5 ms; 1,400-2,000x faster; 3,160 frames/s; 2.4 KB a frame; 0.5 s"
        )
    ]
    assert found == ["2.5 ms", "2,000x faster", "3,160 frames/s", "2.4 KB a frame"]
