"""numba kernel of :mod:`faceretarget.geometry.mesh_ops` (compiled lazily, cached).

The vertex-normal kernels: :func:`vertex_normal_sums` (the area-weighted sums, also used by
the local-frame kernels) and :func:`vertex_normals` (made unit length), which
:func:`faceretarget.geometry.mesh_ops.vertex_normals` runs; per-frame callers (or other
kernels) may call them directly on preallocated arrays.
Serial and ``nogil``: a frame takes a fraction of a millisecond, less than waking numba's
thread pool costs, and callers run chunks of frames in Python threads instead.
"""

from __future__ import annotations

import numba as nb
import numpy as np

#: The smallest positive normal float64: a squared norm at least this has full precision.
_TINY = 2.2250738585072014e-308


@nb.njit(cache=True, nogil=True)
def vertex_normal_sums(vertices: np.ndarray, triangles: np.ndarray, out: np.ndarray) -> None:
    """Each vertex's sum of its triangles' cross products ``(b - a) x (c - a)``, in triangle
    order, into ``out (V, 3)`` (area-weighted, not normalised; zero for isolated vertices):
    one pass over the triangles, each added to its three corners."""
    out[:] = 0.0
    for t in range(triangles.shape[0]):
        a, b, c = triangles[t, 0], triangles[t, 1], triangles[t, 2]
        u0 = vertices[b, 0] - vertices[a, 0]
        u1 = vertices[b, 1] - vertices[a, 1]
        u2 = vertices[b, 2] - vertices[a, 2]
        w0 = vertices[c, 0] - vertices[a, 0]
        w1 = vertices[c, 1] - vertices[a, 1]
        w2 = vertices[c, 2] - vertices[a, 2]
        n0 = u1 * w2 - u2 * w1
        n1 = u2 * w0 - u0 * w2
        n2 = u0 * w1 - u1 * w0
        for v in (a, b, c):
            out[v, 0] += n0
            out[v, 1] += n1
            out[v, 2] += n2


@nb.njit(cache=True, nogil=True)
def vertex_normals(vertices: np.ndarray, triangles: np.ndarray, out: np.ndarray) -> None:
    """Area-weighted unit vertex normals of ``vertices (V, 3)`` over ``triangles (T, 3)``
    into ``out (V, 3)``: each vertex's sum of its triangles' cross products ``(b - a) x
    (c - a)`` (in triangle order), made unit length; zero for isolated vertices and for sums
    with a NaN or infinite component.

    A sum whose squared norm under- or overflows (subnormal or huge coordinates) is first
    divided by its largest component, as :func:`faceretarget.geometry.mesh_ops.unit_rows`
    does, so it still comes out unit length; any other is divided by its norm directly.
    """
    vertex_normal_sums(vertices, triangles, out)
    for v in range(out.shape[0]):
        x, y, z = out[v, 0], out[v, 1], out[v, 2]
        squared = x * x + y * y + z * z
        if squared >= _TINY and squared < np.inf:
            norm = np.sqrt(squared)
            out[v, 0], out[v, 1], out[v, 2] = x / norm, y / norm, z / norm
            continue
        scale = max(abs(x), abs(y), abs(z))
        if not scale > 0.0 or x != x or y != y or z != z:  # zero, or NaN somewhere
            out[v, 0] = out[v, 1] = out[v, 2] = 0.0
            continue
        x, y, z = x / scale, y / scale, z / scale
        norm = np.sqrt(x * x + y * y + z * z)
        if norm > 0.0:  # NaN (an infinite component) is not
            out[v, 0], out[v, 1], out[v, 2] = x / norm, y / norm, z / norm
        else:
            out[v, 0] = out[v, 1] = out[v, 2] = 0.0
