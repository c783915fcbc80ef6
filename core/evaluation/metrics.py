"""Evaluation metrics, registered through the ``faceretarget_metrics`` hook."""
from __future__ import annotations

from ..hookspecs import hookimpl


@hookimpl
def faceretarget_metrics():
    return []
