"""Boundary loops of open triangle meshes."""

from __future__ import annotations

import numpy as np

from ..geometry.mesh_ops import boundary_edges

__all__ = ["boundary_loops"]


def boundary_loops(triangles: np.ndarray) -> list[np.ndarray]:
    """Boundary loops as ordered vertex chains (in the direction of their triangles' edges).

    Loops are returned longest first. A vertex where two loops touch ends the first walk
    there; the remaining edges form further chains.
    """
    edges = boundary_edges(np.asarray(triangles, dtype=np.int64))
    if len(edges) == 0:
        return []
    nxt = dict(zip(edges[:, 0].tolist(), edges[:, 1].tolist()))
    loops, seen = [], set()
    for start in sorted(nxt):
        if start in seen:
            continue
        loop, cur = [start], nxt[start]
        seen.add(start)
        while cur != start and cur not in seen and cur in nxt:
            loop.append(cur)
            seen.add(cur)
            cur = nxt[cur]
        loops.append(np.array(loop, dtype=np.int64))
    loops.sort(key=len, reverse=True)
    return loops
