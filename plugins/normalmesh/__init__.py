"""Built-in retargeter plugin ``normalmesh``: Na & Jung 2004, Hierarchical Retargetting of Fine
Facial Motions (normal meshes of Guskov et al. 2000). See ``docs/methods/normalmesh.md``."""

from faceretarget.hookspecs import hookimpl


@hookimpl
def faceretarget_retargeters():
    from .retargeter import NormalMeshRetargeter  # numba kernels stay out of import time

    return [NormalMeshRetargeter]


@hookimpl
def faceretarget_presets():
    from .presets import PRESETS  # the report's reproductions of the paper; imports no solver

    return list(PRESETS)
