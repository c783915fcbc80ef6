"""Multi-scale decomposition of meshes of one topology (Xu et al. 2014, sec. 3, eq. 1-5).

A mesh ``S`` is split into a smooth mesh ``S~`` (Taubin smoothing, about 40 iterations)
and its Laplacian coating (Sorkine et al. 2004): the difference of Laplacian
coordinates ``xi = M S - M S~ = M (S - S~)``, stored per vertex in the local frame of the
*smooth* mesh (normal + projected edge tangent, :mod:`faceretarget.geometry.local_frames`),
``c = F(S~)^T xi``. Because the frame moves with the surface, ``c`` is invariant to rigid
motion and (nearly) to the large-scale deformation. Reconstruction is eq. 2 / 5::

    S = M^-1 (M S~ + F(S~) c) = S~ + M^-1 (F(S~) c)

a Poisson solve with ``M`` factorized once per mesh. ``M = L + a I`` is the mesh
Laplacian (uniform by default: source and target then share the same operator, so
a detail transferred with identical local coordinates reconstructs identically) plus a
small screening term ``a = screening * mean(diag L)``. The screening makes ``M``
invertible without anchors and keeps the reconstruction of *transferred* coatings local:
per-vertex rotations of the coating do not commute with ``M``, and with ``a -> 0`` the
error of that commutator would be amplified over the whole mesh (our reading of
"L^-1" in eq. 2; the decomposition is exact for any ``a > 0``).
"""

from __future__ import annotations

import numpy as np
import scipy.sparse as sp

from faceretarget.errors import ConfigError, ShapeError
from faceretarget.geometry.factorized import SPDFactor
from faceretarget.geometry.laplacian import cotangent_laplacian, uniform_laplacian
from faceretarget.geometry.local_frames import VertexFrames, frame_neighbors, to_local, to_world
from faceretarget.geometry.smoothing import TaubinSmoother

__all__ = ["MultiScale", "FLOAT32_CONDITION", "filter_pair"]

#: Largest bound on the Poisson system's condition number at which ``solve_dtype="auto"``
#: solves in float32 (relative error ~cond x 6e-8 of the detail offsets: at most ~6e-6).
FLOAT32_CONDITION = 100.0


def filter_pair(
    triangles: np.ndarray, n_vertices: int, iterations: int, smooth_dtype=np.float32
) -> tuple[TaubinSmoother, TaubinSmoother]:
    """The smoothing filter ``G`` of a topology (``smooth_dtype`` kernel) and its adjoint ``G^T``
    (float64: it forms the right-hand sides of the basis weights)."""
    return (
        TaubinSmoother(triangles, n_vertices, iterations=iterations, dtype=smooth_dtype),
        TaubinSmoother(
            triangles, n_vertices, iterations=iterations, dtype=np.float64, adjoint=True
        ),
    )


class MultiScale:
    """Smoothing, coating and reconstruction on one mesh topology.

    Parameters
    ----------
    reference : (V, 3) float
        The mesh whose Laplacian (cotangent case) defines ``M``, and whose decomposition
        is the reference (``S~_0``, coating ``c_0``).
    triangles : (T, 3) int
    iterations : int
        Taubin lambda|mu pairs.
    laplacian : "uniform" or "cotangent"
    screening : float
        ``a / mean(diag L)``.
    neighbors : (V, 2) int, optional
        Tangent neighbours of the local frames (share them between source and target so
        tangents correspond); default: chosen on the smooth reference.
    smooth_dtype : float32 or float64
        Precision of the batched smoothing kernel.
    shared : (smoother, adjoint, smooth_reference), optional
        The two :class:`~faceretarget.geometry.smoothing.TaubinSmoother` of this topology
        (``G`` and ``G^T``) and ``G reference``, when a caller builds them for two meshes of
        one topology at once (``iterations`` and ``smooth_dtype`` are then theirs).
    solve_dtype : "auto", float32 or float64
        Precision of the per-frame Poisson solves of :meth:`reconstruct`
        (:class:`~faceretarget.geometry.factorized.SPDFactor` ``frames_dtype``). "auto":
        float32 (~1.3x faster) when the Gershgorin bound on the screened system's condition
        number, ``max_i sum_j |M_ij| / a`` (:attr:`condition_bound`), is at most
        :data:`FLOAT32_CONDITION` (uniform Laplacian at the default screening: ~20-25; outputs
        within ~3e-8 of the mesh size of float64 solves), else float64 (a cotangent Laplacian
        with sliver triangles, a small screening). float64 reconstructs a decomposition
        exactly (to ~1e-12).
    """

    def __init__(
        self,
        reference,
        triangles,
        *,
        iterations: int,
        laplacian: str,
        screening: float,
        neighbors=None,
        smooth_dtype=np.float32,
        solve_dtype="auto",
        shared=None,
    ):
        ref = np.asarray(reference, dtype=np.float64)
        tri = np.asarray(triangles, dtype=np.int64)
        n = ref.shape[0]
        self.n_vertices = n
        self.triangles = tri
        if shared is None:
            smoother, adjoint = filter_pair(tri, n, iterations, smooth_dtype)
            smooth_reference = smoother(ref)
        else:
            smoother, adjoint, smooth_reference = shared
            for what, filt in (("smoother", smoother), ("adjoint", adjoint)):
                if filt.n_vertices != n or filt.iterations != int(iterations):
                    raise ConfigError(
                        f"MultiScale: the shared {what} is for {filt.n_vertices} vertices and {filt.iterations} "
                        f"iterations; this mesh has {n} vertices and iterations={iterations}"
                    )
            if np.shape(smooth_reference) != ref.shape:
                raise ShapeError(
                    f"MultiScale: the shared smooth reference must be {ref.shape}, got {np.shape(smooth_reference)}"
                )
        self.smoother, self.adjoint = smoother, adjoint
        if laplacian == "uniform":
            lap = uniform_laplacian(tri, n)
        elif laplacian == "cotangent":
            lap = cotangent_laplacian(ref, tri)
        else:
            raise ConfigError(f"laplacian must be 'uniform' or 'cotangent', got {laplacian!r}")
        if not screening > 0:
            raise ConfigError(
                f"screening must be > 0 (it makes the Poisson system invertible), got {screening!r}"
            )
        shift = float(screening) * float(np.mean(lap.diagonal()))
        self.poisson = (lap + shift * sp.identity(n, format="csr")).tocsr()
        self.poisson.sort_indices()
        #: Gershgorin bound on the condition number of ``M = L + a I`` (``L`` PSD: eigenvalues >= a).
        self.condition_bound = float(abs(self.poisson).sum(axis=1).max()) / shift
        if isinstance(solve_dtype, str) and solve_dtype == "auto":
            solve_dtype = np.float32 if self.condition_bound <= FLOAT32_CONDITION else np.float64
        self.factor = SPDFactor(
            self.poisson,
            what="the Poisson system of the Laplacian coating",
            frames_dtype=solve_dtype,
        )
        self.smooth_reference = np.asarray(smooth_reference, dtype=np.float64)
        if neighbors is None:
            neighbors = frame_neighbors(self.smooth_reference, tri)
        self.neighbors = np.asarray(neighbors, dtype=np.int64)
        self.frames = VertexFrames(tri, self.neighbors)
        self.reference = ref
        self.reference_coating = self.coating(ref[None], self.smooth_reference[None])[0]

    def smooth(self, points: np.ndarray) -> np.ndarray:
        """Smooth meshes ``(C, V, 3)`` -> ``(C, V, 3)`` float64."""
        return self.smoother(points)

    def coating(
        self, points: np.ndarray, smooth: np.ndarray, frames: np.ndarray | None = None
    ) -> np.ndarray:
        """Local coating ``c = F(S~)^T M (S - S~)`` -> ``(C, V, 3)`` (eq. 1)."""
        s = np.asarray(smooth, dtype=np.float64)
        if frames is None:
            return self.frames.coating(points, s, self.poisson)
        diff = np.asarray(points, dtype=np.float64) - s
        xi = np.stack([self.poisson @ d for d in diff])
        return to_local(frames, xi)

    def reconstruct(
        self,
        smooth: np.ndarray,
        coating: np.ndarray,
        frames: np.ndarray | None = None,
        *,
        overwrite_coating: bool = False,
    ) -> np.ndarray:
        """``S = S~ + M^-1 (F(S~) c)`` for ``smooth, coating : (C, V, 3)`` (eq. 2 / 5).
        ``overwrite_coating``: work in ``coating`` (C-contiguous float64; the result may be
        it) instead of two new arrays of its size."""
        s = np.asarray(smooth, dtype=np.float64)
        xi = (
            self.frames.apply(s, coating, inverse=False, overwrite_vectors=overwrite_coating)
            if frames is None
            else to_world(frames, coating)
        )
        return self.factor.solve_frames(xi, s, out=xi if xi.flags.c_contiguous else None)

    def decompose(self, points: np.ndarray):
        """``(smooth, coating)`` of meshes ``(C, V, 3)``."""
        s = self.smooth(points)
        return s, self.coating(points, s)
