"""Processes sharing numba's on-disk cache never fail a call (issue 15, hole 10).

Two ``faceretarget demo`` runs at once once ended in an untyped ``RuntimeError: no compiled
object yet`` raised by numba while it saved a kernel another process had just cached.
Every process here gets a temporary ``NUMBA_CACHE_DIR`` (the user's cache is never
touched) and a kernel module of its own in ``tmp_path``: a cached caller linking a cached
callee, the shape of faceretarget's kernels.
"""

import os
import subprocess
import sys
import textwrap

import pytest
from reliability.fuzzkit import count

AREA = "numba cache sharing"

KERNELS = """
import numba as nb


@nb.njit(cache=True)
def callee(x):
    return x * 2.0 + 1.0


@nb.njit(cache=True)
def caller(xs):
    s = 0.0
    for i in range(xs.shape[0]):
        s += callee(xs[i])
    return s
"""

#: Expected result of caller(arange(10.0)): sum(2 i + 1) for i < 10.
EXPECTED = 100.0

SCRIPT = """
import sys
import numpy as np
import faceretarget  # installs the cache guard
sys.path.insert(0, sys.argv[1])
if len(sys.argv) > 2 and sys.argv[2] == "inject":
    # what numba does when the race hits: the cache save finds no compiled object
    from numba.core import codegen

    def no_object(self):
        raise RuntimeError("no compiled object yet for %s" % (self,))

    codegen.CodeLibrary._get_compiled_object = no_object
import fr_test_kernels
print(repr(float(fr_test_kernels.caller(np.arange(10.0)))))
"""


@pytest.fixture
def kernel_dir(tmp_path):
    folder = tmp_path / "kernels"
    folder.mkdir()
    (folder / "fr_test_kernels.py").write_text(textwrap.dedent(KERNELS))
    (tmp_path / "run.py").write_text(textwrap.dedent(SCRIPT))
    return folder


def start(tmp_path, cache, *extra):
    env = {**os.environ, "NUMBA_CACHE_DIR": str(cache)}
    env.pop("NUMBA_DISABLE_JIT", None)
    return subprocess.Popen(
        [sys.executable, str(tmp_path / "run.py"), str(tmp_path / "kernels"), *extra],
        env=env,
        stdout=subprocess.PIPE,
        stderr=subprocess.PIPE,
        text=True,
    )


def finish(proc) -> str:
    out, err = proc.communicate(timeout=300)
    assert proc.returncode == 0, f"a process sharing the numba cache failed:\n{err}"
    assert float(out.strip().splitlines()[-1]) == EXPECTED
    return err


def test_a_failing_cache_save_does_not_fail_the_call(kernel_dir, tmp_path):
    """The error numba raises in the race, injected: the kernel still runs, only its cache entry is lost."""
    count(AREA)
    finish(start(tmp_path, tmp_path / "cache", "inject"))


def test_two_processes_compile_and_load_the_same_cached_kernels_at_once(kernel_dir, tmp_path):
    cache = tmp_path / "cache"
    rounds = 3
    for k in range(rounds):
        if k == 1:  # a cache written by the first round, half of it gone: one loads, one compiles
            for f in cache.rglob("*caller*"):
                f.unlink()
        procs = [start(tmp_path, cache) for _ in range(2)]
        for proc in procs:
            finish(proc)
        count(AREA, 2)
    assert any(cache.rglob("*.nbi")), "the kernels were cached in the temporary NUMBA_CACHE_DIR"
