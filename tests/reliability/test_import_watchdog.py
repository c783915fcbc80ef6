"""A plugin cannot disable the import time limit (issue 15, hole 7).

A plugin that ignored ``SIGALRM`` and slept once hung ``faceretarget list`` forever. The
limit (``FACERETARGET_IMPORT_TIMEOUT``) now has four layers (``faceretarget._deadline``):
the alarm, a watchdog thread that injects the interruption and wakes the main thread,
a hard stop of the program naming the plugin when nothing interrupts it, and a watchdog
process that kills the program when not even a thread can run (the GIL held in C).

Each plugin lives in a fake distribution ``watchplugins`` in ``tmp_path``; every run is
the real command in a process of its own (some of them must end it).
"""

import os
import subprocess
import sys

import pytest
from reliability.fuzzkit import count

AREA = "plugin isolation"
DIST = "watchplugins"

PLUGINS = {
    # the attack of the issue: SIGALRM ignored, then a long sleep
    "wp_ignore_alarm": "import signal, time\nsignal.signal(signal.SIGALRM, signal.SIG_IGN)\ntime.sleep(3600)\n",
    # every signal ignored, and every exception swallowed, in a Python loop
    "wp_swallow_all": (
        "import signal, time\n"
        "for s in signal.valid_signals():\n"
        "    try:\n        signal.signal(s, signal.SIG_IGN)\n    except (OSError, ValueError, RuntimeError):\n        pass\n"
        "while True:\n    try:\n        time.sleep(0.05)\n    except BaseException:\n        pass\n"
    ),
    # every signal blocked, then a sleep in C that holds the GIL: no thread of the process can run
    "wp_hold_gil": (
        "import ctypes, signal\n"
        "signal.pthread_sigmask(signal.SIG_BLOCK, signal.valid_signals())\n"
        "ctypes.PyDLL(None).sleep(3600)\n"
    ),
    "wp_quick": (
        "import faceretarget as fr\n"
        "class Quick(fr.Retargeter):\n    name = 'wp_quick'\n    capabilities = fr.Capabilities(sources=('mesh',))\n"
        "@fr.hookimpl\ndef faceretarget_retargeters():\n    return [Quick]\n"
    ),
}


@pytest.fixture(scope="module")
def site(tmp_path_factory):
    root = tmp_path_factory.mktemp("watchsite")
    info = root / f"{DIST}-1.0.dist-info"
    info.mkdir()
    (info / "METADATA").write_text(f"Metadata-Version: 2.1\nName: {DIST}\nVersion: 1.0\n")
    for name, code in PLUGINS.items():
        (root / f"{name}.py").write_text(code)
    (info / "entry_points.txt").write_text(
        "[faceretarget]\n" + "".join(f"{n} = {n}\n" for n in PLUGINS)
    )
    return root


def list_with(site, *plugins):
    """``faceretarget list`` with the built-ins and only ``plugins`` of the distribution."""
    env = {
        **os.environ,
        "PYTHONPATH": os.pathsep.join([str(site), os.environ.get("PYTHONPATH", "")]),
    }
    env.update(FACERETARGET_PLUGINS=",".join(plugins), FACERETARGET_IMPORT_TIMEOUT="1")
    env.pop("FACERETARGET_DISABLE_PLUGINS", None)
    count(AREA)
    return subprocess.run(
        [sys.executable, "-m", "faceretarget.cli", "list"],
        env=env,
        capture_output=True,
        text=True,
        timeout=120,
    )


def test_a_plugin_ignoring_the_alarm_is_skipped_and_the_rest_listed(site):
    proc = list_with(site, "wp_ignore_alarm", "wp_quick")
    assert proc.returncode == 0, proc.stderr
    assert "wp_quick" in proc.stdout and "spacetime" in proc.stdout
    failed = proc.stdout.split("plugins that failed to load:")[1]
    assert (
        "wp_ignore_alarm" in failed
        and DIST in failed
        and "took longer than 1 s importing" in failed
    )


def test_a_plugin_that_cannot_be_interrupted_ends_the_program_with_its_name(site):
    proc = list_with(site, "wp_swallow_all")
    assert proc.returncode == 2, (proc.returncode, proc.stderr)
    assert "PluginTimeoutError: plugin 'wp_swallow_all' (watchplugins 1.0)" in proc.stderr
    assert "could not be interrupted" in proc.stderr and "FACERETARGET_PLUGINS" in proc.stderr


@pytest.mark.skipif(
    not sys.platform.startswith("linux"), reason="ctypes.PyDLL(None) needs a libc with sleep"
)
def test_a_plugin_holding_the_gil_forever_is_killed_by_the_watchdog_process(site):
    proc = list_with(site, "wp_hold_gil")
    assert proc.returncode == -9, (proc.returncode, proc.stderr)
    assert "PluginTimeoutError: plugin 'wp_hold_gil' (watchplugins 1.0)" in proc.stderr
