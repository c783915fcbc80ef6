"""The parameter-parallel layered model (Kholgade et al. 2011, sec. 3), assembled as arrays.

Reading of Eq. 1-5 (the equations are garbled in our copy of the paper; this is the
reading the prose supports)::

    x_A(t) = R(t) (x_muA + sum_j sum_l w_jl(t) M_Al B_Aj alpha_j(t)) + t(t)      (Eq. 4)
    x_C(t) = R(t) (x_muC + sum_j sum_l w_jl(t) M_Cl B_Cj alpha_j(t)) + t(t)      (Eq. 5)

- ``B_j`` are the layer bases as *displacements* from the mean ``x_mu`` (the mean is
  added once, outside the sum, so the bases cannot be absolute poses). We take ``x_mu``
  = the neutral (the source's marker reference; the character's neutral mesh) and
  ``B_j[:, k] = pose_jk - neutral`` from the :class:`~faceretarget.model.LayeredRig`'s
  absolute poses. With masks that sum to 1 at every point this equals blending the
  absolute poses; where masks sum to less, points fall back to the neutral.
- ``M_l`` is the diagonal of region mask l (values in [0, 1], one value per point,
  repeated over its coordinates); ``w_jl >= 0`` with ``sum_j w_jl = 1`` for each region
  l (Sec. 3.2: "sum to 1 across j"; ``composition="convex"``) or, by default, each
  ``w_jl`` in [0, 1] (the layers add); ``alpha_j`` on the simplex (Sec. 3.1). The data
  determine only the products ``w_jl alpha_jk`` (``Animation.extras["weighted_coefficients"]``).
- 3D markers and 2D tracks are stacked in one vector ``x_A`` of ``D_A = 3 P1 + 2 P2``
  coordinates; their bases come from ``Source.actor_layers`` and
  ``Source.actor_layers_2d`` (same layer names, pose counts and region count).

Units: each part (3D, 2D) is divided by its own RMS basis displacement so the data
term of Eq. 6-7 is unit-free and 2D pixels weigh like 3D centimetres; the solver
divides it by the number of observed points (a mean), so the bias and smoothing
weights mean the same for 54 or 283 markers. This rescaling is ours (the paper gives
sigma = .02, lambda = .2 in unstated units).
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from faceretarget import config
from faceretarget.errors import DegenerateGeometryError, InputError, TopologyMismatchError
from faceretarget.model import LayeredRig

__all__ = [
    "ActorModel",
    "CharacterModel",
    "RigidProjection",
    "build_actor",
    "build_character",
    "match_layers",
]

#: Mask products below this fraction of the largest are treated as zero (region pairs
#: that do not overlap skip their Gram block).
_MASK_EPS = 1e-12
#: Character vertices whose mask value is below this (masks are 0..1) are left out of
#: the region's block: soft (sigmoid) masks never reach 0, and a 1e-9 share of a pose
#: displacement is far below any visible or numerical consequence.
_MASK_CUTOFF = 1e-9


@dataclass
class ActorModel:
    """The actor side, flattened to coordinates ``C = 3 N3 + 2 N2``.

    layer_names : (J,) layer order used everywhere (the actor's)
    pose_names : {layer: (K_j,) names}
    layer_of : (K,) int64, the layer of each stacked pose
    region_names : (m,)
    reference3d : (N3, 3); reference2d : (N2, 2) or None
    scale3d, scale2d : RMS pose displacement of each part (the data unit)
    basis_t : (C, K) normalised displacements ``b_a`` (column a = pose a)
    coord_masks : (C, m) mask value of each coordinate's point
    gram : (m, m, K, K) ``H[l, l', a, b] = b_a^T M_l M_l' b_b``
    pair_used : (m, m) bool, region pairs whose masks overlap (others have H = 0)
    projector_t : (m K, C) rows ``M_l b_a`` (``g = projector_t @ x_hat``)
    rigid_weights3d : (N3,), rigid_weights2d : (N2,) or None
        Procrustes weights: high on points the layers barely move.
    names3d, names2d : point names
    """

    layer_names: tuple
    pose_names: dict
    layer_of: np.ndarray
    region_names: tuple
    reference3d: np.ndarray
    reference2d: np.ndarray | None
    scale3d: float
    scale2d: float
    basis_t: np.ndarray
    coord_masks: np.ndarray
    gram: np.ndarray
    pair_used: np.ndarray
    projector_t: np.ndarray
    rigid_weights3d: np.ndarray
    rigid_weights2d: np.ndarray | None
    names3d: tuple
    names2d: tuple
    rigid_cache: dict = field(default_factory=dict, repr=False, compare=False)

    @property
    def n_layers(self) -> int:
        return len(self.layer_names)

    @property
    def n_regions(self) -> int:
        return len(self.region_names)

    @property
    def n_poses(self) -> int:
        return int(self.layer_of.shape[0])

    @property
    def n3(self) -> int:
        return int(self.reference3d.shape[0])

    @property
    def n2(self) -> int:
        return 0 if self.reference2d is None else int(self.reference2d.shape[0])

    @property
    def offsets(self) -> np.ndarray:
        """(J + 1,) start of each layer in the stacked pose axis."""
        return np.concatenate([[0], np.cumsum(np.bincount(self.layer_of, minlength=self.n_layers))])

    def rigid_projection(self, motion3d: bool, similarity2d: bool) -> RigidProjection | None:
        """The alignment's small motions, for the projected data term of the alignment passes.

        ``motion3d``: the 3D head motion is estimated (6 rigid parameters);
        ``similarity2d``: the 2D tracks are aligned (4 similarity parameters). None when
        neither. Cached per combination.
        """
        similarity2d = bool(similarity2d and self.n2)
        key = (bool(motion3d), similarity2d)
        if not any(key):
            return None
        if key not in self.rigid_cache:
            self.rigid_cache[key] = _rigid_projection(self, *key)
        return self.rigid_cache[key]

    def pose_index(self, layer: str, pose) -> int:
        """Stacked index of ``pose`` (name or position) in ``layer``."""
        j = self.layer_names.index(layer)
        names = self.pose_names[layer]
        k = names.index(pose) if isinstance(pose, str) else int(pose)
        return int(self.offsets[j] + k)


@dataclass
class RigidProjection:
    """Small-motion Jacobian of the aligned data and its reduced forms (see ``_kernels``).

    jac : (C, r) derivative of ``x_hat`` (normalised units) with respect to the r motion
        parameters (3D: rotation about the markers' centroid and translation; 2D: rotation,
        scale, translation), zero rows elsewhere; jac_t : (r, C) its transpose (contiguous)
    jtj : (r, r); uraw : (r, m, K) ``jac^T M_l b_a``
    """

    jac: np.ndarray
    jac_t: np.ndarray
    jtj: np.ndarray
    uraw: np.ndarray


def _rigid_projection(actor: ActorModel, motion3d: bool, similarity2d: bool) -> RigidProjection:
    n_coords = actor.basis_t.shape[0]
    cols = []
    if motion3d:
        p = actor.reference3d - actor.reference3d.mean(axis=0)
        block = np.zeros((actor.n3, 3, 6))
        # d(local point)/d(rotation w) = [p]x (local p' = p - w x p), d/d(translation) = -I
        block[:, 0, 1], block[:, 0, 2] = -p[:, 2], p[:, 1]
        block[:, 1, 0], block[:, 1, 2] = p[:, 2], -p[:, 0]
        block[:, 2, 0], block[:, 2, 1] = -p[:, 1], p[:, 0]
        block[:, :, 3:] = -np.eye(3)
        jac = np.zeros((n_coords, 6))
        jac[: 3 * actor.n3] = block.reshape(3 * actor.n3, 6) / actor.scale3d
        cols.append(jac)
    if similarity2d:
        p = actor.reference2d - actor.reference2d.mean(axis=0)
        block = np.zeros((actor.n2, 2, 4))
        block[:, 0, 0], block[:, 1, 0] = p[:, 1], -p[:, 0]  # rotation
        block[:, :, 1] = -p  # scale
        block[:, :, 2:] = -np.eye(2)  # translation
        jac = np.zeros((n_coords, 4))
        jac[3 * actor.n3 :] = block.reshape(2 * actor.n2, 4) / actor.scale2d
        cols.append(jac)
    jac = np.ascontiguousarray(np.concatenate(cols, axis=1))
    m, K = actor.n_regions, actor.n_poses
    jtj = jac.T @ jac
    uraw = (jac.T @ actor.projector_t.T).reshape(-1, m, K)
    return RigidProjection(
        jac=jac,
        jac_t=np.ascontiguousarray(jac.T),
        jtj=np.ascontiguousarray(jtj),
        uraw=np.ascontiguousarray(uraw),
    )


@dataclass
class CharacterModel:
    """The character side: neutral plus, per region, its masked displacement block.

    neutral : (V, 3)
    regions : list of (vertex ids (S_l,), block (K, 3 S_l)) with ``block = M_Cl B_C``
        restricted to the vertices the mask touches (views into ``block_data``).
    block_data : all blocks, flat row-major; block_offsets : (m + 1,) their starts
    offsets : (m + 1,) cumulative widths (3 S_l) of the region products ``beta_l @ block_l``
    vertex_ptr : (V + 1,), entry_region, entry_col : (E,) CSR map vertex -> (region, column
        of the x of its 3-vector in that region's product); no entry outside every region.
    n_layer_regions : m; a further block after the m region blocks is the residual's
        (the character's blendshape deltas, driven by the residual weights)
    """

    neutral: np.ndarray
    regions: list
    block_data: np.ndarray
    block_offsets: np.ndarray
    offsets: np.ndarray
    vertex_ptr: np.ndarray
    entry_region: np.ndarray
    entry_col: np.ndarray
    n_layer_regions: int = -1

    @property
    def n_vertices(self) -> int:
        return int(self.neutral.shape[0])


def match_layers(actor: LayeredRig, other: LayeredRig, what: str) -> list[np.ndarray]:
    """Poses of ``other`` per layer in the actor's layer and pose order.

    Layers are matched by name (every actor layer must exist in ``other`` with the same
    pose count); poses by name when both sides name them with the same set of custom
    names, otherwise by position. Region counts must agree (region i <-> region i).
    """
    missing = [n for n in actor.layer_names if n not in other.layers]
    extra = [n for n in other.layer_names if n not in actor.layers]
    if missing or extra:
        raise TopologyMismatchError(
            f"{what}: layer names differ from the actor's ({', '.join(actor.layer_names)}): "
            f"missing {missing or 'none'}, unexpected {extra or 'none'}; both sides need the same layers"
        )
    if other.n_regions != actor.n_regions:
        raise TopologyMismatchError(
            f"{what}: {other.n_regions} region masks but the actor has {actor.n_regions}; "
            "region i of the actor drives region i of the other side, so the counts must match"
        )
    out = []
    for name in actor.layer_names:
        poses = np.asarray(other.layers[name])
        k_actor = actor.layers[name].shape[0]
        if poses.shape[0] != k_actor:
            raise TopologyMismatchError(
                f"{what}: layer {name!r} has {poses.shape[0]} poses but the actor's has {k_actor}; "
                "parallel layers need one pose per actor pose"
            )
        a_names, o_names = list(actor.pose_names[name]), list(other.pose_names[name])
        default = [f"{name}{i}" for i in range(k_actor)]
        if a_names != o_names and set(a_names) == set(o_names) and a_names != default:
            poses = poses[[o_names.index(n) for n in a_names]]
        out.append(poses)
    return out


def _part(poses: list[np.ndarray], reference: np.ndarray, what: str):
    """Displacements (K, P, D), their RMS scale and the Procrustes weights of one part."""
    disp = np.concatenate([p - reference[None] for p in poses], axis=0)
    scale = float(np.sqrt(np.mean(np.sum(disp**2, axis=-1))))
    if not np.isfinite(scale) or scale <= 1e-12 * max(1.0, float(np.abs(reference).max())):
        raise DegenerateGeometryError(
            f"{what}: every pose equals the neutral reference, so the layers carry no expression; "
            "build the bases from expressive frames (actor_layers_from_frames)"
        )
    # rigidity weights 1 / (eps^2 + m^2), m = RMS displacement of the point over the poses,
    # eps = config.HEAD_MOTION_RIGIDITY face sizes (as faceretarget.geometry.head_motion does)
    motion2 = np.mean(np.sum(disp**2, axis=-1), axis=0)
    size = float(np.sqrt(np.mean(np.sum((reference - reference.mean(axis=0)) ** 2, axis=-1))))
    eps2 = (config.HEAD_MOTION_RIGIDITY * size) ** 2
    if not eps2 > 0:
        eps2 = float(motion2.mean()) or 1.0
    rigid = 1.0 / (eps2 + motion2)
    return disp, scale, rigid / rigid.mean()


def build_actor(
    layers3d: LayeredRig,
    reference3d,
    layers2d: LayeredRig | None = None,
    reference2d=None,
    names3d=(),
    names2d=(),
) -> ActorModel:
    """Assemble the actor's bases, masks and Gram tensor (see :class:`ActorModel`)."""
    ref3 = np.asarray(reference3d, dtype=np.float64)
    if layers3d.dim != 3 or layers3d.n_points != ref3.shape[0]:
        raise TopologyMismatchError(
            f"actor layers are over {layers3d.n_points} {layers3d.dim}D points but the source has "
            f"{ref3.shape[0]} 3D markers; build them over the same markers"
        )
    poses3 = [np.asarray(layers3d.layers[n], dtype=np.float64) for n in layers3d.layer_names]
    disp3, scale3, rigid3 = _part(poses3, ref3, "Source.actor_layers")
    parts = [(disp3 / scale3).reshape(disp3.shape[0], -1)]
    masks = [np.repeat(np.asarray(layers3d.masks, dtype=np.float64), 3, axis=1)]
    ref2 = rigid2 = None
    scale2 = 1.0
    if layers2d is not None:
        ref2 = np.asarray(reference2d, dtype=np.float64)
        if layers2d.dim != 2 or layers2d.n_points != ref2.shape[0]:
            raise TopologyMismatchError(
                f"Source.actor_layers_2d: bases over {layers2d.n_points} {layers2d.dim}D points but the "
                f"tracks have {ref2.shape[0]} 2D points"
            )
        poses2 = match_layers(layers3d, layers2d, "Source.actor_layers_2d")
        disp2, scale2, rigid2 = _part(poses2, ref2, "Source.actor_layers_2d")
        parts.append((disp2 / scale2).reshape(disp2.shape[0], -1))
        masks.append(np.repeat(np.asarray(layers2d.masks, dtype=np.float64), 2, axis=1))
    basis = np.concatenate(parts, axis=1)  # (K, C)
    coord_masks = np.ascontiguousarray(np.concatenate(masks, axis=1).T)  # (C, m)
    m = coord_masks.shape[1]
    # points outside every region carry no parameter: the model keeps them at the neutral
    products = coord_masks[:, :, None] * coord_masks[:, None, :]  # (C, m, m)
    gram = np.einsum("clm,ac,bc->lmab", products, basis, basis, optimize=True)
    biggest = float(np.abs(gram).max()) if gram.size else 0.0
    gram[np.abs(gram) <= _MASK_EPS * biggest] = 0.0
    projector = (coord_masks[:, :, None] * basis.T[:, None, :]).reshape(
        basis.shape[1], m * basis.shape[0]
    )
    layer_of = np.repeat(np.arange(len(poses3)), [p.shape[0] for p in poses3]).astype(np.int64)
    return ActorModel(
        layer_names=tuple(layers3d.layer_names),
        pose_names={k: tuple(v) for k, v in layers3d.pose_names.items()},
        layer_of=layer_of,
        region_names=tuple(layers3d.region_names),
        reference3d=ref3,
        reference2d=ref2,
        scale3d=scale3,
        scale2d=scale2,
        basis_t=np.ascontiguousarray(basis.T),
        coord_masks=coord_masks,
        gram=np.ascontiguousarray(gram),
        pair_used=np.abs(gram).reshape(m, m, -1).max(axis=2) > 0,
        projector_t=np.ascontiguousarray(projector.T),
        rigid_weights3d=rigid3,
        rigid_weights2d=rigid2,
        names3d=tuple(names3d),
        names2d=tuple(names2d),
    )


def build_character(
    layers: LayeredRig, neutral, actor_layers: LayeredRig, extra=None
) -> CharacterModel:
    """The character's masked displacement blocks, in the actor's layer/pose order.

    ``extra (M, V, 3)``: further displacements (the residual's blendshape deltas), one
    more block over the vertices they move.
    """
    base = np.asarray(neutral, dtype=np.float64)
    if layers.dim != 3 or layers.n_points != base.shape[0]:
        raise TopologyMismatchError(
            f"TargetRig.layers: poses over {layers.n_points} {layers.dim}D points; the neutral has {base.shape[0]} vertices"
        )
    poses = match_layers(actor_layers, layers, "TargetRig.layers")
    disp = np.concatenate(
        [np.asarray(p, dtype=np.float64) - base[None] for p in poses], axis=0
    )  # (K, V, 3)
    masks = np.asarray(layers.masks, dtype=np.float64)
    if not np.all(np.isfinite(disp)):
        raise InputError("TargetRig.layers: poses hold NaN or infinite values")
    regions, vertex_of, region_of, columns = [], [], [], []
    for l in range(masks.shape[0]):
        ids = np.flatnonzero(masks[l] > _MASK_CUTOFF * max(1.0, float(masks.max())))
        block = (disp[:, ids, :] * masks[l, ids, None]).reshape(disp.shape[0], -1)
        regions.append((ids, np.ascontiguousarray(block)))
        vertex_of.append(ids)
        region_of.append(np.full(ids.size, l))
        columns.append(3 * np.arange(ids.size))
    if extra is not None:
        extra = np.asarray(extra, dtype=np.float64)
        ids = np.flatnonzero(np.abs(extra).max(axis=(0, 2)) > 0)
        regions.append((ids, np.ascontiguousarray(extra[:, ids, :].reshape(extra.shape[0], -1))))
        vertex_of.append(ids)
        region_of.append(np.full(ids.size, masks.shape[0]))
        columns.append(3 * np.arange(ids.size))
    vertex_of, region_of, columns = (
        np.concatenate(vertex_of),
        np.concatenate(region_of),
        np.concatenate(columns),
    )
    order = np.argsort(vertex_of, kind="stable")
    ptr = np.zeros(base.shape[0] + 1, dtype=np.int64)
    np.add.at(ptr, vertex_of + 1, 1)
    widths = [block.shape[1] for _, block in regions]
    sizes = [block.size for _, block in regions]
    block_offsets = np.concatenate([[0], np.cumsum(sizes)]).astype(np.int64)
    block_data = np.concatenate([block.ravel() for _, block in regions]) if regions else np.zeros(0)
    regions = [
        (ids, block_data[block_offsets[l] : block_offsets[l + 1]].reshape(block.shape))
        for l, (ids, block) in enumerate(regions)
    ]
    return CharacterModel(
        neutral=base,
        regions=regions,
        block_data=block_data,
        block_offsets=block_offsets,
        offsets=np.concatenate([[0], np.cumsum(widths)]).astype(np.int64),
        vertex_ptr=np.cumsum(ptr),
        entry_region=region_of[order].astype(np.int64),
        entry_col=columns[order].astype(np.int64),
        n_layer_regions=int(masks.shape[0]),
    )
