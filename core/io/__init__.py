"""File formats: readers and writers registered through the plugin hooks."""
from __future__ import annotations

from ..hookspecs import hookimpl


@hookimpl
def faceretarget_readers():
    return []


@hookimpl
def faceretarget_writers():
    return []
