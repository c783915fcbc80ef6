"""Built-in retargeter plugin ``coating``: Xu et al. 2014 and the deformation-transfer baseline.

- ``coating``: Controllable High-fidelity Facial Performance Transfer (Xu, Chai, Liu,
  Yang; ACM TOG 33(4) 2014): multi-scale decomposition (Taubin smoothing + Laplacian
  coating), blendshape bases selected from the source by greedy NNLS, feature-preserving
  deformation transfer of the bases, local-frame coating transfer of the details, and
  spacetime editing of bases, weights and wrinkles.
- ``deformation_transfer``: per-frame Sumner & Popovic (2004) deformation transfer.

Importing this package does not import numba; kernels compile on first use.
"""

from faceretarget.hookspecs import hookimpl

__all__ = ["faceretarget_retargeters", "DetailEdit"]


@hookimpl
def faceretarget_retargeters():
    from .retargeter import CoatingRetargeter, DeformationTransferRetargeter

    return [CoatingRetargeter, DeformationTransferRetargeter]


@hookimpl
def faceretarget_presets():
    from .presets import PRESETS  # the report's reproductions of the paper; imports no solver

    return list(PRESETS)


def __getattr__(name):
    if name == "DetailEdit":
        from .details import DetailEdit

        return DetailEdit
    raise AttributeError(f"module {__name__!r} has no attribute {name!r}")
