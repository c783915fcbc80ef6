"""Loop subdivision as sparse operators, with boundary rules that keep boundaries.

One step maps a mesh with V0 vertices and T triangles to one with V1 = V0 + E vertices
(E = unique edges) and 4T triangles. The new ("odd") vertex on edge ``e`` has index
``V0 + e`` (edges in :func:`mesh_ops.unique_edges` order); old ("even") vertices keep their
indices. Triangle ``t = (a, b, c)`` has children ``4t + 0..3`` = ``(a, ab, ca)``,
``(ab, b, bc)``, ``(ca, bc, c)``, ``(ab, bc, ca)``, so the ancestor of a level-L triangle is
``t >> 2L``.

Rules (Loop 1987; boundary rules of Hoppe et al. 1994):

- odd, interior edge ``ab`` with opposite corners ``c, d``: 3/8 (a + b) + 1/8 (c + d)
- odd, boundary edge: (a + b) / 2
- even, interior vertex of valence n: (1 - n beta) v + beta * sum(neighbours),
  beta = (5/8 - (3/8 + cos(2 pi / n) / 4)^2) / n
- even, boundary vertex with two boundary neighbours b1, b2: 3/4 v + 1/8 (b1 + b2)
  (the boundary curve is subdivided as a cubic B-spline, independently of the interior)
- even, corner (a boundary vertex with other than two boundary neighbours) or isolated: kept.

``even="keep"`` gives the *unlifted* (interpolating) variant used by normal meshes
(Guskov et al. 2000): odd vertices by the rules above, even vertices unchanged.

The operator is built once per topology (:func:`loop_step`) and applied to any number of
frames as a sparse product.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import scipy.sparse as sp

from ..errors import DegenerateGeometryError, ShapeError
from .mesh_ops import directed_edges

__all__ = ["LoopStep", "loop_step", "loop_hierarchy", "subdivide", "apply", "edge_table"]

EVEN_RULES = ("loop", "keep")


@dataclass(frozen=True)
class LoopStep:
    """One Loop subdivision step of a fixed topology.

    matrix : (V1, V0) CSR operator, ``new_vertices = matrix @ vertices``
    triangles : (4T, 3) int64 triangles of the subdivided mesh
    edges : (E, 2) int64 edge endpoints (a < b); odd vertex ``V0 + e`` lies on edge ``e``
    opposite : (E, 2) int64 the corners opposite edge ``e`` in its triangles (-1 if none)
    boundary_edge : (E,) bool edges used by one triangle
    boundary_vertex : (V1,) bool vertices of the subdivided mesh on its boundary
    """

    matrix: sp.csr_matrix
    triangles: np.ndarray
    edges: np.ndarray
    opposite: np.ndarray
    boundary_edge: np.ndarray
    boundary_vertex: np.ndarray

    @property
    def n_coarse(self) -> int:
        return int(self.matrix.shape[1])

    @property
    def n_fine(self) -> int:
        return int(self.matrix.shape[0])

    @property
    def n_odd(self) -> int:
        return int(self.edges.shape[0])


def edge_table(triangles: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Unique undirected edges of ``triangles (T, 3)`` through int64 keys (fast at 100K+ triangles).

    Returns ``edges (E, 2)`` (smaller index first, sorted), ``inverse (3T,)`` mapping each
    directed edge of :func:`mesh_ops.directed_edges` to its edge, and ``counts (E,)`` the
    number of triangles using each edge (1 = boundary).
    """
    directed = directed_edges(np.asarray(triangles, dtype=np.int64))
    lo, hi = directed.min(axis=1), directed.max(axis=1)
    base = int(hi.max()) + 1 if len(hi) else 1
    keys, inverse, counts = np.unique(lo * base + hi, return_inverse=True, return_counts=True)
    edges = np.stack([keys // base, keys % base], axis=1)
    return edges, inverse.ravel(), counts


def loop_step(triangles: np.ndarray, n_vertices: int, *, even: str = "loop") -> LoopStep:
    """Build one subdivision step for ``triangles (T, 3)`` over ``n_vertices`` vertices.

    Raises DegenerateGeometryError for an edge shared by more than two triangles
    (Loop subdivision needs a manifold mesh).
    """
    if even not in EVEN_RULES:
        raise ShapeError(f"loop_step: even must be one of {EVEN_RULES}, got {even!r}")
    tri = np.asarray(triangles, dtype=np.int64)
    if tri.ndim != 2 or tri.shape[1] != 3 or tri.shape[0] == 0:
        raise ShapeError(f"loop_step: triangles must be (T, 3) with T >= 1, got {tri.shape}")
    n_tri = len(tri)
    edges, inverse, counts = edge_table(tri)  # directed edge k of triangle t at row k*T + t
    if (counts > 2).any():
        e = edges[np.flatnonzero(counts > 2)[0]].tolist()
        raise DegenerateGeometryError(
            f"loop_step: edge {e} is shared by {int(counts.max())} triangles; Loop subdivision needs a manifold mesh"
        )
    n_edges = len(edges)
    boundary_edge = counts == 1
    # corner opposite each directed edge: edge (0,1) -> corner 2, (1,2) -> 0, (2,0) -> 1
    opp_corner = np.concatenate([tri[:, 2], tri[:, 0], tri[:, 1]])
    opposite = np.full((n_edges, 2), -1, dtype=np.int64)
    order = np.argsort(inverse, kind="stable")
    first = np.ones(len(order), dtype=bool)
    first[1:] = inverse[order][1:] != inverse[order][:-1]
    opposite[inverse[order[first]], 0] = opp_corner[order[first]]
    opposite[inverse[order[~first]], 1] = opp_corner[order[~first]]

    rows, cols, vals = [], [], []
    odd = n_vertices + np.arange(n_edges)
    inner = ~boundary_edge
    rows += [odd[inner]] * 4 + [odd[boundary_edge]] * 2
    cols += [
        edges[inner, 0],
        edges[inner, 1],
        opposite[inner, 0],
        opposite[inner, 1],
        edges[boundary_edge, 0],
        edges[boundary_edge, 1],
    ]
    vals += (
        [np.full(inner.sum(), 3 / 8)] * 2
        + [np.full(inner.sum(), 1 / 8)] * 2
        + [np.full(boundary_edge.sum(), 0.5)] * 2
    )

    # even vertices
    b_edges = edges[boundary_edge]
    n_bnb = np.bincount(b_edges.ravel(), minlength=n_vertices)  # boundary neighbours
    valence = np.bincount(edges.ravel(), minlength=n_vertices)
    ids = np.arange(n_vertices)
    if even == "keep":
        rows.append(ids)
        cols.append(ids)
        vals.append(np.ones(n_vertices))
    else:
        on_boundary = n_bnb > 0
        smooth_boundary = n_bnb == 2
        interior = ~on_boundary & (valence > 0)
        n = np.maximum(valence, 1).astype(float)
        beta = (5 / 8 - (3 / 8 + np.cos(2 * np.pi / n) / 4) ** 2) / n
        self_w = np.where(interior, 1 - valence * beta, np.where(smooth_boundary, 3 / 4, 1.0))
        rows.append(ids)
        cols.append(ids)
        vals.append(self_w)
        # interior neighbours: every edge contributes beta of each end's ring
        both = np.concatenate([edges, edges[:, ::-1]])  # (v, neighbour)
        take = interior[both[:, 0]]
        rows.append(both[take, 0])
        cols.append(both[take, 1])
        vals.append(beta[both[take, 0]])
        bboth = np.concatenate([b_edges, b_edges[:, ::-1]])
        take = smooth_boundary[bboth[:, 0]]
        rows.append(bboth[take, 0])
        cols.append(bboth[take, 1])
        vals.append(np.full(take.sum(), 1 / 8))
    n_fine = n_vertices + n_edges
    matrix = sp.csr_matrix(
        (np.concatenate(vals), (np.concatenate(rows), np.concatenate(cols))),
        shape=(n_fine, n_vertices),
    )
    matrix.sum_duplicates()

    e_ab, e_bc, e_ca = (odd[inverse[k * n_tri : (k + 1) * n_tri]] for k in range(3))
    a, b, c = tri[:, 0], tri[:, 1], tri[:, 2]
    children = np.stack(
        [
            np.stack([a, e_ab, e_ca], axis=1),
            np.stack([e_ab, b, e_bc], axis=1),
            np.stack([e_ca, e_bc, c], axis=1),
            np.stack([e_ab, e_bc, e_ca], axis=1),
        ],
        axis=1,
    ).reshape(-1, 3)
    boundary_vertex = np.zeros(n_fine, dtype=bool)
    boundary_vertex[:n_vertices] = n_bnb > 0
    boundary_vertex[odd[boundary_edge]] = True
    return LoopStep(matrix, children, edges, opposite, boundary_edge, boundary_vertex)


def loop_hierarchy(
    triangles: np.ndarray, n_vertices: int, levels: int, *, even: str = "loop"
) -> list[LoopStep]:
    """``levels`` successive :func:`loop_step` operators starting from ``triangles``."""
    if int(levels) < 0:
        raise ShapeError(f"loop_hierarchy: levels must be >= 0, got {levels}")
    steps = []
    tri, n = np.asarray(triangles, dtype=np.int64), int(n_vertices)
    for _ in range(int(levels)):
        step = loop_step(tri, n, even=even)
        steps.append(step)
        tri, n = step.triangles, step.n_fine
    return steps


def subdivide(
    vertices: np.ndarray, triangles: np.ndarray, levels: int = 1, *, even: str = "loop"
) -> tuple[np.ndarray, np.ndarray]:
    """Loop-subdivide ``vertices (V, 3)`` (or ``(F, V, 3)`` frames) ``levels`` times.

    Returns the new vertices (same leading shape) and triangles.
    """
    v = np.asarray(vertices, dtype=np.float64)
    if v.ndim not in (2, 3) or v.shape[-1] != 3:
        raise ShapeError(f"subdivide: vertices must be (V, 3) or (F, V, 3), got {v.shape}")
    tri = np.asarray(triangles, dtype=np.int64)
    for step in loop_hierarchy(tri, v.shape[-2], levels, even=even):
        v = apply(step, v)
        tri = step.triangles
    return v, tri


def apply(step: LoopStep, vertices: np.ndarray) -> np.ndarray:
    """``step.matrix @ vertices`` for ``(V0, D)`` or frames ``(F, V0, D)``."""
    v = np.asarray(vertices, dtype=np.float64)
    if v.ndim == 2:
        return step.matrix @ v
    f, n, d = v.shape
    flat = np.moveaxis(v, 0, 1).reshape(n, f * d)
    return np.moveaxis((step.matrix @ flat).reshape(-1, f, d), 1, 0)
