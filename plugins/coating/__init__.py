"""Built-in retargeter plugin `coating` (being implemented)."""
from faceretarget.hookspecs import hookimpl


@hookimpl
def faceretarget_retargeters():
    return []
