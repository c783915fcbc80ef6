"""Supervised worker processes: every task ends in exactly one outcome, overrunning or
crashing workers are replaced and their groups go on."""

import multiprocessing as mp
import os
import signal
import subprocess
import sys
import textwrap
import time
from pathlib import Path

import numpy as np
import pytest
import worker_tasks as t

import faceretarget as fr
from faceretarget.evaluation._workers import DIED, DONE, ERROR, TIMEOUT, Task, run_supervised


def outcomes(groups, workers=1):
    got = []
    run_supervised(groups, workers=workers, on_outcome=got.append)
    return {o.key: o for o in got}, [o.key for o in got]


def test_every_task_ends_once_with_its_value_or_error():
    groups = [
        [
            Task("sum", t.add, (2, 3)),
            Task("boom", t.fail, ("no luck",)),
            Task("exit", t.exit_call),
            Task("after", t.add, (1, 1)),
        ]
    ]
    got, order = outcomes(groups)
    assert order == ["sum", "boom", "exit", "after"], "tasks of a group run in order"
    assert got["sum"].status == DONE and got["sum"].value == 5
    assert got["boom"].status == ERROR and got["boom"].message == "ValueError: no luck"
    assert "ValueError" in got["boom"].value, "the worker's traceback comes back for --debug"
    assert got["exit"].status == ERROR and "SystemExit" in got["exit"].message
    assert got["after"].value == 2, "a task that raised leaves the worker usable"


def test_overrunning_tasks_are_killed_and_their_group_goes_on():
    groups = [
        [Task("sleepy", t.sleep, (600,), timeout=1.0), Task("next", t.add, (1, 2), timeout=1.0)],
        [Task("spinner", t.spin, (), timeout=1.0), Task("then", t.add, (2, 2))],
    ]
    got, _ = outcomes(groups, workers=2)
    for key in ("sleepy", "spinner"):
        assert got[key].status == TIMEOUT and got[key].started
        assert (
            got[key].message
            == "did not finish within its time limit of 1 s; its worker process was stopped"
        )
        assert got[key].seconds >= 1.0
    assert got["next"].value == 3 and got["then"].value == 4


def test_a_fast_task_is_not_stopped_by_a_limit():
    got, _ = outcomes([[Task("quick", t.sleep, (0.1,), timeout=30.0)]])
    assert got["quick"].status == DONE and got["quick"].value == "woke up"


def test_a_dying_worker_is_reported_and_replaced():
    got, _ = outcomes([[Task("pid1", t.pid), Task("dies", t.die, (7,)), Task("pid2", t.pid)]])
    assert (
        got["dies"].status == DIED
        and got["dies"].message == "its worker process exited with code 7 while running it"
    )
    assert got["pid1"].value != got["pid2"].value, "the rest of the group runs in a fresh worker"


def test_unsendable_results_and_unloadable_tasks_are_errors():
    got, _ = outcomes(
        [
            [
                Task("lambda", t.unsendable),
                Task("unloadable", t.add, (t.Unloadable(), 1)),
                Task("fine", t.add, (1, 1)),
            ]
        ]
    )
    assert got["lambda"].status == ERROR and "could not be sent back" in got["lambda"].message
    assert got["unloadable"].status == ERROR and not got["unloadable"].started
    assert (
        got["unloadable"].message
        == "the worker could not load the task: RuntimeError: this object cannot be loaded in a worker"
    )
    assert got["fine"].value == 2


def test_a_task_that_does_not_pickle_is_an_error_and_the_rest_runs():
    got, order = outcomes(
        [[Task("first", t.add, (1, 2)), Task("lambda", lambda: 1), Task("last", t.add, (3, 4))]]
    )
    assert got["lambda"].status == ERROR and got["lambda"].message.startswith(
        "the task could not be handed to a worker process"
    )
    assert got["first"].value == 3 and got["last"].value == 7
    assert order.index("lambda") < order.index("last")


def test_more_workers_than_groups_and_empty_groups():
    got, _ = outcomes([[Task("a", t.add, (1, 1))], [], [Task("b", t.add, (2, 2))]], workers=4)
    assert {k: o.value for k, o in got.items()} == {"a": 2, "b": 4}
    assert outcomes([], workers=2) == ({}, [])


def test_workers_start_inside_daemonic_processes(monkeypatch):
    """A Dask worker is a daemonic process, where multiprocessing may not start children."""
    monkeypatch.setattr(
        mp.current_process(), "_config", {**mp.current_process()._config, "daemon": True}
    )
    got, _ = outcomes(
        [
            [
                Task("sum", t.add, (2, 5)),
                Task("sleepy", t.sleep, (600,), timeout=1.0),
                Task("dies", t.die, (3,)),
                Task("after", t.add, (1, 1)),
            ]
        ]
    )
    assert got["sum"].value == 7 and got["sleepy"].status == TIMEOUT
    assert got["dies"].status == DIED and "exited with code 3" in got["dies"].message
    assert got["after"].value == 2


def test_a_worker_never_runs_two_owners_tasks():
    """A death after a task has returned is charged to that task's owner, not to the next one."""
    groups = [
        [Task("a1", t.pid, owner="a"), Task("a2", t.pid, owner="a")],
        [Task("b1", t.pid, owner="b")],
        [Task("a3", t.pid, owner="a")],
    ]
    got, order = outcomes(groups, workers=1)
    assert order == ["a1", "a2", "a3", "b1"], "a worker prefers more of its owner's groups"
    assert got["a1"].value == got["a2"].value == got["a3"].value != got["b1"].value


def test_time_limit_settings(monkeypatch):
    from faceretarget import config
    from faceretarget.errors import ConfigError

    assert (
        config.check_timeout(None) is None
        and config.check_timeout(0) is None
        and config.check_timeout(2) == 2.0
    )
    for bad in (-1, float("nan"), float("inf"), 1e7, 1e300, True, "10"):
        with pytest.raises(ConfigError, match="number of seconds from 0 to"):
            config.check_timeout(bad)
    monkeypatch.delenv(config.ENV_RUN_TIMEOUT, raising=False)
    assert (
        config.seconds_setting(config.ENV_RUN_TIMEOUT, config.DEFAULT_RUN_TIMEOUT)
        == config.DEFAULT_RUN_TIMEOUT
    )
    monkeypatch.setenv(config.ENV_RUN_TIMEOUT, "0")
    assert config.seconds_setting(config.ENV_RUN_TIMEOUT, 5) is None
    for bad in ("soon", "-3", "inf", "1e10"):
        monkeypatch.setenv(config.ENV_RUN_TIMEOUT, bad)
        with pytest.raises(ConfigError, match="FACERETARGET_TIMEOUT"):
            config.seconds_setting(config.ENV_RUN_TIMEOUT, 5)


def test_compare_and_batch_refuse_bad_time_limits(tiny, fake_registry, capsys):
    from faceretarget import cli
    from faceretarget.errors import ConfigError
    from faceretarget.evaluation import compare

    with pytest.raises(ConfigError, match="compare: timeout"):
        compare([tiny], methods=["fake_neutral"], registry=fake_registry, timeout=-1)
    assert cli.main(["compare", "synthetic", "--timeout", "nan"]) == cli.EXIT_ERROR
    assert "--timeout must be a number of seconds from 0 to" in capsys.readouterr().err


def test_deadline_interrupts_python_code_and_restores_the_previous_timer():
    from faceretarget._deadline import DeadlineExpired, deadline

    fired = []

    def outer(*args):
        fired.append("outer")

    previous = signal.signal(signal.SIGALRM, outer)
    signal.setitimer(signal.ITIMER_REAL, 30)
    try:
        with pytest.raises(DeadlineExpired), deadline(0.2):
            time.sleep(10)
        with deadline(5):
            pass
        left, _ = signal.getitimer(signal.ITIMER_REAL)
        assert 0 < left <= 30, "the outer timer is re-armed with the time it had left"
        assert signal.getsignal(signal.SIGALRM) is outer and not fired
    finally:
        signal.setitimer(signal.ITIMER_REAL, 0)
        signal.signal(signal.SIGALRM, previous)


def test_deadline_cannot_be_swallowed_by_plugin_code():
    """Code that catches Exception or OSError (as import machinery does) is still stopped."""
    from faceretarget._deadline import DeadlineExpired, deadline

    handler = signal.getsignal(signal.SIGALRM)
    start = time.monotonic()
    with pytest.raises(DeadlineExpired), deadline(0.2):
        while time.monotonic() - start < 20:
            try:
                time.sleep(0.05)
            except Exception:
                pass
    assert signal.getsignal(signal.SIGALRM) is handler, "the handler in place before is back"
    # catching even BaseException does not help
    with pytest.raises(DeadlineExpired, match="ran past"), deadline(0.2):
        while time.monotonic() - start < 1.0:
            try:
                time.sleep(0.05)
            except BaseException:
                pass


def test_a_result_that_does_not_load_here_is_an_error():
    got, _ = outcomes([[Task("odd", t.result_that_does_not_load), Task("after", t.add, (2, 2))]])
    assert (
        got["odd"].status == ERROR
        and "could not be loaded by the supervising process" in got["odd"].message
    )
    assert got["after"].value == 4


def test_big_task_payloads_arrive():
    got, _ = outcomes([[Task("big", t.nbytes, (np.zeros(2_000_000),), timeout=60.0)]])
    assert got["big"].value == 16_000_000


def running(pid: int) -> bool:
    try:
        state = Path(f"/proc/{pid}/stat").read_text().rsplit(")", 1)[1].split()[0]
    except (FileNotFoundError, ProcessLookupError, IndexError):
        return False
    return state not in ("Z", "X")


def wait_until_gone(pid: int, seconds: float = 10.0) -> bool:
    end = time.monotonic() + seconds
    while time.monotonic() < end:
        if not running(pid):
            return True
        time.sleep(0.1)
    return False


@pytest.mark.skipif(not Path("/proc/self/stat").exists(), reason="reads process states from /proc")
def test_a_worker_that_dies_behind_a_helper_process_is_seen_and_its_helpers_are_stopped(tmp_path):
    pid_file = tmp_path / "helper.pid"
    got, _ = outcomes(
        [
            [
                Task("dies", t.fork_helper_then_die, (str(pid_file),), timeout=60.0),
                Task("after", t.add, (1, 1)),
            ]
        ]
    )
    assert got["dies"].status == DIED and "exited with code 4" in got["dies"].message, got["dies"]
    assert got["after"].value == 2
    assert wait_until_gone(int(pid_file.read_text())), (
        "the helper process of a dead worker must be stopped with it"
    )


def test_a_supervisor_run_from_standard_input():
    """``python - < script.py`` (its main module is '<stdin>', no file): the workers start
    without it (they used to fail while loading the main module)."""
    script = textwrap.dedent(f"""
        import sys
        sys.path[:0] = {[str(Path(t.__file__).parent)]!r}
        import worker_tasks as t
        from faceretarget.evaluation._workers import Task, run_supervised
        run_supervised([[Task("sum", t.add, (2, 3))]], workers=1, on_outcome=lambda o: print(o.status, o.value))
    """)
    done = subprocess.run(
        [sys.executable, "-"], input=script, capture_output=True, text=True, timeout=120
    )
    assert done.returncode == 0, done.stderr
    assert done.stdout.split() == [DONE, "5"], done.stderr


def test_a_task_defined_in_the_supervisors_own_script(tmp_path):
    """The workers load the main script (spawn's init_main_from_path) when it is a file."""
    script = tmp_path / "supervisor.py"
    script.write_text(
        textwrap.dedent("""
        from faceretarget.evaluation._workers import Task, run_supervised
        def add(a, b):
            return a + b
        if __name__ == "__main__":
            run_supervised([[Task("sum", add, (2, 3))]], workers=1, on_outcome=lambda o: print(o.status, o.value))
    """)
    )
    done = subprocess.run(
        [sys.executable, str(script)], capture_output=True, text=True, timeout=120
    )
    assert done.returncode == 0, done.stderr
    assert done.stdout.split() == [DONE, "5"], (done.stdout, done.stderr)


@pytest.mark.skipif(not Path("/proc/self/stat").exists(), reason="reads process states from /proc")
def test_workers_die_with_their_supervisor(tmp_path):
    """A supervisor killed outright (SIGKILL, OOM killer, a cancelled cluster job) leaves no worker spinning."""
    pid_file = tmp_path / "worker.pid"
    script = textwrap.dedent(f"""
        import sys
        sys.path[:0] = {[str(Path(t.__file__).parent)]!r}
        import worker_tasks as t
        from faceretarget.evaluation._workers import Task, run_supervised
        if __name__ == "__main__":
            run_supervised([[Task("spin", t.worker_pid_then_spin, ({str(pid_file)!r},))]], workers=1, on_outcome=print)
    """)
    (tmp_path / "supervisor.py").write_text(script)
    supervisor = subprocess.Popen([sys.executable, str(tmp_path / "supervisor.py")])
    try:
        end = time.monotonic() + 60
        while not pid_file.exists() or not pid_file.read_text():
            assert time.monotonic() < end and supervisor.poll() is None, "the worker never started"
            time.sleep(0.1)
        worker = int(pid_file.read_text())
        assert running(worker)
        supervisor.kill()
        supervisor.wait()
        assert wait_until_gone(worker), "the worker outlived its supervisor"
    finally:
        if supervisor.poll() is None:
            supervisor.kill()


def test_pool_workers_are_single_threaded_and_this_process_environment_is_untouched(monkeypatch):
    """The workers get one thread each through their own environment; this process's stays
    as it is while they run (numba re-reads NUMBA_NUM_THREADS at every compilation here and
    raises once its threads run with another count), and a count the user set is kept."""
    from faceretarget.evaluation._workers import THREAD_VARIABLES, single_threaded_environ

    for name in THREAD_VARIABLES:
        monkeypatch.delenv(name, raising=False)
    monkeypatch.setenv("OMP_NUM_THREADS", "3")
    seen_here = []

    def on_outcome(outcome):
        seen_here.append({k: os.environ.get(k) for k in THREAD_VARIABLES})
        got.append(outcome)

    got = []
    run_supervised(
        [[Task("env", t.environ, (THREAD_VARIABLES,))]],
        workers=1,
        on_outcome=on_outcome,
        env=single_threaded_environ(),
    )
    assert got[0].value == {
        "OMP_NUM_THREADS": "3",
        "OPENBLAS_NUM_THREADS": "1",
        "MKL_NUM_THREADS": "1",
        "NUMBA_NUM_THREADS": "1",
    }
    assert seen_here == [
        {
            "OMP_NUM_THREADS": "3",
            "OPENBLAS_NUM_THREADS": None,
            "MKL_NUM_THREADS": None,
            "NUMBA_NUM_THREADS": None,
        }
    ]


def test_compare_in_workers_leaves_this_process_environment_alone(monkeypatch):
    """compare(n_jobs=2) computes metrics here while the workers run: the thread variables
    must not be set in this process meanwhile (the regression: a metric compiling a kernel
    here raised numba's 'Cannot set NUMBA_NUM_THREADS ...')."""
    from faceretarget.evaluation import harness

    monkeypatch.delenv("NUMBA_NUM_THREADS", raising=False)
    seen = []
    real = harness._metric_rows

    def spy(run, case, metrics):
        seen.append(os.environ.get("NUMBA_NUM_THREADS"))
        return real(run, case, metrics)

    monkeypatch.setattr(harness, "_metric_rows", spy)
    result = harness.compare(
        ["synthetic?resolution=300&n_frames=4"],
        methods=["spacetime_noconst", "deformation_transfer"],
        n_jobs=2,
        metrics=["vertex_error_rms"],
    )
    assert len(result.runs) == 2 and seen == [None, None]


def test_the_built_ins_share_workers_and_third_party_plugins_keep_their_own():
    """A worker starting afresh cost 1-2 s of CPU (7 times in a demo): the built-ins, one
    distribution, share workers; two third-party plugins never share one."""
    from faceretarget.evaluation._workers import plugin_owner

    assert plugin_owner("coating", True) == plugin_owner("spacetime", True)
    assert plugin_owner("mine", False) != plugin_owner("theirs", False)
    assert plugin_owner("coating", True) != plugin_owner("coating", False)
    groups = [
        [Task("c", t.pid, owner=plugin_owner("coating", True))],
        [Task("x", t.pid, owner=plugin_owner("mine", False))],
        [Task("s", t.pid, owner=plugin_owner("spacetime", True))],
    ]
    got, order = outcomes(groups, workers=1)
    assert order == ["c", "s", "x"]
    assert got["c"].value == got["s"].value != got["x"].value


def test_compare_and_presets_give_the_built_ins_one_owner():
    from types import SimpleNamespace

    from faceretarget.evaluation._workers import BUILTIN_OWNER, plugin_owner
    from faceretarget.evaluation.harness import _methods, _owner
    from faceretarget.evaluation.presets import chosen_presets, isolated_groups
    from faceretarget.registry import registry

    methods = _methods(["coating", "spacetime", "layers"], registry())
    assert {_owner(m) for m in methods} == {BUILTIN_OWNER}
    for given in (None, registry()):  # the global registry by default
        groups = isolated_groups(chosen_presets(), {}, None, given)
        assert len(groups) > 1 and {task.owner for g in groups for task in g} == {BUILTIN_OWNER}
    no_builtins = SimpleNamespace(plugins=[])  # a registry where these plugins are third-party
    assert BUILTIN_OWNER not in {
        task.owner for g in isolated_groups(chosen_presets(), {}, None, no_builtins) for task in g
    }

    class Local(fr.Retargeter):  # a class handed over directly: answerable as its module
        pass

    (local,) = _methods([Local], registry())
    assert _owner(local) == plugin_owner(__name__, False)


def test_a_third_party_plugin_keeps_a_worker_of_its_own(fake_registry):
    from faceretarget.evaluation._workers import BUILTIN_OWNER, plugin_owner
    from faceretarget.evaluation.harness import _methods, _owner

    (fake,) = _methods(["fake_neutral"], fake_registry)
    assert _owner(fake) == plugin_owner(fake.plugin, False) != BUILTIN_OWNER
