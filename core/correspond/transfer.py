"""Closest-point correspondence between surfaces, and carrying per-vertex values across it."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import numpy.typing as npt
import scipy.sparse as sp

from ..errors import ShapeError
from ..geometry.mesh_ops import barycentric_matrix
from ..model import Mesh

__all__ = ["Correspondence", "closest_point_transfer", "transfer_back"]


@dataclass(frozen=True)
class Correspondence:
    """For each of P points, a point on a mesh with V vertices.

    triangle_ids : (P,) int64
    barycentric : (P, 3) float64
    distances : (P,) float64 unsigned distance from each point to its mesh point
    triangles : (T, 3) int64 the mesh's triangles
    n_vertices : int
    """

    triangle_ids: np.ndarray
    barycentric: np.ndarray
    distances: np.ndarray
    triangles: np.ndarray
    n_vertices: int

    @property
    def matrix(self) -> sp.csr_matrix:
        """(P, V) sparse interpolation matrix (three barycentric weights per row)."""
        return barycentric_matrix(
            self.triangles[self.triangle_ids], self.barycentric, self.n_vertices
        )

    def apply(self, values: npt.ArrayLike) -> np.ndarray:
        """Interpolate per-vertex ``values`` at the corresponding points.

        ``values`` has the vertex axis second to last, ``(..., V, K)``, or is ``(V,)``;
        the result replaces V by P (e.g. a sequence ``(F, V, 3)`` becomes ``(F, P, 3)``).
        """
        x = np.asarray(values)
        if x.dtype.kind not in "fiu":
            x = np.asarray(x, dtype=np.float64)
        squeeze = x.ndim == 1
        if squeeze:
            x = x[:, None]
        if x.shape[-2] != self.n_vertices:
            raise ShapeError(
                f"Correspondence.apply: values have {x.shape[-2]} vertices, the mesh has {self.n_vertices}"
            )
        corners = self.triangles[self.triangle_ids]  # (P, 3)
        bary = np.asarray(self.barycentric, dtype=np.float64)
        # gather the three corners (no transposed copy of the whole sequence, no sparse matrix)
        out = x[..., corners[:, 0], :] * bary[:, 0, None]
        out += x[..., corners[:, 1], :] * bary[:, 1, None]
        out += x[..., corners[:, 2], :] * bary[:, 2, None]
        return out[:, 0] if squeeze else out


def closest_point_transfer(points: Mesh | npt.ArrayLike, mesh: Mesh) -> Correspondence:
    """Closest points on ``mesh`` of ``points`` (a Mesh's vertices or a (P, 3) array)."""
    from ..geometry.raycast import RayCaster

    pts = points.vertices if isinstance(points, Mesh) else np.asarray(points, dtype=np.float64)
    if pts.ndim != 2 or pts.shape[1] != 3:
        raise ShapeError(f"closest_point_transfer: points must be (P, 3), got {pts.shape}")
    hits = RayCaster(mesh.vertices, mesh.triangles, backend="bvh").closest(pts)
    return Correspondence(
        hits.triangle,
        hits.barycentric,
        np.abs(hits.distance),
        np.asarray(mesh.triangles),
        mesh.n_vertices,
    )


def transfer_back(resampled: Mesh, values: npt.ArrayLike, target: Mesh) -> np.ndarray:
    """Carry per-vertex ``values`` of a resampled mesh back to the target's own vertices.

    ``resampled`` is the target surface in another topology (e.g. from
    :func:`~faceretarget.correspond.resample_to_topology`) and ``values (..., V_r, K)``
    (or ``(V_r,)``) live on its vertices, e.g. a frame sequence ``(F, V_r, 3)``; each
    target vertex takes the barycentric interpolation at its closest point on
    ``resampled``. Returns ``(..., V_target, K)``.
    """
    if not isinstance(resampled, Mesh) or not isinstance(target, Mesh):
        raise ShapeError(
            "transfer_back(resampled, values, target): resampled and target must be Mesh objects"
        )
    return closest_point_transfer(target, resampled).apply(values)
