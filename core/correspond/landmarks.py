"""Landmarks as vertex ids or barycentric points: conversion and projection onto meshes."""

from __future__ import annotations

from collections.abc import Iterable

import numpy as np
import numpy.typing as npt

from ..errors import ShapeError, TopologyMismatchError
from ..model import Landmarks, Mesh

__all__ = [
    "landmark_positions",
    "project_landmarks",
    "to_barycentric",
    "to_vertex_ids",
    "paired_positions",
]


def landmark_positions(mesh: Mesh, landmarks: Landmarks) -> np.ndarray:
    """(N, 3) positions of ``landmarks`` on ``mesh`` (vertex ids or barycentric points)."""
    landmarks.validate_for(mesh)
    return np.asarray(landmarks.positions(mesh.vertices, mesh.triangles), dtype=np.float64)


def project_landmarks(
    mesh: Mesh, points: npt.ArrayLike, names: Iterable[str] | None = None
) -> Landmarks:
    """Barycentric landmarks at the closest surface points of ``mesh`` to ``points (N, 3)``."""
    from ..geometry.raycast import RayCaster

    pts = np.asarray(points, dtype=np.float64)
    if pts.ndim != 2 or pts.shape[1] != 3 or len(pts) == 0:
        raise ShapeError(f"project_landmarks: points must be (N, 3) with N >= 1, got {pts.shape}")
    hits = RayCaster(mesh.vertices, mesh.triangles, backend="bvh").closest(pts)
    return Landmarks(triangle_ids=hits.triangle, barycentric=hits.barycentric, names=names)


def to_barycentric(landmarks: Landmarks, mesh: Mesh) -> Landmarks:
    """The same points as barycentric landmarks (a vertex id becomes a corner of one of its triangles)."""
    landmarks.validate_for(mesh)
    if landmarks.vertex_ids is None:
        return landmarks
    ids = landmarks.vertex_ids
    tri = mesh.triangles
    # first triangle using each vertex, and the corner it occupies
    flat = tri.ravel()
    order = np.argsort(flat, kind="stable")
    first = np.full(mesh.n_vertices, -1, dtype=np.int64)
    uniq, start = np.unique(flat[order], return_index=True)
    first[uniq] = order[start]
    if np.any(first[ids] < 0):
        bad = ids[first[ids] < 0][:5].tolist()
        raise TopologyMismatchError(
            f"to_barycentric: landmark vertices {bad} belong to no triangle"
        )
    t_ids, corner = np.divmod(first[ids], 3)
    bary = np.zeros((len(ids), 3))
    bary[np.arange(len(ids)), corner] = 1.0
    return Landmarks(triangle_ids=t_ids, barycentric=bary, names=landmarks.names)


def to_vertex_ids(landmarks: Landmarks, mesh: Mesh) -> Landmarks:
    """The nearest mesh vertex of each landmark (barycentric points snap to their largest weight)."""
    landmarks.validate_for(mesh)
    if landmarks.vertex_ids is not None:
        return landmarks
    assert landmarks.barycentric is not None  # no vertex ids: triangle ids and barycentric
    corners = mesh.triangles[landmarks.triangle_ids]
    ids = corners[np.arange(len(corners)), np.argmax(landmarks.barycentric, axis=1)]
    return Landmarks(ids, names=landmarks.names)


def paired_positions(
    mesh_a: Mesh, landmarks_a: Landmarks, mesh_b: Mesh, landmarks_b: Landmarks
) -> tuple[np.ndarray, np.ndarray]:
    """Positions of two landmark sets paired by order: ``(N, 3)`` and ``(N, 3)``."""
    if len(landmarks_a) != len(landmarks_b):
        raise TopologyMismatchError(
            f"landmark sets differ in size ({len(landmarks_a)} vs {len(landmarks_b)}); landmark i of one must "
            "correspond to landmark i of the other"
        )
    return landmark_positions(mesh_a, landmarks_a), landmark_positions(mesh_b, landmarks_b)
