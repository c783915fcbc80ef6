"""The data model: meshes, performances, rigs and results.

Arrays are numpy and frames come first: a mesh sequence is ``(F, V, 3)``,
weights ``(F, M)``, markers ``(F, N, 3)`` (or ``(F, N, 2)`` for 2D tracks).
Missing marker samples are NaN. Units are the caller's (the ICT data is in
centimetres); nothing here rescales.

Constructors validate shapes, index ranges and finite values and raise typed
errors (:mod:`faceretarget.errors`). They accept float32 and read-only arrays
and never modify their inputs: every stored array is a read-only view or copy.
Derived operators (normals, adjacency) are computed on first use and cached
read-only. This module knows nothing of plugins, files or the CLI.
"""

from __future__ import annotations

from collections.abc import Iterable, Mapping, Sequence
from functools import cached_property
from typing import TYPE_CHECKING, Any

import numpy as np
import numpy.typing as npt

if TYPE_CHECKING:
    from scipy import sparse

from . import config
from ._validate import (
    all_finite,
    as_array,
    as_float_array,
    as_fps,
    as_index_array,
    as_names,
    readonly,
)
from .errors import (
    DegenerateGeometryError,
    InputError,
    NonFiniteError,
    ShapeError,
    TopologyMismatchError,
)

__all__ = [
    "Mesh",
    "Landmarks",
    "MarkerSequence",
    "MeshSequence",
    "WeightSequence",
    "BlendshapeRig",
    "LayeredRig",
    "Source",
    "TargetRig",
    "Animation",
    "FrameSource",
    "apply_head_motion",
]

_CHUNK = 1 << 22  # elements per chunk when scanning large (memory-mapped) arrays


# ---------------------------------------------------------------------------------------
# Meshes and landmarks
# ---------------------------------------------------------------------------------------
class Mesh:
    """A triangle mesh.

    Parameters
    ----------
    vertices : (V, 3) float
        Vertex positions.
    triangles : (T, 3) int
        Vertex indices of each triangle, counter-clockwise seen from outside (0-based).
    name : str, optional

    Raises
    ------
    ShapeError, NonFiniteError, IndexRangeError
        Wrong shapes, NaN/inf coordinates, indices out of range.
    DegenerateGeometryError
        A triangle repeats a vertex, or the same triangle appears twice.

    Zero-*area* triangles (distinct but collinear corners) are accepted here, since
    many production meshes have a few; :meth:`degenerate_triangles` finds them and
    methods that need a triangle frame reject them with a clear error.
    """

    __slots__ = ("vertices", "triangles", "name", "__dict__")

    def __init__(
        self,
        vertices: npt.ArrayLike,
        triangles: npt.ArrayLike,
        *,
        name: str | None = None,
        _trusted: bool = False,
    ) -> None:
        self.vertices = as_float_array(vertices, "Mesh.vertices", (None, 3))
        if _trusted:
            self.triangles = readonly(np.asarray(triangles, dtype=np.int64))
        else:
            n_vertices = self.vertices.shape[0]
            if n_vertices < 3:
                raise ShapeError(
                    f"Mesh.vertices: a mesh needs at least 3 vertices, got {n_vertices}"
                )
            self.triangles = as_index_array(
                triangles, "Mesh.triangles", (None, 3), upper=n_vertices
            )
            if self.triangles.shape[0] == 0:
                raise ShapeError("Mesh.triangles: a mesh needs at least one triangle, got (0, 3)")
            _check_triangle_indices(self.triangles)
        self.name = name

    # construction helpers -------------------------------------------------------------
    def with_vertices(self, vertices: npt.ArrayLike) -> Mesh:
        """A mesh with the same triangles and new ``vertices : (V, 3)``."""
        vertices = as_float_array(vertices, "vertices", (self.n_vertices, 3))
        return Mesh(vertices, self.triangles, name=self.name, _trusted=True)

    # sizes ----------------------------------------------------------------------------
    @property
    def n_vertices(self) -> int:
        return int(self.vertices.shape[0])

    @property
    def n_triangles(self) -> int:
        return int(self.triangles.shape[0])

    @property
    def height(self) -> float:
        """Extent along y (the face height for faces modelled y-up), in mesh units."""
        return float(np.ptp(self.vertices[:, 1]))

    @property
    def scale(self) -> float:
        """Diagonal of the bounding box, a size for relative tolerances."""
        return float(np.linalg.norm(np.ptp(self.vertices, axis=0)))

    # cached derived quantities --------------------------------------------------------
    @cached_property
    def face_normals(self) -> np.ndarray:
        """(T, 3) float64 unit normals (zero for zero-area triangles)."""
        from .geometry.mesh_ops import face_normals

        return readonly(face_normals(self.vertices, self.triangles))

    @cached_property
    def face_areas(self) -> np.ndarray:
        """(T,) float64 triangle areas."""
        from .geometry.mesh_ops import face_areas

        return readonly(face_areas(self.vertices, self.triangles))

    @cached_property
    def vertex_normals(self) -> np.ndarray:
        """(V, 3) float64 area-weighted unit vertex normals."""
        from .geometry.mesh_ops import vertex_normals

        return readonly(vertex_normals(self.vertices, self.triangles))

    @cached_property
    def edges(self) -> np.ndarray:
        """(E, 2) int64 unique undirected edges, smaller index first."""
        from .geometry.mesh_ops import unique_edges

        return readonly(unique_edges(self.triangles))

    @cached_property
    def boundary_vertices(self) -> np.ndarray:
        """(B,) int64 sorted ids of vertices on a boundary (edges used by one triangle)."""
        from .geometry.mesh_ops import boundary_edges

        return readonly(np.unique(boundary_edges(self.triangles)))

    @cached_property
    def adjacency(self) -> sparse.csr_matrix:
        """(V, V) scipy CSR 0/1 vertex adjacency (read-only use)."""
        from .geometry.mesh_ops import vertex_adjacency

        return vertex_adjacency(self.triangles, self.n_vertices)

    def degenerate_triangles(self, ratio: float = config.DEGENERATE_AREA_RATIO) -> np.ndarray:
        """Ids of triangles whose area is below ``ratio`` times the mean area, or below ``ratio``
        times the square of their own longest edge (collinear corners, even when every
        triangle of the mesh is degenerate and the mean area is no yardstick)."""
        areas = self.face_areas
        corners = self.vertices[self.triangles]  # (T, 3, 3)
        longest = (np.diff(corners, axis=1, append=corners[:, :1]) ** 2).sum(axis=2).max(axis=1)
        small = areas <= ratio * max(float(areas.mean()), np.finfo(float).tiny)
        return np.flatnonzero(small | (areas <= ratio * longest))

    def check_nondegenerate(self, what: str = "this method") -> None:
        """Raise :class:`DegenerateGeometryError` if any triangle has (near) zero area."""
        bad = self.degenerate_triangles()
        if bad.size:
            raise DegenerateGeometryError(
                f"{what} needs triangles with non-zero area, but mesh {self.name or ''} has {bad.size} "
                f"zero-area triangle(s) (first: {bad[:5].tolist()}); remove or repair them "
                "(e.g. trimesh's remove_degenerate_faces) and keep vertex order"
            )

    def __repr__(self) -> str:
        return f"Mesh({self.n_vertices} vertices, {self.n_triangles} triangles{', ' + repr(self.name) if self.name else ''})"

    def __getstate__(self) -> dict[str, Any]:
        return {
            "vertices": np.array(self.vertices),
            "triangles": np.array(self.triangles),
            "name": self.name,
        }

    def __setstate__(self, state: dict[str, Any]) -> None:
        self.__init__(state["vertices"], state["triangles"], name=state["name"], _trusted=True)  # type: ignore[misc]


def _check_triangle_indices(triangles: np.ndarray) -> None:
    t = triangles
    repeated = (t[:, 0] == t[:, 1]) | (t[:, 1] == t[:, 2]) | (t[:, 0] == t[:, 2])
    if repeated.any():
        i = int(np.flatnonzero(repeated)[0])
        raise DegenerateGeometryError(
            f"Mesh.triangles: {int(repeated.sum())} triangle(s) repeat a vertex (first: #{i} = {t[i].tolist()}); "
            "remove degenerate triangles before use"
        )
    key = np.sort(t, axis=1)
    uniq, counts = np.unique(key, axis=0, return_counts=True)
    if (counts > 1).any():
        dup = uniq[counts > 1][0].tolist()
        raise DegenerateGeometryError(
            f"Mesh.triangles: {int((counts > 1).sum())} triangle(s) appear more than once (e.g. vertices {dup}); "
            "remove duplicate triangles"
        )


class Landmarks:
    """Points on a mesh: vertex ids, or barycentric points inside triangles.

    Parameters
    ----------
    vertex_ids : (N,) int, optional
        Vertex ids (give this *or* ``triangle_ids`` + ``barycentric``).
    triangle_ids : (N,) int, optional
    barycentric : (N, 3) float, optional
        Barycentric coordinates in the triangles (rows sum to 1).
    names : sequence of N str, optional
        Names, used to pair landmarks with source markers of the same name.
    """

    def __init__(
        self,
        vertex_ids: npt.ArrayLike | None = None,
        *,
        triangle_ids: npt.ArrayLike | None = None,
        barycentric: npt.ArrayLike | None = None,
        names: Iterable[str] | None = None,
    ) -> None:
        if (vertex_ids is None) == (triangle_ids is None):
            raise InputError(
                "Landmarks: give either vertex_ids, or triangle_ids with barycentric coordinates"
            )
        if vertex_ids is not None:
            self.vertex_ids: np.ndarray | None = as_index_array(
                vertex_ids, "Landmarks.vertex_ids", (None,)
            )
            self.triangle_ids: np.ndarray | None = None
            self.barycentric: np.ndarray | None = None
            count = self.vertex_ids.shape[0]
        else:
            if barycentric is None:
                raise InputError(
                    "Landmarks: triangle_ids need barycentric coordinates of shape (N, 3)"
                )
            self.vertex_ids = None
            self.triangle_ids = as_index_array(triangle_ids, "Landmarks.triangle_ids", (None,))
            count = self.triangle_ids.shape[0]
            self.barycentric = as_float_array(barycentric, "Landmarks.barycentric", (count, 3))
            if np.any(np.abs(self.barycentric.sum(axis=1) - 1.0) > 1e-6):
                raise InputError("Landmarks.barycentric: each row must sum to 1")
        if count == 0:
            raise ShapeError("Landmarks: at least one landmark is needed")
        self.names = as_names(names, "Landmarks.names", count, default_prefix="landmark")

    def __len__(self) -> int:
        return len(self.names)

    def validate_for(self, mesh: Mesh, what: str = "landmarks") -> Landmarks:
        """Check the ids fit ``mesh``; returns self."""
        if self.vertex_ids is not None:
            as_index_array(self.vertex_ids, f"{what}.vertex_ids", (None,), upper=mesh.n_vertices)
        else:
            as_index_array(
                self.triangle_ids, f"{what}.triangle_ids", (None,), upper=mesh.n_triangles
            )
        return self

    def positions(self, vertices: np.ndarray, triangles: np.ndarray | None = None) -> np.ndarray:
        """Landmark positions on ``vertices : (..., V, 3)`` -> ``(..., N, 3)``.

        Barycentric landmarks need the mesh ``triangles : (T, 3)``.
        """
        vertices = np.asarray(vertices)
        if self.vertex_ids is not None:
            return vertices[..., self.vertex_ids, :]
        if triangles is None:
            raise InputError("Landmarks.positions: barycentric landmarks need the mesh triangles")
        corners = np.asarray(triangles)[self.triangle_ids]  # (N, 3)
        pts = vertices[..., corners, :]  # (..., N, 3, 3)
        assert self.barycentric is not None  # no vertex ids: triangle ids and barycentric
        return np.einsum("...nkd,nk->...nd", pts, self.barycentric)

    def __repr__(self) -> str:
        kind = "vertex ids" if self.vertex_ids is not None else "barycentric points"
        return f"Landmarks({len(self)} {kind})"


# ---------------------------------------------------------------------------------------
# Performances
# ---------------------------------------------------------------------------------------
class MarkerSequence:
    """Motion-capture markers over time.

    Parameters
    ----------
    positions : (F, N, 3) or (F, N, 2) float
        Marker positions; NaN marks a missing sample (a whole marker at one frame).
    names : sequence of N str, optional
    fps : float
    reference : (N, 3) or (N, 2) float, optional
        The neutral (rest) pose. Defaults to the first frame, which must then be complete.
    """

    kind = "markers"

    def __init__(
        self,
        positions: npt.ArrayLike,
        *,
        names: Iterable[str] | None = None,
        fps: float = 30.0,
        reference: npt.ArrayLike | None = None,
    ) -> None:
        arr = as_array(positions, "MarkerSequence.positions")
        if getattr(arr, "ndim", 0) != 3 or arr.shape[-1] not in (2, 3):
            raise ShapeError(
                f"MarkerSequence.positions: expected shape (F, N, 3) or (F, N, 2), got {tuple(np.shape(arr))}"
            )
        dim = arr.shape[-1]
        self.positions = as_float_array(
            arr, "MarkerSequence.positions", (None, None, dim), allow_nan=True
        )
        n_frames, n_markers = self.positions.shape[:2]
        if n_frames == 0 or n_markers == 0:
            raise ShapeError(
                f"MarkerSequence.positions: needs at least one frame and one marker, got {self.positions.shape}"
            )
        partial = np.isnan(self.positions).any(axis=-1) & ~np.isnan(self.positions).all(axis=-1)
        if partial.any():
            f, n = (int(i) for i in np.argwhere(partial)[0])
            raise NonFiniteError(
                f"MarkerSequence.positions: marker {n} at frame {f} has some coordinates NaN and others not; "
                "a missing sample must be NaN in every coordinate"
            )
        self.names = as_names(names, "MarkerSequence.names", n_markers, default_prefix="marker")
        self.fps = as_fps(fps)
        if reference is None:
            if np.isnan(self.positions[0]).any():
                raise NonFiniteError(
                    "MarkerSequence: frame 0 has missing markers, so it cannot serve as the neutral reference; "
                    "pass reference= (the neutral marker positions)"
                )
            reference = self.positions[0]
        self.reference = as_float_array(reference, "MarkerSequence.reference", (n_markers, dim))

    @property
    def n_frames(self) -> int:
        return int(self.positions.shape[0])

    @property
    def n_markers(self) -> int:
        return int(self.positions.shape[1])

    @property
    def dim(self) -> int:
        return int(self.positions.shape[2])

    @property
    def missing(self) -> np.ndarray:
        """(F, N) bool: True where a marker sample is missing."""
        return np.isnan(self.positions[..., 0])

    def __len__(self) -> int:
        return self.n_frames

    def __repr__(self) -> str:
        return f"MarkerSequence({self.n_frames} frames, {self.n_markers} {self.dim}D markers, {self.fps:g} fps)"


class MeshSequence:
    """A dense mesh animation with fixed topology.

    Parameters
    ----------
    vertices : (F, V, 3) float
        Per-frame vertex positions. float32 and float64 (either byte order) are kept as
        given, so a memory-mapped point cache is not loaded into memory.
    triangles : (T, 3) int
    fps : float
    reference : Mesh or (V, 3) float, optional
        The neutral pose; defaults to the first frame.
    """

    kind = "mesh"

    def __init__(
        self,
        vertices: npt.ArrayLike,
        triangles: npt.ArrayLike,
        *,
        fps: float = 30.0,
        reference: Mesh | npt.ArrayLike | None = None,
        name: str | None = None,
    ) -> None:
        arr = as_array(vertices, "MeshSequence.vertices")
        # 4- and 8-byte floats of either byte order are kept as given, so a memory-mapped
        # point cache (PC2 little-endian, MDD big-endian) stays on disk.
        keep = arr.dtype.kind == "f" and arr.dtype.itemsize in (4, 8)
        dtype = arr.dtype if keep else np.float64
        if arr.ndim != 3 or arr.shape[-1] != 3:
            raise ShapeError(
                f"MeshSequence.vertices: expected shape (F, V, 3), got {tuple(arr.shape)}"
            )
        if arr.shape[0] == 0:
            raise ShapeError("MeshSequence.vertices: the sequence has no frames")
        if arr.dtype != dtype:
            arr = as_float_array(arr, "MeshSequence.vertices", (None, None, 3))
        else:
            _check_finite_chunked(arr, "MeshSequence.vertices")
            arr = readonly(arr)
        self.vertices = arr
        if isinstance(reference, Mesh):
            if reference.n_vertices != arr.shape[1]:
                raise TopologyMismatchError(
                    f"MeshSequence: reference mesh has {reference.n_vertices} vertices but frames have {arr.shape[1]}"
                )
            self.reference = Mesh(reference.vertices, triangles, name=name or reference.name)
        else:
            ref = np.asarray(arr[0], dtype=np.float64) if reference is None else reference
            self.reference = Mesh(ref, triangles, name=name)
            if self.reference.n_vertices != arr.shape[1]:
                raise TopologyMismatchError(
                    f"MeshSequence: reference has {self.reference.n_vertices} vertices but frames have {arr.shape[1]}"
                )
        self.triangles = self.reference.triangles
        self.fps = as_fps(fps)
        self.name = name

    @property
    def n_frames(self) -> int:
        return int(self.vertices.shape[0])

    @property
    def n_vertices(self) -> int:
        return int(self.vertices.shape[1])

    def frame(self, index: int) -> Mesh:
        """Frame ``index`` as a :class:`Mesh`."""
        return self.reference.with_vertices(np.asarray(self.vertices[index], dtype=np.float64))

    def __len__(self) -> int:
        return self.n_frames

    def __repr__(self) -> str:
        return f"MeshSequence({self.n_frames} frames, {self.n_vertices} vertices, {self.fps:g} fps)"


class WeightSequence:
    """Blendshape weight curves.

    Parameters
    ----------
    weights : (F, M) float
    names : sequence of M str
        Shape names (e.g. ARKit ``jawOpen``).
    fps : float
    """

    kind = "weights"
    #: Set by readers that find them (the Live Link Face CSV reader); absent otherwise.
    head_motion: np.ndarray
    extras: dict[str, Any]

    def __init__(self, weights: npt.ArrayLike, names: Iterable[str], *, fps: float = 30.0) -> None:
        self.weights = as_float_array(weights, "WeightSequence.weights", (None, None))
        if self.weights.shape[0] == 0:
            raise ShapeError("WeightSequence.weights: the sequence has no frames")
        self.names = as_names(names, "WeightSequence.names", self.weights.shape[1])
        self.fps = as_fps(fps)

    @property
    def n_frames(self) -> int:
        return int(self.weights.shape[0])

    @property
    def reference(self) -> np.ndarray:
        """(M,) zeros: the neutral pose in weight space."""
        return np.zeros(self.weights.shape[1])

    def __len__(self) -> int:
        return self.n_frames

    def __repr__(self) -> str:
        return f"WeightSequence({self.n_frames} frames, {len(self.names)} shapes, {self.fps:g} fps)"


def _check_finite_chunked(arr: np.ndarray, name: str) -> None:
    if arr.size == 0:
        return
    flat = arr.reshape(arr.shape[0], -1)
    step = max(1, _CHUNK // max(1, flat.shape[1]))
    for start in range(0, flat.shape[0], step):
        block = np.asarray(flat[start : start + step])
        if not all_finite(block):
            f, k = (int(i) for i in np.argwhere(~np.isfinite(block))[0])
            raise NonFiniteError(
                f"{name}: NaN or infinite coordinate at frame {start + f}, vertex {k // 3}"
            )


# ---------------------------------------------------------------------------------------
# Rigs
# ---------------------------------------------------------------------------------------
class BlendshapeRig:
    """A delta blendshape model: ``x(w) = neutral + sum_k w_k * deltas[k]``.

    Parameters
    ----------
    neutral : Mesh
    deltas : (M, V, 3) float
        Shape minus neutral, one per blendshape.
    names : sequence of M str
    bounds : (M, 2) float, optional
        Artist weight range per shape (lower, upper); default none.

    The rig views the arrays it is given (float64 ones are not copied) and derives matrices
    from them on first use (:attr:`delta_matrix`, the ``[deltas; neutral]`` matrix of
    :meth:`evaluate`): make a new rig rather than change those arrays afterwards.
    """

    def __init__(
        self,
        neutral: Mesh,
        deltas: npt.ArrayLike,
        names: Iterable[str],
        *,
        bounds: npt.ArrayLike | None = None,
    ) -> None:
        if not isinstance(neutral, Mesh):
            raise InputError(
                f"BlendshapeRig.neutral: expected a Mesh, got {type(neutral).__name__}"
            )
        self.neutral = neutral
        arr = as_array(deltas, "BlendshapeRig.deltas")
        if arr.ndim == 3 and arr.shape[1] != neutral.n_vertices:
            raise TopologyMismatchError(
                f"BlendshapeRig.deltas: shapes have {arr.shape[1]} vertices but the neutral has {neutral.n_vertices}"
            )
        self.deltas = as_float_array(arr, "BlendshapeRig.deltas", (None, neutral.n_vertices, 3))
        if self.deltas.shape[0] == 0:
            raise ShapeError("BlendshapeRig.deltas: a rig needs at least one blendshape")
        self.names = as_names(names, "BlendshapeRig.names", self.deltas.shape[0])
        if bounds is not None:
            bounds = as_float_array(bounds, "BlendshapeRig.bounds", (self.n_shapes, 2))
            if np.any(bounds[:, 0] > bounds[:, 1]):
                raise InputError(
                    "BlendshapeRig.bounds: every lower bound must be <= its upper bound"
                )
        self.bounds = bounds

    @property
    def n_shapes(self) -> int:
        return int(self.deltas.shape[0])

    @cached_property
    def delta_matrix(self) -> np.ndarray:
        """(3V, M) float64 column matrix of the deltas (x-y-z interleaved per vertex)."""
        return readonly(np.ascontiguousarray(self.deltas.reshape(self.n_shapes, -1).T))

    @cached_property
    def delta_extent(self) -> np.ndarray:
        """(M,) float64 largest absolute coordinate of each shape's deltas: with the neutral's,
        a bound on the coordinates any weights reach (a finiteness check without evaluating)."""
        return readonly(np.abs(self.deltas).max(axis=(1, 2), initial=0.0))

    def evaluate(self, weights: npt.ArrayLike) -> np.ndarray:
        """Vertices for ``weights : (M,) or (F, M)`` -> ``(V, 3)`` or ``(F, V, 3)``."""
        w = as_array(weights, "BlendshapeRig.evaluate: weights")
        if w.ndim not in (1, 2) or w.shape[-1] != self.n_shapes:
            raise ShapeError(
                f"BlendshapeRig.evaluate: weights must be (M,) or (F, M) with M={self.n_shapes}, got {w.shape}"
            )
        w = as_float_array(w, "BlendshapeRig.evaluate: weights", w.shape)
        rows = w.reshape(-1, self.n_shapes)
        affine = self._affine
        if affine is not None:
            flat = _affine_product(rows, affine)
        else:
            flat = _affine_rows(
                rows, self.deltas.reshape(self.n_shapes, -1), self.neutral.vertices.reshape(-1)
            )
        return flat.reshape(w.shape[:-1] + (self.neutral.n_vertices, 3))

    @cached_property
    def _affine(self) -> np.ndarray | None:
        """``(M + 1, 3V)``: the deltas' rows, then the neutral's (see :func:`_affine_product`);
        None above ``config.RIG_AFFINE_MAX_BYTES``."""
        from . import config

        m, size = self.n_shapes, self.neutral.vertices.size
        if (m + 1) * size * 8 > config.RIG_AFFINE_MAX_BYTES:
            return None
        out = np.empty((m + 1, size))
        out[:m] = self.deltas.reshape(m, size)
        out[m] = self.neutral.vertices.reshape(size)
        return readonly(out)

    def index(self, name: str) -> int:
        """Position of shape ``name`` (exact match; an unknown name is an
        :class:`~faceretarget.errors.UnknownNameError` suggesting the closest shape names)."""
        from ._validate import did_you_mean
        from .errors import UnknownNameError

        try:
            return self.names.index(name)
        except ValueError:
            listed = ", ".join(self.names[:60]) + (
                f" ... ({len(self.names)} in all)" if len(self.names) > 60 else ""
            )
            raise UnknownNameError(
                f"no blendshape named {name!r}{did_you_mean(name, self.names)}; this rig has: {listed}"
            ) from None

    def __repr__(self) -> str:
        return f"BlendshapeRig({self.n_shapes} shapes on {self.neutral!r})"

    def __getstate__(self) -> dict[str, Any]:
        """Without the matrices derived from the deltas (rebuilt on first use): a pickled
        result does not carry its rig's deltas twice."""
        return {k: v for k, v in self.__dict__.items() if k not in _RIG_DERIVED}


_RIG_DERIVED = frozenset({"delta_matrix", "delta_extent", "_affine"})


def _affine_product(w: np.ndarray, affine: np.ndarray) -> np.ndarray:
    """``[w, 1] @ affine`` (F, K) for (F, M) ``w`` and ``affine (M + 1, K)`` C-contiguous
    float64: :func:`_affine_rows` with the offset as the product's last row, so that one
    BLAS ``dgemm`` writes the result once (no pass filling it with the offset first)."""
    from scipy.linalg.blas import dgemm

    n, m = w.shape
    lifted = np.empty((m + 1, n), order="F")  # [w, 1]^T, Fortran-ordered for dgemm
    lifted[:m] = w.T
    lifted[m] = 1.0
    out = np.empty((n, affine.shape[1]))
    if out.size == 0:
        return out
    # out.T (K, F), Fortran-ordered, = affine.T @ lifted: transposed views, no copies
    res = dgemm(1.0, affine.T, lifted, beta=0.0, c=out.T, overwrite_c=True)
    if not np.shares_memory(res, out):  # not expected (out.T is Fortran-ordered float64)
        out[:] = res.T
    return out


def _affine_rows(w: np.ndarray, d: np.ndarray, offset: np.ndarray) -> np.ndarray:
    """``w @ d + offset`` (F, K) for (F, M) ``w``, (M, K) ``d`` and (K,) ``offset``: one BLAS
    ``dgemm`` with ``beta = 1`` onto rows filled with ``offset`` (the sum is made inside the
    product: a separate ``+=`` pass over a 300 x 28,227 result took 6-8 ms beside the product's 10)."""
    out = np.empty((w.shape[0], d.shape[1]))
    if w.dtype != np.float64 or d.dtype != np.float64 or not d.flags.c_contiguous or out.size == 0:
        np.matmul(w, d, out=out)
        out += offset
        return out
    from scipy.linalg.blas import dgemm

    out[:] = offset
    # out.T (K, F), Fortran-ordered, = d.T @ w.T + out.T: transposed views, no copies
    res = dgemm(1.0, d.T, np.asfortranarray(w.T), beta=1.0, c=out.T, overwrite_c=True)
    if not np.shares_memory(res, out):  # not expected (out.T is Fortran-ordered float64)
        out[:] = res.T
    return out


class LayeredRig:
    """Parameter-parallel layers (Kholgade et al. 2011): per layer a simplicial pose set.

    The same class holds the character side (points = mesh vertices, D = 3) and the
    actor side (points = markers, D = 3, or 2D tracks, D = 2).

    Parameters
    ----------
    layers : mapping name -> (K_j, P, D) float
        Absolute poses (extremes) of each layer; a frame of layer j is a convex
        combination of its K_j poses. Order is kept; names and count are data.
    masks : (R, P) float
        Region masks, values >= 0 (usually 0..1), one row per region.
    pose_names : mapping name -> sequence of K_j str, optional
    region_names : sequence of R str, optional
    """

    def __init__(
        self,
        layers: Mapping[str, npt.ArrayLike],
        masks: npt.ArrayLike,
        *,
        pose_names: Mapping[str, Sequence[str]] | None = None,
        region_names: Iterable[str] | None = None,
    ) -> None:
        if not isinstance(layers, Mapping) or not layers:
            raise InputError(
                "LayeredRig.layers: expected a non-empty mapping of layer name -> (K, P, D) poses"
            )
        items = {}
        shape: tuple[int, ...] | None = None
        for lname, poses in layers.items():
            arr = as_array(poses, f"LayeredRig.layers[{lname!r}]")
            if arr.ndim != 3 or arr.shape[-1] not in (2, 3):
                raise ShapeError(
                    f"LayeredRig.layers[{lname!r}]: expected (K, P, 3) or (K, P, 2), got {tuple(arr.shape)}"
                )
            if shape is None:
                shape = arr.shape[1:]
            elif arr.shape[1:] != shape:
                raise TopologyMismatchError(
                    f"LayeredRig.layers[{lname!r}]: poses are {tuple(arr.shape[1:])} but the first layer's are {tuple(shape)}"
                )
            if arr.shape[0] == 0:
                raise ShapeError(f"LayeredRig.layers[{lname!r}]: a layer needs at least one pose")
            items[str(lname)] = as_float_array(
                arr, f"LayeredRig.layers[{lname!r}]", (None,) + tuple(shape)
            )
        as_names(list(items), "LayeredRig layer names")
        self.layers = items
        assert shape is not None  # set by the first of the (non-empty) layers
        self.n_points, self.dim = int(shape[0]), int(shape[1])
        self.masks = as_float_array(masks, "LayeredRig.masks", (None, self.n_points))
        if self.masks.shape[0] == 0:
            raise ShapeError("LayeredRig.masks: at least one region is needed")
        if np.any(self.masks < 0):
            raise InputError("LayeredRig.masks: mask values must be >= 0")
        self.region_names = as_names(
            region_names, "LayeredRig.region_names", self.masks.shape[0], default_prefix="region"
        )
        if pose_names is not None and not isinstance(pose_names, Mapping):
            raise InputError(
                "LayeredRig.pose_names: expected a mapping of layer name -> pose names"
            )
        self.pose_names = {
            lname: as_names(
                (pose_names or {}).get(lname),
                f"LayeredRig.pose_names[{lname!r}]",
                poses.shape[0],
                default_prefix=f"{lname}",
            )
            for lname, poses in items.items()
        }

    @property
    def layer_names(self) -> tuple[str, ...]:
        return tuple(self.layers)

    @property
    def n_regions(self) -> int:
        return int(self.masks.shape[0])

    def __repr__(self) -> str:
        sizes = ", ".join(f"{k}: {v.shape[0]}" for k, v in self.layers.items())
        return f"LayeredRig({sizes}; {self.n_regions} regions on {self.n_points} points)"


# ---------------------------------------------------------------------------------------
# What a retargeter consumes
# ---------------------------------------------------------------------------------------
def _as_head_motion(value: npt.ArrayLike | None, n_frames: int, name: str) -> np.ndarray | None:
    if value is None:
        return None
    arr = as_float_array(value, name, (n_frames, 4, 4))
    if np.any(np.abs(arr[:, 3, :] - [0.0, 0.0, 0.0, 1.0]) > 1e-6):
        raise InputError(
            f"{name}: each transform must be a 4x4 rigid matrix with last row (0, 0, 0, 1)"
        )
    return arr


def _as_feature_lines(
    value: Mapping[str, npt.ArrayLike] | None, n_points: int | None, name: str
) -> dict[str, np.ndarray]:
    if value is None:
        return {}
    if not isinstance(value, Mapping):
        raise InputError(f"{name}: expected a mapping of line name -> vertex-id chain")
    out = {}
    for k, chain in value.items():
        out[str(k)] = as_index_array(chain, f"{name}[{k!r}]", (None,), upper=n_points)
        if out[str(k)].shape[0] < 2:
            raise ShapeError(f"{name}[{k!r}]: a feature line needs at least 2 vertices")
    return out


class Source:
    """One performance to retarget, with its reference and optional extras.

    Parameters
    ----------
    performance : MarkerSequence, MeshSequence or WeightSequence
    head_motion : (F, 4, 4) float, optional
        Known rigid head motion (neutral-frame coordinates to world), if captured apart.
    landmarks : Landmarks, optional
        For a mesh sequence: the points (in its topology) that correspond to the
        target's landmarks, in the same order (or matched by name).
    feature_lines : mapping name -> (L,) int, optional
        Vertex chains around eyes and mouth on the source mesh (names match the target's).
    examples : (M, P, 3) float, optional
        Source example poses (key expressions) paired by name with ``TargetRig.examples``;
        P is the source vertex count (mesh) or marker count (markers).
    example_names : sequence of M str, optional
    rig : BlendshapeRig, optional
        The source's own blendshape rig (needed to turn a WeightSequence into geometry).
    actor_layers : LayeredRig, optional
        The actor's simplicial bases over the markers (Kholgade et al. 2011).
    tracks2d : MarkerSequence, optional
        2D tracks (AAM-style points) over the same frames, ``(F, N2, 2)``.
    actor_layers_2d : LayeredRig, optional
        The actor's bases over the 2D tracks (same layer names and pose counts).
    """

    def __init__(
        self,
        performance: MarkerSequence | MeshSequence | WeightSequence,
        *,
        head_motion: npt.ArrayLike | None = None,
        landmarks: Landmarks | None = None,
        feature_lines: Mapping[str, npt.ArrayLike] | None = None,
        examples: npt.ArrayLike | None = None,
        example_names: Iterable[str] | None = None,
        rig: BlendshapeRig | None = None,
        actor_layers: LayeredRig | None = None,
        tracks2d: MarkerSequence | None = None,
        actor_layers_2d: LayeredRig | None = None,
        name: str | None = None,
    ) -> None:
        if not isinstance(performance, (MarkerSequence, MeshSequence, WeightSequence)):
            raise InputError(
                f"Source.performance: expected a MarkerSequence, MeshSequence or WeightSequence, got {type(performance).__name__}"
            )
        self.performance = performance
        self.name = name
        n_frames = performance.n_frames
        self.head_motion = _as_head_motion(head_motion, n_frames, "Source.head_motion")
        n_points = None
        if landmarks is not None and not isinstance(landmarks, Landmarks):
            raise InputError(
                f"Source.landmarks: expected a faceretarget.Landmarks, got {type(landmarks).__name__}"
            )
        if isinstance(performance, MeshSequence):
            n_points = performance.n_vertices
            if landmarks is not None:
                landmarks.validate_for(performance.reference, "Source.landmarks")
        elif isinstance(performance, MarkerSequence):
            n_points = performance.n_markers
            if landmarks is not None:
                raise InputError(
                    "Source.landmarks: only a MeshSequence source takes landmarks (markers already are points)"
                )
        self.landmarks = landmarks
        self.feature_lines = _as_feature_lines(feature_lines, n_points, "Source.feature_lines")
        if examples is not None:
            self.examples: np.ndarray | None = as_float_array(
                examples, "Source.examples", (None, n_points, 3)
            )
            self.example_names = as_names(
                example_names,
                "Source.example_names",
                self.examples.shape[0],
                default_prefix="example",
            )
        else:
            self.examples, self.example_names = None, ()
        if rig is not None and not isinstance(rig, BlendshapeRig):
            raise InputError(f"Source.rig: expected a BlendshapeRig, got {type(rig).__name__}")
        if isinstance(performance, WeightSequence) and rig is not None:
            missing = [n for n in performance.names if n not in rig.names]
            if missing:
                raise TopologyMismatchError(
                    f"Source: weight curves name shapes the source rig lacks: {', '.join(missing[:10])}"
                )
        self.rig = rig
        if actor_layers is not None:
            if not isinstance(actor_layers, LayeredRig):
                raise InputError("Source.actor_layers: expected a LayeredRig over the markers")
            if isinstance(performance, MarkerSequence) and (
                actor_layers.n_points,
                actor_layers.dim,
            ) != (
                performance.n_markers,
                performance.dim,
            ):
                raise TopologyMismatchError(
                    f"Source.actor_layers: bases are over {actor_layers.n_points} {actor_layers.dim}D points "
                    f"but the performance has {performance.n_markers} {performance.dim}D markers"
                )
        self.actor_layers = actor_layers
        if tracks2d is not None:
            if not isinstance(tracks2d, MarkerSequence) or tracks2d.dim != 2:
                raise InputError(
                    "Source.tracks2d: expected a MarkerSequence of 2D points (F, N, 2)"
                )
            if tracks2d.n_frames != n_frames:
                raise ShapeError(
                    f"Source.tracks2d: {tracks2d.n_frames} frames but the performance has {n_frames}"
                )
        self.tracks2d = tracks2d
        if actor_layers_2d is not None and tracks2d is None:
            raise InputError("Source.actor_layers_2d: given without tracks2d")
        self.actor_layers_2d = actor_layers_2d

    def replace(self, **changes: Any) -> Source:
        """A new Source with some constructor arguments changed (validated again).

        Dropping ``examples`` (``examples=None``) drops their names too.
        """
        args: dict[str, Any] = dict(
            performance=self.performance,
            head_motion=self.head_motion,
            landmarks=self.landmarks,
            feature_lines=self.feature_lines,
            examples=self.examples,
            example_names=self.example_names or None,
            rig=self.rig,
            actor_layers=self.actor_layers,
            tracks2d=self.tracks2d,
            actor_layers_2d=self.actor_layers_2d,
            name=self.name,
        )
        if changes.get("examples", 0) is None:
            args["example_names"] = None
        args.update(changes)
        return Source(args.pop("performance"), **args)

    @property
    def kind(self) -> str:
        """'markers', 'mesh' or 'weights'."""
        return self.performance.kind

    @property
    def n_frames(self) -> int:
        return self.performance.n_frames

    @property
    def fps(self) -> float:
        return self.performance.fps

    def marker_positions(self) -> np.ndarray:
        """(F, N, 3) marker trajectories: the markers, or the mesh sampled at its landmarks.

        NaN marks missing samples (markers only).
        """
        perf = self.performance
        if isinstance(perf, MarkerSequence):
            return np.asarray(perf.positions)
        if isinstance(perf, MeshSequence):
            if self.landmarks is None:
                from .errors import CapabilityError

                raise CapabilityError(
                    "this source is a mesh sequence without landmarks; pass Source(..., landmarks=...)"
                )
            return self.landmarks.positions(perf.vertices, perf.triangles)
        from .errors import CapabilityError

        raise CapabilityError("a weight-curve source has no marker positions")

    def marker_reference(self) -> np.ndarray:
        """(N, 3) neutral marker positions (see :meth:`marker_positions`)."""
        perf = self.performance
        if isinstance(perf, MarkerSequence):
            return np.asarray(perf.reference)
        if isinstance(perf, MeshSequence) and self.landmarks is not None:
            return self.landmarks.positions(perf.reference.vertices, perf.triangles)
        return self.marker_positions()[0]

    def __repr__(self) -> str:
        return (
            f"Source({self.performance!r}{', head motion' if self.head_motion is not None else ''})"
        )


class TargetRig:
    """The character: a neutral mesh plus whichever rig parts it has.

    Parameters
    ----------
    neutral : Mesh
    blendshapes : BlendshapeRig, optional
        Must be built on a neutral of the same topology.
    layers : LayeredRig, optional
        Character layered poses over the neutral's vertices.
    landmarks : Landmarks, optional
        Points corresponding (in order or by name) to the source markers / landmarks.
    feature_lines : mapping name -> (L,) int, optional
        Vertex chains around eyes and mouth (names match the source's).
    examples : (M, V, 3) float, optional
        Target example poses paired by name with ``Source.examples``.
    example_names : sequence of M str, optional
    """

    PARTS = ("blendshapes", "layers", "landmarks", "feature_lines", "examples")

    def __init__(
        self,
        neutral: Mesh,
        *,
        blendshapes: BlendshapeRig | None = None,
        layers: LayeredRig | None = None,
        landmarks: Landmarks | None = None,
        feature_lines: Mapping[str, npt.ArrayLike] | None = None,
        examples: npt.ArrayLike | None = None,
        example_names: Iterable[str] | None = None,
        name: str | None = None,
    ) -> None:
        if not isinstance(neutral, Mesh):
            raise InputError(f"TargetRig.neutral: expected a Mesh, got {type(neutral).__name__}")
        self.neutral = neutral
        self.name = name
        if blendshapes is not None:
            if not isinstance(blendshapes, BlendshapeRig):
                raise InputError("TargetRig.blendshapes: expected a BlendshapeRig")
            if blendshapes.neutral.n_vertices != neutral.n_vertices or not np.array_equal(
                blendshapes.neutral.triangles, neutral.triangles
            ):
                raise TopologyMismatchError(
                    "TargetRig.blendshapes: the rig's neutral has a different topology from TargetRig.neutral"
                )
        self.blendshapes = blendshapes
        if layers is not None:
            if not isinstance(layers, LayeredRig):
                raise InputError("TargetRig.layers: expected a LayeredRig")
            if layers.n_points != neutral.n_vertices or layers.dim != 3:
                raise TopologyMismatchError(
                    f"TargetRig.layers: poses are over {layers.n_points} {layers.dim}D points; the neutral has {neutral.n_vertices} vertices"
                )
        self.layers = layers
        if landmarks is not None:
            if not isinstance(landmarks, Landmarks):
                raise InputError("TargetRig.landmarks: expected a Landmarks")
            landmarks.validate_for(neutral, "TargetRig.landmarks")
        self.landmarks = landmarks
        self.feature_lines = _as_feature_lines(
            feature_lines, neutral.n_vertices, "TargetRig.feature_lines"
        )
        if examples is not None:
            self.examples: np.ndarray | None = as_float_array(
                examples, "TargetRig.examples", (None, neutral.n_vertices, 3)
            )
            self.example_names = as_names(
                example_names,
                "TargetRig.example_names",
                self.examples.shape[0],
                default_prefix="example",
            )
        else:
            self.examples, self.example_names = None, ()

    def replace(self, **changes: Any) -> TargetRig:
        """A new TargetRig with some constructor arguments changed (validated again).

        Dropping ``examples`` (``examples=None``) drops their names too.
        """
        args: dict[str, Any] = dict(
            neutral=self.neutral,
            blendshapes=self.blendshapes,
            layers=self.layers,
            landmarks=self.landmarks,
            feature_lines=self.feature_lines,
            examples=self.examples,
            example_names=self.example_names or None,
            name=self.name,
        )
        if changes.get("examples", 0) is None:
            args["example_names"] = None
        args.update(changes)
        return TargetRig(args.pop("neutral"), **args)

    def has(self, part: str) -> bool:
        """Whether the rig has ``part`` (one of :attr:`PARTS`)."""
        value = getattr(self, part, None)
        return value is not None and not (isinstance(value, dict) and not value)

    def parts(self) -> tuple[str, ...]:
        return tuple(p for p in self.PARTS if self.has(p))

    def __repr__(self) -> str:
        return f"TargetRig({self.neutral!r}; {', '.join(self.parts()) or 'no rig parts'})"


# ---------------------------------------------------------------------------------------
# The result
# ---------------------------------------------------------------------------------------
def apply_head_motion(head_motion: np.ndarray | None, points: np.ndarray) -> np.ndarray:
    """Apply rigid transforms ``(F, 4, 4)`` to ``points : (F, P, 3)`` -> ``(F, P, 3)``."""
    if head_motion is None or (head_motion == np.eye(4)).all():
        return points
    out = np.matmul(points, head_motion[:, :3, :3].transpose(0, 2, 1))  # 10x the equivalent einsum
    out += head_motion[:, None, :3, 3]
    return out


class FrameSource:
    """Final target vertices computed on demand, some frames at a time: the lazy form of an
    :class:`Animation`'s ``vertices`` for results whose frames cost real work (e.g. an edit
    that re-synthesizes only the frames that are read).

    Parameters
    ----------
    frames : callable ``(ids : (n,) int64) -> (n, V, 3) float``
        The final vertices (head motion included) of frames ``ids``, in that order. Make it
        picklable (a module-level function or class instance, not a closure) if results
        cross processes (``compare``, ``batch``).
    n_frames, n_vertices : int
    chunk : int
        Frames computed at a time when every frame is read (bounds the temporaries).
    """

    __slots__ = ("_frames", "n_frames", "n_vertices", "chunk")

    def __init__(self, frames: Any, n_frames: int, n_vertices: int, *, chunk: int = 32) -> None:
        if not callable(frames):
            raise InputError(f"FrameSource: frames must be callable, got {type(frames).__name__}")
        self._frames = frames
        self.n_frames = int(n_frames)
        self.n_vertices = int(n_vertices)
        self.chunk = max(1, int(chunk))
        if self.n_frames <= 0 or self.n_vertices <= 0:
            raise ShapeError(
                f"FrameSource: needs frames and vertices, got {self.n_frames} frames of {self.n_vertices} vertices"
            )

    def __call__(self, ids: np.ndarray) -> np.ndarray:
        """(n, V, 3) float vertices of frames ``ids``, checked (shape, finite)."""
        out = np.asarray(self._frames(ids))
        if out.shape != (ids.size, self.n_vertices, 3):
            raise ShapeError(
                f"FrameSource: {ids.size} frames of {self.n_vertices} vertices asked, got shape {out.shape}"
            )
        if out.size and not np.isfinite(out).all():
            f, v = (int(i) for i in np.argwhere(~np.isfinite(out))[0][:2])
            raise NonFiniteError(
                f"FrameSource: NaN or infinite coordinate at frame {int(ids[f])}, vertex {v}"
            )
        return out

    def all(self) -> np.ndarray:
        """(F, V, 3) every frame, ``chunk`` frames at a time."""
        first = self(np.arange(min(self.chunk, self.n_frames)))
        out = np.empty((self.n_frames, self.n_vertices, 3), dtype=first.dtype)
        out[: first.shape[0]] = first
        for start in range(first.shape[0], self.n_frames, self.chunk):
            stop = min(start + self.chunk, self.n_frames)
            out[start:stop] = self(np.arange(start, stop))
        return out


class Animation:
    """The result of a retargeting: target geometry and/or weights, plus provenance.

    Parameters
    ----------
    vertices : (F, V, 3) float or FrameSource, optional
        Final target vertices (head motion included); a :class:`FrameSource` computes them
        when read (:meth:`frames` computes only the frames asked for).
    weights : (F, M) float, optional
        Blendshape weights; with ``rig`` they define the vertices lazily.
    rig : BlendshapeRig, optional
    head_motion : (F, 4, 4) float, optional
        Rigid head motion; applied on top of the rig when vertices come from weights.
    triangles : (T, 3) int, optional
        Target topology (taken from ``rig`` when absent).
    fps : float
    weight_names : sequence of M str, optional (default: the rig's names)
    provenance : dict, optional
        method, version, parameters, timings (s), diagnostics.
    extras : dict, optional
        Method-specific outputs (e.g. the per-frame normal mesh).
    """

    def __init__(
        self,
        *,
        vertices: npt.ArrayLike | None = None,
        weights: npt.ArrayLike | None = None,
        rig: BlendshapeRig | None = None,
        head_motion: npt.ArrayLike | None = None,
        triangles: npt.ArrayLike | None = None,
        fps: float = 30.0,
        weight_names: Iterable[str] | None = None,
        provenance: dict | None = None,
        extras: dict | None = None,
    ) -> None:
        if vertices is None and (weights is None or rig is None):
            raise InputError(
                "Animation: give vertices, or weights together with the rig that turns them into vertices"
            )
        if rig is not None and not isinstance(rig, BlendshapeRig):
            raise InputError(f"Animation.rig: expected a BlendshapeRig, got {type(rig).__name__}")
        for label, value in (("provenance", provenance), ("extras", extras)):
            if value is not None and not isinstance(value, Mapping):
                raise InputError(f"Animation.{label}: expected a dict, got {type(value).__name__}")
        self._vertices = None
        self._lazy: FrameSource | None = None
        if isinstance(vertices, FrameSource):
            if rig is not None and vertices.n_vertices != rig.neutral.n_vertices:
                raise TopologyMismatchError(
                    f"Animation: vertices have {vertices.n_vertices} vertices but the rig's neutral has {rig.neutral.n_vertices}"
                )
            self._lazy = vertices
        elif vertices is not None:
            arr = as_array(vertices, "Animation.vertices")
            if arr.ndim != 3 or arr.shape[-1] != 3:
                raise ShapeError(f"Animation.vertices: expected (F, V, 3), got {tuple(arr.shape)}")
            if arr.shape[1] == 0:
                raise ShapeError("Animation.vertices: no vertices, shape (F, 0, 3)")
            if arr.shape[0] == 0:
                raise ShapeError(f"Animation.vertices: no frames, shape {tuple(arr.shape)}")
            if arr.dtype in (np.float32, np.float64):
                _check_finite_chunked(arr, "Animation.vertices")  # no full-size temporary
            else:
                arr = as_float_array(arr, "Animation.vertices", (None, None, 3))
            if rig is not None and arr.shape[1] != rig.neutral.n_vertices:
                raise TopologyMismatchError(
                    f"Animation: vertices have {arr.shape[1]} vertices but the rig's neutral has {rig.neutral.n_vertices}"
                )
            self._vertices = readonly(arr)
        self.rig = rig
        self.weights = None
        if weights is not None:
            self.weights = as_float_array(
                weights, "Animation.weights", (None, rig.n_shapes if rig is not None else None)
            )
        if self._vertices is not None:
            n_frames = self._vertices.shape[0]
        elif self._lazy is not None:
            n_frames = self._lazy.n_frames
        else:
            assert self.weights is not None  # checked above: without vertices, weights and a rig
            n_frames = self.weights.shape[0]
        if (
            (self._vertices is not None or self._lazy is not None)
            and self.weights is not None
            and self.weights.shape[0] != n_frames
        ):
            raise ShapeError(
                f"Animation: {self.weights.shape[0]} weight frames but {n_frames} vertex frames"
            )
        if n_frames == 0:
            raise ShapeError("Animation: no frames")
        self.head_motion = _as_head_motion(head_motion, n_frames, "Animation.head_motion")
        if triangles is None and rig is not None:
            triangles = rig.neutral.triangles
        n_vertices = self.n_vertices
        self.triangles = (
            None
            if triangles is None
            else as_index_array(triangles, "Animation.triangles", (None, 3), upper=n_vertices)
        )
        self.fps = as_fps(fps)
        if self.weights is not None:
            default = rig.names if rig is not None else None
            self.weight_names = as_names(
                weight_names if weight_names is not None else default,
                "Animation.weight_names",
                self.weights.shape[1],
                default_prefix="shape",
            )
        else:
            self.weight_names = ()
        self.provenance = dict(provenance or {})
        self.extras = dict(extras or {})

    @property
    def n_frames(self) -> int:
        if self._vertices is not None:
            return int(self._vertices.shape[0])
        if self._lazy is not None:
            return self._lazy.n_frames
        assert self.weights is not None  # an Animation without vertices has weights and a rig
        return int(self.weights.shape[0])

    @property
    def n_vertices(self) -> int:
        if self._vertices is not None:
            return int(self._vertices.shape[1])
        if self._lazy is not None:
            return self._lazy.n_vertices
        assert self.rig is not None  # an Animation without vertices has weights and a rig
        return int(self.rig.neutral.n_vertices)

    @property
    def vertices(self) -> np.ndarray:
        """(F, V, 3) final target vertices (computed from the weights, or the frame source,
        on first use)."""
        if self._vertices is None:
            if self._lazy is not None:
                self._vertices = readonly(self._lazy.all())
                self._lazy = None
            else:
                # an Animation without vertices has weights and a rig
                assert self.rig is not None and self.weights is not None
                local = self.rig.evaluate(self.weights)
                self._vertices = readonly(apply_head_motion(self.head_motion, local))
        return self._vertices

    def frames(self, ids: int | slice | npt.ArrayLike) -> np.ndarray:
        """Final vertices of some frames, ``(n, V, 3)`` (``(V, 3)`` for one ``int``), computing
        only those while the vertices are lazy (blendshape results, a :class:`FrameSource`);
        :attr:`vertices` computes every frame."""
        key: Any = ids if isinstance(ids, (int, np.integer, slice)) else np.asarray(ids)
        if self._vertices is not None:
            return self._vertices[key]
        one = isinstance(ids, (int, np.integer))
        idx = np.atleast_1d(np.arange(self.n_frames)[key]).astype(np.int64, copy=False)
        if self._lazy is not None:
            out = self._lazy(idx)
        else:
            assert self.rig is not None and self.weights is not None
            motion = None if self.head_motion is None else self.head_motion[idx]
            out = apply_head_motion(motion, self.rig.evaluate(self.weights[idx]))
        return out[0] if one else out

    @property
    def is_computed(self) -> bool:
        """True once the vertices exist as an array (always for mesh results given as arrays;
        for blendshape results and a :class:`FrameSource` after the first read of
        :attr:`vertices` or :meth:`compute`)."""
        return self._vertices is not None

    def compute(self) -> Animation:
        """Evaluate the vertices now if they are lazy (blendshape results: ``neutral + weights @
        deltas`` and the head motion, one BLAS product, timed for 300 frames x 9,409 vertices
        in docs/performance.md; a :class:`FrameSource`: every frame, a chunk at a time);
        returns ``self``. Reading :attr:`vertices` does the same on first use: call
        this to choose when the time and memory are spent."""
        _ = self.vertices
        return self

    @property
    def local_vertices(self) -> np.ndarray:
        """(F, V, 3) target vertices without the rigid head motion."""
        if self.head_motion is None:
            return self.vertices
        if self.weights is not None and self.rig is not None:
            return self.rig.evaluate(self.weights)
        inv = np.linalg.inv(self.head_motion)
        return apply_head_motion(inv, np.asarray(self.vertices, dtype=np.float64))

    @property
    def is_blendshape_based(self) -> bool:
        return self.weights is not None and self.rig is not None

    def mesh(self, frame: int = 0) -> Mesh:
        """Frame ``frame`` as a :class:`Mesh` (needs triangles)."""
        if self.triangles is None:
            raise InputError("Animation.mesh: this animation has no triangles")
        return Mesh(
            np.asarray(self.frames(int(frame)), dtype=np.float64), self.triangles, _trusted=True
        )

    def replace(self, **changes: Any) -> Animation:
        """A copy with some constructor arguments changed (e.g. ``weights=...``)."""
        args: dict[str, Any] = dict(
            vertices=None
            if self.is_blendshape_based
            else (self._vertices if self._vertices is not None else self._lazy),
            weights=self.weights,
            rig=self.rig,
            head_motion=self.head_motion,
            triangles=self.triangles,
            fps=self.fps,
            weight_names=self.weight_names or None,
            provenance=self.provenance,
            extras=self.extras,
        )
        args.update(changes)
        return Animation(**args)

    def __repr__(self) -> str:
        what = []
        if self.weights is not None:
            what.append(f"{self.weights.shape[1]} weights")
        if self._vertices is not None or self._lazy is not None or self.rig is not None:
            what.append(f"{self.n_vertices} vertices")
        method = self.provenance.get("method")
        return f"Animation({self.n_frames} frames, {', '.join(what)}{', by ' + method if method else ''})"
