"""One broken plugin never takes down the rest, and is reported with its name and distribution.

A fake installed distribution ``brokenplugins`` (a ``.dist-info`` folder on a temporary
``sys.path`` entry, as pip would leave it) brings plugins that raise on import, raise in
``fit`` or ``retarget``, return the wrong number of vertices or frames, or NaN, never
finish (sleeping, or spinning in a loop), kill their own process, and one that works. A
second distribution ``slowplugins`` takes a minute to import. ``faceretarget list``, ``compare``, ``batch`` and ``run`` must go on with
the others, name the culprit and its distribution, and never write a wrong result.
"""

import importlib
import json
import textwrap

import numpy as np
import pytest
from reliability.fuzzkit import count

import faceretarget as fr
from faceretarget import cli
from faceretarget import registry as registry_module
from faceretarget.registry import Registry

AREA = "plugin isolation"
DIST = "brokenplugins"

COMMON = """
import numpy as np
import faceretarget as fr


class Base(fr.Retargeter):
    capabilities = fr.Capabilities(sources=("mesh", "markers"))

    def __init__(self, *, gain=1.0):
        self.gain = gain

    def _fit(self, source, target):
        self.neutral_ = np.asarray(target.neutral.vertices)

    def _result(self, source, vertices):
        return fr.Animation(vertices=vertices, triangles=None, fps=source.fps)

    def _retarget(self, source):
        return self._result(source, np.repeat(self.neutral_[None], source.n_frames, axis=0))
"""

PLUGINS = {
    "bp_good": "class Good(Base):\n    name = 'bp_good'\nCLS = Good\n",
    "bp_fit": "class Fit(Base):\n    name = 'bp_fit'\n    def _fit(self, source, target):\n        raise RuntimeError('fit exploded')\nCLS = Fit\n",
    "bp_retarget": "class Ret(Base):\n    name = 'bp_retarget'\n    def _retarget(self, source):\n        return 1 / 0\nCLS = Ret\n",
    "bp_vertices": (
        "class Verts(Base):\n    name = 'bp_vertices'\n"
        "    def _retarget(self, source):\n"
        "        return self._result(source, np.repeat(self.neutral_[None, :-1], source.n_frames, axis=0))\nCLS = Verts\n"
    ),
    "bp_frames": (
        "class Frames(Base):\n    name = 'bp_frames'\n"
        "    def _retarget(self, source):\n"
        "        return self._result(source, self.neutral_[None])\nCLS = Frames\n"
    ),
    "bp_nan": (
        "class Nan(Base):\n    name = 'bp_nan'\n"
        "    def _retarget(self, source):\n"
        "        anim = Base._retarget(self, source)\n"
        "        bad = np.array(anim.vertices); bad[0, 0, 0] = np.nan; bad.flags.writeable = False\n"
        "        anim._vertices = bad  # sneaks NaN past the Animation constructor\n"
        "        return anim\nCLS = Nan\n"
    ),
    "bp_type": "class Typ(Base):\n    name = 'bp_type'\n    def _retarget(self, source):\n        return {'vertices': self.neutral_}\nCLS = Typ\n",
    # sys.exit(0) in fit once made `faceretarget run` exit 0 with no output and no message (issue 15, hole 10)
    "bp_sysexit": "import sys\nclass SysExit(Base):\n    name = 'bp_sysexit'\n    def _fit(self, source, target):\n        sys.exit(0)\nCLS = SysExit\n",
}
BAD = ["bp_fit", "bp_retarget", "bp_vertices", "bp_frames", "bp_nan", "bp_type", "bp_sysexit"]
#: Plugins that never return or take their process down (only run under a time limit).
SLOW = {
    "bp_sleep": "import time\nclass Sleep(Base):\n    name = 'bp_sleep'\n    def _retarget(self, source):\n        time.sleep(3600)\nCLS = Sleep\n",
    "bp_spin": "class Spin(Base):\n    name = 'bp_spin'\n    def _fit(self, source, target):\n        while True:\n            pass\nCLS = Spin\n",
    "bp_exit": "import os\nclass Exit(Base):\n    name = 'bp_exit'\n    def _retarget(self, source):\n        os._exit(9)\nCLS = Exit\n",
}


def plugin_module(name: str) -> str:
    return (
        COMMON
        + {**PLUGINS, **SLOW}[name]
        + "\n@fr.hookimpl\ndef faceretarget_retargeters():\n    return [CLS]\n"
    )


@pytest.fixture(scope="module")
def site(tmp_path_factory):
    """The fake distribution on disk: one module per plugin + one that fails to import."""
    root = tmp_path_factory.mktemp("site")
    info = root / f"{DIST}-0.3.dist-info"
    info.mkdir()
    (info / "METADATA").write_text(f"Metadata-Version: 2.1\nName: {DIST}\nVersion: 0.3\n")
    modules = {name: plugin_module(name) for name in [*PLUGINS, *SLOW]}
    modules["bp_import"] = "raise RuntimeError('import exploded')\n"
    for name, code in modules.items():
        (root / f"{name}.py").write_text(textwrap.dedent(code))
    (info / "entry_points.txt").write_text(
        "[faceretarget]\n" + "\n".join(f"{n} = {n}" for n in modules) + "\n"
    )
    return root


@pytest.fixture
def reg(site, monkeypatch):
    """A registry loaded with the fake distribution installed, used as the process-wide one."""
    monkeypatch.syspath_prepend(str(site))
    monkeypatch.setenv("PYTHONPATH", str(site))  # for spawned batch workers
    monkeypatch.delenv("FACERETARGET_DISABLE_PLUGINS", raising=False)
    monkeypatch.delenv("FACERETARGET_PLUGINS", raising=False)
    importlib.invalidate_caches()
    loaded = Registry().load()
    monkeypatch.setattr(registry_module, "_REGISTRY", loaded)
    return loaded


@pytest.fixture(scope="module")
def case():
    return fr.cases.synthetic(resolution=300, n_frames=4)


def named(text: str, plugin: str) -> bool:
    return plugin in text and DIST in text


def test_import_failure_is_recorded_and_others_load(reg):
    count(AREA)
    failures = {f.name: f for f in reg.failures}
    assert "bp_import" in failures and failures["bp_import"].distribution == DIST
    assert "import exploded" in failures["bp_import"].error
    for name in PLUGINS:
        assert name in reg.retargeters, f"{name} was not loaded next to the broken plugin"
    builtins = [n for n, e in reg.retargeters.items() if e.plugin.builtin]
    assert builtins, "the built-in retargeters must still load"


def test_list_goes_on_and_names_the_broken_plugin(reg, capsys):
    count(AREA)
    assert cli.main(["list"]) == 0
    out = capsys.readouterr().out
    for name in PLUGINS:
        assert name in out
    failed = out.split("plugins that failed to load:")[1]
    assert named(failed, "bp_import") and "import exploded" in failed
    assert cli.main(["list", "--json"]) == 0
    data = json.loads(capsys.readouterr().out)
    assert {k: data["failed_plugins"][0][k] for k in ("plugin", "distribution")} == {
        "plugin": "bp_import",
        "distribution": DIST,
    }


def test_compare_goes_on_and_names_each_failure(reg, case):
    from faceretarget.evaluation import compare

    result = compare([case], methods=list(PLUGINS), registry=reg, metrics=["vertex_error_mean"])
    runs = {r.method: r for r in result.runs}
    count(AREA, len(runs))
    assert runs["bp_good"].status == "ok"
    for name in BAD:
        run = runs[name]
        assert run.status == "error", f"{name}: {run.status} {run.reason}"
        assert named(run.reason, name), (
            f"{name}: the reason must name the plugin and its distribution: {run.reason}"
        )
    assert (
        runs["bp_vertices"].error["type"] == "PluginOutputError"
        and runs["bp_nan"].error["type"] == "PluginOutputError"
    )


@pytest.fixture
def bundles(case, tmp_path):
    src, tgt = tmp_path / "source.npz", tmp_path / "target.npz"
    fr.io.save_bundle(case.source, src)
    fr.io.save_bundle(case.target, tgt)
    return src, tgt


def batch_manifest(folder, bundles, names, extra=None):
    """``folder/shots.toml`` with one job per plugin in ``names`` (outputs under ``out/``)."""
    src, tgt = bundles
    jobs = [
        f'[[job]]\nshot = "{src.name}"\ncharacter = "{tgt.name}"\nmethod = "{n}"\nout = "out/{n}.npz"\n'
        for n in names
    ]
    for n, lines in (extra or {}).items():
        jobs[names.index(n)] += lines
    (folder / "out").mkdir()
    manifest = folder / "shots.toml"
    manifest.write_text("\n".join(jobs))
    return manifest


@pytest.mark.parametrize("name", BAD)
def test_run_refuses_to_write_a_broken_result(name, reg, bundles, tmp_path, capsys):
    src, tgt = bundles
    out = tmp_path / "out.npz"
    count(AREA)
    code = cli.main(["run", name, "--source", str(src), "--target", str(tgt), "--out", str(out)])
    err = capsys.readouterr().err
    assert code == cli.EXIT_ERROR, err
    errors = [
        line
        for line in err.strip().splitlines()
        if not line.startswith("faceretarget: warning: plugin")
    ]
    assert len(errors) == 1 and "Traceback" not in err, (
        err
    )  # warnings name the plugins that were skipped (bp_import)
    err = errors[0]
    assert named(err, name), f"the error must name the plugin and its distribution: {err}"
    assert not out.exists(), "nothing may be written for a failed or invalid result"
    assert sorted(p.name for p in tmp_path.iterdir()) == ["source.npz", "target.npz"]


def test_run_good_plugin_writes(reg, bundles, tmp_path, capsys):
    src, tgt = bundles
    out = tmp_path / "out.npz"
    assert (
        cli.main(["run", "bp_good", "--source", str(src), "--target", str(tgt), "--out", str(out)])
        == 0
    ), capsys.readouterr().err
    assert np.asarray(fr.load(out, kind="animation").vertices).shape[0] == 4


def batch_with_failures(tmp_path, bundles, reg, bad, extra=None, **options):
    """Run bp_good and the plugins ``bad`` as a batch: bp_good's job is done and is the only
    output, every other job failed naming its plugin and distribution; returns the results."""
    from faceretarget.evaluation.batch import run_batch

    summary = run_batch(
        batch_manifest(tmp_path, bundles, ["bp_good", *bad], extra),
        registry=reg,
        progress=False,
        **options,
    )
    results = {r.name: r for r in summary.results}
    count(AREA, len(results))
    assert results.pop("out/bp_good.npz").status == "done"
    assert sorted(p.name for p in (tmp_path / "out").iterdir()) == ["bp_good.npz"], (
        "failed jobs must write nothing"
    )
    for _name, r in results.items():
        assert r.status == "failed" and named(r.error, r.method), (
            f"batch must name the plugin and its distribution: {r.error}"
        )
    return results


def test_batch_goes_on_and_names_each_failure(reg, bundles, tmp_path):
    assert len(batch_with_failures(tmp_path, bundles, reg, BAD, workers=1)) == len(BAD)


# ---------------------------------------------------------------------------------------
# Very slow plugins: stopped at their time limit, reported, the rest goes on
# ---------------------------------------------------------------------------------------
LIMIT = 2.0


def test_compare_stops_slow_and_crashing_plugins_and_goes_on(reg, case):
    from faceretarget.evaluation import compare

    result = compare(
        [case],
        methods=["bp_good", *SLOW],
        registry=reg,
        metrics=["vertex_error_mean"],
        timeout=LIMIT,
        n_jobs=2,
    )
    runs = {r.method: r for r in result.runs}
    count(AREA, len(runs))
    assert (
        runs["bp_good"].status == "ok"
        and result.value(runs["bp_good"].case, "bp_good", "vertex_error_mean") is not None
    )
    for name in SLOW:
        run = runs[name]
        assert run.status == "error" and named(run.reason, name), (
            f"{name}: {run.status} {run.reason}"
        )
    for name in ("bp_sleep", "bp_spin"):
        assert runs[name].error["type"] == "PluginTimeoutError"
        assert f"did not finish within its time limit of {LIMIT:g} s" in runs[name].reason
    assert "exited with code 9" in runs["bp_exit"].reason
    rows = [row for row in result.rows if row["method"] in SLOW]
    assert rows and all(row["status"] == "error" and row["value"] is None for row in rows)


def test_compare_command_reports_a_slow_plugin(reg, capsys):
    count(AREA)
    spec = "synthetic?resolution=300&n_frames=4"
    code = cli.main(
        [
            "compare",
            spec,
            "--methods",
            "bp_good",
            "bp_sleep",
            "--metrics",
            "vertex_error_mean",
            "--timeout",
            str(LIMIT),
            "--quiet",
        ]
    )
    captured = capsys.readouterr()
    out = captured.out
    assert code == cli.EXIT_FAILED, (
        "a compare in which a method failed must not exit 0 (issue 15, hole 10)"
    )
    assert "1 of 2 runs failed" in captured.err and "--keep-going" in captured.err
    line = next(line for line in out.splitlines() if "bp_sleep:" in line)
    assert "error" in line and named(line, "bp_sleep") and "PluginTimeoutError" in line


def test_batch_stops_slow_and_crashing_jobs_and_goes_on(reg, bundles, tmp_path):
    extra = {"bp_sleep": "timeout = 1.5\n"}  # a job's own limit wins over the batch's
    results = batch_with_failures(
        tmp_path, bundles, reg, list(SLOW), extra, workers=2, timeout=LIMIT
    )
    assert (
        "PluginTimeoutError: did not finish within its time limit of 1.5 s"
        in results["out/bp_sleep.npz"].error
    )
    assert f"time limit of {LIMIT:g} s" in results["out/bp_spin.npz"].error
    assert "PluginError: its worker process exited with code 9" in results["out/bp_exit.npz"].error


@pytest.fixture
def slow_site(tmp_path, monkeypatch):
    """A distribution with one plugin that takes a minute to import and one that is fine."""
    info = tmp_path / "slowplugins-1.0.dist-info"
    info.mkdir()
    (info / "METADATA").write_text("Metadata-Version: 2.1\nName: slowplugins\nVersion: 1.0\n")
    (tmp_path / "sp_slow_import.py").write_text("import time\ntime.sleep(60)\n")
    (
        tmp_path / "sp_stubborn_import.py"
    ).write_text(  # swallows what it can, as import machinery does
        "import os, time\nend = time.monotonic() + 60\nwhile time.monotonic() < end:\n"
        "    try:\n        time.sleep(0.05)\n        os.stat('/no/such/file')\n    except (OSError, Exception):\n        pass\n"
    )
    (tmp_path / "sp_quick.py").write_text(
        textwrap.dedent(plugin_module("bp_good").replace("bp_good", "sp_quick"))
    )
    (tmp_path / "sp_slow_hook.py").write_text(
        "import time\nimport faceretarget as fr\n@fr.hookimpl\ndef faceretarget_retargeters():\n    time.sleep(60)\n    return []\n"
    )
    names = ("sp_slow_import", "sp_stubborn_import", "sp_quick", "sp_slow_hook")
    (info / "entry_points.txt").write_text(
        "[faceretarget]\n" + "".join(f"{n} = {n}\n" for n in names)
    )
    monkeypatch.syspath_prepend(str(tmp_path))
    monkeypatch.delenv("FACERETARGET_DISABLE_PLUGINS", raising=False)
    monkeypatch.setenv("FACERETARGET_PLUGINS", "slowplugins")
    monkeypatch.setenv("FACERETARGET_IMPORT_TIMEOUT", "1")
    importlib.invalidate_caches()
    return tmp_path


def test_a_plugin_slow_to_import_is_skipped_and_named(slow_site, monkeypatch, capsys):
    loaded = Registry().load()
    count(AREA, 4)
    failures = {f.name: f for f in loaded.failures}
    assert set(failures) == {"sp_slow_import", "sp_stubborn_import", "sp_slow_hook"}
    assert "took longer than 1 s importing" in failures["sp_slow_import"].error
    assert "took longer than 1 s importing" in failures["sp_stubborn_import"].error
    assert "took longer than 1 s calling its registration hooks" in failures["sp_slow_hook"].error
    assert all(
        f.distribution == "slowplugins" and "FACERETARGET_IMPORT_TIMEOUT" in f.error
        for f in failures.values()
    )
    assert "sp_quick" in loaded.retargeters and any(
        e.plugin.builtin for e in loaded.retargeters.values()
    )
    monkeypatch.setattr(registry_module, "_REGISTRY", loaded)
    assert cli.main(["list"]) == 0
    failed = capsys.readouterr().out.split("plugins that failed to load:")[1]
    assert (
        "sp_slow_import" in failed and "slowplugins" in failed and "took longer than 1 s" in failed
    )


def test_no_import_time_limit_loads_third_party_plugins(tmp_path, monkeypatch):
    """FACERETARGET_IMPORT_TIMEOUT=0 means no limit: a third-party plugin still loads (the
    message for a stuck plugin was once built from the limit even when there was none, and
    every third-party plugin failed with a TypeError)."""
    info = tmp_path / "quickplugins-1.0.dist-info"
    info.mkdir()
    (info / "METADATA").write_text("Metadata-Version: 2.1\nName: quickplugins\nVersion: 1.0\n")
    (tmp_path / "qp_quick.py").write_text(
        textwrap.dedent(plugin_module("bp_good").replace("bp_good", "qp_quick"))
    )
    (info / "entry_points.txt").write_text("[faceretarget]\nqp_quick = qp_quick\n")
    monkeypatch.syspath_prepend(str(tmp_path))
    monkeypatch.delenv("FACERETARGET_DISABLE_PLUGINS", raising=False)
    monkeypatch.setenv("FACERETARGET_PLUGINS", "quickplugins")
    monkeypatch.setenv("FACERETARGET_IMPORT_TIMEOUT", "0")
    importlib.invalidate_caches()
    loaded = Registry().load()
    assert loaded.failures == []
    assert "qp_quick" in loaded.retargeters


def test_dask_batch_stops_a_slow_job(reg, bundles, tmp_path):
    """On Dask (daemonic worker processes) a job with a limit runs in a child process of its own."""
    pytest.importorskip("distributed")
    results = batch_with_failures(
        tmp_path, bundles, reg, ["bp_sleep"], executor="dask", workers=2, timeout=LIMIT
    )
    assert "PluginTimeoutError" in results["out/bp_sleep.npz"].error


# ---------------------------------------------------------------------------------------
# Hooks that return the wrong thing (issue 15, hole 6): one bad hook once made `list`,
# `formats`, `run` and `batch --check` all exit 3 with an internal TypeError
# ---------------------------------------------------------------------------------------
HOOK_PLUGINS = {
    "hp_int_readers": "@fr.hookimpl\ndef faceretarget_readers():\n    return 42\n",
    "hp_int_retargeters": "@fr.hookimpl\ndef faceretarget_retargeters():\n    return 42\n",
    "hp_str_metrics": "@fr.hookimpl\ndef faceretarget_metrics():\n    return 'abc'\n",
    "hp_bad_reader": (
        "@fr.hookimpl\ndef faceretarget_readers():\n"
        "    return [fr.Reader(name='hp', kind='mesh', extensions=42, read=print)]\n"
    ),
    "hp_bad_writer": (
        "@fr.hookimpl\ndef faceretarget_writers():\n"
        "    return [fr.Writer(name=7, kind='animation', extensions=('.hp',), write=print)]\n"
    ),
    "hp_bad_aliases": (
        "class Aliased(fr.Retargeter):\n    name = 'hp_aliased'\n    aliases = 42\n"
        "    capabilities = fr.Capabilities(sources=('mesh',))\n"
        "@fr.hookimpl\ndef faceretarget_retargeters():\n    return [Aliased]\n"
    ),
}
#: plugin -> the hook its error must name
HOOK_OF = {
    "hp_int_readers": "faceretarget_readers",
    "hp_int_retargeters": "faceretarget_retargeters",
    "hp_str_metrics": "faceretarget_metrics",
    "hp_bad_reader": "faceretarget_readers",
    "hp_bad_writer": "faceretarget_writers",
}


@pytest.fixture
def hook_site(tmp_path, monkeypatch):
    """A distribution ``hookplugins``: hooks returning 42, a string, invalid records, and
    one good retargeter (hp_good); loaded by the command itself (no registry cached)."""
    root = tmp_path / "site"
    info = root / "hookplugins-2.0.dist-info"
    info.mkdir(parents=True)
    (info / "METADATA").write_text("Metadata-Version: 2.1\nName: hookplugins\nVersion: 2.0\n")
    modules = {name: "import faceretarget as fr\n" + code for name, code in HOOK_PLUGINS.items()}
    modules["hp_good"] = textwrap.dedent(plugin_module("bp_good").replace("bp_good", "hp_good"))
    for name, code in modules.items():
        (root / f"{name}.py").write_text(code)
    (info / "entry_points.txt").write_text(
        "[faceretarget]\n" + "".join(f"{n} = {n}\n" for n in modules)
    )
    monkeypatch.syspath_prepend(str(root))
    monkeypatch.setenv("PYTHONPATH", str(root))
    monkeypatch.delenv("FACERETARGET_DISABLE_PLUGINS", raising=False)
    monkeypatch.setenv("FACERETARGET_PLUGINS", "hookplugins")
    monkeypatch.setattr(registry_module, "_REGISTRY", None)
    monkeypatch.setattr(registry_module, "_CATALOGUE", None)
    importlib.invalidate_caches()
    return root


def test_a_hook_returning_the_wrong_type_skips_only_its_plugin(hook_site):
    loaded = Registry().load()
    count(AREA, len(HOOK_PLUGINS))
    failures = {f.name: f for f in loaded.failures}
    assert set(failures) == set(HOOK_PLUGINS), failures
    for name, f in failures.items():
        assert (
            f.distribution == "hookplugins" and name in f.error and "hookplugins 2.0" in f.error
        ), f.error
        if name in HOOK_OF:
            assert HOOK_OF[name] in f.error, f"the error must name the hook: {f.error}"
    assert "returned 42 (int), expected a list" in failures["hp_int_readers"].error
    assert "hp_good" in loaded.retargeters and "hp_aliased" not in loaded.retargeters
    assert not any(r.name == "hp" for r, _ in loaded.readers) and not any(
        w.name == 7 for w, _ in loaded.writers
    )


def warnings_name_each_skipped_plugin(err: str) -> None:
    lines = [line for line in err.splitlines() if line.startswith("faceretarget: warning: plugin")]
    for name in HOOK_PLUGINS:
        assert any(
            name in line and "hookplugins 2.0" in line and "was skipped" in line for line in lines
        ), err
    assert "internal error" not in err and "Traceback" not in err


def test_list_and_formats_go_on_past_a_bad_hook(hook_site, capsys):
    count(AREA, 2)
    assert cli.main(["list"]) == 0
    out = capsys.readouterr().out
    assert "hp_good" in out
    failed = out.split("plugins that failed to load:")[1]
    assert (
        all(name in failed for name in HOOK_PLUGINS)
        and "faceretarget_readers: returned 42" in failed
    )
    assert cli.main(["formats"]) == 0
    captured = capsys.readouterr()
    assert "readers:" in captured.out
    warnings_name_each_skipped_plugin(captured.err)


def test_run_and_batch_check_go_on_past_a_bad_hook(hook_site, bundles, tmp_path, capsys):
    src, tgt = bundles
    out = tmp_path / "out.npz"
    count(AREA, 2)
    code = cli.main(
        ["run", "hp_good", "--source", str(src), "--target", str(tgt), "--out", str(out)]
    )
    captured = capsys.readouterr()
    assert code == 0 and out.exists(), captured.err
    warnings_name_each_skipped_plugin(captured.err)
    manifest = tmp_path / "shots.toml"
    manifest.write_text(
        f'[[job]]\nshot = "{src.name}"\ncharacter = "{tgt.name}"\nmethod = "hp_good"\nout = "o.npz"\n'
    )
    assert cli.main(["batch", str(manifest), "--check"]) == 0
    captured = capsys.readouterr()
    assert "manifest OK" in captured.out
    warnings_name_each_skipped_plugin(captured.err)


# ---------------------------------------------------------------------------------------
# Exit codes that tell the truth (issue 15, hole 10)
# ---------------------------------------------------------------------------------------
def test_run_exits_non_zero_when_a_plugin_calls_sys_exit_0(site, bundles, tmp_path):
    """The attack as a user meets it: the real command in its own process."""
    import os
    import subprocess
    import sys

    src, tgt = bundles
    out = tmp_path / "out.npz"
    env = {
        **os.environ,
        "PYTHONPATH": os.pathsep.join([str(site), os.environ.get("PYTHONPATH", "")]),
        "FACERETARGET_PLUGINS": DIST,
    }
    env.pop("FACERETARGET_DISABLE_PLUGINS", None)
    proc = subprocess.run(
        [
            sys.executable,
            "-m",
            "faceretarget.cli",
            "run",
            "bp_sysexit",
            "--source",
            str(src),
            "--target",
            str(tgt),
            "--out",
            str(out),
        ],
        env=env,
        capture_output=True,
        text=True,
        timeout=300,
    )
    count(AREA)
    assert proc.returncode == cli.EXIT_ERROR, (proc.returncode, proc.stderr)
    assert (
        "SystemExit(0)" in proc.stderr and named(proc.stderr, "bp_sysexit") and "fit" in proc.stderr
    ), proc.stderr
    assert not out.exists()


def test_a_plugin_ending_the_program_elsewhere_is_not_a_success(reg, monkeypatch, capsys):
    """SystemExit raised outside a plugin call (a reader, a constructor): exit 2, with where it came from."""

    def leave(args):
        raise SystemExit(0)

    monkeypatch.setattr(cli, "cmd_formats", leave)
    count(AREA)
    parser_code = cli.main(["formats"])
    err = capsys.readouterr().err
    assert (
        parser_code == cli.EXIT_ERROR
        and "SystemExit(0)" in err
        and "test_plugin_isolation.py" in err
    )


@pytest.mark.parametrize("keep_going", [False, True])
def test_compare_exits_non_zero_when_a_method_failed(reg, capsys, keep_going):
    spec = "synthetic?resolution=300&n_frames=4"
    argv = [
        "compare",
        spec,
        "--methods",
        "bp_good",
        "bp_fit",
        "bp_sysexit",
        "--metrics",
        "vertex_error_mean",
        "--quiet",
        "--timeout",
        "0",
    ]
    count(AREA)
    code = cli.main(argv + (["--keep-going"] if keep_going else []))
    captured = capsys.readouterr()
    assert code == (0 if keep_going else cli.EXIT_FAILED), captured.err
    assert "2 of 3 runs failed" in captured.err
    assert (
        named(captured.out, "bp_sysexit") and "SystemExit" in captured.out
    )  # in-process (--timeout 0): still a failure


@pytest.mark.parametrize("keep_going", [False, True])
def test_batch_exits_non_zero_with_a_summary_when_a_job_failed(
    reg, bundles, tmp_path, capsys, keep_going
):
    manifest = batch_manifest(tmp_path, bundles, ["bp_good", "bp_sysexit"])
    count(AREA)
    code = cli.main(
        ["batch", str(manifest), "--workers", "1", "--quiet"]
        + (["--keep-going"] if keep_going else [])
    )
    captured = capsys.readouterr()
    assert code == (0 if keep_going else cli.EXIT_FAILED), captured.err
    assert "1 of 2 jobs failed" in captured.err
    assert "FAILED" in captured.out and named(captured.out, "bp_sysexit")


@pytest.mark.parametrize("value", ["-1", "0", "-5G", "nan", "inf", "0.5"])
def test_a_memory_budget_that_is_not_positive_is_refused(
    value, monkeypatch, bundles, tmp_path, capsys
):
    from faceretarget import config
    from faceretarget.errors import ConfigError

    monkeypatch.setenv(config.ENV_MEMORY_BUDGET, value)
    count(AREA)
    with pytest.raises(ConfigError, match="FACERETARGET_MEMORY_BUDGET.*not a positive size"):
        config.memory_budget()
    src, _ = bundles
    assert cli.main(["convert", str(src), str(tmp_path / "copy.npz")]) == cli.EXIT_ERROR
    assert "FACERETARGET_MEMORY_BUDGET" in capsys.readouterr().err
