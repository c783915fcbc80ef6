"""Preprocessing (Xu et al. 2014, sec. 3): source and target references on one topology.

The method needs the source and target reference meshes in one topology. When the
target already shares the source's triangles nothing is done. Otherwise the target is
resampled in the source's topology by the landmark-guided non-rigid ICP of
:mod:`faceretarget.correspond` (the paper's semi-automatic registration after Huang et
al. 2011), the whole transfer runs in the source topology, and the results are carried
back to the target's own vertices.
"""

from __future__ import annotations

import hashlib
import threading
from collections import OrderedDict
from collections.abc import Callable
from dataclasses import dataclass, field
from typing import Any

import numpy as np

from faceretarget.errors import CapabilityError
from faceretarget.model import Mesh, Source, TargetRig

__all__ = ["CommonTopology", "BackMap", "OutputMap", "common_topology", "same_topology"]


def same_topology(a: Mesh, b: Mesh) -> bool:
    return (
        a.n_vertices == b.n_vertices
        and a.triangles.shape == b.triangles.shape
        and np.array_equal(a.triangles, b.triangles)
    )


@dataclass
class CommonTopology:
    """The target expressed in the source topology.

    target_reference : (V_s, 3) the target neutral resampled in the source topology
    target_lines : feature lines as vertex chains of the source topology
    back : maps ``(C, V_s, 3)`` frames (head motion removed) to the target's own
        ``(C, V_t, 3)``: the displacement from the resampled neutral, interpolated at each
        target vertex's closest point, added to the target neutral (identity when the
        topologies agree)
    target_vertex : (V_t,) the source-topology vertex standing for each target vertex
        (for edit constraints given on target vertices)
    report : quality report of the correspondence (empty when not needed)
    """

    same: bool
    target_reference: np.ndarray
    target_lines: dict
    back: Callable[[np.ndarray], np.ndarray]
    target_vertex: np.ndarray
    report: dict = field(default_factory=dict)


def _identity(frames: np.ndarray) -> np.ndarray:
    return frames


#: Resampled targets kept per process (by content): each costs a non-rigid ICP (seconds at 20K
#: vertices), and fitting several methods, or one method several times, on the same pair
#: repeats it (the demo's detail-transfer reproductions spent 38% of their time there).
_CACHE_SIZE = 4
_cache: OrderedDict[bytes, CommonTopology] = OrderedDict()
_cache_lock = threading.Lock()


def _content_key(source: Source, target: TargetRig) -> bytes:
    """A digest of everything :func:`common_topology` reads of its inputs."""
    digest = hashlib.blake2b(digest_size=20)
    for mesh in (source.performance.reference, target.neutral):
        digest.update(np.ascontiguousarray(mesh.vertices, dtype=np.float64).tobytes())
        digest.update(np.ascontiguousarray(mesh.triangles, dtype=np.int64).tobytes())
    for marks in (source.landmarks, target.landmarks):
        for part in (marks.vertex_ids, marks.triangle_ids, marks.barycentric):
            digest.update(b"-" if part is None else np.ascontiguousarray(part).tobytes())
        digest.update(repr(tuple(marks.names)).encode())
    for name, chain in sorted(target.feature_lines.items()):
        digest.update(name.encode() + np.ascontiguousarray(chain, dtype=np.int64).tobytes())
    return digest.digest()


def common_topology(source: Source, target: TargetRig, *, what: str) -> CommonTopology:
    """Bring ``target`` into the topology of the source's mesh sequence (resamplings are
    cached by content: the arrays of the result are read-only and shared)."""
    src_mesh = source.performance.reference
    tgt_mesh = target.neutral
    if same_topology(src_mesh, tgt_mesh):
        return CommonTopology(
            True,
            np.asarray(tgt_mesh.vertices, dtype=np.float64),
            dict(target.feature_lines),
            _identity,
            np.arange(tgt_mesh.n_vertices),
        )
    if source.landmarks is None or target.landmarks is None:
        raise CapabilityError(
            f"{what}: the target mesh ({tgt_mesh.n_vertices} vertices) has a different topology from the source "
            f"({src_mesh.n_vertices} vertices); resampling it needs landmarks on both: pass Source(..., landmarks=...) "
            "and TargetRig(..., landmarks=...) (corresponding points, same order)"
        )
    key = _content_key(source, target)
    with _cache_lock:
        hit = _cache.get(key)
        if hit is not None:
            _cache.move_to_end(key)
    if hit is None:
        hit = _resample(source, target)
        with _cache_lock:
            _cache[key] = hit
            while len(_cache) > _CACHE_SIZE:
                _cache.popitem(last=False)
    return CommonTopology(
        False,
        hit.target_reference,
        dict(hit.target_lines),
        hit.back,
        hit.target_vertex,
        dict(hit.report),
    )


def _resample(source: Source, target: TargetRig) -> CommonTopology:
    from faceretarget.correspond import closest_point_transfer, resample_to_topology

    src_mesh = source.performance.reference
    tgt_mesh = target.neutral
    resampled, report = resample_to_topology(src_mesh, source.landmarks, tgt_mesh, target.landmarks)
    verts = np.asarray(resampled.vertices, dtype=np.float64)
    from scipy.spatial import cKDTree

    target_vertex = cKDTree(verts).query(np.asarray(tgt_mesh.vertices))[1].astype(np.int64)
    lines = {}
    for name, chain in target.feature_lines.items():
        ids = target_vertex[np.asarray(chain)]
        keep = np.concatenate([[True], ids[1:] != ids[:-1]])
        ids = ids[keep]
        if ids.size >= 2:
            lines[name] = ids
    back = BackMap(
        np.asarray(tgt_mesh.vertices, dtype=np.float64),
        verts,
        closest_point_transfer(tgt_mesh, resampled),
    )
    info = report.as_dict() if hasattr(report, "as_dict") else dict(report)
    for array in (verts, target_vertex, back.rest, back.resampled, *lines.values()):
        array.flags.writeable = False  # shared by every fit on this pair
    return CommonTopology(False, verts, lines, back, target_vertex, info)


class BackMap:
    """Frames in the common topology -> the target's own vertices.

    Carries displacements (not positions) through the closest-point correspondence, so
    the target at rest is exactly its neutral.
    """

    def __init__(self, rest: np.ndarray, resampled: np.ndarray, correspondence):
        self.rest = rest
        self.resampled = resampled
        self.correspondence = correspondence

    def __call__(self, frames: np.ndarray) -> np.ndarray:
        return self.rest + self.correspondence.apply(
            np.asarray(frames, dtype=np.float64) - self.resampled
        )


class OutputMap:
    """The transfer's coordinates -> the target's own vertices: ``back(placement.to_target(frames))``."""

    def __init__(self, placement, back):
        self.placement = placement
        self.back = back

    def __call__(self, frames: np.ndarray) -> np.ndarray:
        return self.back(self.placement.to_target(frames))


def describe(report: dict[str, Any]) -> dict[str, Any]:
    """JSON-friendly copy of a correspondence report."""
    out = {}
    for k, v in report.items():
        out[str(k)] = v.tolist() if isinstance(v, np.ndarray) else v
    return out
