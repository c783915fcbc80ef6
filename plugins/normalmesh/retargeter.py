"""The ``normalmesh`` retargeter: Na & Jung 2004, hierarchical retargeting through normal meshes.

fit(source, target)
    1. feature points (landmarks, or ``source_feature_points`` / ``target_feature_points``) on
       both neutrals; base connectivity given (``base_triangles``) or automatic (base_mesh);
    2. the normal mesh of the target's neutral and of the source's neutral (``levels`` levels),
       with piercing errors repaired and counted (Table 1);
    3. per base point, the example-based multiquadric map (Eq. 3-4, base_retarget);
    4. delta = finest-level area of the target / of the source (Eq. 9; ``detail_scale``);
    5. each target vertex attached to the finest level of the target's normal mesh: closest
       triangle, barycentric point and its offset (in that triangle's frame if the vertex is on
       the normal mesh; in head coordinates beyond its border, see attach).
retarget(source), per frame
    1. rigid head motion: ``Source.head_motion`` if given, else fitted (weighted Procrustes,
       then two robust reweightings) to the 2000 source vertices the examples move least
       (forehead, temples, nose bridge); removed from the frame, re-applied to the result;
    2. the frame's normal offsets over its own base mesh (temporal correspondence, sec. 3.1);
    3. target base = target neutral base + map(source base displacement) (Eq. 3);
    4. target levels: prediction + (TN_0 + delta * (SN_k - SN_0)) (Eq. 5-8) for the first
       ``detail_levels`` levels, TN_0 alone above; boundary vertices' displacement vectors
       (sec. 4.4), in their local frames, change the same way (``boundary_motion="transfer"``)
       or stay the target neutral's (``"initial"``, the paper);
    5. target vertices carried by their finest-level triangles.
"""
from __future__ import annotations

from typing import ClassVar

import numpy as np

from faceretarget._validate import as_array, check_choice, check_number
from faceretarget.errors import InputError, ShapeError, TopologyMismatchError
from faceretarget.geometry.procrustes import fit_rigid, to_matrix
from faceretarget.geometry.raycast import RayCaster
from faceretarget.model import Animation, Landmarks, MeshSequence, Source, TargetRig
from faceretarget.retargeter import Capabilities, Retargeter

from . import base_mesh as bm
from .attach import attach, carry
from .base_retarget import fit_base_map
from .normal_mesh import (
    KIND_BOUNDARY,
    FrameDecomposer,
    Surface,
    build_normal_mesh,
    feature_point_loops,
    make_hierarchy,
    normal_mesh_area,
    reconstruct,
)

#: Most subdivision levels accepted (level 7 of a 54-point base is ~1.5M vertices).
MAX_LEVELS = 7
#: Robust reweighting rounds of the head-motion fit.
HEAD_REWEIGHTS = 2
#: Source vertices (the most stable under the examples) the head motion is fitted to.
HEAD_VERTICES = 2000
#: Frames per chunk of the retargeting loop (each chunk starts its walks from the neutral).
CHUNK_FRAMES = 32
#: Upper bounds of the numeric parameters, far beyond any useful value (they keep the RBF
#: solve and the offsets finite).
MAX_RBF_C = 1e6
MAX_RBF_SMOOTHING = 1e6
MAX_OFFSET = 1e3
MAX_DETAIL_SCALE = 1e3
DETAIL_SCALES = ("area", "length")
HEAD_MOTIONS = ("auto", "estimate", "none")
BOUNDARY_MOTIONS = ("transfer", "initial")
BACKENDS = ("auto", "embree", "bvh")

PARAMETER_DOCS = {
    "levels": "normal-mesh levels above the base mesh (paper: 4-5); each level has 4x the triangles",
    "detail_levels": "levels whose source normal-offset changes are transferred (Eq. 8); -1 = all, 0 = base motion only",
    "rbf_c": "multiquadric c of Eq. 3, in units of the mean distance between a base point's example displacements",
    "rbf_smoothing": "ridge of the per-point RBF solve, times c (0 = exact interpolation of the examples, Eq. 4)",
    "detail_scale": "scale delta of the offset changes: 'area' = target/source area (Eq. 9), 'length' = its square root, or a number",
    "max_offset": "piercing error if the hit is farther than this times the length of the edge the new vertex splits",
    "base_triangles": "base connectivity (K, 3) over the feature points; default None = automatic (Delaunay in a shared 2D projection)",
    "source_feature_points": "Landmarks on the source mesh for the base mesh; default None = Source.landmarks",
    "target_feature_points": "Landmarks on the target mesh, in the same order; default None = TargetRig.landmarks",
    "head_motion": "'auto' = Source.head_motion if given else estimated from the feature points; 'estimate'; 'none'",
    "boundary_motion": "boundary vertices: 'transfer' their displacement-vector changes like the normal offsets, or keep the neutral's vectors ('initial', sec. 4.4)",
    "backend": "ray casting: 'auto' (Embree if embreex imports, else the numba BVH), 'embree' or 'bvh'",
}


class NormalMeshRetargeter(Retargeter):
    """Na & Jung 2004: example-based base mesh + normal-offset details, level by level."""

    name: ClassVar[str] = "normalmesh"
    capabilities: ClassVar[Capabilities] = Capabilities(
        sources=("mesh",),
        needs=("landmarks", "source_landmarks", "examples", "source_examples"),
        outputs="vertices",
        stream=False,
        edit=False,
        same_topology=False,
    )
    summary: ClassVar[str] = "example-based RBF on a base mesh, then normal-mesh offset details level by level"
    parameter_docs: ClassVar[dict[str, str]] = PARAMETER_DOCS

    def __init__(
        self,
        *,
        levels=4,
        detail_levels=-1,
        rbf_c=1.0,
        rbf_smoothing=0.05,
        detail_scale="area",
        max_offset=1.0,
        base_triangles=None,
        source_feature_points=None,
        target_feature_points=None,
        head_motion="auto",
        boundary_motion="transfer",
        backend="auto",
    ):
        self.levels = levels
        self.detail_levels = detail_levels
        self.rbf_c = rbf_c
        self.rbf_smoothing = rbf_smoothing
        self.detail_scale = detail_scale
        self.max_offset = max_offset
        self.base_triangles = base_triangles
        self.source_feature_points = source_feature_points
        self.target_feature_points = target_feature_points
        self.head_motion = head_motion
        self.boundary_motion = boundary_motion
        self.backend = backend

    # ------------------------------------------------------------------------------
    # fit
    # ------------------------------------------------------------------------------
    def _check_params(self) -> None:
        """Every constructor parameter: an :class:`InputError` naming it, its valid values and the
        value given. (The feature points and base triangles are checked where they are read.)"""
        check_number(self.levels, "normalmesh.levels", integer=True, low=0, high=MAX_LEVELS)
        check_number(self.detail_levels, "normalmesh.detail_levels (-1 = all levels)", integer=True, low=-1)
        check_number(self.rbf_c, "normalmesh.rbf_c", low=0, open_low=True, high=MAX_RBF_C)
        check_number(self.rbf_smoothing, "normalmesh.rbf_smoothing", low=0, high=MAX_RBF_SMOOTHING)
        check_number(self.max_offset, "normalmesh.max_offset", low=0, open_low=True, high=MAX_OFFSET)
        check_number(self.detail_scale, "normalmesh.detail_scale", low=0, high=MAX_DETAIL_SCALE, choices=DETAIL_SCALES)
        check_choice(self.head_motion, "normalmesh.head_motion", HEAD_MOTIONS)
        check_choice(self.boundary_motion, "normalmesh.boundary_motion", BOUNDARY_MOTIONS)
        check_choice(self.backend, "normalmesh.backend", BACKENDS)

    def _feature_points(self, source: Source, target: TargetRig) -> tuple[Landmarks, Landmarks]:
        src = self.source_feature_points if self.source_feature_points is not None else source.landmarks
        tgt = self.target_feature_points if self.target_feature_points is not None else target.landmarks
        for lm, what in ((src, "source"), (tgt, "target")):
            if not isinstance(lm, Landmarks):
                raise InputError(f"normalmesh: the {what} feature points must be a faceretarget.Landmarks, got {type(lm).__name__}")
        src.validate_for(source.performance.reference, "normalmesh source feature points")
        tgt.validate_for(target.neutral, "normalmesh target feature points")
        if len(src) != len(tgt):
            raise TopologyMismatchError(
                f"normalmesh: {len(src)} source feature points but {len(tgt)} on the target; "
                "feature point i of the target must correspond to feature point i of the source"
            )
        if len(src) < bm.MIN_FEATURE_POINTS:
            raise ShapeError(
                f"normalmesh: {len(src)} feature points; a base mesh needs at least {bm.MIN_FEATURE_POINTS} "
                "(the paper uses 78 dots over the face)"
            )
        return src, tgt

    @staticmethod
    def _paired_examples(source: Source, target: TargetRig) -> tuple[np.ndarray, np.ndarray, tuple[str, ...]]:
        s_names, t_names = list(source.example_names), list(target.example_names)
        only_t = [n for n in t_names if n not in s_names]
        only_s = [n for n in s_names if n not in t_names]
        if only_t or only_s:
            parts = []
            if only_t:
                parts.append(f"the target has {', '.join(map(repr, only_t[:8]))} which the source lacks")
            if only_s:
                parts.append(f"the source has {', '.join(map(repr, only_s[:8]))} which the target lacks")
            raise TopologyMismatchError(
                f"normalmesh: example poses are paired by example_names, but {'; '.join(parts)}; "
                "give both sides the same example names"
            )
        order = [s_names.index(n) for n in t_names]
        return np.asarray(source.examples)[order], np.asarray(target.examples), tuple(t_names)

    def _fit(self, source: Source, target: TargetRig) -> None:
        self._check_params()
        src_lm, tgt_lm = self._feature_points(source, target)
        src_ex, tgt_ex, names = self._paired_examples(source, target)
        src_mesh = source.performance.reference
        tgt_mesh = target.neutral
        src_v = np.asarray(src_mesh.vertices, dtype=np.float64)
        tgt_v = np.asarray(tgt_mesh.vertices, dtype=np.float64)
        src_pts = src_lm.positions(src_v, src_mesh.triangles)
        tgt_pts = tgt_lm.positions(tgt_v, tgt_mesh.triangles)
        src_nrm = bm.point_normals(src_lm, src_mesh.vertex_normals, src_mesh.triangles)
        tgt_nrm = bm.point_normals(tgt_lm, tgt_mesh.vertex_normals, tgt_mesh.triangles)
        src_caster = RayCaster(src_v, src_mesh.triangles, backend=self.backend)
        tgt_caster = RayCaster(tgt_v, tgt_mesh.triangles, backend=self.backend)
        if self.base_triangles is None:
            base_tri = bm.automatic_base_triangles(src_pts, src_v, src_mesh.vertex_normals, src_caster, tgt_pts, tgt_caster, src_nrm, tgt_nrm, src_lm.names)
        else:
            base_tri = bm.as_base_triangles(as_array(self.base_triangles, "normalmesh.base_triangles"), len(src_lm))
        bm.check_base_triangles(base_tri, src_pts, src_nrm, "source", src_lm.names)
        bm.check_base_triangles(base_tri, tgt_pts, tgt_nrm, "target", tgt_lm.names)
        hierarchy = make_hierarchy(base_tri, len(src_lm), int(self.levels))

        src_surface = Surface.of(src_mesh.triangles, src_mesh.n_vertices)
        tgt_surface = Surface.of(tgt_mesh.triangles, tgt_mesh.n_vertices)
        max_offset = float(self.max_offset)
        src_nm = build_normal_mesh(
            src_v, src_surface, src_pts, feature_point_loops(src_pts, src_v, src_surface), hierarchy, max_offset=max_offset, caster=src_caster
        )
        tgt_nm = build_normal_mesh(
            tgt_v, tgt_surface, tgt_pts, feature_point_loops(tgt_pts, tgt_v, tgt_surface), hierarchy, max_offset=max_offset, caster=tgt_caster
        )
        decomposer = FrameDecomposer(src_surface, src_nm, hierarchy, max_offset=max_offset, neutral_vertices=src_v)
        src_offsets0, src_pierced0, _ = decomposer(src_v, src_pts)

        ratio = normal_mesh_area(tgt_nm, hierarchy) / max(normal_mesh_area(src_nm, hierarchy), np.finfo(float).tiny)
        ds = self.detail_scale
        delta = ratio if ds == "area" else (np.sqrt(ratio) if ds == "length" else float(ds))

        src_ex_pts = src_lm.positions(np.asarray(src_ex, dtype=np.float64), src_mesh.triangles)
        tgt_ex_pts = tgt_lm.positions(np.asarray(tgt_ex, dtype=np.float64), tgt_mesh.triangles)
        base_map = fit_base_map(src_pts, tgt_pts, src_ex_pts, tgt_ex_pts, rbf_c=float(self.rbf_c), rbf_smoothing=float(self.rbf_smoothing))

        attachment = attach(tgt_v, reconstruct(tgt_pts, hierarchy, tgt_nm.tangent, tgt_nm.offset)[-1], hierarchy.triangles(hierarchy.levels))

        head_ids, head_w = stable_vertices(src_v, np.asarray(src_ex, dtype=np.float64))

        n_levels = hierarchy.levels
        n_detail = n_levels if self.detail_levels == -1 else min(int(self.detail_levels), n_levels)
        self.base_triangles_ = base_tri
        self.hierarchy_ = hierarchy
        self.source_feature_points_ = src_lm
        self.target_feature_points_ = tgt_lm
        self.example_names_ = names
        self.source_surface_ = src_surface
        self.source_normal_mesh_ = src_nm
        self.source_offsets0_ = src_offsets0
        self.target_normal_mesh_ = tgt_nm
        self.source_base0_ = src_pts
        self.target_base0_ = tgt_pts
        self.base_map_ = base_map
        self.delta_ = float(delta)
        self.target_coords0_ = [np.column_stack([t, o]) for t, o in zip(tgt_nm.tangent, tgt_nm.offset)]
        keep_initial = self.boundary_motion == "initial"
        self.detail_masks_ = [
            (1.0 if level < n_detail else 0.0)
            * np.where((tgt_nm.kind[level] == KIND_BOUNDARY)[:, None] & keep_initial, 0.0, 1.0)
            * np.ones((1, 3))
            for level in range(n_levels)
        ]
        self.attachment_ = attachment
        self.head_vertices_ = head_ids
        self.head_weights_ = head_w
        self.source_shape_ = (src_mesh.n_vertices, np.array(src_mesh.triangles))
        self.source_neutral_ = src_v
        self.piercing_errors_ = {
            "target": tgt_nm.n_pierced,
            "source_neutral": src_pierced0,
            "normal_mesh_vertices": hierarchy.n_vertices(n_levels),
        }

    # ------------------------------------------------------------------------------
    # retarget
    # ------------------------------------------------------------------------------
    def _head_motion(self, source: Source, stable_frames: np.ndarray) -> np.ndarray:
        if self.head_motion == "none":
            return np.repeat(np.eye(4)[None], len(stable_frames), axis=0)
        if self.head_motion == "auto" and source.head_motion is not None:
            return np.asarray(source.head_motion, dtype=np.float64)
        return estimate_head_motion(self.source_neutral_[self.head_vertices_], stable_frames, self.head_weights_)

    def _check_source(self, source: Source) -> MeshSequence:
        perf = source.performance
        n_vertices, triangles = self.source_shape_
        if perf.n_vertices != n_vertices or not np.array_equal(perf.triangles, triangles):
            raise TopologyMismatchError(
                f"normalmesh: this source mesh has {perf.n_vertices} vertices / {len(perf.triangles)} triangles but the "
                f"retargeter was fitted on {n_vertices} / {len(triangles)}; fit on a source of the same topology"
            )
        return perf

    def _run(self, source: Source, level: int | None = None) -> dict:
        """Retarget every frame. Returns world-coordinate arrays: ``vertices (F, V, 3)``,
        ``base (F, N, 3)``, ``normal_mesh (F, V_level, 3)`` (``level`` given), ``pierced (F,)``
        and ``motion (F, 4, 4)``.

        Frames go in chunks of ``CHUNK_FRAMES``, each walked from the neutral's hits (so the
        result does not depend on how many threads run the chunks), on up to
        ``os.cpu_count()`` threads (the kernels release the GIL).
        """
        import os
        from concurrent.futures import ThreadPoolExecutor

        perf = self._check_source(source)
        motion = self._head_motion(source, np.asarray(perf.vertices[:, self.head_vertices_], dtype=np.float64))
        n_frames, hier = perf.n_frames, self.hierarchy_
        out = {
            "vertices": np.empty((n_frames, len(self.attachment_.triangle), 3)),
            "base": np.empty((n_frames, hier.n_base, 3)),
            "normal_mesh": None if level is None else np.empty((n_frames, hier.n_vertices(level), 3)),
            "pierced": np.zeros(n_frames, dtype=np.int64),
            "motion": motion,
        }
        chunks = [range(a, min(a + CHUNK_FRAMES, n_frames)) for a in range(0, n_frames, CHUNK_FRAMES)]
        workers = max(1, min(len(chunks), os.cpu_count() or 1))
        if workers == 1:
            for chunk in chunks:
                self._run_chunk(perf, chunk, level, out)
        else:
            with ThreadPoolExecutor(workers) as pool:
                for done in [pool.submit(self._run_chunk, perf, chunk, level, out) for chunk in chunks]:
                    done.result()
        return out

    def _run_chunk(self, perf: MeshSequence, frames: range, level: int | None, out: dict) -> None:
        lm, tri, hier = self.source_feature_points_, perf.triangles, self.hierarchy_
        decomposer = FrameDecomposer(self.source_surface_, self.source_normal_mesh_, hier, max_offset=float(self.max_offset), neutral_vertices=self.source_neutral_)
        for f in frames:
            rot = np.ascontiguousarray(out["motion"][f, :3, :3])
            rot_t, trans = np.ascontiguousarray(rot.T), out["motion"][f, :3, 3]
            local = (np.asarray(perf.vertices[f], dtype=np.float64) - trans) @ rot
            s_base = lm.positions(local, tri)
            offsets, out["pierced"][f], _ = decomposer(local, s_base)
            t_base = self.target_base0_ + self.base_map_((s_base - self.source_base0_)[None])[0]
            # Eq. 8: TN_k = TN_0 + delta * (SN_k - SN_0), level by level (with tangent parts)
            coords = [c0 + self.delta_ * m * (sk - s0) for c0, m, sk, s0 in zip(self.target_coords0_, self.detail_masks_, offsets, self.source_offsets0_)]
            levels = reconstruct(t_base, hier, [c[:, :2] for c in coords], [c[:, 2] for c in coords])
            out["vertices"][f] = carry(self.attachment_, levels[-1]) @ rot_t + trans
            out["base"][f] = t_base @ rot_t + trans
            if level is not None:
                out["normal_mesh"][f] = levels[level] @ rot_t + trans

    def _retarget(self, source: Source) -> Animation:
        run = self._run(source)
        diagnostics = dict(self.piercing_errors_)
        diagnostics["source_mean_per_frame"] = float(np.mean(run["pierced"]))
        diagnostics["delta"] = self.delta_
        return Animation(
            vertices=run["vertices"],
            head_motion=run["motion"],
            triangles=self.target_.neutral.triangles,
            fps=source.fps,
            provenance={"diagnostics": {"piercing_errors": diagnostics}},
            extras={
                "base_triangles": self.base_triangles_,
                "base_vertices": run["base"],
                "piercing_errors_per_frame": run["pierced"],
                "delta": self.delta_,
            },
        )

    def normal_mesh_sequence(self, source: Source, level: int | None = None) -> MeshSequence:
        """The target's per-frame normal mesh at ``level`` (default: the finest), head motion applied."""
        self._check_fitted()
        level = self.hierarchy_.levels if level is None else int(level)
        if not 0 <= level <= self.hierarchy_.levels:
            raise InputError(f"normalmesh: level must be 0..{self.hierarchy_.levels}, got {level}")
        frames = self._run(source, level)["normal_mesh"]
        return MeshSequence(frames, self.hierarchy_.triangles(level), fps=source.fps, reference=frames[0])


def stable_vertices(neutral: np.ndarray, examples: np.ndarray, count: int = HEAD_VERTICES) -> tuple[np.ndarray, np.ndarray]:
    """The ``count`` source vertices the example poses move least, and their weights.

    Weights ``1 / (1 + (d / s)^2)`` of each vertex's largest example displacement ``d``, with
    ``s`` the displacement of the least-moving 20% of the vertices (at least 0.1% of the
    largest displacement), so rigid parts (forehead, temples, nose bridge) dominate the fit.
    """
    d = np.linalg.norm(examples - neutral, axis=-1).max(axis=0) if len(examples) else np.zeros(len(neutral))
    ids = np.sort(np.argsort(d, kind="stable")[: min(count, len(neutral))])
    scale = max(float(np.percentile(d, 20)), 1e-3 * float(d.max()), np.finfo(float).tiny)
    return ids, 1.0 / (1.0 + (d[ids] / scale) ** 2)


def estimate_head_motion(reference: np.ndarray, frames: np.ndarray, weights: np.ndarray) -> np.ndarray:
    """(F, 4, 4) rigid motion of points ``frames (F, N, 3)`` from ``reference (N, 3)``.

    Weighted Procrustes, then ``HEAD_REWEIGHTS`` rounds down-weighting points by their residual
    (Cauchy weights at the median residual), so expression moves little of the estimate.
    """
    w = np.broadcast_to(np.asarray(weights, dtype=np.float64), frames.shape[:2]).copy()
    rot, trans, _ = fit_rigid(reference, frames, w)
    for _ in range(HEAD_REWEIGHTS):
        fitted = np.einsum("fij,nj->fni", rot, reference) + trans[:, None]
        r = np.linalg.norm(fitted - frames, axis=-1)
        scale = np.median(r, axis=1, keepdims=True)
        scale = np.where(scale > 0, scale, 1.0)
        rot, trans, _ = fit_rigid(reference, frames, w / (1.0 + (r / scale) ** 2))
    return to_matrix(rot, trans)
