"""Built-in retargeter plugin ``spacetime``: Seol et al. 2012, Spacetime Expression Cloning for Blendshapes.

Registers ``spacetime`` (movement matching with PCA prior and spacetime editing) and the
paper's per-frame baselines ``spacetime_noconst``, ``spacetime_rangepf`` and
``spacetime_priorpf``. Importing this package does not import numba: the kernels compile
on first use.
"""

from faceretarget.hookspecs import hookimpl


@hookimpl
def faceretarget_retargeters():
    from .retargeter import RETARGETERS

    return list(RETARGETERS)


@hookimpl
def faceretarget_presets():
    from .presets import PRESETS  # the report's reproductions of the paper; imports no solver

    return list(PRESETS)
