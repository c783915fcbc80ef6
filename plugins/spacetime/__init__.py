"""Built-in retargeter plugin `spacetime` (being implemented)."""
from faceretarget.hookspecs import hookimpl


@hookimpl
def faceretarget_retargeters():
    return []
