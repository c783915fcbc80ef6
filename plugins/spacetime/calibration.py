"""Preprocessing (Seol et al. 2012, sec. 3): correspondences, head motion, scale-proportion matching.

- :func:`pair_markers`: which source marker each target landmark corresponds to.
- :func:`head_motion`: rigid head motion per frame by Procrustes against the neutral
  (sec. 3.1), optionally refined jointly with the expression (:func:`refine_head_motion`).
- :func:`warp_blendshapes`: the RBF warp ``d`` (kernel ``phi(r) = r`` plus a linear
  polynomial) trained on neutral correspondences (target landmarks -> source markers) and
  applied to the target's landmark positions on every blendshape, ``b*_ij = d(b_ij)``.
- :func:`face_size`: the size used to scale ``alpha``.
"""

from __future__ import annotations

import numpy as np
import scipy.linalg

from faceretarget.errors import DegenerateGeometryError, TopologyMismatchError
from faceretarget.geometry import procrustes
from faceretarget.geometry.rbf import fit_rbf

#: Face size (RMS distance of the neutral markers from their centroid) for which ``alpha`` is
#: quoted: we read the paper's ``alpha = 0.01`` as given in millimetres, the unit of optical
#: motion capture, for a human face (brow-to-chin markers: RMS radius about 60 mm; the ICT
#: face's 68 landmarks give 59 mm). ``alpha`` is rescaled by ``(size / FACE_SIZE_REF)**2`` so the
#: same value means the same balance in any length unit (the matching term grows with the
#: square of the face size, the PCA prior is unit-free).
FACE_SIZE_REF = 60.0
#: Frame rate for which ``alpha`` is quoted. Summed over frames, the velocity term scales like
#: 1 / fps and the per-frame prior like fps, so ``alpha`` is rescaled by ``(FPS_REF / fps)**2``
#: to keep the same time constant in seconds.
FPS_REF = 30.0


def pair_markers(source_names, target_names) -> np.ndarray:
    """Index of the source marker paired with each target landmark: ``(N_target,)`` int.

    Same names in the same order, or every target name found among the source names:
    paired by name. Names with nothing in common (e.g. default ``marker0`` / ``landmark0``)
    and equal counts: paired by order. Anything else is a missing correspondence.
    """
    src = list(source_names)
    tgt = list(target_names)
    if src == tgt:
        return np.arange(len(tgt))
    position = {name: i for i, name in enumerate(src)}
    found = [n for n in tgt if n in position]
    if len(found) == len(tgt):
        return np.array([position[n] for n in tgt], dtype=np.int64)
    if not found and len(src) == len(tgt):
        return np.arange(len(tgt))
    missing = [n for n in tgt if n not in position]
    raise TopologyMismatchError(
        f"spacetime: missing correspondences: the target has {len(tgt)} landmarks and the source {len(src)} "
        f"markers, and target landmark(s) {', '.join(missing[:8])}{' ...' if len(missing) > 8 else ''} have no "
        "source marker of the same name; name the landmarks like the markers (or give equal counts in the same order)"
    )


def face_size(points: np.ndarray) -> float:
    """RMS distance of ``points (N, 3)`` from their centroid."""
    p = np.asarray(points, dtype=np.float64)
    return float(np.sqrt(np.mean(np.sum((p - p.mean(axis=0)) ** 2, axis=1))))


def check_spread(points: np.ndarray, what: str) -> None:
    """Raise :class:`DegenerateGeometryError` if ``points (N, 3)`` are coincident or collinear."""
    p = np.asarray(points, dtype=np.float64)
    centred = p - p.mean(axis=0)
    sig = np.linalg.svd(centred, compute_uv=False) if len(p) >= 3 else np.zeros(2)
    if sig[0] == 0.0 or sig[1] <= 1e-9 * sig[0]:
        raise DegenerateGeometryError(
            f"spacetime: the {what} are coincident or collinear ({len(p)} points); scale-proportion matching "
            "and head-motion removal need at least 3 points spread over the face"
        )


def warp_blendshapes(
    target_neutral: np.ndarray,
    target_deltas: np.ndarray,
    source_neutral: np.ndarray,
    kernel: str = "linear",
):
    """Scale-proportion matching (sec. 3.2).

    Parameters
    ----------
    target_neutral : (N, 3)   target landmark positions on the neutral
    target_deltas : (M, N, 3) landmark displacements of each blendshape
    source_neutral : (N, 3)   source neutral markers (same order)
    kernel : RBF kernel (``"linear"`` = the paper's ``phi(r) = r``)

    Returns
    -------
    neutral : (N, 3)   warped target neutral, ``d(n_tgt)`` (equals the source neutral up
                       to round-off)
    deltas : (M, N, 3) warped blendshape deltas ``d(n_tgt + delta_j) - d(n_tgt)``
    warp : the fitted interpolant ``d`` (callable on (P, 3) points)
    """
    warp = fit_rbf(target_neutral, source_neutral, kernel=kernel)
    neutral = warp(target_neutral)
    shapes = warp(target_neutral[None] + target_deltas)
    return neutral, shapes - neutral[None], warp


def head_motion(reference: np.ndarray, markers: np.ndarray) -> np.ndarray:
    """Rigid head motion ``(F, 4, 4)`` of ``markers (F, N, 3)`` (NaN = missing) w.r.t. ``reference (N, 3)``.

    Procrustes (Kabsch) per frame, as in sec. 3.1.
    """
    rot, trans, _ = procrustes.fit_rigid(reference, markers)
    return procrustes.to_matrix(rot, trans)


def refine_head_motion(reference, markers, motion, weights, basis, ridge):
    """One Gauss-Newton step of the joint per-frame fit ``min ||R (n + B w) + t - x||^2``.

    Plain Procrustes against the neutral (sec. 3.1) turns part of the expression (a jaw
    opening) into head rotation. Here the markers in the current head frame are fitted by the
    blendshapes *and* a small rigid motion about the neutral's centroid ``c``, linearized at
    the current fitted shape ``p = n + B w``: ``x_local ~ n + B w' + theta x (p - c) + dt``.
    The (M + 6)-unknown normal equations of each frame are reduced to the 6 rigid unknowns
    (Schur complement; the blendshape block ``B^T B + ridge I`` is shared by all complete frames).

    Parameters
    ----------
    reference : (N, 3)          neutral markers ``n``
    markers : (F, N, 3)         world markers, NaN = missing (those rows are dropped)
    motion : (F, 4, 4)          current head motion
    weights : (F, M) or None    current per-frame weights (None: linearize at the neutral)
    basis : (3N, M)             blendshape deltas ``B`` at the markers
    ridge : float               Tikhonov term on the weights (rank-deficient rigs)

    Returns the updated ``motion (F, 4, 4)`` and per-frame weights ``(F, M)``.
    """
    from scipy.spatial.transform import Rotation

    ref = np.asarray(reference, dtype=np.float64)
    local = to_local(motion, markers)
    n_frames, n_markers, _ = local.shape
    m = basis.shape[1]
    valid = ~np.isnan(local[..., 0])
    mask = np.repeat(valid, 3, axis=1)
    target = np.where(mask, (local - ref).reshape(n_frames, -1), 0.0)
    centre = ref.mean(axis=0)
    shape = (
        ref[None] if weights is None else ref + (weights @ basis.T).reshape(n_frames, n_markers, 3)
    )
    q = np.broadcast_to(shape - centre, (n_frames, n_markers, 3))
    gen = np.zeros((n_frames, n_markers, 3, 6))
    # d(theta x q)/d theta = -[q]_x ; translation: identity
    gen[..., 0, 1], gen[..., 0, 2] = q[..., 2], -q[..., 1]
    gen[..., 1, 0], gen[..., 1, 2] = -q[..., 2], q[..., 0]
    gen[..., 2, 0], gen[..., 2, 1] = q[..., 1], -q[..., 0]
    gen[..., 3:] = np.eye(3)
    rigid = gen.reshape(n_frames, -1, 6) * mask[..., None]  # masked rigid Jacobian (F, 3N, 6)
    coupling = np.matmul(basis.T, rigid)  # B^T M R: (F, M, 6)
    rigid_normal = np.matmul(rigid.transpose(0, 2, 1), rigid)  # (F, 6, 6)
    rhs_w = target @ basis  # B^T M y: (F, M)
    rhs_r = np.einsum("frk,fr->fk", rigid, target)
    # Schur complement on the rigid unknowns: x = A^-1 C, (E - C^T x) r = b_r - x^T b_w
    stacked = np.concatenate([coupling, rhs_w[..., None]], axis=2)  # (F, M, 7)
    solved = np.empty_like(stacked)
    gram = basis.T @ basis + ridge * np.eye(m)
    partial = ~valid.all(axis=1)
    full = ~partial
    factor = scipy.linalg.cho_factor(gram)
    solved[full] = (
        scipy.linalg.cho_solve(factor, stacked[full].transpose(1, 0, 2).reshape(m, -1))
        .reshape(m, -1, 7)
        .transpose(1, 0, 2)
    )
    if partial.any():
        rows = basis.reshape(n_markers, 3, m)
        grams = np.einsum("nki,nkj->nij", rows, rows)
        blocks = gram - np.einsum("fn,nij->fij", (~valid[partial]).astype(np.float64), grams)
        solved[partial] = np.linalg.solve(blocks, stacked[partial])
    x, w0 = solved[..., :6], solved[..., 6]
    schur = rigid_normal - np.matmul(coupling.transpose(0, 2, 1), x)
    increment = np.linalg.solve(schur, (rhs_r - np.einsum("fmk,fm->fk", x, rhs_w))[..., None])[
        ..., 0
    ]
    new_weights = w0 - np.einsum("fmk,fk->fm", x, increment)
    d_rot = Rotation.from_rotvec(increment[:, :3]).as_matrix()
    rot = motion[:, :3, :3]
    # local ~ dR (p - c) + c + dt  =>  world = R dR (p - c) + R (c + dt) + t
    shift = centre - np.einsum("fij,j->fi", d_rot, centre) + increment[:, 3:]
    out = motion.copy()
    out[:, :3, :3] = rot @ d_rot
    out[:, :3, 3] = np.einsum("fij,fj->fi", rot, shift) + motion[:, :3, 3]
    return out, new_weights


def to_local(
    motion: np.ndarray | None, markers: np.ndarray, reference: np.ndarray | None = None
) -> np.ndarray:
    """World markers ``(F, N, 3)`` -> neutral-frame coordinates (NaN rows stay NaN); with
    ``reference (N, 3)``, the displacements from it (a new array)."""
    if motion is None:
        local = np.asarray(markers, dtype=np.float64)
        return local if reference is None else local - reference
    return procrustes.remove(motion, markers, reference)


#: With ``transfer="scale"`` the landmark fit's rotation is still applied when it exceeds
#: this angle (degrees): the two faces are then posed in different coordinate frames, not
#: merely shaped differently.
AUTO_ROTATION_DEGREES = 10.0


class Transfer:
    """How target positions and blendshape displacements are carried into the source's space.

    ``"rbf"``: the paper's scale-proportion matching (sec. 3.2), ``d(n + delta) - d(n)`` with
    the landmark RBF warp ``d``. ``"similarity"`` (default) and ``"scale"``: one global
    similarity transform ``x -> s R x + t`` fitted to the neutral landmarks (Umeyama);
    displacements are multiplied by ``s R`` (``"similarity"``: the result does not depend on
    the units or pose of either face) or by ``s`` (``"scale"``; the rotation is used only
    beyond ``AUTO_ROTATION_DEGREES``). Measured on real rig pairs
    (FIDELITY_NOTES), the warp's local Jacobian is a poor displacement scale because the
    phi(r) = r kernel has a kink at every centre and markers sit on the centres.
    """

    def __init__(
        self,
        how: str,
        warp=None,
        scale: float = 1.0,
        rotation=None,
        translation=None,
        angle: float = 0.0,
    ):
        self.how = how
        self.warp = warp
        self.scale = float(scale)
        self.rotation = np.eye(3) if rotation is None else np.asarray(rotation, dtype=np.float64)
        self.translation = (
            np.zeros(3) if translation is None else np.asarray(translation, dtype=np.float64)
        )
        self.angle = float(angle)  # degrees, of the fitted similarity's rotation

    def points(self, points: np.ndarray) -> np.ndarray:
        """Target-space points ``(..., 3)`` in the source's space."""
        p = np.asarray(points, dtype=np.float64)
        if self.warp is not None:
            return self.warp(p.reshape(-1, 3)).reshape(p.shape)
        return self.scale * p @ self.rotation.T + self.translation

    def deltas(self, points: np.ndarray, deltas: np.ndarray) -> np.ndarray:
        """Displacements ``(M, P, 3)`` at target ``points (P, 3)`` carried to the source's space."""
        d = np.asarray(deltas, dtype=np.float64)
        if self.warp is not None:
            base = self.points(points)
            return self.points(np.asarray(points)[None] + d) - base[None]
        return self.scale * d @ self.rotation.T


def fit_transfer(
    target_landmarks: np.ndarray,
    source_landmarks: np.ndarray,
    how: str = "scale",
    kernel: str = "linear",
) -> Transfer:
    """A :class:`Transfer` from corresponding neutral landmarks ``(N, 3)`` of target and source."""
    if how == "rbf":
        return Transfer(how, warp=fit_rbf(target_landmarks, source_landmarks, kernel=kernel))
    rot, trans, scale = procrustes.fit_rigid(target_landmarks, source_landmarks, scale=True)
    angle = float(np.degrees(np.arccos(np.clip((np.trace(rot) - 1.0) / 2.0, -1.0, 1.0))))
    if how == "scale" and angle <= AUTO_ROTATION_DEGREES:
        centre_t = np.mean(target_landmarks, axis=0)
        centre_s = np.mean(source_landmarks, axis=0)
        return Transfer(how, scale=scale, translation=centre_s - scale * centre_t, angle=angle)
    return Transfer(how, scale=scale, rotation=rot, translation=trans, angle=angle)


def similarity_matrix(target_landmarks: np.ndarray, source_landmarks: np.ndarray) -> np.ndarray:
    """(4, 4) similarity ``T`` taking target coordinates to source coordinates,
    ``x_s ~ s R x_t + t``, fitted to corresponding neutral landmarks (Umeyama)."""
    rot, trans, scale = procrustes.fit_rigid(target_landmarks, source_landmarks, scale=True)
    return procrustes.to_matrix(rot[None], trans[None], np.atleast_1d(scale))[0]


def motion_to_target(motion: np.ndarray | None, frame: np.ndarray) -> np.ndarray | None:
    """Source head motion ``(F, 4, 4)`` expressed in the target's units.

    Rotations are kept; translations are converted to the target's length unit (see
    :func:`unit_ratio`; ``frame`` = T is the landmark similarity from target to source).
    Returns ``motion`` itself (as a float64 array) when both are in the same unit.
    """
    if motion is None:
        return None
    motion = np.asarray(motion, dtype=np.float64)
    ratio = unit_ratio(float(np.cbrt(np.linalg.det(frame[:3, :3]))))
    if ratio == 1.0:
        return motion
    out = motion.copy()
    out[:, :3, 3] /= ratio
    return out


def unit_ratio(scale: float) -> float:
    """The power of ten nearest to a source/target size ratio: the ratio of their length units.

    Head translations are carried over in world distance, converted between units (metres to
    centimetres is 0.01) but not stretched by the faces' proportions (a source face 13%
    larger moves its head as far, not 13% farther). The rest of the ratio is the faces' sizes.
    """
    return float(10.0 ** np.round(np.log10(scale)))
