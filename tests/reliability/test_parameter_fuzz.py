"""Bad parameter values are typed errors naming the parameter, in every registered method.

``faceretarget.get(NAME, param=value)`` stores anything (the estimator contract: no
validation in ``__init__``), so ``fit``/``retarget`` must check what they use: a wrong
type, NaN/inf, a negative count or an unknown mode must end in a FaceRetargetError, not
in a TypeError deep inside numpy or numba. ``faceretarget._validate.check_number`` and
``check_choice`` are the shared helpers for that (tested here too).
"""
import numpy as np
import pytest
from hypothesis import given
from hypothesis import strategies as st

import faceretarget as fr
from faceretarget import errors
from faceretarget._validate import check_choice, check_number
from reliability.fuzzkit import failed, fuzz, junk, typed

AREA = "method parameters"
#: methods whose parameter checks still let untyped errors through (owners: plugins/<name>)
KNOWN = {
}
METHODS = [
    pytest.param(a["name"], marks=pytest.mark.xfail(strict=True, reason=KNOWN[a["name"]])) if a["name"] in KNOWN else a["name"]
    for a in fr.available()
]
BAD_VALUES = st.one_of(
    st.sampled_from([None, -1, 0, -0.5, 1e300, -1e300, np.nan, np.inf, -np.inf, "nonsense", "", [], [1, 2], {"a": 1}, True, 10**20, (0,)]),
    junk(),
)


@pytest.fixture(scope="module")
def case():
    return fr.cases.synthetic(resolution=200, n_frames=4)


@pytest.mark.parametrize("method", METHODS)
@given(data=st.data())
@fuzz(10)
def test_any_parameter_value(method, case, data):
    cls = fr.info(method).cls
    param = data.draw(st.sampled_from(sorted(cls.default_params())), label="parameter")
    value = data.draw(BAD_VALUES, label="value")
    source = case.source if case.source.kind in cls.capabilities.sources else None
    if source is None:
        pytest.skip(f"{method} takes no {case.source.kind} source")

    def run():
        return fr.get(method, **{param: value}).fit(source, case.target).retarget(source)

    result = typed(AREA, run)
    if failed(result):
        return
    v = np.asarray(result.vertices)
    assert v.shape == (source.n_frames, case.target.neutral.n_vertices, 3) and np.isfinite(v).all(), (
        f"{method}({param}={value!r}) returned a result that is not finite or of the wrong shape"
    )


@given(value=st.one_of(junk(), st.integers(), st.floats()), integer=st.booleans(), low=st.sampled_from([None, 0, 1]),
       high=st.sampled_from([None, 10]), open_low=st.booleans(), allow_none=st.booleans())
@fuzz(200)
def test_check_number(value, integer, low, high, open_low, allow_none):
    got = typed(AREA, check_number, value, "p", integer=integer, low=low, high=high, open_low=open_low, allow_none=allow_none)
    if failed(got):
        assert isinstance(got, errors.InputError) and str(got).startswith("p: expected")
        return
    if got is None:
        assert value is None and allow_none
        return
    assert type(got) is (int if integer else float) and (integer or np.isfinite(got))
    assert low is None or got > low or (got == low and not open_low)
    assert high is None or got <= high
    assert not isinstance(value, bool)


@given(value=st.one_of(junk(), st.sampled_from(["a", "b", "A"])))
@fuzz(60)
def test_check_choice(value):
    got = typed(AREA, check_choice, value, "mode", ("a", "b"))
    if failed(got):
        assert isinstance(got, errors.InputError) and "'a', 'b'" in str(got)
    else:
        assert got in ("a", "b") and got == value
