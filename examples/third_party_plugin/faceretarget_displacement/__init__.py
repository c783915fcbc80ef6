"""A third-party faceretarget plugin: direct displacement transfer through a landmark RBF warp.

Registered through the entry point ``displacement`` in the group ``faceretarget``
(see this package's pyproject.toml). Install with ``pip install .`` and it appears in
``faceretarget list``.
"""

import faceretarget


@faceretarget.hookimpl
def faceretarget_retargeters():
    from .retargeter import DisplacementRetargeter

    return [DisplacementRetargeter]
