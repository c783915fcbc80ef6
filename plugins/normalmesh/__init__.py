"""Built-in retargeter plugin `normalmesh` (being implemented)."""
from faceretarget.hookspecs import hookimpl


@hookimpl
def faceretarget_retargeters():
    return []
