"""The command line: one-line errors, list/info, version."""

import json
import subprocess
import sys

import pytest

from faceretarget import __version__, errors
from faceretarget._args import parse_sets as parse_params
from faceretarget.cli import main


def run(*args):
    return subprocess.run(
        [sys.executable, "-m", "faceretarget.cli", *args], capture_output=True, text=True
    )


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
    assert (
        len(lines) == 1
        and lines[0].startswith("faceretarget: error:")
        and "no-such-method" in lines[0]
    )
    assert "Traceback" not in out.stderr


def test_debug_shows_traceback_and_keeps_the_exit_status():
    out = run("--debug", "info", "no-such-method")
    assert out.returncode == 2 and "Traceback" in out.stderr
    assert out.stderr.strip().splitlines()[-1].startswith("faceretarget: error:")


def test_every_subcommand_describes_itself():
    from faceretarget.cli import build_parser

    sub = next(a for a in build_parser()._actions if a.dest == "command")
    for name, parser in sub.choices.items():
        assert parser.description, f"`faceretarget {name} --help` has no description"
        for action in parser._actions:
            if action.dest != "help":
                assert action.help, (
                    f"`faceretarget {name}`: {action.option_strings or action.dest} has no help"
                )


def test_info_of_every_retargeter(capsys):
    assert main(["list", "--json"]) == 0
    names = [r["name"] for r in json.loads(capsys.readouterr().out)["retargeters"]]
    for name in names:
        assert main(["info", name]) == 0
        text = capsys.readouterr().out
        assert "parameters:" in text and name in text


def test_parse_params():
    assert parse_params(["alpha=0.5", "mode=range", "flag=true", "window=(1, 4)"]) == {
        "alpha": 0.5,
        "mode": "range",
        "flag": True,
        "window": (1, 4),
    }
    with pytest.raises(errors.InputError, match="KEY=VALUE"):
        parse_params(["alpha"])


def test_run_reports_missing_files_in_one_line(tmp_path):
    out = run(
        "run",
        "spacetime",
        "--source",
        str(tmp_path / "nope.c3d"),
        "--target",
        str(tmp_path / "rig.glb"),
        "--out",
        str(tmp_path / "o.glb"),
    )
    assert out.returncode != 0
    assert len(out.stderr.strip().splitlines()) == 1 and "Traceback" not in out.stderr
    assert not (tmp_path / "o.glb").exists()


# ---------------------------------------------------------------------------------------
# cases export + run on ordinary files
# ---------------------------------------------------------------------------------------
EXPORT_SPEC = "synthetic-human?resolution=500&n_frames=6"


@pytest.fixture(scope="module")
def exported(tmp_path_factory):
    folder = tmp_path_factory.mktemp("export") / "case"
    assert main(["cases", "export", EXPORT_SPEC, str(folder)]) == 0
    return folder


def _commands(folder):
    import shlex

    lines = (folder / "README.txt").read_text().splitlines()
    return {
        shlex.split(l)[2]: shlex.split(l)[1:]
        for l in (l.strip() for l in lines)
        if l.startswith("faceretarget run ")
    }


def test_cases_export_writes_every_part_as_ordinary_files(exported):
    import numpy as np

    import faceretarget as fr

    for name in (
        "source.pc2",
        "source_neutral.obj",
        "character.glb",
        "source_landmarks.json",
        "character_landmarks.json",
        "source_feature_lines.json",
        "character_feature_lines.json",
        "source_examples.npz",
        "character_examples.npz",
        "source_layers.npz",
        "character_layers.npz",
        "truth.npz",
        "case.npz",
        "batch.toml",
        "README.txt",
    ):
        assert (exported / name).is_file(), name
    case = fr.cases.synthetic(resolution=500, n_frames=6)
    lm = json.loads((exported / "character_landmarks.json").read_text())
    assert lm["vertex_ids"] == case.target.landmarks.vertex_ids.tolist() and lm["names"] == list(
        case.target.landmarks.names
    )
    lines = json.loads((exported / "source_feature_lines.json").read_text())
    assert {k: list(v) for k, v in case.source.feature_lines.items()} == lines
    source = fr.io.load_source(exported / "source.pc2", topology=exported / "source_neutral.obj")
    assert np.allclose(source.performance.vertices, case.source.performance.vertices, atol=1e-5)
    assert set(_commands(exported)) == {
        "spacetime",
        "layers",
        "normalmesh",
        "coating",
        "deformation_transfer",
    }
    assert (
        main(["cases", "export", EXPORT_SPEC, str(exported)]) == 2
    )  # never into a folder that holds files


@pytest.mark.parametrize(
    "method", ["spacetime", "layers", "normalmesh", "coating", "deformation_transfer"]
)
def test_every_method_runs_from_the_exported_files_as_on_the_case(
    exported, method, tmp_path, monkeypatch
):
    """`run` on the plain files (take + neutral, glb, json, npz) gives the in-Python result."""
    import numpy as np

    import faceretarget as fr

    argv = _commands(exported)[method]
    out = tmp_path / f"{method}.npz"
    argv[argv.index("--out") + 1] = str(out)
    monkeypatch.chdir(exported)
    assert main(argv) == 0
    case = fr.io.load_bundle(exported / "case.npz")
    expected = fr.get(method).fit(case.source, case.target).retarget(case.source)
    got = fr.io.load(out, kind="animation")
    size = np.ptp(case.target.neutral.vertices, axis=0).max()
    assert np.abs(np.asarray(got.vertices) - np.asarray(expected.vertices)).max() < 1e-4 * size


def test_a_missing_part_names_the_option_that_gives_it(exported, tmp_path, monkeypatch):
    monkeypatch.chdir(exported)
    out = run(
        "run",
        "coating",
        "--source",
        "source.pc2",
        "--source-neutral",
        "source_neutral.obj",
        "--target",
        "character.glb",
        "--out",
        str(tmp_path / "o.glb"),
    )
    assert out.returncode == 2 and "Traceback" not in out.stderr
    assert "--feature-lines" in out.stderr and "--source-feature-lines" in out.stderr
    assert not (tmp_path / "o.glb").exists()


def test_run_help_describes_every_part_option():
    out = run("run", "--help")
    for option in (
        "--source-landmarks",
        "--source-feature-lines",
        "--source-examples",
        "--source-neutral",
        "--topology",
        "--actor-layers",
        "--landmarks",
        "--feature-lines",
        "--examples",
        "--layers",
        "--source-kind",
        "--target-kind",
    ):
        assert option in out.stdout, option


def test_compare_takes_cases_as_an_option(monkeypatch):
    from faceretarget.cli import build_parser
    from faceretarget.evaluation import harness

    seen = {}

    class Stop(Exception):
        pass

    def fake_compare(cases, **kwargs):
        seen["cases"] = cases
        raise Stop

    monkeypatch.setattr(harness, "compare", fake_compare)
    args = build_parser().parse_args(
        ["compare", "--cases", "synthetic", "ict", "--methods", "spacetime"]
    )
    with pytest.raises(Stop):
        args.handler(args)
    assert seen["cases"] == ["synthetic", "ict"]


def test_cases_list_names_the_builtin_cases(capsys):
    assert main(["cases", "list"]) == 0
    text = capsys.readouterr().out
    assert "synthetic-human" in text and "ict" in text
