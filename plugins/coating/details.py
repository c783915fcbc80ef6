"""Fine-scale (wrinkle) editing of a coating result (Xu et al. 2014, sec. 5.2, eq. 17-21).

1. **Selection** at a key frame ``t_k``: a vertex set, or every vertex closer than
   ``radius`` to a curve drawn along a wrinkle.
2. **Active range**: the frames around ``t_k`` whose region coating magnitude
   ``sum_{v in P} |D'_t,v|`` stays above ``threshold`` (0.23) times the key frame's
   (our reading of the garbled ratio in sec. 5.2), found by scanning outward from the key
   frame. ``D'_t`` here is the wrinkle layer alone (the coating against the Taubin-
   smoothed source frame, :meth:`~.track.CoatingTrack.wrinkles`), not the basis-fit
   residual of eq. 7 that the transfer also carries.
3. **Key-frame edit** of the wrinkles ``D'_{t_k}``: scale (enhance / diminish),
   remove (scale 0), copy-paste the region's details through a similarity transform
   (closest transformed source vertex of every destination vertex; the detail vector
   is rotated from the source vertex's frame through the transform into the
   destination vertex's frame: the coating transfer of sec. 5.1), or reshape a
   wrinkle to a drawn curve (eq. 17: arc-length correspondences between the wrinkle
   curve and the drawn curve, Laplacian term with ``lambda_l = 0.2``, then remove the
   old details and paste them onto the deformed region). Edited and original coatings
   are linearly interpolated over ``blend`` rings around the edited vertices.
4. **Propagation** (eq. 18-21) of the key-frame change ``g`` through the window: the
   change ``delta_t`` (``D'_t = R(D_t) + delta_t``) minimises

       lambda_key |delta_tk - g|^2
       + lambda_gradient sum_t (|delta_t+1 - delta_t|^2 + sum_edges |delta_t,i - delta_t,j|^2)
       + lambda_boundary (|delta_ts|^2 + |delta_te|^2)

   Spatial differences are taken in one common frame (the world frame at the key
   frame, so that differently oriented vertex frames compare correctly); the term at a
   window end that is the key frame itself is dropped (the edit wins). The system is
   ``A_time (x) I + lambda_gradient I (x) L_region`` plus diagonal terms in time: with
   the region Laplacian diagonalised (densely up to 600 vertices; beyond, on the Krylov
   space of the change, by Lanczos), every spatial mode is one tridiagonal solve in
   time, so a window of 1,300 frames costs little beyond the eigen-decomposition.
"""

from __future__ import annotations

import time
from dataclasses import dataclass
from typing import Any

import numpy as np
import scipy.sparse as sp

from faceretarget.errors import ConfigError, IndexRangeError, InputError, NonFiniteError, ShapeError
from faceretarget.geometry.procrustes import apply as apply_transform

from .alignment import to_local
from .track import DetailLayer

__all__ = [
    "DetailEdit",
    "select_region",
    "active_range",
    "scan_active_range",
    "propagate",
    "apply_detail_edit",
    "LAMBDA_RESHAPE",
]

#: Weight of the Laplacian term when reshaping a wrinkle to a drawn curve (paper: 0.2).
LAMBDA_RESHAPE = 0.2
#: Regions up to this many vertices are diagonalised densely when propagating an edit.
DENSE_REGION = 600
#: Lanczos steps for larger regions.
LANCZOS_STEPS = 120
_OPERATIONS = ("scale", "remove", "paste", "reshape")


@dataclass(frozen=True)
class DetailEdit:
    """A fine-scale edit at one key frame.

    frame : key frame
    vertices : target vertex ids of the detail region, or
    curve : (n, 3) world-space polyline along a wrinkle at the key frame, with
    radius : selection distance to ``curve`` (mesh units)
    operation : "scale" | "remove" | "paste" | "reshape"
    factor : detail scale for "scale" (2 enhances, 0.5 diminishes)
    transform : (4, 4) world-space similarity for "paste": moves the selected region
        onto the destination at the key frame
    target_curve : (m, 3) world-space polyline drawn as the wrinkle's new shape ("reshape")
    window : (first, last) frames to propagate over; default: the active range
    threshold : active-range threshold (default: the retargeter's ``detail_threshold``)
    blend : rings of linear interpolation between edited and original coating
    """

    frame: int
    vertices: Any = None
    curve: Any = None
    radius: float | None = None
    operation: str = "scale"
    factor: float = 1.0
    transform: Any = None
    target_curve: Any = None
    window: Any = None
    threshold: float | None = None
    blend: int = 2


def _polyline(points, what) -> np.ndarray:
    arr = np.asarray(points, dtype=np.float64)
    if arr.ndim != 2 or arr.shape[1] != 3 or arr.shape[0] < 2:
        raise ShapeError(
            f"coating detail edit: {what} must be an (n >= 2, 3) polyline, got shape {arr.shape}"
        )
    if not np.isfinite(arr).all():
        raise NonFiniteError(f"coating detail edit: {what} holds NaN or infinite coordinates")
    return arr


def _distance_to_polyline(points: np.ndarray, line: np.ndarray) -> np.ndarray:
    """(V,) distance of every point to the polyline."""
    a = line[:-1]
    ab = line[1:] - a
    ap = points[:, None, :] - a[None]
    t = np.clip(
        np.einsum("vsd,sd->vs", ap, ab) / np.maximum(np.einsum("sd,sd->s", ab, ab), 1e-300),
        0.0,
        1.0,
    )
    closest = a[None] + t[..., None] * ab[None]
    return np.linalg.norm(points[:, None, :] - closest, axis=-1).min(axis=1)


def select_region(points: np.ndarray, *, vertices=None, curve=None, radius=None) -> np.ndarray:
    """Region vertex ids: ``vertices`` as given, or those within ``radius`` of ``curve``."""
    if vertices is not None:
        ids = np.unique(np.asarray(vertices, dtype=np.int64).ravel())
        if ids.size == 0:
            raise InputError("coating detail edit: the vertex region is empty")
        if ids.min() < 0 or ids.max() >= points.shape[0]:
            raise IndexRangeError(
                f"coating detail edit: region vertex ids must be in 0..{points.shape[0] - 1}"
            )
        return ids
    if curve is None or radius is None:
        raise InputError(
            "coating detail edit: select the region by vertices= or by curve= with radius="
        )
    if not (np.isfinite(radius) and radius > 0):
        raise ConfigError(f"coating detail edit: radius must be positive, got {radius!r}")
    ids = np.flatnonzero(_distance_to_polyline(points, curve) <= radius)
    if ids.size == 0:
        raise InputError(
            f"coating detail edit: no vertex lies within {radius} of the curve at the key frame; draw it on the face or widen the radius"
        )
    return ids


def active_range(magnitude: np.ndarray, key: int, threshold: float) -> tuple[int, int]:
    """Largest run of frames around ``key`` with ``magnitude_t > threshold * magnitude_key``."""
    m = np.asarray(magnitude, dtype=np.float64)
    if m[key] <= 0:
        return key, key
    above = m > threshold * m[key]
    start = key
    while start > 0 and above[start - 1]:
        start -= 1
    stop = key
    while stop < m.size - 1 and above[stop + 1]:
        stop += 1
    return start, stop


def scan_active_range(
    magnitude_of, key: int, n_frames: int, threshold: float, chunk: int
) -> tuple[int, int]:
    """:func:`active_range` evaluated lazily: ``magnitude_of(frame ids) -> (n,)`` is asked for
    blocks of ``chunk`` frames outward from ``key`` until the magnitude falls to the threshold
    on both sides (the wrinkles cost a smoothing a frame, so only the range and one block
    beyond are computed)."""
    step = max(1, int(chunk))
    known = {key: float(magnitude_of(np.array([key]))[0])}
    ref = known[key]
    if ref <= 0:
        return key, key
    ends = []
    for direction in (-1, 1):
        t = key
        while True:
            nxt = t + direction
            if not 0 <= nxt < n_frames:
                break
            if nxt not in known:
                block = np.arange(nxt, nxt + direction * step, direction)
                block = block[(block >= 0) & (block < n_frames)]
                known.update(
                    zip(
                        block.tolist(),
                        np.asarray(magnitude_of(np.sort(block)), dtype=np.float64)[
                            np.argsort(np.argsort(block))
                        ].tolist(),
                    )
                )
            if not known[nxt] > threshold * ref:
                break
            t = nxt
        ends.append(t)
    return ends[0], ends[1]


def _rings(adj: sp.csr_matrix, seed: np.ndarray, count: int) -> tuple[np.ndarray, np.ndarray]:
    """Vertices within ``count`` edge rings of ``seed`` (adjacency ``adj``) and their ring number."""
    n_vertices = adj.shape[0]
    ring = np.full(n_vertices, -1, dtype=np.int64)
    ring[seed] = 0
    front = np.zeros(n_vertices, dtype=bool)
    front[seed] = True
    for r in range(1, count + 1):
        nxt = (adj @ front.astype(np.float64)) > 0
        nxt &= ring < 0
        ring[nxt] = r
        front = nxt
    ids = np.flatnonzero(ring >= 0)
    return ids, ring[ids]


def _tridiagonal_impulse(diag: np.ndarray, off: float, key: int) -> np.ndarray:
    """Solve ``A z = e_key`` for symmetric tridiagonal ``A`` per mode.

    diag : (T, M) diagonal of each mode's matrix; off : the constant off-diagonal.
    Returns ``z : (T, M)`` (Thomas algorithm vectorised over modes).
    """
    n, m = diag.shape
    c = np.empty((n, m))
    d = np.zeros((n, m))
    denom = diag[0].copy()
    c[0] = off / denom
    d[0] = (1.0 if key == 0 else 0.0) / denom
    for t in range(1, n):
        denom = diag[t] - off * c[t - 1]
        c[t] = off / denom
        d[t] = ((1.0 if t == key else 0.0) - off * d[t - 1]) / denom
    z = np.empty((n, m))
    z[-1] = d[-1]
    for t in range(n - 2, -1, -1):
        z[t] = d[t] - c[t] * z[t + 1]
    return z


def _spatial_modes(lap: sp.csr_matrix, vector: np.ndarray):
    """Eigen-pairs of the region Laplacian that carry ``vector``: ``(sigma (M,), modes (P, M), coef (M,))``.

    Dense ``eigh`` for regions up to ``DENSE_REGION`` vertices (exact). Larger regions use
    the Krylov space of ``vector`` (Lanczos with full reorthogonalisation, at most
    ``LANCZOS_STEPS`` steps): every function of the Laplacian applied to ``vector`` is
    then evaluated on the Ritz pairs, exact once the space is invariant and otherwise
    accurate to the Lanczos approximation of a smooth rational function.
    """
    n = lap.shape[0]
    norm = float(np.linalg.norm(vector))
    if norm == 0.0:
        return np.zeros(0), np.zeros((n, 0)), np.zeros(0)
    if n <= DENSE_REGION:
        sigma, modes = np.linalg.eigh(lap.toarray())
        return np.maximum(sigma, 0.0), modes, modes.T @ vector
    steps = min(n, LANCZOS_STEPS)
    basis = np.zeros((n, steps))
    alpha = np.zeros(steps)
    beta = np.zeros(steps)
    q = vector / norm
    m = 0
    for m in range(steps):
        basis[:, m] = q
        w = lap @ q
        alpha[m] = q @ w
        w -= basis[:, : m + 1] @ (basis[:, : m + 1].T @ w)  # full reorthogonalisation (twice)
        w -= basis[:, : m + 1] @ (basis[:, : m + 1].T @ w)
        b = float(np.linalg.norm(w))
        if b <= 1e-12 * max(abs(alpha[m]), 1.0) or m == steps - 1:
            break
        beta[m] = b
        q = w / b
    m += 1
    from scipy.linalg import eigh_tridiagonal

    theta, s = eigh_tridiagonal(alpha[:m], beta[: m - 1])
    return np.maximum(theta, 0.0), basis[:, :m] @ s, norm * s[0]


def propagate(
    change: np.ndarray,
    edges: np.ndarray,
    key: int,
    n_frames: int,
    *,
    lambda_key: float,
    lambda_gradient: float,
    lambda_boundary: float,
    fix_start: bool,
    fix_end: bool,
) -> np.ndarray:
    """Minimiser of eq. 18 for a key-frame change ``change : (P, 3)`` (common frame).

    edges : (E, 2) local indices of region edges; ``key`` is the key frame's position in
    the window of ``n_frames``. Returns ``delta : (n_frames, P, 3)``.
    """
    g = np.asarray(change, dtype=np.float64)
    n_p = g.shape[0]
    if len(edges):
        i, j = edges[:, 0], edges[:, 1]
        adj = sp.csr_matrix((np.ones(2 * len(i)), (np.r_[i, j], np.r_[j, i])), shape=(n_p, n_p))
    else:
        adj = sp.csr_matrix((n_p, n_p))
    lap = (sp.diags(np.asarray(adj.sum(axis=1)).ravel()) - adj).tocsr()
    base = np.zeros(n_frames)
    if n_frames > 1:
        base[:-1] += lambda_gradient
        base[1:] += lambda_gradient
    base[key] += lambda_key
    if fix_start and key != 0:
        base[0] += lambda_boundary
    if fix_end and key != n_frames - 1:
        base[-1] += lambda_boundary
    out = np.zeros((n_frames, n_p, 3))
    shared = _spatial_modes(lap, np.ones(n_p)) if n_p <= DENSE_REGION else None
    for d in range(3):
        if shared is not None:
            sigma, modes, _ = shared
            coef = modes.T @ g[:, d]
        else:
            sigma, modes, coef = _spatial_modes(lap, g[:, d])
        if sigma.size == 0:
            continue
        z = _tridiagonal_impulse(
            base[:, None] + lambda_gradient * sigma[None, :], -lambda_gradient, key
        )  # (T, M)
        out[:, :, d] = (modes @ (lambda_key * coef[:, None] * z.T)).T
    return out


def _resample(line: np.ndarray, count: int) -> np.ndarray:
    seg = np.linalg.norm(np.diff(line, axis=0), axis=1)
    s = np.concatenate([[0.0], np.cumsum(seg)])
    t = np.linspace(0.0, s[-1], count)
    return np.stack([np.interp(t, s, line[:, k]) for k in range(3)], axis=1)


def _reshape(
    points: np.ndarray,
    adj: sp.csr_matrix,
    region: np.ndarray,
    curve: np.ndarray,
    target_curve: np.ndarray,
) -> np.ndarray:
    """Eq. 17: new positions ``(P, 3)`` of the region vertices, the wrinkle curve moved onto ``target_curve``."""
    from scipy.spatial import cKDTree

    count = max(len(curve), len(target_curve), 16)
    src = _resample(curve, count)
    dst = _resample(target_curve, count)
    x = points[region]
    nearest = cKDTree(x).query(src)[1]
    n_p = region.size
    # umbrella Laplacian rows of the region, restricted to region columns (outside fixed)
    deg = np.asarray(adj.sum(axis=1)).ravel()[region]
    lap = (sp.identity(n_p) - sp.diags(1.0 / deg) @ adj[region][:, region]).tocsr()
    sel = sp.csr_matrix((np.ones(count), (np.arange(count), nearest)), shape=(count, n_p))
    lhs = (sel.T @ sel + LAMBDA_RESHAPE * (lap.T @ lap) + 1e-9 * sp.identity(n_p)).tocsc()
    rhs = sel.T @ dst + LAMBDA_RESHAPE * (lap.T @ (lap @ x))
    from scipy.sparse.linalg import splu

    return splu(lhs).solve(np.ascontiguousarray(rhs))


def _copy_details(
    frames_key: np.ndarray,
    details_key: np.ndarray,
    src_ids,
    src_points,
    dst_points_all,
    rotation,
    spacing,
):
    """Destination ids and their copied local details.

    The moved source points are snapped to their nearest mesh vertices (so a region
    moved slightly off the surface still lands), every vertex within ``spacing`` of a
    moved point joins; each destination copies the detail of its nearest moved point.
    """
    from scipy.spatial import cKDTree

    mesh_tree = cKDTree(dst_points_all)
    gap, snapped = mesh_tree.query(src_points)
    if np.median(gap) > 10.0 * spacing:
        raise InputError(
            f"coating detail edit: the pasted region lies {np.median(gap):.3g} (median) away from the face surface; "
            "check the transform / target curve"
        )
    dist, nearest = cKDTree(src_points).query(dst_points_all)
    dst = np.union1d(np.flatnonzero(dist <= spacing), snapped)
    src = src_ids[nearest[dst]]
    world = np.einsum("pij,pj->pi", frames_key[src], details_key[src]) @ rotation.T
    local = np.einsum("pji,pj->pi", frames_key[dst], world)
    return dst, local


def apply_detail_edit(retargeter, track, animation, spec: DetailEdit):
    """Solve a fine-scale edit; returns ``(new track, changed frame ids, diagnostics)``."""
    if spec.operation not in _OPERATIONS:
        raise ConfigError(
            f"coating detail edit: operation must be one of {_OPERATIONS}, got {spec.operation!r}"
        )
    n_frames = track.n_frames
    key = spec.frame
    if (
        isinstance(key, bool)
        or not isinstance(key, (int, np.integer))
        or not 0 <= int(key) < n_frames
    ):
        raise IndexRangeError(
            f"coating detail edit: key frame {key!r} is outside the animation's {n_frames} frames"
        )
    key = int(key)
    start = time.perf_counter()
    model = track.model
    tri = model.triangles
    n = model.n_vertices
    motion_k = track.motion[key : key + 1]
    smooth_k = model.smooth_target(track.weights[key : key + 1], track.bases)
    frames_k = model.target.frames(smooth_k)[0]
    points_k = model.target.reconstruct(
        smooth_k,
        model.target.reference_coating[None] + model.detail_scale * track.fine_motion([key]),
        frames_k[None],
    )[0]

    def local_curve(c, what):
        return track.placement.to_model(to_local(motion_k, _polyline(c, what)[None])[0])

    curve = None if spec.curve is None else local_curve(spec.curve, "curve")
    vertices = (
        None
        if spec.vertices is None
        else track.target_vertex[np.asarray(spec.vertices, dtype=np.int64).ravel()]
    )
    if spec.vertices is not None and (
        np.min(spec.vertices) < 0 or np.max(spec.vertices) >= track.target_vertex.size
    ):
        raise IndexRangeError(
            f"coating detail edit: region vertex ids must be in 0..{track.target_vertex.size - 1}"
        )
    region = select_region(points_k, vertices=vertices, curve=curve, radius=spec.radius)

    threshold = retargeter.detail_threshold if spec.threshold is None else float(spec.threshold)
    if spec.window is None:
        ts, te = scan_active_range(
            lambda frames: np.linalg.norm(track.wrinkles(frames, region), axis=-1).sum(axis=1),
            key,
            n_frames,
            threshold,
            track.chunk,
        )
    else:
        try:
            ts, te = (int(x) for x in spec.window)
        except (TypeError, ValueError):
            raise ShapeError(
                f"coating detail edit: window must be (first, last), got {spec.window!r}"
            ) from None
        if not 0 <= ts <= key <= te < n_frames:
            raise IndexRangeError(
                f"coating detail edit: window {spec.window} must contain the key frame {key} and lie in 0..{n_frames - 1}"
            )

    details_k = track.wrinkles([key])[0]  # (V, 3) current wrinkles D'_tk (no basis-fit residual)
    edge_len = float(np.mean(np.linalg.norm(points_k[tri[:, [1, 2, 0]]] - points_k[tri], axis=-1)))
    target = details_k.copy()
    edited = region
    if spec.operation in ("scale", "remove"):
        factor = 0.0 if spec.operation == "remove" else float(spec.factor)
        if not np.isfinite(factor):
            raise NonFiniteError(f"coating detail edit: factor must be finite, got {spec.factor!r}")
        target[region] = factor * details_k[region]
    elif spec.operation == "paste":
        if spec.transform is None:
            raise InputError(
                "coating detail edit: 'paste' needs transform= (a 4x4 similarity moving the region onto its destination)"
            )
        m = np.asarray(spec.transform, dtype=np.float64)
        if m.shape != (4, 4) or not np.isfinite(m).all():
            raise ShapeError(
                f"coating detail edit: transform must be a finite 4x4 matrix, got shape {m.shape}"
            )
        head = motion_k[0]
        local_m = track.placement.model_transform(np.linalg.inv(head) @ m @ head)
        lin = local_m[:3, :3]
        scale = float(np.cbrt(abs(np.linalg.det(lin))))
        if scale <= 0:
            raise InputError("coating detail edit: the paste transform is singular")
        moved = apply_transform(local_m[None], points_k[region])[0]
        dst, copied = _copy_details(
            frames_k,
            details_k,
            region,
            moved,
            points_k,
            lin / scale,
            0.75 * edge_len * max(scale, 1.0),
        )
        target[dst] = copied
        edited = dst
    else:
        if curve is None or spec.target_curve is None:
            raise InputError(
                "coating detail edit: 'reshape' needs curve= (along the wrinkle), radius= and target_curve= (its new shape)"
            )
        new_pos = _reshape(
            points_k, model.adjacency, region, curve, local_curve(spec.target_curve, "target_curve")
        )
        target[region] = 0.0
        dst, copied = _copy_details(
            frames_k, details_k, region, new_pos, points_k, np.eye(3), 0.75 * edge_len
        )
        target[dst] = copied
        edited = np.union1d(region, dst)

    blend = int(spec.blend)
    if blend < 0:
        raise ConfigError(f"coating detail edit: blend must be >= 0 rings, got {spec.blend!r}")
    affected, ring = _rings(model.adjacency, edited, blend)
    beta = 1.0 - ring / (blend + 1.0)
    change_local = beta[:, None] * (target[affected] - details_k[affected])
    change = np.einsum("pij,pj->pi", frames_k[affected], change_local)  # world at the key frame
    position = np.full(n, -1, dtype=np.int64)
    position[affected] = np.arange(affected.size)
    e = model.edges
    both = (position[e[:, 0]] >= 0) & (position[e[:, 1]] >= 0)
    local_edges = position[e[both]]
    delta_world = propagate(
        change,
        local_edges,
        key - ts,
        te - ts + 1,
        lambda_key=float(retargeter.lambda_key),
        lambda_gradient=float(retargeter.lambda_gradient),
        lambda_boundary=float(retargeter.lambda_boundary),
        fix_start=True,
        fix_end=True,
    )
    delta = np.einsum("pji,tpj->tpi", frames_k[affected], delta_world)
    layer = DetailLayer(ts, te + 1, affected, delta)
    diagnostics = {
        "kind": "detail",
        "operation": spec.operation,
        "key_frame": key,
        "window": [ts, te],
        "region_vertices": int(region.size),
        "edited_vertices": int(affected.size),
        "solve_s": time.perf_counter() - start,
    }
    return track.replace(layers=track.layers + (layer,)), np.arange(ts, te + 1), diagnostics
