"""Built-in retargeter plugin `layers` (being implemented)."""
from faceretarget.hookspecs import hookimpl


@hookimpl
def faceretarget_retargeters():
    return []
