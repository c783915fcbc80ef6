"""Cold start: one line when our kernels compile, and `faceretarget warmup` to compile them ahead."""

import subprocess
import sys
import types

from faceretarget import _numba_cache


def fake_caching(load_result):
    class Cache:
        def __init__(self, py_func):
            self._py_func = py_func

        def save_overload(self, sig, data):
            return None

        def load_overload(self, sig, target_context):
            return load_result

    return types.SimpleNamespace(Cache=Cache)


def ours():
    pass


ours.__module__ = "faceretarget.plugins.spacetime._kernels"


def theirs():
    pass


theirs.__module__ = "somebody_else"


def test_the_first_miss_of_our_kernel_prints_one_line(monkeypatch, capsys, tmp_path):
    monkeypatch.setattr(_numba_cache, "_noticed", False)
    monkeypatch.setattr(_numba_cache, "_MARKER", str(tmp_path / "marker"))
    caching = fake_caching(None)
    _numba_cache._patch(caching)
    caching.Cache(theirs).load_overload(None, None)
    assert capsys.readouterr().err == ""
    caching.Cache(ours).load_overload(None, None)
    caching.Cache(ours).load_overload(None, None)
    err = capsys.readouterr().err
    assert err.count("compiling numerical kernels") == 1 and "faceretarget warmup" in err


def test_one_notice_for_the_processes_of_one_run(monkeypatch, capsys, tmp_path):
    """demo's workers compile in parallel: the first prints, the others (a fresh process
    each: simulated by resetting the per-process flag) see its marker and stay quiet."""
    monkeypatch.setattr(_numba_cache, "_MARKER", str(tmp_path / "marker"))
    caching = fake_caching(None)
    _numba_cache._patch(caching)
    for _ in range(3):
        monkeypatch.setattr(_numba_cache, "_noticed", False)
        caching.Cache(ours).load_overload(None, None)
    assert capsys.readouterr().err.count("compiling numerical kernels") == 1
    monkeypatch.setattr(_numba_cache, "NOTICE_QUIET_SECONDS", 0.0)  # a later run: told again
    monkeypatch.setattr(_numba_cache, "_noticed", False)
    caching.Cache(ours).load_overload(None, None)
    assert capsys.readouterr().err.count("compiling numerical kernels") == 1


def test_a_cache_hit_prints_nothing(monkeypatch, capsys, tmp_path):
    monkeypatch.setattr(_numba_cache, "_noticed", False)
    monkeypatch.setattr(_numba_cache, "_MARKER", str(tmp_path / "marker"))
    caching = fake_caching(object())
    _numba_cache._patch(caching)
    assert caching.Cache(ours).load_overload(None, None) is not None
    assert capsys.readouterr().err == ""


def test_warmup_runs_a_method_on_every_case_it_applies_to():
    done = subprocess.run(
        [sys.executable, "-m", "faceretarget.cli", "warmup", "--methods", "spacetime"],
        capture_output=True,
        text=True,
        timeout=900,
    )
    assert done.returncode == 0, done.stderr
    line = next(l for l in done.stdout.splitlines() if l.startswith("spacetime"))
    assert (
        int(line.split()[1]) >= 4
    )  # synthetic x2, ict, cross_rig markers and mesh (not the mesh-only target)
    assert "warm in" in done.stdout


def test_a_shared_kernel_file_is_part_of_every_kernel_cache_stamp(monkeypatch, tmp_path):
    """numba keys a cached kernel on its own file only; a caller of a shared kernel (spacetime's
    block solve -> geometry._nnls_kernels.cholesky) must not keep the old callee after that file
    changes: every kernel module's stamp is part of each of our kernels' cache stamp."""
    shared = tmp_path / "_shared_kernels.py"
    shared.write_text("x = 1\n")
    monkeypatch.setattr(_numba_cache, "_kernel_files", lambda: [str(shared)])
    monkeypatch.setattr(_numba_cache, "_stamp", None)

    class Cache:
        def __init__(self, py_func):
            self._py_func = py_func
            self._cache_file = types.SimpleNamespace(_source_stamp=(1.0, 10))

        def save_overload(self, sig, data):
            return None

        def load_overload(self, sig, target_context):
            return None

    caching = types.SimpleNamespace(Cache=Cache)
    _numba_cache._patch(caching)
    before = caching.Cache(ours)._cache_file._source_stamp
    assert before[0] == (1.0, 10) and str(shared) in str(before[1])
    assert caching.Cache(theirs)._cache_file._source_stamp == (
        1.0,
        10,
    )  # somebody else's kernels: untouched
    shared.write_text("x = 22\n")  # the shared file changes (size here; mtime too)
    monkeypatch.setattr(_numba_cache, "_stamp", None)  # a new process
    assert caching.Cache(ours)._cache_file._source_stamp != before
