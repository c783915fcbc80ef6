"""Helper processes a plugin starts die with its worker (issue 15, hole 8).

A plugin that starts a helper with ``start_new_session=True`` (out of the worker's process
group), or a daemon that double-forks (its parent exits at once, so it is orphaned), once
outlived the worker kill of ``compare`` and ``batch``. Each worker now runs under a
shepherd process that is a child subreaper (Linux): every descendant stays in its tree and
is killed when the worker ends, whether it overran its time limit or died.

The fake distribution ``helperplugins`` lives in ``tmp_path``; each helper writes its
process id into a folder the test watches, and ends by itself after two minutes in any case.
"""

import importlib
import os
import signal
import sys
import textwrap
import time

import pytest
from reliability.fuzzkit import count

import faceretarget as fr
from faceretarget.registry import Registry

AREA = "plugin isolation"
DIST = "helperplugins"
LIMIT = 3.0

pytestmark = pytest.mark.skipif(
    not sys.platform.startswith("linux"), reason="the subreaper is Linux only (documented)"
)

COMMON = '''
import os, subprocess, sys, time
import numpy as np
import faceretarget as fr

HELPER = "import os, sys, time; open(os.path.join(sys.argv[1], str(os.getpid())), 'w').close(); time.sleep(120)"


def started(before):
    """Wait until a new helper has written its pid file."""
    folder = os.environ["FR_TEST_HELPERS"]
    end = time.monotonic() + 60
    while time.monotonic() < end and len(os.listdir(folder)) <= before:
        time.sleep(0.02)


class Base(fr.Retargeter):
    capabilities = fr.Capabilities(sources=("mesh", "markers"))

    def _fit(self, source, target):
        self.neutral_ = np.asarray(target.neutral.vertices)

    def _retarget(self, source):
        return fr.Animation(vertices=np.repeat(self.neutral_[None], source.n_frames, axis=0), triangles=None, fps=source.fps)
'''

PLUGINS = {
    # a helper in a session of its own, then the plugin overruns its time limit
    "hx_session": """
class Session(Base):
    name = "hx_session"
    def _retarget(self, source):
        before = len(os.listdir(os.environ["FR_TEST_HELPERS"]))
        subprocess.Popen([sys.executable, "-c", HELPER, os.environ["FR_TEST_HELPERS"]], start_new_session=True)
        started(before)
        time.sleep(3600)
CLS = Session
""",
    # a double-forked daemon (orphaned at once, own session), then the worker dies
    "hx_daemon": """
class Daemon(Base):
    name = "hx_daemon"
    def _retarget(self, source):
        before = len(os.listdir(os.environ["FR_TEST_HELPERS"]))
        launcher = (
            "import subprocess, sys; "
            "subprocess.Popen([sys.executable, '-c', sys.argv[1], sys.argv[2]], start_new_session=True)"
        )
        subprocess.run([sys.executable, "-c", launcher, HELPER, os.environ["FR_TEST_HELPERS"]], check=True)
        started(before)
        os._exit(9)
CLS = Daemon
""",
    "hx_good": "class Good(Base):\n    name = 'hx_good'\nCLS = Good\n",
}


@pytest.fixture
def helpers(tmp_path, monkeypatch):
    """The fake distribution installed on sys.path (and PYTHONPATH, for the workers); yields
    the folder the helpers write their pids into, and kills any survivor afterwards."""
    root = tmp_path / "site"
    info = root / f"{DIST}-1.0.dist-info"
    info.mkdir(parents=True)
    (info / "METADATA").write_text(f"Metadata-Version: 2.1\nName: {DIST}\nVersion: 1.0\n")
    for name, code in PLUGINS.items():
        body = (
            COMMON
            + textwrap.dedent(code)
            + "\n@fr.hookimpl\ndef faceretarget_retargeters():\n    return [CLS]\n"
        )
        (root / f"{name}.py").write_text(body)
    (info / "entry_points.txt").write_text(
        "[faceretarget]\n" + "".join(f"{n} = {n}\n" for n in PLUGINS)
    )
    pids = tmp_path / "helpers"
    pids.mkdir()
    monkeypatch.syspath_prepend(str(root))
    monkeypatch.setenv("PYTHONPATH", os.pathsep.join([str(root), os.environ.get("PYTHONPATH", "")]))
    monkeypatch.setenv("FR_TEST_HELPERS", str(pids))
    monkeypatch.setenv("FACERETARGET_PLUGINS", DIST)
    monkeypatch.delenv("FACERETARGET_DISABLE_PLUGINS", raising=False)
    importlib.invalidate_caches()
    yield pids
    for pid in started_helpers(pids):
        if alive(pid):
            os.kill(pid, signal.SIGKILL)


def started_helpers(folder) -> list[int]:
    return [int(p.name) for p in folder.iterdir()]


def alive(pid: int) -> bool:
    """Running (a zombie, killed and waiting to be reaped, counts as gone)."""
    try:
        with open(f"/proc/{pid}/stat", "rb") as f:
            state = f.read().rsplit(b")", 1)[1].split()[0]
    except (OSError, IndexError):
        return False
    return state not in (b"Z", b"X")


def assert_all_gone(folder, expected: int) -> None:
    pids = started_helpers(folder)
    assert len(pids) == expected, (
        f"the plugins should have started {expected} helpers, found {pids}"
    )
    end = time.monotonic() + 30  # a generous net: the kill is immediate
    while time.monotonic() < end and any(alive(p) for p in pids):
        time.sleep(0.1)
    survivors = [p for p in pids if alive(p)]
    assert not survivors, f"helper processes outlived their worker: {survivors}"


def test_compare_kills_every_helper_of_a_stopped_or_dead_worker(helpers):
    from faceretarget.evaluation import compare

    case = fr.cases.synthetic(resolution=300, n_frames=4)
    reg = Registry().load()
    result = compare(
        [case],
        methods=["hx_good", "hx_session", "hx_daemon"],
        registry=reg,
        metrics=["vertex_error_mean"],
        timeout=LIMIT,
        n_jobs=2,
    )
    runs = {r.method: r for r in result.runs}
    count(AREA, len(runs))
    assert runs["hx_good"].status == "ok"
    assert runs["hx_session"].error["type"] == "PluginTimeoutError", runs["hx_session"].reason
    assert "exited with code 9" in runs["hx_daemon"].reason and DIST in runs["hx_daemon"].reason
    assert_all_gone(helpers, 2)


def test_batch_kills_every_helper_of_a_stopped_or_dead_worker(helpers, tmp_path):
    from faceretarget.evaluation.batch import run_batch

    case = fr.cases.synthetic(resolution=300, n_frames=4)
    fr.io.save_bundle(case.source, tmp_path / "source.npz")
    fr.io.save_bundle(case.target, tmp_path / "target.npz")
    names = ["hx_good", "hx_session", "hx_daemon"]
    (tmp_path / "out").mkdir()
    (tmp_path / "shots.toml").write_text(
        "\n".join(
            f'[[job]]\nshot = "source.npz"\ncharacter = "target.npz"\nmethod = "{n}"\nout = "out/{n}.npz"\n'
            for n in names
        )
    )
    summary = run_batch(
        tmp_path / "shots.toml",
        registry=Registry().load(),
        progress=False,
        workers=2,
        timeout=LIMIT,
    )
    results = {r.method: r for r in summary.results}
    count(AREA, len(results))
    assert results["hx_good"].status == "done"
    assert "PluginTimeoutError" in results["hx_session"].error
    assert "exited with code 9" in results["hx_daemon"].error
    assert_all_gone(helpers, 2)
