"""Movement matching (Seol et al. 2012, sec. 4-5, Eq. 2, 4, 5 and appendix) and per-frame solves.

Energy, for weights ``w_t`` (M,) at frames t = 0..F-1 and source marker deltas ``s_t`` (3N,)::

    E = sum_t ||B (w_t - w_{t-1}) - (s_t - s_{t-1})||^2          movement matching (Eq. 2)
      + alpha * sum_t ||A w_t + a||^2                            PCA prior (Eq. 4)
      + beta  * sum_t ||P^{1/2} (B w_t - s_t)||^2                Sobolev term (sec. 7.1)
      + eps   * sum_t ||P_0 w_t||^2                              ridge (rank-deficient rigs)

with the weights of boundary / user-constrained frames fixed (Dirichlet conditions). Rows
of missing marker samples are dropped: a velocity row needs the marker at both frames.

Regularization: ``P_0`` projects onto the numerical null space of ``G = B^T B`` (eigenvalues
below ``config.RANK_RTOL`` times the largest): duplicate shapes then share their weight
equally and shapes that move no marker get zero weight, while well-determined directions
are not biased at all (a ridge on every direction would be amplified by the time Laplacian,
about F^2 times, in weakly determined directions). A frame whose block is still singular
(markers missing so that some shape is unseen, and no prior) gets ``eps I`` on that block only.

Normal equations, when every frame has every marker: ``(L kron G + I kron K) vec(W) = r``
with the path-graph Laplacian ``L = D^T D`` in time, ``G = B^T B`` and
``K = alpha Q + beta B^T P B + eps I``. The generalized eigendecomposition
``K phi = lam (G + K) phi`` (``Phi^T (G+K) Phi = I``) diagonalizes both m x m matrices, so
``w_t = Phi y_t`` splits the system into m independent tridiagonal systems
``((1 - lam_j) L + lam_j I) y_j = Phi^T r_j`` solved in one O(F m) sweep (numba).

When frames differ (missing markers or per-frame Sobolev weights) the Kronecker structure
is lost; the same normal equations are then solved exactly as a block-tridiagonal system
(block Thomas, O(F m^3) time, F m^2 memory) over the frames concerned.
"""

from __future__ import annotations

import dataclasses
from dataclasses import dataclass, field

import numpy as np
import scipy.linalg

from faceretarget import config
from faceretarget._threads import blas_single_threaded
from faceretarget.errors import DegenerateGeometryError, NumericalError
from faceretarget.geometry.nnls import balanced_rho


@dataclass
class System:
    """Precomputed matrices of the energy for one calibration.

    basis : (3N, M) float64       B (scale-matched blendshape deltas at the markers)
    prior_matrix, prior_vector    alpha Q (M, M) and alpha q (M,), alpha already applied
    beta : float                  Sobolev weight
    marker_weights : (N,) float   per-marker Sobolev weights p_i (default all 1)
    alpha : float                 the prior weight included in prior_matrix (diagnostics only)
    """

    basis: np.ndarray
    prior_matrix: np.ndarray
    prior_vector: np.ndarray
    beta: float
    marker_weights: np.ndarray | None = None
    alpha: float = 0.0  # the prior weight already applied (for diagnostics)
    gram: np.ndarray = field(init=False)
    ridge: float = field(init=False)  # eps
    ridge_matrix: np.ndarray = field(init=False)  # eps P_0 (null space of the Gram)
    position_matrix: np.ndarray = field(init=False)  # alpha Q + eps P_0 (common to all frames)
    _modal: tuple | None = field(default=None, init=False, repr=False)
    _marker_grams: np.ndarray | None = field(default=None, init=False, repr=False)
    _shifted: dict = field(default_factory=dict, init=False, repr=False)
    _factors: dict = field(default_factory=dict, init=False, repr=False)
    _sobolev: np.ndarray | None = field(default=None, init=False, repr=False)
    l1: float | np.ndarray = field(
        default=0.0, init=False
    )  # L1 weight(s) of the bounded solve (normal-equation units)

    def __post_init__(self):
        b = np.ascontiguousarray(self.basis, dtype=np.float64)
        self.basis = b
        if self.marker_weights is None:
            self.marker_weights = np.ones(b.shape[0] // 3)
        self.gram = b.T @ b
        m = b.shape[1]
        trace = float(np.trace(self.gram))
        if not trace > 0.0:
            raise DegenerateGeometryError(
                "spacetime: no blendshape moves any landmark (all blendshape deltas are zero at the "
                "landmarks); check the landmarks and the blendshape deltas"
            )
        self.ridge = config.RIDGE_EPS * trace / m
        evals, evecs = np.linalg.eigh(self.gram)
        null = evecs[:, evals <= config.RANK_RTOL * evals[-1]]
        self.ridge_matrix = self.ridge * (null @ null.T)
        self.position_matrix = self.prior_matrix + self.ridge_matrix

    @property
    def uniform_marker_weights(self) -> bool:
        """Every marker has the same Sobolev weight ``p_0`` (the default: all 1)."""
        p = self.marker_weights
        return bool(np.all(p == p[0]))

    @property
    def folded_beta(self) -> float:
        """The Sobolev weight to use with ``B`` in place of ``P B``: ``beta p_0`` when the
        marker weights are uniform (``P = p_0 I``), else ``beta`` (``P B`` is then needed)."""
        if self.uniform_marker_weights:
            return float(self.beta * self.marker_weights[0])
        return float(self.beta)

    @property
    def n_shapes(self) -> int:
        return int(self.basis.shape[1])

    @property
    def n_markers(self) -> int:
        return int(self.basis.shape[0] // 3)

    @property
    def sobolev_matrix(self) -> np.ndarray:
        """beta B^T P B for the constant per-marker weights (M, M), computed once."""
        if self._sobolev is None:
            if self.beta == 0.0:
                self._sobolev = np.zeros_like(self.gram)
            else:
                p = np.repeat(self.marker_weights, 3)
                self._sobolev = self.beta * (self.basis.T * p) @ self.basis
        return self._sobolev

    def decay_frames(self) -> dict[str, float]:
        """Decay lengths (frames) of the screened Poisson modes, ``sqrt((1 - lam) / lam)``.

        In mode j the prior pulls the solution toward it over about this many frames: motion
        slower than that is attenuated (a high-pass), so the shortest lengths say how much of a
        long, slow expression the prior flattens. Modes without prior (lam = 0) are infinite.
        """
        lam = self.modal[1]
        with np.errstate(divide="ignore"):
            length = np.sqrt(np.where(lam > 0, (1.0 - lam) / lam, np.inf))
        return {"min": float(length.min()), "median": float(np.median(length))}

    @property
    def marker_grams(self) -> np.ndarray:
        """(N, M, M) per-marker Grams B_i^T B_i (for frames with missing markers)."""
        if self._marker_grams is None:
            blocks = self.basis.reshape(self.n_markers, 3, self.n_shapes)
            self._marker_grams = np.ascontiguousarray(np.einsum("nki,nkj->nij", blocks, blocks))
        return self._marker_grams

    @property
    def admm_scale(self) -> np.ndarray:
        """(M,) diagonal ``D`` of the ADMM penalty ``rho/2 ||D^1/2 (w - z + u)||^2``: the diagonal
        of ``G + K`` over its mean, so that shapes of very different sizes (a jaw and an eyelid
        differ ~3,000x in ``G``) converge together (diagonal scaling, Boyd et al. 2011 sec. 3.4.1)."""
        k = self.position_matrix + self.sobolev_matrix
        d = np.diag(self.gram + k).copy()
        d /= max(float(d.mean()), 1e-300)
        return np.maximum(d, 1e-6)

    def shifted_modal(self, rho: float):
        """``(Phi, Phi^T, lam, (G + K + rho D) Phi)`` for the generalized eigenproblem
        ``(K + rho D) phi = lam (G + K + rho D) phi`` (the w-step of the bounded solve, ``D`` =
        :attr:`admm_scale`), cached."""
        cache = self._shifted
        if rho not in cache:
            k = self.position_matrix + self.sobolev_matrix + rho * np.diag(self.admm_scale)
            mass = self.gram + k
            try:
                lam, phi = scipy.linalg.eigh(k, mass)
            except (np.linalg.LinAlgError, scipy.linalg.LinAlgError) as exc:
                raise NumericalError(
                    f"spacetime: generalized eigendecomposition failed ({exc})"
                ) from None
            if len(cache) > 8:
                cache.clear()
            cache[rho] = (
                np.ascontiguousarray(phi),
                np.ascontiguousarray(phi.T),
                np.clip(lam, 0.0, 1.0),
                mass @ phi,
            )
        return cache[rho]

    @property
    def modal(self):
        """(Phi^T, lam, B Phi, (P B) Phi, Phi^T alpha q, (G + K) Phi), computed once."""
        if self._modal is None:
            k = self.position_matrix + self.sobolev_matrix
            mass = self.gram + k
            try:
                lam, phi = scipy.linalg.eigh(k, mass)
            except (np.linalg.LinAlgError, scipy.linalg.LinAlgError) as exc:
                raise NumericalError(
                    f"spacetime: generalized eigendecomposition failed ({exc})"
                ) from None
            lam = np.clip(lam, 0.0, 1.0)
            bphi = self.basis @ phi
            if self.uniform_marker_weights:  # P B Phi = p_0 B Phi: one projection, not two
                pbphi = np.empty((0, bphi.shape[1]))
            else:
                pbphi = np.repeat(self.marker_weights, 3)[:, None] * bphi
            self._modal = (
                np.ascontiguousarray(phi.T),
                lam,
                np.ascontiguousarray(bphi),
                np.ascontiguousarray(pbphi),
                phi.T @ self.prior_vector,
                mass @ phi,
            )
        return self._modal


def flatten_deltas(deltas: np.ndarray) -> np.ndarray:
    """(F, N, 3) marker deltas -> (F, 3N) float64 C-contiguous (NaN kept)."""
    d = np.asarray(deltas, dtype=np.float64)
    return np.ascontiguousarray(d.reshape(d.shape[0], -1))


@blas_single_threaded
def solve_movement(
    system: System,
    deltas: np.ndarray,
    known: np.ndarray,
    known_weights: np.ndarray,
    frame_weights: np.ndarray | None = None,
    terms: dict | None = None,
) -> np.ndarray:
    """Movement matching with the prior and Sobolev terms (Eq. 4 + sec. 7.1).

    Parameters
    ----------
    system : System
    deltas : (F, N, 3) float
        Source marker deltas from the neutral, head motion removed; NaN = missing sample.
    known : (F,) bool
        Frames with fixed weights (boundary conditions and user constraints).
    known_weights : (F, M) float
        Their weights (other rows ignored).
    frame_weights : (F, N) float, optional
        Per-frame, per-marker Sobolev weights (replace ``system.marker_weights``).
    terms : dict, optional
        Receives :func:`energy_terms` of the solution when the structured solve ran (from
        its modal quantities, a fraction of the cost); left empty otherwise.

    Returns
    -------
    (F, M) float64 weights; known frames hold exactly ``known_weights``.
    """
    s = flatten_deltas(deltas)
    known = np.ascontiguousarray(known, dtype=np.bool_)
    wk = np.ascontiguousarray(known_weights, dtype=np.float64)
    missing = np.isnan(s[:, 0::3])
    if not missing.any() and frame_weights is None:
        w = _solve_structured(system, s, known, wk, terms)
    else:
        w = _solve_general(system, s, missing, known, wk, frame_weights)
    w[known] = wk[known]
    return w


@dataclass
class BoundedStats:
    """How a bounded solve went (kept in the retargeter's diagnostics)."""

    iterations: int = 0
    converged: bool = True
    rho: float = 0.0
    primal: float = 0.0
    dual: float = 0.0


@blas_single_threaded
def solve_movement_bounded(
    system: System,
    deltas: np.ndarray,
    known: np.ndarray,
    known_weights: np.ndarray,
    lower: np.ndarray,
    upper: np.ndarray,
    l1: float | np.ndarray = 0.0,
    frame_weights: np.ndarray | None = None,
    stats: BoundedStats | None = None,
) -> np.ndarray:
    """Movement matching (as :func:`solve_movement`) with ``lower <= w <= upper`` and an L1 term.

    Minimizes the energy of :func:`solve_movement` plus ``2 * l1 * sum |w|`` (``l1`` in the
    units of the normal equations, i.e. half the energy weight) over the frames that are not
    known, subject to the per-shape bounds, by ADMM (:func:`._kernels.admm_box`): every
    iteration is one structured solve of the shifted system ``(H + rho I)``, so the cost per
    iteration is that of the unconstrained solve without its data projection. When the
    unconstrained solution already satisfies the bounds and ``l1 == 0`` it is returned as is.

    l1 : float or (M,) per-shape weights.
    lower, upper : (M,) float (``-inf`` / ``inf`` allowed); known frames keep
    ``known_weights`` even outside the bounds (a user's explicit choice).
    Returns (F, M) float64; the unknown frames satisfy the bounds exactly.
    """
    s = flatten_deltas(deltas)
    known = np.ascontiguousarray(known, dtype=np.bool_)
    wk = np.ascontiguousarray(known_weights, dtype=np.float64)
    m = system.n_shapes
    # writable copies: one compiled specialization of the kernels, whatever the caller passes
    lo = np.array(np.broadcast_to(np.asarray(lower, dtype=np.float64), (m,)))
    hi = np.array(np.broadcast_to(np.asarray(upper, dtype=np.float64), (m,)))
    l1 = np.array(np.broadcast_to(np.asarray(l1, dtype=np.float64), (m,)))
    stats = BoundedStats() if stats is None else stats
    missing = np.isnan(s[:, 0::3])
    structured = not missing.any() and frame_weights is None
    if structured:
        r_w = _normal_rhs(system, s, known)
        start = _modal_solve(system, r_w, known, wk, 0.0)
    else:
        start = _solve_general(system, s, missing, known, wk, frame_weights)
    start[known] = wk[known]
    z = np.clip(start, lo, hi)
    z[known] = wk[known]
    if not l1.any() and np.array_equal(z, start):  # the bounds hold already
        stats.iterations, stats.converged = 0, True
        return start
    u = np.zeros_like(z)
    if structured:
        _admm_structured(system, r_w, known, wk, lo, hi, l1, z, u, stats)
    else:
        _admm_general(system, s, missing, known, wk, frame_weights, lo, hi, l1, z, u, stats)
    z[known] = wk[known]
    return z


#: ADMM settings of the bounded solve: absolute / relative tolerances (weights are O(1)),
#: over-relaxation, iterations between step-size updates and in all.
ADMM_EPS_ABS = 1e-5
ADMM_EPS_REL = 2e-3
ADMM_RELAX = 1.8
ADMM_CHUNK = 10
ADMM_MAX_ITER = 2000


#: Initial ADMM step size relative to the mean diagonal of ``G + K``.
ADMM_RHO_SCALE = 0.1

#: Thomas factors of the bounded solve's w-step kept per system (by step size and known
#: frames; each is (F, M) float64, held until a solve needs a third): the first step size's
#: and one adapted.
ADMM_FACTORS_KEPT = 2

#: The w-step's two changes of basis in float32 (twice as fast; relative error ~1e-6, far
#: below ``ADMM_EPS_REL``). False gives the float64 kernel, for tolerances below ~1e-5.
ADMM_SINGLE = True


def _unit(system: System) -> float:
    """The mean diagonal of ``G + K``: the scale of the normal equations (length squared)."""
    k = system.position_matrix + system.sobolev_matrix
    return float(np.trace(k + system.gram) / system.n_shapes)


def _rho_update(rho: float, primal: float, dual: float, eps_p: float, eps_d: float) -> float:
    """Residual balancing (Boyd et al. 2011, sec. 3.4.1; OSQP's ratio of scaled residuals)."""
    ratio = np.sqrt(max(primal / max(eps_p, 1e-300), 1e-12) / max(dual / max(eps_d, 1e-300), 1e-12))
    return balanced_rho(rho, float(ratio))


def _normal_rhs(system: System, s: np.ndarray, known: np.ndarray) -> np.ndarray:
    """Right-hand side (F, M) of the movement-matching normal equations (unknown frames;
    complete data): ``B^T L s_t + beta B^T P s_t + alpha q``."""
    from ._kernels import laplacian_rhs

    b = system.basis
    sb = s @ b
    if system.beta == 0.0 or system.uniform_marker_weights:  # P B = p_0 B: in folded_beta
        spb = sb
    else:
        spb = (s * np.repeat(system.marker_weights, 3)) @ b
    r_w = np.empty((s.shape[0], system.n_shapes))
    laplacian_rhs(sb, spb, system.folded_beta, system.prior_vector, known, r_w)
    return r_w


def _known_modal(wk: np.ndarray, known: np.ndarray, mass_phi: np.ndarray) -> np.ndarray:
    """Modal values ``wk (G + K) Phi`` of the known frames (F, m), or an empty (0, m) array when
    no frame is known (the kernels read them at known rows only)."""
    if known.any():
        return wk @ mass_phi
    return np.empty((0, mass_phi.shape[1]))


def _modal_solve(
    system: System, r_w: np.ndarray, known: np.ndarray, wk: np.ndarray, rho: float
) -> np.ndarray:
    """Solve ``(H + rho I) w = r_w`` with known frames fixed, through the shifted eigenpairs."""
    from ._kernels import tridiagonal_modes

    phi, phi_t, lam, mass_phi = system.shifted_modal(rho)
    y = r_w @ phi
    yk = _known_modal(wk, known, mass_phi)
    tridiagonal_modes(y, lam, known, yk, y, np.empty_like(y))
    return y @ phi_t


def _admm_structured(system, r_w, known, wk, lo, hi, l1, z, u, stats) -> None:
    from ._kernels import admm_box, steady_pivots, thomas_factor

    n_frames, m = z.shape
    unit = _unit(system)
    rho = ADMM_RHO_SCALE * unit
    scale = system.admm_scale
    basis_dtype = np.float32 if ADMM_SINGLE else np.float64
    r_single = r_w.astype(basis_dtype)
    ex = np.empty((n_frames, m), dtype=basis_dtype)
    y = np.empty((n_frames, m), dtype=basis_dtype)
    sweep = np.empty((n_frames, m))
    known_key = known.tobytes()
    done, modal_rho = 0, None
    while True:
        if rho != modal_rho:  # the modal data and the factor change with the step size only
            phi, phi_t, lam, mass_phi = system.shifted_modal(rho)
            yk = _known_modal(wk, known, mass_phi)
            # the factor depends on the step size and the known frames only: kept for the
            # next solve of the same length (the first step size is always the same)
            key = (rho, basis_dtype, known_key)
            if key not in system._factors:
                inv = np.empty((n_frames, m))
                limit, steady = np.empty(m), np.empty(n_frames, dtype=np.bool_)
                thomas_factor(lam, known, inv)
                steady_pivots(lam, known, inv, limit, steady)
                if len(system._factors) >= ADMM_FACTORS_KEPT:
                    system._factors.clear()
                kept = (phi.astype(basis_dtype), phi_t.astype(basis_dtype), inv, limit, steady)
                for a in kept:
                    a.flags.writeable = False
                system._factors[key] = kept
            phi_w, phi_t_w, inv, limit, steady = system._factors[key]
            modal_rho = rho
        chunk = min(ADMM_CHUNK, ADMM_MAX_ITER - done)
        it, primal, dual, eps_p, eps_d = admm_box(
            r_single,
            lam,
            known,
            yk,
            inv,
            limit,
            steady,
            phi_w,
            phi_t_w,
            rho,
            scale,
            ADMM_RELAX,
            lo,
            hi,
            l1,
            z,
            u,
            chunk,
            ADMM_EPS_ABS,
            ADMM_EPS_REL,
            unit,
            ex,
            y,
            sweep,
        )
        done += abs(it)
        stats.iterations, stats.rho, stats.primal, stats.dual = done, rho, primal, dual
        if it > 0:
            stats.converged = True
            return
        if done >= ADMM_MAX_ITER:
            stats.converged = False
            return
        new = _rho_update(rho, primal, dual, eps_p, eps_d)
        u *= rho / new
        rho = new


def _admm_general(system, s, missing, known, wk, frame_weights, lo, hi, l1, z, u, stats) -> None:
    """ADMM as in :func:`_admm_structured`, the w-step by the exact block-tridiagonal solve."""
    unit = _unit(system)
    rho = ADMM_RHO_SCALE * unit
    m = system.n_shapes
    scale = system.admm_scale
    shifted = dataclasses.replace(system, prior_matrix=system.prior_matrix + rho * np.diag(scale))
    done = 0
    free = ~known
    while done < ADMM_MAX_ITER:
        vector = system.prior_vector[None, :] + rho * scale * (z - u)
        w = _solve_general(shifted, s, missing, known, wk, frame_weights, prior_vector=vector)
        done += 1
        wr = ADMM_RELAX * w + (1.0 - ADMM_RELAX) * z
        v = wr + u
        if l1.any():
            v = np.sign(v) * np.maximum(np.abs(v) - l1 / (rho * scale), 0.0)
        znew = np.clip(v, lo, hi)
        u[free] += (wr - znew)[free]
        primal = float(np.linalg.norm((w - znew)[free]))
        dual = rho * float(np.linalg.norm((scale * (znew - z))[free]))
        z[free] = znew[free]
        root = np.sqrt(max(free.sum() * m, 1))
        eps_p = ADMM_EPS_ABS * root + ADMM_EPS_REL * max(
            np.linalg.norm(w[free]), np.linalg.norm(z[free])
        )
        eps_d = ADMM_EPS_ABS * root * unit + ADMM_EPS_REL * rho * np.linalg.norm((scale * u)[free])
        stats.iterations, stats.rho, stats.primal, stats.dual = done, rho, primal, dual
        if primal <= eps_p and dual <= eps_d:
            stats.converged = True
            return
        if done % ADMM_CHUNK == 0:
            new = _rho_update(rho, primal, dual, eps_p, eps_d)
            if new != rho:
                u *= rho / new
                rho = new
                shifted = dataclasses.replace(
                    system, prior_matrix=system.prior_matrix + rho * np.diag(scale)
                )
    stats.converged = False


def _solve_structured(
    system: System, s: np.ndarray, known: np.ndarray, wk: np.ndarray, terms: dict | None = None
) -> np.ndarray:
    from ._kernels import modal_sweep

    phi_t, lam, bphi, pbphi, c0, mass_phi = system.modal
    n_frames, m = s.shape[0], system.n_shapes
    out, y, scratch = np.empty((n_frames, m)), np.empty((n_frames, m)), np.empty((n_frames, m))
    if known.any():
        scratch[known] = wk[known] @ mass_phi  # modal values of the known frames
    # the projection is needed past the right-hand side only for the energies
    z = out if terms is None else np.empty((n_frames, m))
    modal_sweep(s, bphi, pbphi, system.folded_beta, c0, lam, known, phi_t, z, y, scratch, out)
    if terms is not None:
        from ._kernels import modal_energies

        velocity, position = np.empty(n_frames), np.empty(n_frames)
        modal_energies(s, y, z, lam, velocity, position)
        terms.update(velocity=velocity, position=position)
    return out


def _solve_general(system, s, missing, known, wk, frame_weights, prior_vector=None) -> np.ndarray:
    """Block-tridiagonal solve; ``prior_vector`` (F, M) replaces ``system.prior_vector`` when given."""
    from ._kernels import block_thomas

    n_frames, m = s.shape[0], system.n_shapes
    valid = ~missing
    s0 = np.where(np.repeat(valid, 3, axis=1), s, 0.0)
    b = system.basis
    rhs = np.zeros((n_frames, m))
    rhs += system.prior_vector if prior_vector is None else prior_vector
    if n_frames > 1:
        edge_valid = valid[1:] & valid[:-1]
        ds = (s0[1:] - s0[:-1]) * np.repeat(edge_valid, 3, axis=1)
        v = ds @ b
        rhs[1:] += v
        rhs[:-1] -= v
    weights = system.marker_weights[None, :] if frame_weights is None else frame_weights
    pos = system.beta * np.broadcast_to(weights, missing.shape) * valid
    use_pos = bool(system.beta != 0.0 and np.any(pos != 0.0))
    if use_pos:
        rhs += (s0 * np.repeat(pos, 3, axis=1)) @ b
    out = np.empty((n_frames, m))
    coupling = np.empty((n_frames, m, m))
    ok = block_thomas(
        system.gram,
        system.marker_grams,
        system.position_matrix,
        np.ascontiguousarray(missing),
        np.ascontiguousarray(pos, dtype=np.float64),
        use_pos,
        rhs,
        known,
        wk,
        system.ridge,
        config.PIVOT_RTOL,
        out,
        coupling,
    )
    if not ok or not np.isfinite(out).all():
        raise NumericalError(
            "spacetime: the block-tridiagonal solve met a singular frame block (no markers and no prior?)"
        )
    return out


# ---------------------------------------------------------------------------------------
# Per-frame solves ("No Const", "Prior PF", boundary values, "Range PF")
# ---------------------------------------------------------------------------------------
def _masked_rhs(system: System, s: np.ndarray, valid: np.ndarray) -> np.ndarray:
    """B^T s_t with missing rows dropped: (F, M)."""
    return np.where(np.repeat(valid, 3, axis=1), s, 0.0) @ system.basis


def solve_per_frame(system: System, deltas: np.ndarray, *, use_prior: bool) -> np.ndarray:
    """Independent per-frame least squares ``min ||B w - s_t||^2 (+ alpha prior) + eps ||P_0 w||^2``.

    deltas : (F, N, 3) with NaN for missing samples (their rows are dropped; frames are
    grouped by missing pattern and each group is solved with one factorization).
    Returns (F, M).
    """
    s = flatten_deltas(deltas)
    missing = np.isnan(s[:, 0::3])
    valid = ~missing
    m = system.n_shapes
    reg = system.position_matrix if use_prior else system.ridge_matrix
    rhs = _masked_rhs(system, s, valid)
    if use_prior:
        rhs += system.prior_vector
    out = np.empty((s.shape[0], m))
    patterns, inverse = np.unique(missing, axis=0, return_inverse=True)
    inverse = inverse.ravel()
    for p, pattern in enumerate(patterns):
        frames = np.flatnonzero(inverse == p)
        mat = system.gram + reg
        if pattern.any():
            mat = mat - system.marker_grams[pattern].sum(axis=0)
        out[frames] = scipy.linalg.cho_solve(_factor(mat, system.ridge), rhs[frames].T).T
    return out


def _factor(mat: np.ndarray, ridge: float):
    """Cholesky factor of SPD ``mat``; if it is (numerically) singular, of ``mat + ridge I``."""
    for shift in (0.0, ridge):
        try:
            factor = scipy.linalg.cho_factor(mat + shift * np.eye(len(mat)))
        except (np.linalg.LinAlgError, scipy.linalg.LinAlgError):
            continue
        pivots = np.diag(factor[0]) ** 2
        if pivots.min() > config.PIVOT_RTOL * np.diag(mat).max():
            return factor
    raise NumericalError("spacetime: a per-frame system is singular even after regularization")


def solve_bounded(
    system: System,
    deltas: np.ndarray,
    lower: np.ndarray,
    upper: np.ndarray,
    *,
    use_prior: bool = False,
) -> np.ndarray:
    """Per-frame bounded least squares "Range PF": ``min ||B w - s_t||^2, lower <= w <= upper``
    (plus the prior with ``use_prior``: the boundary values of bounded movement matching).

    The shared active-set solver (``geometry.nnls.bounded_lsq_frames``), warm-started from
    the previous frame, on the normal equations (with the null-space ridge so duplicate
    shapes stay well posed); a frame with missing markers drops their Grams, and gets the
    ridge ``eps I`` if that leaves a shape unseen. Returns (F, M).
    """
    from faceretarget.geometry.nnls import bounded_lsq_frames

    s = flatten_deltas(deltas)
    missing = np.isnan(s[:, 0::3])
    rhs = _masked_rhs(system, s, ~missing)
    if use_prior:
        rhs += system.prior_vector
    gram = system.gram + (system.position_matrix if use_prior else system.ridge_matrix)
    try:
        return bounded_lsq_frames(
            gram,
            rhs,
            lower,
            upper,
            dropped=missing,
            block_grams=system.marker_grams,
            ridge=system.ridge,
        )
    except NumericalError as exc:
        raise NumericalError(
            f"spacetime: the bounded per-frame solve failed ({exc}); check for (near-)duplicate blendshapes"
        ) from None


def energy_terms(system: System, deltas: np.ndarray, weights: np.ndarray) -> dict[str, np.ndarray]:
    """Per-frame error terms of a solution, missing rows dropped.

    Returns ``velocity`` (F,) with ``velocity[t] = ||B(w_t - w_{t-1}) - (s_t - s_{t-1})||^2``
    (0 at t = 0; the paper's fig. 11 measure) and ``position`` (F,) ``||B w_t - s_t||^2``.
    One pass over the frames (:func:`._kernels.residual_energies`): ``retarget()`` reports
    them as diagnostics, with no scratch of the sequence's size.
    """
    from ._kernels import residual_energies

    s = flatten_deltas(deltas)
    w = np.ascontiguousarray(weights, dtype=np.float64)
    basis_t = np.ascontiguousarray(system.basis.T)
    position, velocity = np.empty(s.shape[0]), np.empty(s.shape[0])
    residual_energies(s, basis_t, w, velocity, position)
    return {"velocity": velocity, "position": position}
