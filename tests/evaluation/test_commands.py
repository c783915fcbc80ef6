"""`faceretarget compare`, `demo` and `batch` through the CLI entry point."""

import csv
import json
import textwrap
from pathlib import Path

import pytest

from faceretarget._args import parse_sets
from faceretarget.cli import main
from faceretarget.errors import ConfigError, OutputError
from faceretarget.evaluation.commands import _new_folder, demo_cases

SMALL = "synthetic?resolution=200&n_frames=6"


def test_compare_writes_tables_and_report(tmp_path, capsys):
    code = main(
        [
            "compare",
            SMALL,
            "--methods",
            "spacetime",
            "deformation_transfer",
            "--set",
            "spacetime.alpha=0.02",
            "--out",
            str(tmp_path / "rep"),
            "--csv",
            str(tmp_path / "t.csv"),
            "--json",
            str(tmp_path / "t.json"),
            "--quiet",
        ]
    )
    out = capsys.readouterr().out
    assert code == 0
    assert "spacetime" in out and "deformation_transfer" in out and "report:" in out
    with open(tmp_path / "t.csv") as fh:
        rows = list(csv.DictReader(fh))
    assert {r["method"] for r in rows} == {"spacetime", "deformation_transfer"}
    runs = json.loads((tmp_path / "t.json").read_text())["runs"]
    assert next(r for r in runs if r["method"] == "spacetime")["parameters"]["alpha"] == 0.02
    assert (tmp_path / "rep" / "report.html").stat().st_size > 10_000


def test_compare_errors_are_one_line(capsys):
    assert main(["compare", SMALL, "--set", "alpha=1"]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert err == [
        "faceretarget: error: --set 'alpha=1': expected METHOD.PARAM=VALUE, e.g. --set METHOD.alpha=0.05"
    ]
    assert main(["compare", "nosuchcase"]) == 2
    assert "valid cases" in capsys.readouterr().err


def test_demo_writes_report_table_and_glb(tmp_path, capsys):
    out = tmp_path / "demo"
    code = main(
        [
            "demo",
            "--out",
            str(out),
            "--frames",
            "4",
            "--methods",
            "spacetime",
            "--no-presets",
            "--quiet",
        ]
    )
    printed = capsys.readouterr().out
    assert code == 0 and f"report:  {out / 'report.html'}" in printed
    with open(out / "results.csv") as fh:
        rows = list(csv.DictReader(fh))
    assert {(r["case"], r["method"]) for r in rows} == {
        (c, "spacetime") for c in ("synthetic-human", "synthetic-stylized", "ict")
    }
    glbs = sorted(p.name for p in (out / "glb").iterdir())
    assert glbs == [
        "ict-spacetime.glb",
        "synthetic-human-spacetime.glb",
        "synthetic-stylized-spacetime.glb",
    ]
    assert all((out / "glb" / g).read_bytes()[:4] == b"glTF" for g in glbs)
    # never overwrites
    assert (
        main(
            [
                "demo",
                "--out",
                str(out),
                "--frames",
                "4",
                "--methods",
                "spacetime",
                "--no-presets",
                "--quiet",
            ]
        )
        == 2
    )
    assert "never overwrites" in capsys.readouterr().err


def test_demo_folder_is_always_new(tmp_path, monkeypatch):
    monkeypatch.chdir(tmp_path)
    first, second = _new_folder(None, "faceretarget-demo"), _new_folder(None, "faceretarget-demo")
    assert (
        first != second
        and first.parent == second.parent == tmp_path
        and first.name.startswith("faceretarget-demo-")
    )
    (tmp_path / "taken").mkdir()
    (tmp_path / "taken" / "x").write_text("keep")
    with pytest.raises(OutputError):
        _new_folder(tmp_path / "taken", "x")
    assert demo_cases(10)["ict"] == "ict?n_frames=10"
    with pytest.raises(ConfigError):
        demo_cases(1)
    assert parse_sets(["a.b=1", "a.c=x", "d.e=[1, 2]"], per_method=True) == {
        "a": {"b": 1, "c": "x"},
        "d": {"e": [1, 2]},
    }


def test_batch_command(tmp_path, capsys):
    manifest = tmp_path / "shots.toml"
    manifest.write_text(
        textwrap.dedent(f"""
        [defaults]
        method = "spacetime"
        shot = "case:{SMALL}"
        [[job]]
        out = "out/a.glb"
        [[job]]
        out = "out/b.glb"
        params = {{ alpha = 0.5 }}
    """)
    )
    assert main(["batch", str(manifest), "--check"]) == 0
    assert "2 job(s); manifest OK" in capsys.readouterr().out
    assert (
        main(
            [
                "batch",
                str(manifest),
                "--workers",
                "1",
                "--quiet",
                "--summary",
                str(tmp_path / "summary.json"),
            ]
        )
        == 0
    )
    assert "2 done, 0 skipped" in capsys.readouterr().out
    assert (tmp_path / "out" / "a.glb").read_bytes()[:4] == b"glTF"
    assert json.loads((tmp_path / "summary.json").read_text())["done"] == 2
    assert main(["batch", str(manifest), "--quiet"]) == 0
    assert "0 done, 2 skipped" in capsys.readouterr().out
    Path(manifest).write_text(manifest.read_text() + '[[job]]\nout = "../escape.glb"\n')
    assert main(["batch", str(manifest)]) == 2
    assert "outside the manifest's folder" in capsys.readouterr().err
