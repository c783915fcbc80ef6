"""Peak memory of a reader call, and the largest size it checked against the memory budget.

Import as ``from memtools import traced_memory`` (``tests/`` is on the test path).
"""

from __future__ import annotations

import tracemalloc

import pytest

#: Modules whose ``check_budget`` the text readers call.
TEXT_READER_MODULES = (
    "faceretarget.io._common",
    "faceretarget.io.meshes",
    "faceretarget.io.markers",
    "faceretarget.io.weights",
)
#: ... and the binary and glTF readers.
READER_MODULES = TEXT_READER_MODULES + ("faceretarget.io.gltf", "faceretarget.io.sequences")


def traced_memory(call, modules=READER_MODULES):
    """``(result of call(), peak traced bytes, largest size checked against the budget)``;
    with ``modules=()`` nothing is spied (the last item is then 0)."""
    from faceretarget.io import _common

    checked = [0.0]
    real = _common.check_budget

    def spy(path, nbytes, what):
        checked[0] = max(checked[0], float(nbytes))
        return real(path, nbytes, what)

    mp = pytest.MonkeyPatch()
    for module in modules:
        mp.setattr(f"{module}.check_budget", spy, raising=False)
    tracemalloc.start()
    try:
        tracemalloc.reset_peak()
        result = call()
        return result, tracemalloc.get_traced_memory()[1], checked[0]
    finally:
        tracemalloc.stop()
        mp.undo()
