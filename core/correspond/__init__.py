"""Correspondence between meshes of different topologies.

- landmarks as vertex ids or barycentric points: :func:`project_landmarks`,
  :func:`to_barycentric`, :func:`to_vertex_ids`, :func:`landmark_positions`;
- :func:`rbf_warp`: the landmark RBF warp of space (phi(r) = r + linear part, Seol 2012 sec. 3.2);
- :func:`closest_point_transfer` / :class:`Correspondence`: closest surface points as
  triangle + barycentric, with interpolation of per-vertex values;
- :func:`resample_to_topology`: landmark-guided non-rigid ICP that refits the source mesh
  onto a target surface (the target in the source topology) with a :class:`QualityReport`,
  and :func:`transfer_back` to carry results back to the target's own vertices.
"""

from .landmarks import (
    landmark_positions,
    paired_positions,
    project_landmarks,
    to_barycentric,
    to_vertex_ids,
)
from .nricp import DEFAULT_STIFFNESS, QualityReport, quality_report, resample_to_topology
from .topology import boundary_loops
from .transfer import Correspondence, closest_point_transfer, transfer_back
from .warp import rbf_warp

__all__ = [
    "Correspondence",
    "DEFAULT_STIFFNESS",
    "QualityReport",
    "boundary_loops",
    "closest_point_transfer",
    "landmark_positions",
    "paired_positions",
    "project_landmarks",
    "quality_report",
    "rbf_warp",
    "resample_to_topology",
    "to_barycentric",
    "to_vertex_ids",
    "transfer_back",
]
