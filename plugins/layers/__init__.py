"""Built-in retargeter plugin ``layers``: Kholgade, Matthews & Sheikh 2011,
"Content Retargeting Using Parameter-Parallel Facial Layers" (SCA 2011).

The retargeter class lives in :mod:`.retargeter`; helpers that build the layered bases
(``actor_layers_from_frames``, ``layered_rig_from_blendshapes``, ``default_masks``) in
:mod:`.build`. Nothing here imports numba (kernels compile on first use).
"""

from faceretarget.hookspecs import hookimpl

__all__ = [
    "actor_layers_from_frames",
    "layered_rig_from_blendshapes",
    "default_masks",
    "LayersRetargeter",
]


@hookimpl
def faceretarget_retargeters():
    from .retargeter import LayersRetargeter  # numba stays out of import time

    return [LayersRetargeter]


@hookimpl
def faceretarget_presets():
    from .presets import PRESETS  # the report's reproductions of the paper; imports no solver

    return list(PRESETS)


def __getattr__(name):
    if name in ("actor_layers_from_frames", "layered_rig_from_blendshapes", "default_masks"):
        from . import build

        return getattr(build, name)
    if name == "LayersRetargeter":
        from .retargeter import LayersRetargeter

        return LayersRetargeter
    raise AttributeError(name)
