"""Shared machinery of the reliability suite (imported as ``reliability.fuzzkit``).

- :func:`fuzz`: hypothesis settings. CI mode (default) runs a few dozen examples per
  test, derandomized so a CI failure reproduces; ``FACERETARGET_FUZZ_EXAMPLES=N`` runs N
  random examples per test (the long mode, see docs/reliability.md).
- :func:`typed`: run a call and return its result or the :class:`FaceRetargetError` it
  raised; any other exception fails the test with the exception type and the line that
  raised it.
- :data:`TRIED`: inputs tried per area; ``conftest.py`` prints it at the end of the run.
- Strategies for "anything a user could pass" (:func:`junk`) and for near-valid arrays.
"""

from __future__ import annotations

import collections
import json
import math
import os
import traceback
from datetime import timedelta

import numpy as np
from hypothesis import HealthCheck, Phase, settings
from hypothesis import strategies as st
from hypothesis.extra import numpy as hnp

from faceretarget.errors import FaceRetargetError

EXAMPLES_ENV = "FACERETARGET_FUZZ_EXAMPLES"

#: Inputs tried, by area ("model", "readers", ...); printed by the conftest summary.
TRIED: collections.Counter = collections.Counter()
#: Of those, how many ended in a typed error (the rest were clean results).
REJECTED: collections.Counter = collections.Counter()
#: Inputs that raised anything else (each one also fails its test).
UNTYPED: collections.Counter = collections.Counter()
#: (method, scenario) -> how a numerical edge case ended; printed by the conftest summary.
OUTCOMES: dict = {}


def long_mode() -> bool:
    return bool(os.environ.get(EXAMPLES_ENV, "").strip())


def examples(default: int) -> int:
    """Examples per test: ``default`` in CI mode, ``$FACERETARGET_FUZZ_EXAMPLES`` in long mode."""
    raw = os.environ.get(EXAMPLES_ENV, "").strip()
    return max(1, int(raw)) if raw else default


def fuzz(default: int = 30, **overrides):
    """Hypothesis settings for one fuzz test (``default`` examples in CI mode).

    The per-example deadline is far above any normal run time: it only catches hangs
    (pytest-timeout is the second net, see conftest).
    """
    kw = dict(
        max_examples=examples(default),
        deadline=timedelta(seconds=20),
        derandomize=not long_mode(),
        database=None,
        print_blob=True,
        phases=[Phase.explicit, Phase.reuse, Phase.generate, Phase.target, Phase.shrink],
        suppress_health_check=[
            HealthCheck.too_slow,
            HealthCheck.data_too_large,
            HealthCheck.filter_too_much,
            HealthCheck.function_scoped_fixture,
            HealthCheck.large_base_example,
        ],
    )
    kw.update(overrides)
    return settings(**kw)


def count(area: str, n: int = 1) -> None:
    """Count ``n`` inputs tried under ``area`` that do not go through :func:`typed`."""
    TRIED[area] += n


def typed(area: str, call, *args, **kwargs):
    """``call(*args, **kwargs)``: its result, or the FaceRetargetError it raised.

    Counts the input under ``area``. Any other exception fails the test, naming the
    exception type and the source line that raised it.
    """
    TRIED[area] += 1
    try:
        return call(*args, **kwargs)
    except FaceRetargetError as exc:
        REJECTED[area] += 1
        assert str(exc).strip(), f"{type(exc).__name__} raised without a message"
        return exc
    except Exception as exc:  # the failure this suite exists to find
        UNTYPED[area] += 1
        frame = traceback.extract_tb(exc.__traceback__)[-1]
        raise AssertionError(
            f"untyped {type(exc).__module__}.{type(exc).__name__} from {getattr(call, '__qualname__', call)}: {exc} "
            f"(raised at {frame.filename}:{frame.lineno}: {frame.line})"
        ) from exc


def failed(result) -> bool:
    return isinstance(result, FaceRetargetError)


# ---------------------------------------------------------------------------------------
# strategies
# ---------------------------------------------------------------------------------------
SPECIAL_FLOATS = [0.0, -0.0, 1.0, -1.0, np.nan, np.inf, -np.inf, 1e-300, 1e300, 5e-324]


def any_floats():
    return st.one_of(
        st.floats(allow_nan=True, allow_infinity=True), st.sampled_from(SPECIAL_FLOATS)
    )


def finite_floats(bound: float = 1e3):
    return st.floats(-bound, bound, allow_nan=False, allow_infinity=False)


_DTYPES = [
    np.float64,
    np.float32,
    np.float16,
    np.int64,
    np.int32,
    np.uint8,
    np.bool_,
    np.complex128,
    "U3",
    "S2",
    "datetime64[s]",
]


def _object_array(draw_list):
    arr = np.empty(len(draw_list), dtype=object)
    arr[:] = draw_list
    return arr


def small_arrays(max_dims: int = 4, max_side: int = 5):
    """numpy arrays of every dtype kind (NaN/inf included), ranks 0..max_dims, sides 0..max_side."""
    shapes = hnp.array_shapes(min_dims=0, max_dims=max_dims, min_side=0, max_side=max_side)
    plain = st.sampled_from(_DTYPES).flatmap(lambda dt: hnp.arrays(np.dtype(dt), shapes))
    objects = st.lists(
        st.one_of(st.none(), st.integers(), any_floats(), st.text(max_size=3)), max_size=6
    ).map(_object_array)
    return st.one_of(plain, objects)


def ragged():
    """Lists of rows of unequal lengths (numpy cannot make them rectangular)."""
    lengths = st.tuples(st.integers(0, 3), st.integers(1, 3))
    return lengths.flatmap(
        lambda ab: st.tuples(
            st.lists(finite_floats(), min_size=ab[0], max_size=ab[0]),
            st.lists(finite_floats(), min_size=ab[0] + ab[1], max_size=ab[0] + ab[1]),
        )
    ).map(list)


def ragged_frames(dim: int = 3):
    """A list of per-frame ``(V_f, dim)`` arrays whose vertex counts differ between frames."""
    counts = st.lists(st.integers(1, 5), min_size=2, max_size=4).filter(lambda c: len(set(c)) > 1)
    return counts.map(lambda c: [np.arange(n * dim, dtype=float).reshape(n, dim) for n in c])


def junk():
    """Anything a user might pass where an array, name list or number is expected."""
    scalars = st.one_of(
        st.none(),
        st.booleans(),
        st.integers(),
        any_floats(),
        st.complex_numbers(),
        st.text(max_size=4),
        st.binary(max_size=4),
    )
    return st.one_of(
        scalars,
        small_arrays(),
        ragged(),
        ragged_frames(),
        st.lists(scalars, max_size=4),
        st.dictionaries(st.text(max_size=3), scalars, max_size=3),
    )


def float_array(shape, *, special: bool = True, bound: float = 1e3, dtype=np.float64):
    """A float array of exactly ``shape``; with ``special`` some entries may be NaN/inf/extreme."""
    elements = (
        st.one_of(finite_floats(bound), st.sampled_from(SPECIAL_FLOATS))
        if special
        else finite_floats(bound)
    )
    return hnp.arrays(np.dtype(dtype), shape, elements=elements)


def index_array(shape, low: int, high: int):
    return hnp.arrays(np.int64, shape, elements=st.integers(low, high))


def names(count: int | None = None):
    """Unicode names: sometimes blank, duplicated, not strings, or of the wrong count."""
    name = st.one_of(
        st.text(max_size=6),
        st.sampled_from(
            [
                "",
                " ",
                "jawOpen",
                "JawOpen",
                "mouthSmile_L",
                "\u00e9\u00e8",
                "\U0001f600",
                "a\x00b",
                "x\ny",
            ]
        ),
        st.sampled_from([None, 0, 1.5, b"jawOpen", np.nan]),  # not names at all
    )
    size = (
        st.integers(0, 6)
        if count is None
        else st.sampled_from([count, count, count, max(0, count - 1), count + 1])
    )
    return size.flatmap(lambda n: st.lists(name, min_size=n, max_size=n))


def unique_names(count: int):
    return st.lists(
        st.text(min_size=1, max_size=6).filter(lambda s: s.strip()),
        min_size=count,
        max_size=count,
        unique=True,
    )


# ---------------------------------------------------------------------------------------
# a small TOML writer (values, inline tables), enough to build any document shape
# ---------------------------------------------------------------------------------------
def toml_value(v) -> str:
    if isinstance(v, bool):
        return "true" if v else "false"
    if isinstance(v, int):
        return str(v)
    if isinstance(v, float):
        if math.isnan(v):
            return "nan"
        if math.isinf(v):
            return "inf" if v > 0 else "-inf"
        return repr(v)
    if isinstance(v, str):
        return json.dumps(v)
    if isinstance(v, list):
        return "[" + ", ".join(toml_value(x) for x in v) + "]"
    if isinstance(v, dict):
        return (
            "{" + ", ".join(f"{json.dumps(str(k))} = {toml_value(x)}" for k, x in v.items()) + "}"
        )
    raise TypeError(v)


def toml_document(doc: dict) -> str:
    return "\n".join(f"{json.dumps(str(k))} = {toml_value(v)}" for k, v in doc.items()) + "\n"


def toml_values(words=()):
    """Any TOML value (nested arrays and tables), strings sometimes drawn from ``words``."""
    pools = [st.booleans(), st.integers(-(2**63), 2**63 - 1), st.floats(), st.text(max_size=8)]
    if words:
        pools.append(st.sampled_from(list(words)))
    return st.recursive(
        st.one_of(*pools),
        lambda inner: st.one_of(
            st.lists(inner, max_size=3), st.dictionaries(st.text(max_size=4), inner, max_size=3)
        ),
        max_leaves=8,
    )
