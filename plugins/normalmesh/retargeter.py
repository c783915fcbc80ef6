"""The ``normalmesh`` retargeter: Na & Jung 2004, hierarchical retargeting through normal meshes.

fit(source, target)
    1. feature points (landmarks, or ``source_feature_points`` / ``target_feature_points``) on
       both neutrals; base connectivity given (``base_triangles``) or automatic (base_mesh);
    2. ``levels`` (default: from the source's resolution); the normal mesh of the target's
       neutral and of the source's neutral, with piercing errors repaired and counted (Table
       1); base triangles whose patch fails on more than ``max_piercing`` of its vertices (on
       either neutral or a source example) are removed and the meshes built again;
    3. per base point, the example-based multiquadric map (Eq. 3-4, base_retarget);
    4. delta = (finest-level area of the target / of the source) ** 1/2 (``detail_scale``;
       Eq. 9 without the root is ``"area"``);
    5. each target vertex attached to the finest level of the target's normal mesh: closest
       triangle, barycentric point and its offset (see attach), and its coverage: 1 on the
       normal mesh, 0 off it, a smoothstep over ``BAND`` edges in between;
    6. the dense fallback (``fallback="examples"``): every target vertex not fully covered
       gets its own example-based map (Eq. 3-4, as a base point without a base mesh) from its
       corresponding source point (the same vertex for same-topology pairs with the same
       feature points; else an RBF warp through the feature points and the two normal meshes,
       then the closest source point).
retarget(source), per frame
    1. rigid head motion: ``Source.head_motion`` if given, else fitted (weighted Procrustes,
       then two robust reweightings) to the 2000 source vertices the examples move least
       (forehead, temples, nose bridge) and kept if it explains the motion of those vertices
       (``HEAD_SIGNIFICANCE``); removed from the frame, re-applied to the result (its
       translation converted to the target's units);
    2. the frame's normal offsets over its own base mesh (temporal correspondence, sec. 3.1);
    3. target base = target neutral base + map(source base displacement) (Eq. 3);
    4. target levels: prediction + (TN_0 + delta * (SN_k - SN_0)) (Eq. 5-8) for the first
       ``detail_levels`` levels, TN_0 alone above; boundary vertices' displacement vectors
       (sec. 4.4), in their local frames, change the same way (``boundary_motion="transfer"``)
       or stay the target neutral's (``"initial"``, the paper);
    5. ``sliding="transfer"``: each finest-level vertex also slides over the target as the
       source's material point under it slides away from the source's normal-mesh vertex
       (in local frames, times delta): normal-mesh vertices are not material points;
    6. target vertices carried by their finest-level triangles, blended by coverage with the
       dense fallback.
"""

from __future__ import annotations

from functools import partial
from typing import ClassVar

import numpy as np
import scipy.sparse as sp

from faceretarget import manifest
from faceretarget._validate import as_array, readonly
from faceretarget.errors import (
    DegenerateGeometryError,
    InputError,
    ShapeError,
    TopologyMismatchError,
)
from faceretarget.geometry.mesh_ops import barycentric_matrix
from faceretarget.geometry.procrustes import fit_rigid, to_matrix
from faceretarget.geometry.raycast import RayCaster
from faceretarget.model import Animation, Landmarks, MeshSequence, Source, TargetRig
from faceretarget.retargeter import Retargeter
from faceretarget.validation import validate_params

from . import base_mesh as bm
from .attach import attach, carry, coverage
from .base_retarget import fit_base_map
from .normal_mesh import (
    KIND_BOUNDARY,
    KIND_REPAIRED,
    FrameDecomposer,
    Surface,
    build_normal_mesh,
    feature_point_loops,
    make_hierarchy,
    normal_mesh_area,
    piercing_share,
    reconstruct,
)

#: Most subdivision levels accepted (level 7 of a 54-point base is ~1.5M vertices).
MAX_LEVELS = 7
#: ``levels="auto"``: the finest level's median edge at most this times the source's (median
#: edges of irregular meshes vary by some 20%).
LEVEL_EDGE = 1.2
#: Robust reweighting rounds of the head-motion fit.
HEAD_REWEIGHTS = 2
#: Source vertices (the most stable under the examples) the head motion is fitted to.
HEAD_VERTICES = 2000
#: An estimated head motion is kept (``head_motion="auto"``) only if, over the shot, it
#: removes more than this share of the weighted squared motion of the stable vertices.
HEAD_SIGNIFICANCE = 0.5
#: Frames per chunk of the retargeting loop (each chunk starts its walks from the neutral), at
#: most; a shot is cut into at least ``MIN_CHUNKS`` chunks, so that a short one keeps two
#: cores busy (bench_normalmesh --quick, 16 frames: 27 -> 14.4 ms a frame). The chunks depend
#: on the number of frames only, never on the number of threads.
CHUNK_FRAMES = 32
MIN_CHUNKS = 2
#: Width of the band over which the output passes from the normal mesh to the dense
#: fallback, in median edges of the target's finest normal-mesh level or of the target mesh,
#: whichever are longer.
BAND = 2.0
#: Rounds of removing base triangles with too many piercing errors (``max_piercing``).
PRUNE_ROUNDS = 3
#: A warning names the removed base triangles when they made up more than this share of the
#: base mesh's area on the target.
REMOVED_WARNING = 0.25
#: Most vertex pairs of the two normal meshes used to warp the target onto the source for
#: the fallback's correspondence (the finest level with at most this many vertices).
WARP_PAIRS = 1500


class NormalMeshRetargeter(Retargeter):
    """Na & Jung 2004: example-based base mesh + normal-offset details, level by level."""

    #: Capabilities and summary: registry.toml (Retargeter.packaged_manifest), by this name.
    name: ClassVar[str] = "normalmesh"
    #: Types, ranges and choices of the parameters, with their meanings: registry.toml.
    parameter_constraints: ClassVar[dict] = manifest.constraints("normalmesh")

    def __init__(
        self,
        *,
        levels="auto",
        detail_levels=-1,
        rbf_c=1.0,
        rbf_smoothing=0.05,
        detail_scale="length",
        max_offset=1.0,
        repair="surface",
        max_piercing=0.1,
        sliding="transfer",
        fallback="examples",
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
        self.repair = repair
        self.max_piercing = max_piercing
        self.sliding = sliding
        self.fallback = fallback
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
        """Every constructor parameter against its declared constraints (registry.toml): a
        :class:`~faceretarget.errors.ParameterError` (an InputError) naming it, its valid values
        and the value given. (The feature points and base triangles are checked where read.)"""
        validate_params(self)

    def _feature_points(self, source: Source, target: TargetRig) -> tuple[Landmarks, Landmarks]:
        src = (
            self.source_feature_points
            if self.source_feature_points is not None
            else source.landmarks
        )
        tgt = (
            self.target_feature_points
            if self.target_feature_points is not None
            else target.landmarks
        )
        for lm, what in ((src, "source"), (tgt, "target")):
            if not isinstance(lm, Landmarks):
                raise InputError(
                    f"normalmesh: the {what} feature points must be a faceretarget.Landmarks, got {type(lm).__name__}"
                )
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
    def _paired_examples(
        source: Source, target: TargetRig
    ) -> tuple[np.ndarray, np.ndarray, tuple[str, ...]]:
        s_names, t_names = list(source.example_names), list(target.example_names)
        only_t = [n for n in t_names if n not in s_names]
        only_s = [n for n in s_names if n not in t_names]
        if only_t or only_s:
            parts = []
            if only_t:
                parts.append(
                    f"the target has {', '.join(map(repr, only_t[:8]))} which the source lacks"
                )
            if only_s:
                parts.append(
                    f"the source has {', '.join(map(repr, only_s[:8]))} which the target lacks"
                )
            raise TopologyMismatchError(
                f"normalmesh: example poses are paired by example_names, but {'; '.join(parts)}; "
                "give both sides the same example names"
            )
        order = [s_names.index(n) for n in t_names]
        return np.asarray(source.examples)[order], np.asarray(target.examples), tuple(t_names)

    def _levels(
        self,
        base_tri: np.ndarray,
        src_pts: np.ndarray,
        src_v: np.ndarray,
        src_tri: np.ndarray,
        tgt_pts: np.ndarray | None = None,
        tgt_v: np.ndarray | None = None,
        tgt_tri: np.ndarray | None = None,
    ) -> int:
        """``levels``, or with "auto" the fewest halvings of the base mesh's median edge that
        reach ``LEVEL_EDGE`` times the *sampling edge* ``h = clip(h_t / 2, h_s / 2, h_s)``
        (``h_s``, ``h_t`` the source and target meshes' median edges, measured on each side
        against its own base mesh): at least the source's density (the paper's 69K-vertex faces
        over 78 dots: 5 levels), and half the target's edge where the source has detail at that
        scale, so that the target's vertices, interpolated from the finest level, lose nothing
        to it (the finest level is itself a resampling of the source surface; at the source's
        own spacing the two resamplings took 30-40% of the depth of wrinkles 4-5 edges long).
        A target at least twice as coarse as the source: ``h = h_s``."""
        if self.levels != "auto":
            return int(self.levels)
        tiny = np.finfo(float).tiny
        ratio = bm.median_edge(src_pts, base_tri) / max(bm.median_edge(src_v, src_tri), tiny)
        if tgt_v is not None:
            # the target's edge in the source's scale (the two base meshes are the same connectivity)
            h_t = bm.median_edge(tgt_v, tgt_tri) / max(bm.median_edge(tgt_pts, base_tri), tiny)
            ratio = max(ratio, 1.0 / max(np.clip(h_t / 2.0, 0.5 / ratio, 1.0 / ratio), tiny))
        return int(np.clip(np.ceil(np.log2(max(ratio / LEVEL_EDGE, 1.0))), 1, MAX_LEVELS))

    def _normal_meshes(self, base_tri, levels, src, tgt, src_examples):
        """Hierarchy and normal meshes of both neutrals; base triangles whose patch has more than
        ``max_piercing`` piercing errors (either neutral, or the source's normal mesh walked onto a
        source example) are removed and the meshes built again (``PRUNE_ROUNDS`` times at most).
        ``src``, ``tgt``: dicts of vertices, surface, points, loops, caster, landmarks.
        Returns hierarchy, source and target normal meshes, kept and removed base triangles."""
        max_offset = float(self.max_offset)
        removed = np.zeros((0, 3), dtype=np.int64)
        for rnd in range(PRUNE_ROUNDS + 1):
            hierarchy = make_hierarchy(base_tri, len(src["points"]), levels)
            nms = [
                build_normal_mesh(
                    m["vertices"],
                    m["surface"],
                    m["points"],
                    m["loops"],
                    hierarchy,
                    max_offset=max_offset,
                    caster=m["caster"],
                    repair=self.repair,
                )
                for m in (src, tgt)
            ]
            if self.max_piercing >= 1.0 or levels == 0 or rnd == PRUNE_ROUNDS:
                break
            share = np.maximum(
                piercing_share(hierarchy, nms[0].kind), piercing_share(hierarchy, nms[1].kind)
            )
            for example in src_examples:
                decomposer = FrameDecomposer(
                    src["surface"],
                    nms[0],
                    hierarchy,
                    max_offset=max_offset,
                    neutral_vertices=src["vertices"],
                    repair=self.repair,
                )
                decomposer(example, src["landmarks"].positions(example, src["triangles"]))
                share = np.maximum(share, piercing_share(hierarchy, decomposer.flagged))
            drop = share > float(self.max_piercing)
            if not drop.any():
                break
            if drop.all():
                raise DegenerateGeometryError(
                    f"normalmesh: the normal mesh of every base triangle has piercing errors on more than "
                    f"{100 * float(self.max_piercing):g}% of its vertices; raise max_piercing (1 keeps every triangle) or "
                    "max_offset, or give more feature points where the faces curve most"
                )
            removed = np.vstack([removed, base_tri[drop]])
            base_tri = base_tri[~drop]
        return hierarchy, nms[0], nms[1], base_tri, removed

    def _correspondence(self, ids, src, tgt, src_nm, tgt_nm, hierarchy, same_topology: bool):
        """Source points corresponding to target vertices ``ids``: corners (P, 3) of source
        triangles and barycentric weights (P, 3). Same topology and feature points: the same
        vertex. Otherwise the target vertices are warped into the source's space (RBF, phi(r) =
        r + linear, in units of each face's size) through pairs of points known to correspond
        (the feature points and the vertices of the two normal meshes' finest level with at
        most ``WARP_PAIRS`` vertices, without off-surface repaired ones) and moved to their
        closest point on the source's neutral."""
        from faceretarget.geometry.rbf import fit_rbf

        if same_topology:
            return np.repeat(ids[:, None], 3, axis=1), np.tile([1.0, 0.0, 0.0], (len(ids), 1))
        level = max(
            [l for l in range(hierarchy.levels + 1) if hierarchy.n_vertices(l) <= WARP_PAIRS] or [0]
        )
        keep = np.ones(hierarchy.n_vertices(level), dtype=bool)
        for nm in (src_nm, tgt_nm):
            off = np.concatenate(
                [np.zeros(hierarchy.n_base, dtype=bool)]
                + [
                    (k == KIND_REPAIRED) & (a < 0)
                    for k, a in zip(nm.kind[:level], nm.anchor[:level])
                ]
            )
            keep &= ~off
        t_pairs, s_pairs = tgt_nm.positions[level][keep], src_nm.positions[level][keep]
        t_c, s_c = tgt["vertices"].mean(axis=0), src["vertices"].mean(axis=0)
        t_s = float(np.sqrt(np.mean(np.sum((tgt["vertices"] - t_c) ** 2, axis=1))))
        s_s = float(np.sqrt(np.mean(np.sum((src["vertices"] - s_c) ** 2, axis=1))))
        warp = fit_rbf((t_pairs - t_c) / t_s, (s_pairs - s_c) / s_s, kernel="linear")
        guess = warp((tgt["vertices"][ids] - t_c) / t_s) * s_s + s_c
        hits = src["caster"].closest(guess)
        return np.asarray(src["triangles"])[hits.triangle], hits.barycentric

    def _fit(self, source: Source, target: TargetRig) -> None:
        self._check_params()
        self.__dict__.pop("samplers_", None)  # built from the previous fit's points
        src_lm, tgt_lm = self._feature_points(source, target)
        src_ex, tgt_ex, names = self._paired_examples(source, target)
        src_ex = np.asarray(src_ex, dtype=np.float64)
        tgt_ex = np.asarray(tgt_ex, dtype=np.float64)
        src_mesh = source.performance.reference
        tgt_mesh = target.neutral
        sides = []
        for mesh, lm in ((src_mesh, src_lm), (tgt_mesh, tgt_lm)):
            v = np.asarray(mesh.vertices, dtype=np.float64)
            pts = lm.positions(v, mesh.triangles)
            surface = Surface.of(mesh.triangles, mesh.n_vertices)
            sides.append(
                dict(
                    vertices=v,
                    triangles=np.asarray(mesh.triangles),
                    points=pts,
                    landmarks=lm,
                    surface=surface,
                    loops=feature_point_loops(pts, v, surface),
                    caster=RayCaster(v, mesh.triangles, backend=self.backend),
                    normals=bm.point_normals(lm, mesh.vertex_normals, mesh.triangles),
                )
            )
        src, tgt = sides
        src_v, tgt_v, src_pts, tgt_pts = (
            src["vertices"],
            tgt["vertices"],
            src["points"],
            tgt["points"],
        )
        if self.base_triangles is None:
            surfaces = [
                (
                    m["points"],
                    bm.nearest_vertices(m["landmarks"], m["vertices"], m["triangles"]),
                    m["vertices"],
                    m["triangles"],
                )
                for m in sides
            ]
            base_tri = bm.automatic_base_triangles(
                src_pts,
                src_v,
                src_mesh.vertex_normals,
                src["caster"],
                tgt_pts,
                tgt["caster"],
                src["normals"],
                tgt["normals"],
                src_lm.names,
                surfaces=surfaces,
            )
        else:
            base_tri = bm.as_base_triangles(
                as_array(self.base_triangles, "normalmesh.base_triangles"), len(src_lm)
            )
        bm.check_base_triangles(base_tri, src_pts, src["normals"], "source", src_lm.names)
        bm.check_base_triangles(base_tri, tgt_pts, tgt["normals"], "target", tgt_lm.names)
        levels = self._levels(
            base_tri, src_pts, src_v, src["triangles"], tgt_pts, tgt_v, tgt["triangles"]
        )
        hierarchy, src_nm, tgt_nm, base_tri, removed = self._normal_meshes(
            base_tri, levels, src, tgt, src_ex
        )
        removed_share = _area(tgt_pts, removed) / max(
            _area(tgt_pts, removed) + _area(tgt_pts, base_tri), np.finfo(float).tiny
        )
        if removed_share > REMOVED_WARNING:
            import warnings

            from faceretarget.errors import FaceRetargetWarning

            point_names = tgt_lm.names or [str(i) for i in range(len(tgt_lm))]
            listed = "; ".join(", ".join(point_names[i] for i in t) for t in removed[:6])
            warnings.warn(
                f"normalmesh: {len(removed)} base triangles ({100 * removed_share:.0f}% of the base mesh's area) had piercing "
                f"errors on more than {100 * float(self.max_piercing):g}% of their vertices and were removed (first: {listed}); "
                "their region moves with the dense fallback, without the normal mesh's detail transfer. More feature "
                "points there, base_triangles or a larger max_offset keep them",
                FaceRetargetWarning,
                stacklevel=3,
            )
        max_offset = float(self.max_offset)
        decomposer = FrameDecomposer(
            src["surface"],
            src_nm,
            hierarchy,
            max_offset=max_offset,
            neutral_vertices=src_v,
            repair=self.repair,
        )
        src_offsets0, src_pierced0, src_levels0 = decomposer(src_v, src_pts, keep_positions=True)

        ratio = normal_mesh_area(tgt_nm, hierarchy) / max(
            normal_mesh_area(src_nm, hierarchy), np.finfo(float).tiny
        )
        ds = self.detail_scale
        delta = np.sqrt(ratio) if ds == "length" else (ratio if ds == "area" else float(ds))

        src_ex_pts = src_lm.positions(src_ex, src["triangles"])
        tgt_ex_pts = tgt_lm.positions(tgt_ex, tgt["triangles"])
        base_map = fit_base_map(
            src_pts,
            tgt_pts,
            src_ex_pts,
            tgt_ex_pts,
            rbf_c=float(self.rbf_c),
            rbf_smoothing=float(self.rbf_smoothing),
        )

        n_levels = hierarchy.levels
        finest_tri = hierarchy.triangles(n_levels)
        finest = reconstruct(tgt_pts, hierarchy, tgt_nm.tangent, tgt_nm.offset)[-1]
        attachment = attach(tgt_v, finest, finest_tri)
        if self.fallback == "examples":
            band = BAND * max(
                bm.median_edge(finest, finest_tri), bm.median_edge(tgt_v, tgt["triangles"])
            )
            weight = coverage(tgt_v, attachment, finest, finest_tri, band)
        else:
            weight = np.ones(len(tgt_v))
        dense_ids = np.flatnonzero(weight < 1.0)
        same_topology = (
            len(src_v) == len(tgt_v)
            and np.array_equal(src["triangles"], tgt["triangles"])
            and _same_landmarks(src_lm, tgt_lm)
        )
        corners, bary = self._correspondence(
            dense_ids, src, tgt, src_nm, tgt_nm, hierarchy, same_topology
        )
        src_at = np.einsum("pk,pkd->pd", bary, src_v[corners])
        src_ex_at = np.einsum("pk,mpkd->mpd", bary, src_ex[:, corners])
        dense_map = fit_base_map(
            src_at,
            tgt_v[dense_ids],
            src_ex_at,
            tgt_ex[:, dense_ids],
            rbf_c=float(self.rbf_c),
            rbf_smoothing=float(self.rbf_smoothing),
            linear=base_map.linear,
        )

        # sliding: the source material point under each finest-level vertex of the neutral
        neighbour = frame_neighbours(finest_tri, hierarchy.n_vertices(n_levels))
        y0 = src_levels0[-1]
        under = src["caster"].closest(y0)
        slide_corners, slide_bary = src["triangles"][under.triangle], under.barycentric
        slide0 = np.einsum("pkd,pd->pk", local_frames(y0, finest_tri, neighbour), under.points - y0)

        head_ids, head_w = stable_vertices(src_v, src_ex)
        scale = float(np.linalg.norm(base_map.linear[:, 0]))

        n_detail = n_levels if self.detail_levels == -1 else min(int(self.detail_levels), n_levels)
        self.levels_ = n_levels
        self.base_triangles_ = base_tri
        self.removed_base_triangles_ = removed
        self.hierarchy_ = hierarchy
        self.source_feature_points_ = src_lm
        self.target_feature_points_ = tgt_lm
        self.example_names_ = names
        self.source_surface_ = src["surface"]
        self.source_normal_mesh_ = src_nm
        self.source_offsets0_ = src_offsets0
        self.target_normal_mesh_ = tgt_nm
        self.source_base0_ = src_pts
        self.target_base0_ = tgt_pts
        self.base_map_ = base_map
        self.delta_ = float(delta)
        self.target_coords0_ = [
            np.column_stack([t, o]) for t, o in zip(tgt_nm.tangent, tgt_nm.offset)
        ]
        keep_initial = self.boundary_motion == "initial"
        self.detail_masks_ = [
            (1.0 if level < n_detail else 0.0)
            * np.where((tgt_nm.kind[level] == KIND_BOUNDARY)[:, None] & keep_initial, 0.0, 1.0)
            * np.ones((1, 3))
            for level in range(n_levels)
        ]
        self.attachment_ = attachment
        self.coverage_ = weight
        self.dense_vertices_ = dense_ids
        self.dense_corners_ = corners
        self.dense_barycentric_ = bary
        self.dense_map_ = dense_map
        self.dense_source0_ = src_at
        self.frame_neighbours_ = neighbour
        self.slide_corners_ = slide_corners
        self.slide_barycentric_ = slide_bary
        self.slide0_ = slide0
        self.head_vertices_ = head_ids
        self.head_weights_ = head_w
        # head-motion translations are in the source's units: to the target's by the power of
        # ten nearest the feature points' similarity scale (1 for faces in the same units)
        self.unit_ratio_ = float(10.0 ** np.round(np.log10(max(scale, np.finfo(float).tiny))))
        self.source_shape_ = (src_mesh.n_vertices, np.array(src_mesh.triangles))
        self.source_neutral_ = src_v
        self.target_neutral_ = tgt_v
        n_nm = hierarchy.n_vertices(n_levels)
        self.piercing_errors_ = {
            "target": tgt_nm.n_pierced,
            "source_neutral": src_pierced0,
            "normal_mesh_vertices": n_nm,
            "target_share": tgt_nm.n_pierced / n_nm,
        }
        self.coverage_stats_ = {
            "removed_area_share": float(removed_share),
            "covered": float(np.mean(weight >= 1.0)),
            "blended": float(np.mean((weight > 0.0) & (weight < 1.0))),
            "fallback": float(np.mean(weight <= 0.0)),
            "removed_base_triangles": int(len(removed)),
        }

    # ------------------------------------------------------------------------------
    # retarget
    # ------------------------------------------------------------------------------
    def _head_motion(self, source: Source, stable_frames: np.ndarray) -> np.ndarray:
        """(F, 4, 4) head motion in the source's coordinates."""
        if self.head_motion == "none":
            return np.repeat(np.eye(4)[None], len(stable_frames), axis=0)
        if self.head_motion == "auto" and source.head_motion is not None:
            return np.asarray(source.head_motion, dtype=np.float64)
        reference = self.source_neutral_[self.head_vertices_]
        motion = estimate_head_motion(reference, stable_frames, self.head_weights_)
        if self.head_motion == "auto" and not significant_motion(
            reference, stable_frames, self.head_weights_, motion
        ):
            return np.repeat(np.eye(4)[None], len(stable_frames), axis=0)
        return motion

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
        and ``motion (F, 4, 4)`` (the head motion in the target's units).

        Frames go in chunks of at most ``CHUNK_FRAMES`` (at least ``MIN_CHUNKS`` of them when
        there are that many frames), each walked from the neutral's hits (so the result does
        not depend on how many threads run the chunks), on ``_threads.worker_count`` threads
        (the kernels release the GIL).
        """
        from faceretarget._threads import in_threads, worker_count

        perf = self._check_source(source)
        motion = self._head_motion(
            source, np.asarray(perf.vertices[:, self.head_vertices_], dtype=np.float64)
        )
        target_motion = motion.copy()
        target_motion[:, :3, 3] *= self.unit_ratio_
        n_frames, hier = perf.n_frames, self.hierarchy_
        out = {
            "vertices": np.empty((n_frames, len(self.attachment_.triangle), 3)),
            "base": np.empty((n_frames, hier.n_base, 3)),
            "normal_mesh": None
            if level is None
            else np.empty((n_frames, hier.n_vertices(level), 3)),
            "pierced": np.zeros(n_frames, dtype=np.int64),
            "source_motion": motion,
            "motion": target_motion,
        }
        self._samplers()  # built before the threads share them
        size = min(CHUNK_FRAMES, max(1, -(-n_frames // MIN_CHUNKS)))
        chunks = [range(a, min(a + size, n_frames)) for a in range(0, n_frames, size)]
        in_threads(
            [partial(self._run_chunk, perf, chunk, level, out) for chunk in chunks],
            worker_count(len(chunks)),
        )
        return out

    def _samplers(self) -> tuple[sp.csr_matrix, sp.csr_matrix]:
        """``(P, V)`` sparse barycentric matrices of the source points the sliding and the
        dense fallback read (a frame's points in one sparse product, not a gather of three
        corners a point), built on first use (absent from older pickles)."""
        samplers = self.__dict__.get("samplers_")
        if samplers is None:
            n = len(self.source_neutral_)
            samplers = self.__dict__["samplers_"] = (
                barycentric_matrix(self.slide_corners_, self.slide_barycentric_, n),
                barycentric_matrix(self.dense_corners_, self.dense_barycentric_, n),
            )
        return samplers

    def _run_chunk(self, perf: MeshSequence, frames: range, level: int | None, out: dict) -> None:
        from faceretarget.geometry._mesh_ops_kernels import vertex_normals

        from . import _kernels as k

        lm, tri, hier = self.source_feature_points_, perf.triangles, self.hierarchy_
        decomposer = FrameDecomposer(
            self.source_surface_,
            self.source_normal_mesh_,
            hier,
            max_offset=float(self.max_offset),
            neutral_vertices=self.source_neutral_,
            repair=self.repair,
        )
        finest_tri = hier.triangles(hier.levels)
        sliding = self.sliding == "transfer"
        dense = self.dense_vertices_
        w = self.coverage_[dense][:, None]
        slide_at, dense_at = self._samplers()
        for f in frames:
            rot = np.ascontiguousarray(out["source_motion"][f, :3, :3])
            local = (
                np.asarray(perf.vertices[f], dtype=np.float64) - out["source_motion"][f, :3, 3]
            ) @ rot
            s_base = lm.positions(local, tri)
            offsets, out["pierced"][f], positions = decomposer(
                local, s_base, keep_positions=sliding
            )
            t_base = self.target_base0_ + self.base_map_((s_base - self.source_base0_)[None])[0]
            # Eq. 8: TN_k = TN_0 + delta * (SN_k - SN_0), level by level (with tangent parts)
            coords = [
                c0 + self.delta_ * m * (sk - s0)
                for c0, m, sk, s0 in zip(
                    self.target_coords0_, self.detail_masks_, offsets, self.source_offsets0_
                )
            ]
            levels = reconstruct(
                t_base, hier, [c[:, :2] for c in coords], [c[:, 2] for c in coords]
            )
            finest = levels[-1]
            if sliding:
                y = np.ascontiguousarray(positions[-1])
                material = slide_at @ local
                y_normals, t_normals = np.empty_like(y), np.empty_like(finest)
                # read-only inputs, as geometry.mesh_ops passes them: one compiled kernel
                vertex_normals(readonly(y), readonly(finest_tri), y_normals)
                vertex_normals(readonly(finest), readonly(finest_tri), t_normals)
                slid = np.empty_like(finest)
                k.slide(
                    y,
                    y_normals,
                    material,
                    finest,
                    t_normals,
                    self.frame_neighbours_,
                    self.slide0_,
                    self.delta_,
                    slid,
                )
                finest = slid
            result = carry(self.attachment_, finest)
            if dense.size:
                moved = dense_at @ local - self.dense_source0_
                fallback = self.target_neutral_[dense] + self.dense_map_.one(moved)
                result[dense] = w * result[dense] + (1.0 - w) * fallback
            rot_t = np.ascontiguousarray(out["motion"][f, :3, :3].T)
            trans = out["motion"][f, :3, 3]
            out["vertices"][f] = result @ rot_t + trans
            out["base"][f] = t_base @ rot_t + trans
            if level is not None:
                out["normal_mesh"][f] = levels[level] @ rot_t + trans

    def _retarget(self, source: Source) -> Animation:
        run = self._run(source)
        diagnostics = dict(self.piercing_errors_)
        diagnostics["source_mean_per_frame"] = float(np.mean(run["pierced"]))
        diagnostics["source_share_per_frame"] = (
            diagnostics["source_mean_per_frame"] / self.piercing_errors_["normal_mesh_vertices"]
        )
        diagnostics["delta"] = self.delta_
        return Animation(
            vertices=run["vertices"],
            head_motion=run["motion"],
            triangles=self.target_.neutral.triangles,
            fps=source.fps,
            provenance={
                "diagnostics": {
                    "piercing_errors": diagnostics,
                    "coverage": dict(self.coverage_stats_),
                    "levels": self.levels_,
                }
            },
            extras={
                "base_triangles": self.base_triangles_,
                "base_vertices": run["base"],
                "piercing_errors_per_frame": run["pierced"],
                "delta": self.delta_,
                "coverage": self.coverage_,
            },
        )

    def normal_mesh_sequence(self, source: Source, level: int | None = None) -> MeshSequence:
        """The target's per-frame normal mesh at ``level`` (default: the finest), head motion applied."""
        self._check_fitted()
        level = self.hierarchy_.levels if level is None else int(level)
        if not 0 <= level <= self.hierarchy_.levels:
            raise InputError(f"normalmesh: level must be 0..{self.hierarchy_.levels}, got {level}")
        frames = self._run(source, level)["normal_mesh"]
        return MeshSequence(
            frames, self.hierarchy_.triangles(level), fps=source.fps, reference=frames[0]
        )


def _area(points: np.ndarray, triangles: np.ndarray) -> float:
    """Total area of ``triangles`` over ``points``."""
    if len(triangles) == 0:
        return 0.0
    a, b, c = (points[triangles[:, k]] for k in range(3))
    return float(0.5 * np.linalg.norm(np.cross(b - a, c - a), axis=1).sum())


def _same_landmarks(a: Landmarks, b: Landmarks) -> bool:
    """Whether two Landmarks name the same points of one topology."""
    if a.vertex_ids is not None and b.vertex_ids is not None:
        return np.array_equal(a.vertex_ids, b.vertex_ids)
    if a.vertex_ids is None and b.vertex_ids is None:
        return np.array_equal(a.triangle_ids, b.triangle_ids) and np.array_equal(
            a.barycentric, b.barycentric
        )
    return False


def frame_neighbours(triangles: np.ndarray, n_vertices: int) -> np.ndarray:
    """(V,) one neighbour of each vertex (fixing the tangent direction of its local frame)."""
    out = np.arange(n_vertices, dtype=np.int64)
    for k in range(3):
        out[triangles[:, k]] = triangles[:, (k + 1) % 3]
    return out


def local_frames(X: np.ndarray, triangles: np.ndarray, neighbour: np.ndarray) -> np.ndarray:
    """(V, 3, 3) rows t1, t2, n at each vertex of ``X``: n the unit vertex normal, t1 the
    direction to ``neighbour`` made perpendicular to n, t2 = n x t1."""
    from faceretarget.geometry._mesh_ops_kernels import vertex_normals

    from . import _kernels as k

    X = np.ascontiguousarray(X, dtype=np.float64)
    n = np.empty_like(X)
    vertex_normals(readonly(X), readonly(triangles), n)  # read-only, as everywhere: one kernel
    out = np.empty((len(X), 3, 3))
    k.local_frames(X, n, neighbour, out)
    return out


def stable_vertices(
    neutral: np.ndarray, examples: np.ndarray, count: int = HEAD_VERTICES
) -> tuple[np.ndarray, np.ndarray]:
    """The ``count`` source vertices the example poses move least, and their weights.

    Weights ``1 / (1 + (d / s)^2)`` of each vertex's largest example displacement ``d``, with
    ``s`` the displacement of the least-moving 20% of the vertices (at least 0.1% of the
    largest displacement), so rigid parts (forehead, temples, nose bridge) dominate the fit.
    """
    d = (
        np.linalg.norm(examples - neutral, axis=-1).max(axis=0)
        if len(examples)
        else np.zeros(len(neutral))
    )
    ids = np.sort(np.argsort(d, kind="stable")[: min(count, len(neutral))])
    scale = max(float(np.percentile(d, 20)), 1e-3 * float(d.max()), np.finfo(float).tiny)
    return ids, 1.0 / (1.0 + (d[ids] / scale) ** 2)


def estimate_head_motion(
    reference: np.ndarray, frames: np.ndarray, weights: np.ndarray
) -> np.ndarray:
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


def significant_motion(
    reference: np.ndarray, frames: np.ndarray, weights: np.ndarray, motion: np.ndarray
) -> bool:
    """Whether the rigid ``motion (F, 4, 4)`` removes more than ``HEAD_SIGNIFICANCE`` of the
    weighted squared motion of ``frames (F, N, 3)`` away from ``reference (N, 3)`` over the
    shot. A source without head motion still gets a small rigid fit of its expressions (on
    the synthetic faces ~1e-7 rad) that would move a target placed elsewhere."""
    w = np.asarray(weights, dtype=np.float64)
    total = float(np.einsum("n,fn->", w, np.sum((frames - reference) ** 2, axis=-1)))
    fitted = np.einsum("fij,nj->fni", motion[:, :3, :3], reference) + motion[:, None, :3, 3]
    left = float(np.einsum("n,fn->", w, np.sum((frames - fitted) ** 2, axis=-1)))
    return total - left > HEAD_SIGNIFICANCE * total
