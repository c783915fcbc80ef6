"""Cold start (issue 16 item 6): every numba specialization compiles apart (seconds each),
so a kernel must not be compiled twice for the same work. Two accidental sources are
guarded here: a literal integer argument from a jitted caller (``nf = 0`` counters, module
constants), which numba compiles as its own ``Literal[int]`` specialization, and a read-only
and a writable array for the same argument. The methods run in a fresh process, so only
what the library itself compiles is seen (tests call some kernels directly)."""

import json
import subprocess
import sys

import pytest

PROBE = """
import gc, json
from numba.core.registry import CPUDispatcher
import faceretarget as fr
case = fr.cases.synthetic(seed=0, resolution=800, n_frames=4)
for name in ("spacetime", "spacetime_rangepf", "layers", "coating", "deformation_transfer", "normalmesh"):
    fr.get(name).fit(case.source, case.target).retarget(case.source).compute()
print(json.dumps({
    f"{d.py_func.__module__}.{d.py_func.__name__}": [[str(a) for a in s] for s in d.signatures]
    for d in gc.get_objects()
    if isinstance(d, CPUDispatcher) and d.py_func.__module__.startswith("faceretarget")
}))
"""


@pytest.fixture(scope="module")
def signatures():
    done = subprocess.run(
        [sys.executable, "-c", PROBE], capture_output=True, text=True, timeout=900, check=True
    )
    return json.loads(done.stdout.strip().splitlines()[-1])


def test_the_methods_compile_kernels(signatures):
    assert len(signatures) > 20  # the probe saw the kernels (not an empty scan)


def test_no_kernel_is_specialized_on_a_literal_argument(signatures):
    literal = sorted(
        f"{name}{sig}" for name, sigs in signatures.items() for sig in sigs if "Literal" in str(sig)
    )
    assert not literal, (
        "kernels compiled for literal arguments (pass np.int64(...) or a non-literal "
        f"variable from the jitted caller): {literal}"
    )


def test_no_kernel_is_compiled_for_read_only_and_writable_twins(signatures):
    twins = sorted(
        name
        for name, sigs in signatures.items()
        if len({tuple(a.replace("readonly ", "") for a in s) for s in sigs}) < len(sigs)
    )
    assert not twins, (
        "kernels compiled for both read-only and writable arrays of the same type (pass "
        f"faceretarget._validate.readonly(...) views of read-only inputs): {twins}"
    )
