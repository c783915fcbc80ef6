"""Retargeting (Kholgade et al. 2011, sec. 5): the character side of Eq. 5.

``x_C(t) = R(t) (x_muC + sum_l M_Cl sum_j w_jl(t) B_Cj alpha_j(t)) + t(t)`` with the
actor's 3D head motion. Per region l the inner sum is one matrix product
``beta_l(t) @ block_l`` where ``beta_l[a] = w_{j(a) l} alpha_a`` and ``block_l`` holds
``M_Cl B_C`` on the vertices the mask touches, so a batch of frames is m BLAS calls
(cost ~ K x the touched coordinates a frame), done in chunks of frames to bound memory.

Optional projection onto the character's blendshapes (the paper renders in Maya "by
projecting [the mesh] onto a set of blendshapes created by the artist"): non-negative
(or the rig's bounds) least squares, ``argmin_w |D w - (x_local - neutral)|``, solved
on the Gram matrix; the right-hand side is ``sum_l beta_l @ (block_l D_l^T)`` so the
dense vertices never need forming.
"""

from __future__ import annotations

from functools import partial

import numpy as np

from faceretarget._threads import in_threads, single_threaded_blas, worker_count
from faceretarget.errors import ShapeError

from .model import CharacterModel

#: Frames per chunk: few BLAS calls, and a scratch of CHUNK x 3V floats per thread (15 MB at
#: 10K vertices).
CHUNK = 64

__all__ = [
    "CHUNK",
    "region_coefficients",
    "world_vertices",
    "ProjectionModel",
    "build_projection",
    "project",
]


def region_coefficients(
    weights: np.ndarray, coefficients: np.ndarray, layer_of: np.ndarray
) -> np.ndarray:
    """``beta (F, m, K)``: ``beta[t, l, a] = w[t, l, layer_of[a]] * alpha[t, a]``."""
    return weights[:, :, layer_of] * coefficients[:, None, :]


def world_vertices(
    character: CharacterModel,
    beta: np.ndarray,
    head_motion: np.ndarray | None = None,
    extra: np.ndarray | None = None,
    out: np.ndarray | None = None,
    workers: int | None = None,
) -> np.ndarray:
    """Eq. 5: ``(F, V, 3)`` character vertices for ``beta (F, m, K)`` and head motion ``(F, 4, 4)``,
    written into ``out`` (C-contiguous float64) when given.

    Without ``head_motion`` the local (neutral-frame) vertices. ``extra (F, M)``: weights
    of the character's residual block (its blendshape deltas), when it has one. Frames go
    in chunks: one BLAS product per region into a scratch buffer, then one numba pass
    (``_kernels.assemble``) that adds each vertex's region products to the neutral and
    applies the rigid motion, writing the output once. The chunks are dealt out in turn to
    ``_threads.worker_count`` threads (``workers`` of them when given; the kernel releases
    the GIL), every product on one BLAS thread, so the numbers do not depend on the thread
    count. A single frame (streaming) only reads the rows of each block whose coefficient
    is not zero.
    """
    n_frames = beta.shape[0]
    shape = (n_frames, character.n_vertices, 3)
    if out is None:
        out = np.empty(shape)
    elif out.shape != shape or out.dtype != np.float64 or not out.flags.c_contiguous:
        raise ShapeError(
            f"world_vertices: out must be C-contiguous float64 {shape}, got {out.dtype} {out.shape}"
        )
    motion = (
        np.tile(np.eye(4), (n_frames, 1, 1))
        if head_motion is None
        else np.ascontiguousarray(head_motion, dtype=np.float64)
    )
    starts = list(range(0, n_frames, CHUNK))
    workers = worker_count(len(starts)) if workers is None else max(1, int(workers))
    runs = [
        partial(_assemble_chunks, character, beta, motion, extra, out, starts[i::workers])
        for i in range(workers)
    ]
    with single_threaded_blas():
        in_threads(runs, workers)
    return out


def _assemble_chunks(character, beta, motion, extra, out, starts) -> None:
    """Frames ``start : start + CHUNK`` of :func:`world_vertices` for each of ``starts``."""
    from ._kernels import assemble

    n_frames = beta.shape[0]
    offsets = character.offsets
    n_layer = beta.shape[1]
    scratch = np.empty(min(CHUNK, n_frames) * int(offsets[-1]))
    for start in starts:
        stop = min(start + CHUNK, n_frames)
        n = stop - start
        for l, (ids, block) in enumerate(character.regions):
            if not ids.size:
                continue
            dest = scratch[n * offsets[l] : n * offsets[l + 1]].reshape(n, block.shape[1])
            if l < n_layer:
                coef = beta[start:stop, l, :]
            elif extra is not None:
                coef = extra[start:stop]
            else:
                dest[:] = 0.0
                continue
            if n == 1:
                nz = np.flatnonzero(coef[0])
                if nz.size < 0.7 * coef.shape[1]:
                    np.matmul(coef[:, nz], block[nz], out=dest)
                    continue
            np.matmul(np.ascontiguousarray(coef), block, out=dest)
        assemble(
            scratch,
            offsets,
            n,
            character.neutral,
            character.vertex_ptr,
            character.entry_region,
            character.entry_col,
            motion[start:stop],
            out[start:stop],
        )


class ProjectionModel:
    """Precomputed pieces of the blendshape projection: Gram, per-region maps, bounds."""

    def __init__(self, gram, maps, offset, lower, upper):
        self.gram = gram  # (M, M)
        self.maps = maps  # per region (K, M): block_l @ D_l^T
        self.offset = offset  # (M,): D (neutral_C - rig neutral)
        self.lower = lower
        self.upper = upper


def build_projection(character: CharacterModel, rig) -> ProjectionModel:
    """Set up the projection onto ``rig`` (a BlendshapeRig over the character's vertices)."""
    deltas = np.asarray(rig.deltas, dtype=np.float64)  # (M, V, 3)
    flat = deltas.reshape(deltas.shape[0], -1)
    gram = flat @ flat.T
    maps = [
        block @ deltas[:, ids, :].reshape(deltas.shape[0], -1).T for ids, block in character.regions
    ]
    offset = flat @ (character.neutral - np.asarray(rig.neutral.vertices, dtype=np.float64)).ravel()
    if rig.bounds is None:
        lower, upper = np.zeros(rig.n_shapes), np.full(rig.n_shapes, np.inf)
    else:
        lower, upper = np.asarray(rig.bounds[:, 0], float), np.asarray(rig.bounds[:, 1], float)
    return ProjectionModel(gram, maps, offset, lower, upper)


def project(
    model: ProjectionModel, beta: np.ndarray, x0=None, extra: np.ndarray | None = None
) -> np.ndarray:
    """Blendshape weights ``(F, M)`` closest to the layered output for ``beta (F, m, K)``
    (plus the residual block driven by ``extra (F, M_r)``, when the character has one)."""
    from faceretarget.geometry.nnls import bounded_lsq_gram

    n_layer = beta.shape[1]
    rhs = model.offset + sum(beta[:, l, :] @ mp for l, mp in enumerate(model.maps[:n_layer]))
    if extra is not None and len(model.maps) > n_layer:
        rhs = rhs + extra @ model.maps[n_layer]
    return bounded_lsq_gram(model.gram, rhs, model.lower, model.upper, x0=x0)
