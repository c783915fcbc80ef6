"""spacetime's registered variants are plain subclasses that change only defaults."""

import inspect

import pytest

import faceretarget as fr
from faceretarget import manifest
from faceretarget.plugins.spacetime import retargeter as st

VARIANTS = {
    "spacetime_paper": (st.SpacetimePaper, {}),
    "spacetime_noconst": (st.SpacetimeNoconst, {"mode": "noconst"}),
    "spacetime_rangepf": (st.SpacetimeRangepf, {"mode": "rangepf"}),
    "spacetime_priorpf": (st.SpacetimePriorpf, {"mode": "priorpf", "alpha": 0.5}),
}


@pytest.mark.parametrize("name", sorted(VARIANTS))
def test_variant_is_a_plain_subclass_with_the_papers_defaults(name):
    cls, own = VARIANTS[name]
    assert cls.__bases__ == (st.SpacetimeRetargeter,) and "__init__" in vars(cls)
    assert not hasattr(cls.__init__, "__signature__")  # its own signature, not a rewritten one
    assert cls.name == name and fr.get(name).__class__ is cls
    assert cls.default_params() == {**st.SpacetimeRetargeter.default_params(), **st.PAPER, **own}
    assert not manifest.disagreements(cls, manifest.builtin()[name])
    # every argument reaches the base class
    params = {p: v for p, v in cls.default_params().items()}
    params.update(alpha=0.25, lower=-0.25, max_samples=50)
    assert cls(**params).get_params() == params
    base = inspect.signature(st.SpacetimeRetargeter.__init__).parameters
    assert list(inspect.signature(cls.__init__).parameters) == list(base)


def test_variants_keep_their_capabilities():
    assert st.SpacetimePaper.capabilities == st.SpacetimeRetargeter.capabilities
    for cls in (st.SpacetimeNoconst, st.SpacetimeRangepf, st.SpacetimePriorpf):
        assert cls.capabilities.edit is False
        assert {
            **cls.capabilities.as_dict(),
            "edit": True,
        } == st.SpacetimeRetargeter.capabilities.as_dict()
