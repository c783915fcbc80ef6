"""Brute-force reference of the layered-model extraction (Kholgade et al. 2011, Eq. 7).

Works in the full coordinate space (no reduced Gram tensor) and solves each frame with
scipy's SLSQP on the joint variables, as the paper did with a generic constrained
optimiser. Variables: ``W (m, J)`` (row l = region l, sums to 1 over layers) and the
stacked simplex coefficients ``alpha (K,)`` (block j sums to 1).
"""

from __future__ import annotations

import numpy as np
from scipy.optimize import minimize


def layered_output(basis, masks, layer_of, W, alpha):
    """``f = sum_l sum_j W[l, j] M_l B_j alpha_j``: basis (K, C), masks (C, m) -> (C,)."""
    out = np.zeros(basis.shape[1])
    for l in range(masks.shape[1]):
        for j in range(W.shape[1]):
            sel = layer_of == j
            out += W[l, j] * masks[:, l] * (alpha[sel] @ basis[sel])
    return out


def frame_objective(
    xhat,
    valid,
    basis,
    masks,
    layer_of,
    W,
    alpha,
    c_d,
    c_b,
    c_s,
    mouth,
    speech,
    closed,
    W_prev,
    a_prev,
    additive=False,
    rigid_jac=None,
):
    """E of one frame: c_d |x_hat - f|^2 (observed coordinates) + c_b bias + c_s smoothing.

    ``additive``: the bias pulls the speech coefficients only (the weights are left to the data).
    ``rigid_jac (C, r)``: measure the data modulo the alignment's small motions, i.e.
    ``|P r|^2`` with ``P`` the orthogonal projector off the columns of ``rigid_jac``
    restricted to the observed coordinates (an alignment pass).
    """
    r = (xhat - layered_output(basis, masks, layer_of, W, alpha))[valid]
    if rigid_jac is not None:
        j = np.asarray(rigid_jac)[valid]
        r = r - j @ np.linalg.lstsq(j, r, rcond=None)[0]
    e = c_d * float(r @ r)
    if c_b > 0 and mouth >= 0:
        target = np.zeros(W.shape[1])
        target[speech] = 1.0
        if (
            not additive
        ):  # additive: the bias picks the viseme only, the weights are left to the data
            e += c_b * float(np.sum((W[mouth] - target) ** 2))
        sel = layer_of == speech
        a_t = np.zeros(alpha.shape[0])
        a_t[closed] = 1.0
        e += c_b * float(np.sum((alpha[sel] - a_t[sel]) ** 2))
    if c_s > 0:
        e += c_s * float(np.sum((W - W_prev) ** 2) + np.sum((alpha - a_prev) ** 2))
    return e


def slsqp_frame(
    xhat,
    valid,
    basis,
    masks,
    layer_of,
    c_d,
    c_b,
    c_s,
    mouth,
    speech,
    closed,
    W_prev,
    a_prev,
    W0,
    a0,
    additive=False,
    rigid_jac=None,
):
    """One frame by SLSQP from (W0, a0); returns (W, alpha, E).

    ``additive``: each W[l, j] in [0, 1] (no sum over the layers); ``rigid_jac``: see
    :func:`frame_objective`.
    """
    m, J = W0.shape
    K = a0.shape[0]

    def unpack(z):
        return z[K:].reshape(m, J), z[:K]

    def fun(z):
        W, a = unpack(z)
        return frame_objective(
            xhat,
            valid,
            basis,
            masks,
            layer_of,
            W,
            a,
            c_d,
            c_b,
            c_s,
            mouth,
            speech,
            closed,
            W_prev,
            a_prev,
            additive,
            rigid_jac,
        )

    cons = [
        {"type": "eq", "fun": (lambda z, j=j: z[:K][layer_of == j].sum() - 1.0)} for j in range(J)
    ]
    if not additive:
        cons += [
            {"type": "eq", "fun": (lambda z, l=l: z[K:].reshape(m, J)[l].sum() - 1.0)}
            for l in range(m)
        ]
    z0 = np.concatenate([a0, W0.ravel()])
    bounds = [(0.0, None)] * K + [(0.0, 1.0 if additive else None)] * (m * J)
    res = minimize(
        fun,
        z0,
        method="SLSQP",
        bounds=bounds,
        constraints=cons,
        options={"ftol": 1e-10, "maxiter": 500},
    )
    z = np.clip(res.x, 0.0, None)
    W, a = unpack(z)
    # back onto the constraint set (SLSQP satisfies it only to its tolerance)
    W = np.clip(W, 0.0, 1.0) if additive else W / W.sum(axis=1, keepdims=True)
    for j in range(J):
        a[layer_of == j] /= a[layer_of == j].sum()
    return W, a, fun(np.concatenate([a, W.ravel()]))


def slsqp_sequence(
    xhat,
    valid,
    basis,
    masks,
    layer_of,
    c_d,
    c_b,
    c_s,
    mouth,
    speech,
    closed,
    W0,
    a0,
    additive=False,
):
    """Frames in order, each warm-started from (and smoothed towards) the previous result."""
    W_prev, a_prev = W0.copy(), a0.copy()
    out_w, out_a, out_e = [], [], []
    for t in range(xhat.shape[0]):
        cs = c_s[t] if t > 0 else 0.0
        W, a, e = slsqp_frame(
            xhat[t],
            valid[t],
            basis,
            masks,
            layer_of,
            c_d[t],
            c_b[t],
            cs,
            mouth,
            speech,
            closed,
            W_prev,
            a_prev,
            W_prev,
            a_prev,
            additive,
        )
        out_w.append(W)
        out_a.append(a)
        out_e.append(e)
        W_prev, a_prev = W, a
    return np.array(out_w), np.array(out_a), np.array(out_e)


# ---------------------------------------------------------------------------------------
# A synthetic layered actor/character pair with known parameters (tests and benchmark)
# ---------------------------------------------------------------------------------------
def _surface(uv, depth):
    """Face-like surface over (u, v) in [-1, 1]^2: (P, 3)."""
    u, v = uv[:, 0], uv[:, 1]
    return np.stack([u, v, -depth * (u**2 + 0.6 * v**2)], axis=1)


def _bump(uv, centre, radius):
    d2 = ((uv - np.asarray(centre)) ** 2).sum(axis=1)
    return np.exp(-d2 / (2 * radius**2))


def _fields(uv, rng_state, sizes):
    """Displacement fields (K, P, 3) of the layers at parameter points ``uv`` (same meaning on any face).

    Layer 0 (emotion): smooth global fields plus two local bumps, pose 0 neutral. Layer 1 (speech): around the mouth
    (u = 0, v = -0.6), pose 0 closes the lips, the others open the jaw by different amounts.
    Layer 2 (blink): around the eyes (v = 0.4), pose 0 open (zero), then closing. Further layers:
    smooth fields like emotion.
    """
    rng = np.random.default_rng(rng_state)
    u, v = uv[:, 0], uv[:, 1]
    poly = np.stack([np.ones_like(u), u, v, u * v, u**2, v**2], axis=1)
    out = []
    for j, k in enumerate(sizes):
        poses = np.zeros((k, len(uv), 3))
        for i in range(k):
            if j == 1:
                mouth = _bump(uv, (0.0, -0.6), 0.25)
                below = 1.0 / (1.0 + np.exp(-(-0.6 - v) / 0.03))  # lower lip and jaw
                above = 1.0 - below
                if i == 0:
                    poses[i, :, 1] = 0.04 * mouth * (below - above)  # lips pressed together
                else:
                    jaw = rng.uniform(0.05, 0.25)
                    poses[i, :, 1] = -jaw * mouth * below
                    poses[i, :, 0] = rng.uniform(-0.08, 0.08) * u * mouth
                    poses[i, :, 2] = rng.uniform(-0.05, 0.05) * mouth
            elif j == 2:
                eyes = _bump(uv, (0.4, 0.4), 0.12) + _bump(uv, (-0.4, 0.4), 0.12)
                poses[i, :, 1] = -0.08 * (i / max(k - 1, 1)) * eyes
            elif i > 0 or j > 2:
                poses[i] = poly @ rng.normal(0, 0.04, size=(6, 3))
                for centre in rng.uniform(
                    -0.8, 0.8, size=(2, 2)
                ):  # local detail: poses affinely independent
                    poses[i] += 0.04 * _bump(uv, centre, 0.3)[:, None] * rng.normal(size=3)
        out.append(poses)
    return out


def _masks(uv, n_regions, soft):
    """(R, P) masks by height v (upper face first, mouth region last), summing to 1 at every point."""
    v = uv[:, 1]
    cuts = np.array([0.55, 0.1]) if n_regions == 3 else np.linspace(0.8, -0.2, n_regions + 1)[1:-1]
    above = [1.0 / (1.0 + np.exp(-(v - c) / 0.05)) if soft else (v > c).astype(float) for c in cuts]
    if n_regions == 1:
        return np.ones((1, len(v)))
    rows = (
        [above[0]] + [above[i] - above[i - 1] for i in range(1, n_regions - 1)] + [1.0 - above[-1]]
    )
    return np.clip(np.array(rows), 0.0, None)


def _simplex_path(rng, n_frames, k, n_keys=6, sharp=0.5):
    keys = rng.dirichlet(np.full(k, sharp), size=n_keys)
    t = np.linspace(0, n_keys - 1, n_frames)
    i = np.minimum(t.astype(int), n_keys - 2)
    s = t - i
    return (1 - s)[:, None] * keys[i] + s[:, None] * keys[i + 1]


def _rotations(rng, n_frames, degrees):
    from scipy.spatial.transform import Rotation

    angles = np.cumsum(rng.normal(0, 1, size=(n_frames, 3)), axis=0)
    angles = degrees * angles / max(np.abs(angles).max(), 1e-12)
    return Rotation.from_euler("xyz", angles, degrees=True).as_matrix()


def make_problem(
    seed=0,
    *,
    n_markers=80,
    n_tracks=0,
    sizes=(6, 5, 3),
    layer_names=None,
    n_regions=3,
    n_vertices=600,
    n_frames=40,
    soft=True,
    head_motion=True,
    noise=0.0,
    fields_seed=123,
    with_truth=True,
    weights=None,
    coefficients=None,
    composition="convex",
):
    """A parallel actor/character pair with known per-frame parameters.

    Returns a dict: ``source`` (Source of markers, optional 2D tracks), ``target`` (TargetRig with
    layers), ``weights (F, m, J)``, ``coefficients (F, K)``, ``head_motion (F, 4, 4)``, ``truth``
    (F, V, 3) the character driven by the known parameters and head motion (Eq. 5),
    ``actor_local`` (F, N, 3) the noiseless actor markers without head motion, the (u, v)
    parameters, masks and poses of both sides. Marker 0 / 1 are the upper / lower lip centres.
    ``composition``: "convex" (each region's layer weights sum to 1, the paper) or "additive"
    (each in [0, 1]).
    """
    import faceretarget as fr

    rng = np.random.default_rng(seed)
    names = list(layer_names or ("emotion", "speech", "blink", "extra")[: len(sizes)])
    grid = rng.uniform(-1, 1, size=(n_markers - 2, 2))
    uv_a = np.vstack([[0.0, -0.55], [0.0, -0.65], grid])  # the two lip markers first
    marker_names = ["lip_upper_center", "lip_lower_center"] + [
        f"m{i}" for i in range(n_markers - 2)
    ]
    uv_c = rng.uniform(-1, 1, size=(n_vertices, 2))
    actor_neutral = _surface(uv_a, 0.3) * np.array([8.0, 10.0, 8.0])
    char_neutral = _surface(uv_c, 0.6) * np.array([11.0, 9.0, 6.0])
    fa = _fields(uv_a, fields_seed, sizes)
    fc = _fields(uv_c, fields_seed, sizes)
    amp_a, amp_c = np.array([8.0, 10.0, 8.0]), np.array([14.0, 8.0, 9.0])
    actor_poses = {n: actor_neutral + f * amp_a for n, f in zip(names, fa)}
    char_poses = {n: char_neutral + f * amp_c for n, f in zip(names, fc)}
    masks_a, masks_c = _masks(uv_a, n_regions, soft), _masks(uv_c, n_regions, soft)
    layer_of = np.repeat(np.arange(len(sizes)), sizes)
    W = np.stack(
        [_simplex_path(rng, n_frames, len(sizes), sharp=1.0) for _ in range(n_regions)], axis=1
    )
    if composition == "additive":  # every layer weight in [0, 1] on its own (the layers add)
        W = np.clip(W * len(sizes), 0.0, 1.0)
    A = np.concatenate([_simplex_path(rng, n_frames, k) for k in sizes], axis=1)
    if weights is not None:
        W = np.asarray(weights, dtype=float)
    if coefficients is not None:
        A = np.asarray(coefficients, dtype=float)

    def compose(neutral, poses, masks):
        disp = np.concatenate([poses[n] - neutral for n in names])  # (K, P, 3)
        out = np.repeat(neutral[None], n_frames, axis=0).astype(float)
        for l in range(n_regions):
            beta = W[:, l, layer_of] * A  # (F, K)
            out += masks[l][None, :, None] * np.einsum("fk,kpd->fpd", beta, disp)
        return out

    actor_local = compose(actor_neutral, actor_poses, masks_a)
    char_local = compose(char_neutral, char_poses, masks_c) if with_truth else None
    motion = np.tile(np.eye(4), (n_frames, 1, 1))
    if head_motion:
        motion[:, :3, :3] = _rotations(rng, n_frames, 12.0)
        motion[:, :3, 3] = np.cumsum(rng.normal(0, 0.3, size=(n_frames, 3)), axis=0)
    world = np.einsum("fij,fpj->fpi", motion[:, :3, :3], actor_local) + motion[:, None, :3, 3]
    world = world + rng.normal(0, noise, size=world.shape) if noise else world
    truth = (
        np.einsum("fij,fpj->fpi", motion[:, :3, :3], char_local) + motion[:, None, :3, 3]
        if with_truth
        else None
    )
    pose_names = {n: [f"{n}_{i}" for i in range(k)] for n, k in zip(names, sizes)}
    actor_layers = fr.LayeredRig(actor_poses, masks_a, pose_names=pose_names)
    tracks = layers2d = None
    if n_tracks:
        ids = np.argsort(np.abs(uv_a[:, 1] + 0.6) + np.abs(uv_a[:, 0]) * 0.5)[
            :n_tracks
        ]  # points around the mouth
        scale2d = 40.0
        proj = lambda p: scale2d * p[..., :2]  # noqa: E731 - orthographic camera in pixels
        local2d = proj(actor_local[:, ids])
        ang = np.deg2rad(np.cumsum(rng.normal(0, 1.0, n_frames)))
        rot2 = np.stack(
            [np.stack([np.cos(ang), -np.sin(ang)], 1), np.stack([np.sin(ang), np.cos(ang)], 1)], 1
        )
        zoom = 1.0 + 0.05 * np.sin(np.linspace(0, 3, n_frames))
        shift = np.cumsum(rng.normal(0, 2.0, size=(n_frames, 2)), axis=0)
        world2d = zoom[:, None, None] * np.einsum("fij,fpj->fpi", rot2, local2d) + shift[:, None]
        tracks = fr.MarkerSequence(
            world2d, names=[f"t{i}" for i in range(n_tracks)], reference=proj(actor_neutral[ids])
        )
        layers2d = fr.LayeredRig(
            {n: proj(p[:, ids]) for n, p in actor_poses.items()},
            masks_a[:, ids],
            pose_names=pose_names,
        )
    source = fr.Source(
        fr.MarkerSequence(world, names=marker_names, reference=actor_neutral),
        actor_layers=actor_layers,
        tracks2d=tracks,
        actor_layers_2d=layers2d,
    )
    tris = np.array([[0, 1, 2]])
    target = fr.TargetRig(
        fr.Mesh(char_neutral, tris),
        layers=fr.LayeredRig(char_poses, masks_c, pose_names=pose_names),
    )
    return dict(
        source=source,
        target=target,
        weights=W,
        coefficients=A,
        head_motion=motion,
        truth=truth,
        actor_local=actor_local,
        layer_of=layer_of,
        uv_actor=uv_a,
        uv_character=uv_c,
        masks_actor=masks_a,
        masks_character=masks_c,
        actor_poses=actor_poses,
        character_poses=char_poses,
    )
