"""Type aliases of the package's annotations."""

from __future__ import annotations

import os
from typing import TYPE_CHECKING, TypeAlias

if TYPE_CHECKING:
    from .model import MarkerSequence, MeshSequence, WeightSequence

#: A file system path as the public functions take it: a string or a ``pathlib.Path``
#: (any ``os.PathLike[str]``).
PathLike: TypeAlias = str | os.PathLike[str]

#: What a :class:`~faceretarget.model.Source` performs: markers, a mesh sequence or weight curves.
Performance: TypeAlias = "MarkerSequence | MeshSequence | WeightSequence"
