"""Batch manifests: checks, the local process pool, Dask, and resuming after a kill."""

import os
import signal
import subprocess
import sys
import textwrap
import time
from pathlib import Path

import fake_retargeters as fakes
import numpy as np
import pytest

from faceretarget.errors import ConfigError, UnknownNameError
from faceretarget.evaluation.batch import RUN_DEFAULT, load_manifest, run_batch

SHOT = "case:synthetic?resolution=60&n_frames=4"
HERE = Path(__file__).parent


def manifest(folder: Path, body: str, name: str = "shots.toml") -> Path:
    path = folder / name
    path.write_text(textwrap.dedent(body))
    return path


def many_jobs(folder: Path, count: int, delay: float) -> Path:
    jobs = "".join(f'[[job]]\nout = "out/shot{i:02d}.fnpz"\n' for i in range(count))
    return manifest(
        folder,
        f'[defaults]\nmethod = "fake_transfer"\nshot = "{SHOT}"\nparams = {{ delay = {delay} }}\n{jobs}',
    )


@pytest.mark.parametrize(
    "body, error, match",
    [
        (
            '[[job]]\nshot = "../elsewhere.c3d"\ncharacter = "c.glb"\nmethod = "fake_transfer"\nout = "o.fnpz"',
            ConfigError,
            "outside the manifest's folder",
        ),
        (
            '[[job]]\nshot = "s.c3d"\ncharacter = "c.glb"\nmethod = "fake_transfer"\nout = "/tmp/o.fnpz"',
            ConfigError,
            "outside the manifest's folder",
        ),
        (
            '[[job]]\nshot = "s.c3d"\ncharacter = "c.glb"\nmethod = "fake_transfer"\nout = "link/o.fnpz"',
            ConfigError,
            "outside the manifest's folder",
        ),
        (
            f'[[job]]\nshot = "{SHOT}"\nmethod = "fake_transfer"\nout = "o.fnpz"\ncolour = "red"',
            ConfigError,
            "unknown key",
        ),
        (f'[[job]]\nshot = "{SHOT}"\nmethod = "fake_transfer"', ConfigError, "missing out"),
        (
            '[[job]]\nshot = "s.c3d"\nmethod = "fake_transfer"\nout = "o.fnpz"',
            ConfigError,
            "missing character",
        ),
        (
            f'[[job]]\nshot = "{SHOT}"\nmethod = "nope"\nout = "o.fnpz"',
            UnknownNameError,
            "valid choices",
        ),
        (
            f'[[job]]\nshot = "{SHOT}"\nmethod = "fake_transfer"\nout = "o.fnpz"\nparams = {{ gian = 2 }}',
            UnknownNameError,
            "no parameter",
        ),
        (
            f'[[job]]\nshot = "{SHOT}"\nmethod = "fake_transfer"\nout = "o.xyz"',
            ConfigError,
            "no registered writer",
        ),
        (
            f'[[job]]\nshot = "{SHOT}"\nmethod = "fake_transfer"\nout = "o.fnpz"\n[[job]]\nshot = "{SHOT}"\nmethod = "fake_neutral"\nout = "o.fnpz"',
            ConfigError,
            "already written by",
        ),
        (
            '[[job]]\nshot = "case:nope"\nmethod = "fake_transfer"\nout = "o.fnpz"',
            UnknownNameError,
            "no case named",
        ),
        ("[[job]\nshot = ", ConfigError, "not valid TOML"),
        ("[defaults]\nmethod = 'x'\n", ConfigError, "no \\[\\[job\\]\\] entries"),
        (
            f'[[job]]\nshot = "{SHOT}"\nmethod = "fake_transfer"\nout = "o.fnpz"\ntimeout = -5',
            ConfigError,
            "job #1: timeout must be a number of seconds from 0 to",
        ),
        (
            f'[[job]]\nshot = "{SHOT}"\nmethod = "fake_transfer"\nout = "o.fnpz"\ntimeout = "soon"',
            ConfigError,
            "timeout must be",
        ),
        (
            f'[defaults]\ntimeout = inf\n[[job]]\nshot = "{SHOT}"\nmethod = "fake_transfer"\nout = "o.fnpz"',
            ConfigError,
            "timeout must be",
        ),
    ],
)
def test_manifest_is_checked_before_running(tmp_path, fake_registry, body, error, match):
    (tmp_path / "link").symlink_to(
        tmp_path.parent, target_is_directory=True
    )  # a link out of the folder
    with pytest.raises(error, match=match):
        load_manifest(manifest(tmp_path, body), registry=fake_registry)


def test_manifest_resolves_paths_and_merges_defaults(tmp_path, fake_registry):
    path = manifest(
        tmp_path,
        f"""
        [defaults]
        method = "fake_transfer"
        params = {{ gain = 2.0 }}
        [[job]]
        shot = "{SHOT}"
        out = "out/a.fnpz"
        params = {{ delay = 0.5 }}
        [[job]]
        shot = "shots/s.c3d"
        character = "chars/hero.glb"
        method = "fake_neutral"
        params = {{}}
        out = "out/b.fnpz"
        name = "second"
        """,
    )
    with pytest.raises(UnknownNameError, match="fake_neutral has no parameter"):
        load_manifest(path, registry=fake_registry)  # defaults' params are merged into every job
    path.write_text(path.read_text().replace("params = { gain = 2.0 }\n", ""))
    a, b = load_manifest(path, registry=fake_registry)
    assert (
        a.params == {"delay": 0.5}
        and a.character == SHOT
        and a.out == str(tmp_path.resolve() / "out/a.fnpz")
        and a.name == "out/a.fnpz"
    )
    assert (
        b.name == "second"
        and b.shot == str(tmp_path.resolve() / "shots/s.c3d")
        and b.cls is fakes.NeutralFake
    )
    assert a.timeout == b.timeout == RUN_DEFAULT  # the run's time limit applies
    from faceretarget.evaluation._workers import plugin_owner

    plugin = fake_registry.resolve("fake_neutral").plugin  # workers: one per owner
    assert b.owner == plugin_owner(plugin.name, plugin.builtin) is not None
    path.write_text(
        path.read_text()
        .replace('name = "second"', 'name = "second"\ntimeout = 0')
        .replace("[defaults]", "[defaults]\ntimeout = 90")
    )
    a, b = load_manifest(path, registry=fake_registry)
    assert (
        a.timeout == 90.0 and b.timeout is None
    )  # 0: no limit, as everywhere (even when the run has one)


def test_local_pool_reports_failures_and_skips_finished(tmp_path, fake_registry):
    path = manifest(
        tmp_path,
        f"""
        [defaults]
        shot = "{SHOT}"
        [[job]]
        method = "fake_transfer"
        out = "out/ok1.fnpz"
        [[job]]
        method = "fake_broken"
        out = "out/broken.fnpz"
        [[job]]
        method = "fake_wrongshape"
        out = "out/wrong.fnpz"
        [[job]]
        method = "fake_neutral"
        out = "out/ok2.fnpz"
        """,
    )
    summary = run_batch(path, registry=fake_registry, workers=2, progress=False)
    status = {r.name: r.status for r in summary.results}
    assert status == {
        "out/ok1.fnpz": "done",
        "out/broken.fnpz": "failed",
        "out/wrong.fnpz": "failed",
        "out/ok2.fnpz": "done",
    }
    errors = {r.name: r.error for r in summary.failed}
    assert (
        errors["out/broken.fnpz"]
        == "fake_broken [plugin fakes (local -)]: RuntimeError: boom in fit"
    )
    assert errors["out/wrong.fnpz"].startswith(
        "fake_wrongshape [plugin fakes (local -)]: PluginOutputError: fake_wrongshape: returned 95 vertices per frame but the target has 96"
    )
    saved = np.load(tmp_path / "out/ok1.fnpz")
    assert saved["vertices"].shape[0] == 4 and str(saved["method"]) == "fake_transfer"
    assert sorted(p.name for p in (tmp_path / "out").iterdir()) == [
        "ok1.fnpz",
        "ok2.fnpz",
    ]  # no partial files
    again = run_batch(path, registry=fake_registry, workers=2, progress=False)
    assert [r.status for r in again.results] == ["skipped", "failed", "failed", "skipped"]


_RUNNER = """
import sys
sys.path.insert(0, {here!r})
import fake_retargeters
from faceretarget.evaluation.batch import run_batch
run_batch({manifest!r}, executor="dask", workers=2, dask_processes=False, registry=fake_retargeters.fake_registry(), progress=False)
"""


def test_dask_batch_killed_halfway_resumes_only_missing_jobs(tmp_path, fake_registry):
    count = 24
    path = many_jobs(tmp_path, count, delay=0.3)
    out = tmp_path / "out"
    proc = subprocess.Popen(
        [sys.executable, "-c", _RUNNER.format(here=str(HERE), manifest=str(path))],
        stdout=subprocess.DEVNULL,
        stderr=subprocess.DEVNULL,
        start_new_session=True,
    )
    try:
        deadline = time.monotonic() + 120
        while time.monotonic() < deadline and proc.poll() is None:
            # finished outputs only: a killed write leaves ".shotNN.fnpz.<pid>...frtmp.fnpz"
            if out.is_dir() and len(list(out.glob("shot*.fnpz"))) >= 6:
                break
            time.sleep(0.05)
    finally:
        os.killpg(proc.pid, signal.SIGKILL)
        proc.wait()
    finished = {p.name: p.stat().st_mtime_ns for p in out.glob("shot*.fnpz")}
    assert 6 <= len(finished) < count, f"{len(finished)} outputs when killed"
    for name in finished:
        assert np.load(out / name)["vertices"].shape[0] == 4  # complete files
    summary = run_batch(
        path,
        executor="dask",
        workers=2,
        dask_processes=False,
        registry=fake_registry,
        progress=False,
    )
    skipped = {Path(r.out).name for r in summary.results if r.status == "skipped"}
    done = {Path(r.out).name for r in summary.results if r.status == "done"}
    assert skipped == set(finished) and len(done) == count - len(finished) and not summary.failed
    assert {
        p.name: p.stat().st_mtime_ns for p in out.glob("shot*.fnpz") if p.name in finished
    } == finished  # untouched
    assert sorted(p.name for p in out.iterdir()) == [
        f"shot{i:02d}.fnpz" for i in range(count)
    ]  # no temporaries left


def test_batch_on_a_running_scheduler(tmp_path, fake_registry):
    from distributed import LocalCluster

    path = many_jobs(tmp_path, 4, delay=0.0)
    with LocalCluster(
        n_workers=2,
        threads_per_worker=1,
        processes=False,
        host="127.0.0.1",
        protocol="tcp://",
        dashboard_address=None,
    ) as cluster:
        assert cluster.scheduler_address.startswith("tcp://127.0.0.1:")
        summary = run_batch(
            path,
            executor="dask",
            scheduler=cluster.scheduler_address,
            registry=fake_registry,
            progress=False,
        )
    assert [r.status for r in summary.results] == ["done"] * 4
    assert len(list((tmp_path / "out").glob("*.fnpz"))) == 4


def test_the_supervisor_gives_each_task_its_jobs_owner(monkeypatch):
    """Workers are shared by owner (:func:`._workers.plugin_owner`): the tasks carry the
    owner the manifest gave each job; a job without one is owned by its class's module."""
    from faceretarget.evaluation import _workers, batch

    seen = []
    monkeypatch.setattr(
        _workers, "run_supervised", lambda groups, **_: seen.extend(t for g in groups for t in g)
    )
    jobs = [
        batch.Job("a", "s", "c", "m", {}, "a.npz", cls=fakes.NeutralFake, owner=("built-ins",)),
        batch.Job("b", "s", "c", "m", {}, "b.npz", cls=fakes.NeutralFake),
    ]
    batch._supervised(jobs, 1, None, lambda result: None)
    assert [t.owner for t in seen] == [("built-ins",), fakes.NeutralFake.__module__]
