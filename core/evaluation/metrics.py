"""Evaluation metrics, registered through the ``faceretarget_metrics`` hook.

Every metric is a :class:`faceretarget.hookspecs.Metric` whose ``description`` is its
pinned definition (the same text as the docstring of the function computing it). A
metric's ``compute(animation, case, context)`` returns a float, a mapping ``{label:
float}`` (one value per region; the harness reports it as rows ``NAME[label]``), or
``None`` when it does not apply, and then ``why_not(animation, case)`` says why (the
built-ins also record the reason in ``context["reasons"][name]``, so the harness need not
recompute). ``better`` is "lower", "higher" or "none" (descriptive, never ranked).
``context`` (from the harness) holds ``fit_s``, ``retarget_s``, ``total_s``,
``peak_memory_mib``, ``method``, a ``cache`` dict shared by the metrics of one run and
``reasons``.

Conventions shared by the definitions:

- ``X`` is the result ``animation.vertices`` and ``Y`` the ground truth
  ``case.truth.vertices``, both ``(F, V, 3)`` in world coordinates (head motion included).
- ``H`` is the target face height, ``case.target.neutral.height`` (extent along y);
  lengths are reported in **% of H** (``100 * length / H``).
- *Head frame*: dynamic metrics (velocity, acceleration, jitter, FDD, detail) map both X
  and Y into the ground truth's head frame, ``x -> R_t^T (x - t_t)`` with the truth's head
  motion ``[R_t | t_t]``, so rigid head motion is excluded, and a result that carries the
  head motion wrongly is penalized rather than excused.
- Differences in time are per frame (no division by the frame interval).
- Landmarks ``P = landmarks(X)``, ``Q = landmarks(Y)``: ``case.target.landmarks`` on X, Y.
- *Feature groups* come from the target's feature lines, by name (case-insensitive):
  a line whose name contains "lip" or "mouth" belongs to the mouth, one with "eye" or
  "lid" to an eye (side from a left/right marker in the name: "left", "_l", "l_", ...).
  When a group has lines named "inner" (the lip contact contour), only those are used.
  Inside a group, lines named with "upper"/"top" and "lower"/"bottom" give the upper and
  lower chains; otherwise the group's vertices are split at the group centroid's y on the
  target neutral (above = upper). *Closure pairs*: each upper vertex ``u`` is paired with
  the lower vertex ``l(u)`` nearest to it on the target neutral.
- *Upper face*: target vertices whose neutral y is above the midpoint between the mean y
  of the eye groups and the mean y of the mouth group.
- *Regions* (per-region errors): the target's layer masks (``TargetRig.layers``): vertex
  ``v`` is in region ``r`` when ``masks[r, v] >= 0.5``; without layers, the upper and
  lower face as defined above.
- *Fine-scale detail* (``detail_error``, ``detail_correlation``): for a displacement field
  ``d : (F, V, 3)`` on the target mesh, ``h(d) = d - S^k d`` is its high-pass, with ``S`` one
  step of uniform Laplacian smoothing ``(1 - lambda) I + lambda D^-1 A`` (k = 5, lambda = 0.5)
  in which a vertex on a boundary (eye, mouth, outer rim) averages only its two neighbours
  along that boundary, so the smooth motion of lids and lips is not mistaken for detail; and
  ``hn(d)`` is the component of ``h(d)`` along the target neutral's vertex normal (wrinkles
  are offsets along the normal; a tangential high-frequency field only slides vertices
  within the surface). The smoothing counts edges, not lengths, so it is free of the
  target's units; the cut-off is in edges, so "fine" means the finest few rings of the
  target mesh. At the built-in cases' resolutions it keeps about 97% of the synthetic
  wrinkles (wavelength about 4% of H) and leaves under 2% (RMS) of a smooth error bump 20%
  of H wide and under 1% of an affine or rotation error. It is a *fine-scale* error, not a
  wrinkle error: the high-pass also holds the sharp part of the large-scale motion (lid and
  lip contours, a jaw crease at the mouth corners). On the synthetic cases at 1,500 vertices
  that part of the truth's motion is larger than the wrinkles' (0.031% vs 0.018% of H) and
  it makes up most of every dense method's detail error (the wrinkle-free twin gives 97-99%
  of the value for the built-in dense methods). To see the wrinkles alone, compare
  against the case built without them (the detail presets' "wrinkle transfer error").
"""

from __future__ import annotations

import re
import weakref
from collections.abc import Callable, Mapping
from typing import TYPE_CHECKING, Any, TypeAlias

import numpy as np

from ..hookspecs import Metric, hookimpl
from ..model import Animation, Landmarks, TargetRig

if TYPE_CHECKING:
    import scipy.sparse as sp

    from ..cases import Case

#: The ``context`` dict of a metric's ``compute`` (the harness's timings, the shared views'
#: cache, the reasons of the metrics that did not apply), or None.
Context: TypeAlias = "dict[str, Any] | None"
#: A structural check: the reason a metric does not apply to (animation, case), or None.
Check: TypeAlias = "Callable[[Animation, Case], str | None]"

__all__ = [
    "METRICS",
    "NotApplicable",
    "RANKED_METRICS",
    "builtin_metrics",
    "closure_pairs",
    "feature_groups",
    "upper_face_vertices",
    "velocity_error_per_frame",
    "landmark_velocity_curve",
    "per_vertex_error",
    "regions",
    "high_pass",
    "detail_smoothing_operator",
    "normal_detail",
]

#: Laplacian smoothing used as the low-pass of ``detail_error`` and ``detail_correlation``:
#: steps and step size of ``x <- x + lambda * (mean of neighbours - x)`` (uniform weights;
#: boundary vertices average their boundary neighbours only).
DETAIL_SMOOTHING_STEPS = 5
DETAIL_SMOOTHING_LAMBDA = 0.5
#: |w| below this counts as an inactive weight for ``weight_sparsity``.
SPARSITY_THRESHOLD = 0.01
#: Weights outside their range by more than this count as outside.
RANGE_TOLERANCE = 1e-6
#: Mask value from which a vertex belongs to a layer region.
REGION_MASK_THRESHOLD = 0.5

PERCENT = "% face height"


class NotApplicable(Exception):
    """Raised inside a metric when it cannot be computed; the message is the reason.

    ``compute`` turns it into ``None`` and records the reason in ``context["reasons"]``.
    """


# ---------------------------------------------------------------------------------------
# Shared views of one (animation, case) pair, cached in context["cache"]
# ---------------------------------------------------------------------------------------
class _Views:
    """Float64 arrays derived once per (animation, case) and shared by the metrics."""

    def __init__(self, animation: Animation, case: Case) -> None:
        self.animation = animation
        self.case = case
        self.target = case.target
        self.height = float(case.target.neutral.height) or 1.0
        self._cache: dict[str, Any] = {}

    def get(self, key: str, make: Callable[[], Any]) -> Any:
        if key not in self._cache:
            self._cache[key] = make()
        return self._cache[key]

    @property
    def truth(self) -> Animation:
        """The case's ground truth (the metrics that read it need it: ``_needs_truth``)."""
        truth = self.case.truth
        assert truth is not None  # _needs_truth ran before any metric that reads it
        return truth

    @property
    def landmarks(self) -> Landmarks:
        """The target's landmarks (the metrics that read them need them: ``_needs_landmarks``)."""
        landmarks = self.target.landmarks
        assert landmarks is not None  # _needs_landmarks ran before any metric that reads them
        return landmarks

    @property
    def X(self) -> np.ndarray:
        return self.get("X", lambda: np.asarray(self.animation.vertices, dtype=np.float64))

    @property
    def Y(self) -> np.ndarray:
        return self.get("Y", lambda: np.asarray(self.truth.vertices, dtype=np.float64))

    @property
    def X_local(self) -> np.ndarray:
        return self.get("X_local", lambda: to_head_frame(self.X, self.truth.head_motion))

    @property
    def Y_local(self) -> np.ndarray:
        return self.get("Y_local", lambda: to_head_frame(self.Y, self.truth.head_motion))

    @property
    def distances(self) -> np.ndarray:
        """(F, V) ||X - Y|| in % of H."""
        return self.get(
            "distances", lambda: 100.0 * np.linalg.norm(self.X - self.Y, axis=-1) / self.height
        )


class _TruthCache:
    """Arrays derived from a ground-truth animation alone, shared by every run scored
    against it (compare scores each method on the same truth; a preset scores several).
    Keyed by the animation's identity and dropped with it (animations are not modified)."""

    def __init__(self) -> None:
        self._items: dict[int, tuple[weakref.ref, dict[str, Any]]] = {}

    def get(self, truth: Animation, key: str, make: Callable[[], Any]) -> Any:
        entry = self._items.get(id(truth))
        if entry is None or entry[0]() is not truth:
            ident = id(truth)
            entry = (weakref.ref(truth, lambda _: self._items.pop(ident, None)), {})
            self._items[ident] = entry
        values = entry[1]
        if key not in values:
            values[key] = make()
        return values[key]


_TRUTH = _TruthCache()


def _views(animation: Animation, case: Case, context: Context) -> _Views:
    if context is None:
        return _Views(animation, case)
    cache = context.setdefault("cache", {})
    key = (id(animation), id(case))
    views = cache.get(key)
    if views is None:
        views = cache[key] = _Views(animation, case)
    return views


def to_head_frame(vertices: np.ndarray, head_motion: np.ndarray | None) -> np.ndarray:
    """``vertices : (F, V, 3)`` mapped by the inverse of ``head_motion : (F, 4, 4)``."""
    if head_motion is None:
        return vertices
    rot = np.asarray(head_motion[:, :3, :3], dtype=np.float64)
    trans = np.asarray(head_motion[:, None, :3, 3], dtype=np.float64)
    return np.matmul(vertices - trans, rot)  # row vectors: (x - t)^T R = (R^T (x - t))^T


# ---------------------------------------------------------------------------------------
# Geometry helpers (plain arrays; also used by the report)
# ---------------------------------------------------------------------------------------
_LEFT = re.compile(r"(left|(^|[_\-. ])l($|[_\-. ]))", re.I)
_RIGHT = re.compile(r"(right|(^|[_\-. ])r($|[_\-. ]))", re.I)


def _side(name: str) -> str:
    if _LEFT.search(name) and not _RIGHT.search(name):
        return "left"
    if _RIGHT.search(name) and not _LEFT.search(name):
        return "right"
    return ""


def feature_groups(
    feature_lines: Mapping[str, np.ndarray], neutral: np.ndarray
) -> dict[str, tuple[np.ndarray, np.ndarray]]:
    """Upper and lower vertex chains of the mouth and each eye.

    feature_lines : name -> (L,) vertex ids; neutral : (V, 3) target neutral vertices.
    Returns ``{"mouth" | "eye_left" | "eye_right" | "eye": (upper ids, lower ids)}`` for
    the groups found (see the module docstring for the naming rules).
    """
    members: dict[str, dict[str, list[tuple[str, np.ndarray]]]] = {}
    for name, chain in feature_lines.items():
        low = name.lower()
        if "lip" in low or "mouth" in low:
            group = "mouth"
        elif "eye" in low or "lid" in low:
            side = _side(name)
            group = f"eye_{side}" if side else "eye"
        else:
            continue
        part = (
            "upper"
            if ("upper" in low or "top" in low)
            else "lower"
            if ("lower" in low or "bottom" in low)
            else "any"
        )
        members.setdefault(group, {}).setdefault(part, []).append(
            (low, np.asarray(chain, dtype=np.int64))
        )
    out = {}
    for group, named in members.items():
        inner = any("inner" in low for chains in named.values() for low, _ in chains)
        parts = {
            k: [c for low, c in chains if "inner" in low or not inner]
            for k, chains in named.items()
        }
        if parts.get("upper") and parts.get("lower"):
            upper = np.unique(np.concatenate(parts["upper"]))
            lower = np.unique(np.concatenate(parts["lower"]))
        else:
            ids = np.unique(np.concatenate([c for chains in parts.values() for c in chains]))
            y = neutral[ids, 1]
            centre = y.mean()
            upper, lower = ids[y > centre], ids[y <= centre]
        upper = np.setdiff1d(upper, lower) if upper.size > 1 else upper
        if upper.size and lower.size:
            out[group] = (upper, lower)
    return out


def closure_pairs(
    upper: np.ndarray, lower: np.ndarray, neutral: np.ndarray
) -> tuple[np.ndarray, np.ndarray]:
    """Pair each upper vertex with the lower vertex nearest to it on ``neutral : (V, 3)``.

    Returns ``(u, l)`` index arrays of equal length.
    """
    d = np.linalg.norm(neutral[upper][:, None, :] - neutral[lower][None, :, :], axis=-1)
    return upper, lower[np.argmin(d, axis=1)]


def opening(vertices: np.ndarray, pairs: tuple[np.ndarray, np.ndarray]) -> np.ndarray:
    """(F,) mean over pairs of ``||x_u - x_l(u)||`` for ``vertices : (F, V, 3)``."""
    u, l = pairs
    return np.linalg.norm(vertices[:, u] - vertices[:, l], axis=-1).mean(axis=1)


_NO_UPPER_FACE = "cannot find the upper face: the target needs eye and mouth feature lines"


def upper_face_vertices(
    groups: Mapping[str, tuple[np.ndarray, np.ndarray]], neutral: np.ndarray
) -> np.ndarray | None:
    """Vertex ids above the midpoint between eyes and mouth (None without both groups)."""
    eyes = [np.concatenate(v) for k, v in groups.items() if k.startswith("eye")]
    if "mouth" not in groups or not eyes:
        return None
    y_eye = neutral[np.concatenate(eyes), 1].mean()
    y_mouth = neutral[np.concatenate(groups["mouth"]), 1].mean()
    if y_eye <= y_mouth:
        return None
    return np.flatnonzero(neutral[:, 1] > 0.5 * (y_eye + y_mouth))


def regions(target: TargetRig) -> dict[str, np.ndarray]:
    """Region name -> vertex ids (layer masks, else upper / lower face; may be empty)."""
    if target.layers is not None:
        masks = np.asarray(target.layers.masks)
        out = {
            name: np.flatnonzero(masks[r] >= REGION_MASK_THRESHOLD)
            for r, name in enumerate(target.layers.region_names)
        }
        return {k: v for k, v in out.items() if v.size}
    neutral = np.asarray(target.neutral.vertices)
    upper = upper_face_vertices(feature_groups(target.feature_lines, neutral), neutral)
    if upper is None or upper.size == 0 or upper.size == neutral.shape[0]:
        return {}
    return {"upper face": upper, "lower face": np.setdiff1d(np.arange(neutral.shape[0]), upper)}


def per_vertex_error(result: np.ndarray, truth: np.ndarray, height: float) -> np.ndarray:
    """(V,) mean over frames of ``||x - y||`` in % of ``height``."""
    return (
        100.0
        * np.linalg.norm(np.asarray(result, np.float64) - truth, axis=-1).mean(axis=0)
        / height
    )


def velocity_error_per_frame(
    result_points: np.ndarray, truth_points: np.ndarray, height: float
) -> np.ndarray:
    """(F-1,) ``sum_i ||(p_{t+1,i} - p_{t,i}) - (q_{t+1,i} - q_{t,i})||^2 / H^2``.

    result_points, truth_points : (F, N, 3) corresponding points (landmarks).
    """
    diff = np.diff(result_points, axis=0) - np.diff(truth_points, axis=0)
    return np.einsum("fnd,fnd->f", diff, diff) / height**2


def landmark_velocity_curve(
    vertices: np.ndarray, truth: Animation, target: TargetRig
) -> np.ndarray:
    """(F-1,) :func:`velocity_error_per_frame` of ``target.landmarks`` on ``vertices : (F, V, 3)``
    against ``truth`` (an Animation), both in the truth's head frame, relative to the face height.

    Landmarks are affine combinations of vertices, so they are sampled first and then
    mapped to the head frame.
    """
    lm, tri = target.landmarks, target.neutral.triangles
    assert lm is not None  # the callers check that the target has landmarks
    p = to_head_frame(lm.positions(np.asarray(vertices, dtype=np.float64), tri), truth.head_motion)
    q = to_head_frame(
        lm.positions(np.asarray(truth.vertices, dtype=np.float64), tri), truth.head_motion
    )
    return velocity_error_per_frame(p, q, float(target.neutral.height) or 1.0)


def second_difference(x: np.ndarray) -> np.ndarray:
    """(F-2, ...) ``x_{t+1} - 2 x_t + x_{t-1}``."""
    return x[2:] - 2.0 * x[1:-1] + x[:-2]


def smoothing_operator(
    n_vertices: int, triangles: np.ndarray, lam: float = DETAIL_SMOOTHING_LAMBDA
) -> sp.csr_matrix:
    """Sparse ``S = (1 - lam) I + lam D^-1 A`` (one uniform Laplacian smoothing step; isolated vertices stay)."""
    import scipy.sparse as sp

    from ..geometry.laplacian import umbrella_operator

    neighbours = umbrella_operator(np.asarray(triangles), n_vertices)
    has = np.diff(neighbours.indptr) > 0
    return (sp.diags(np.where(has, 1.0 - lam, 1.0)) + lam * neighbours).tocsr()


def detail_smoothing_operator(
    n_vertices: int, triangles: np.ndarray, lam: float = DETAIL_SMOOTHING_LAMBDA
) -> sp.csr_matrix:
    """Sparse ``S`` of the detail metrics: :func:`smoothing_operator`, except that a vertex on a
    boundary edge averages only its neighbours along boundary edges (a smooth field along an
    eye, mouth or outer rim stays nearly smooth, as it would in the interior).

    Rows sum to 1 (constants pass unchanged); the weights count edges, never lengths, so the
    operator is the same in any unit.
    """
    import scipy.sparse as sp

    from ..geometry.mesh_ops import boundary_edges

    interior = smoothing_operator(n_vertices, triangles, lam)
    edges = boundary_edges(np.asarray(triangles))
    if len(edges) == 0:
        return interior
    rows = np.concatenate([edges[:, 0], edges[:, 1]])
    cols = np.concatenate([edges[:, 1], edges[:, 0]])
    ring = sp.csr_matrix((np.ones(rows.size), (rows, cols)), shape=(n_vertices, n_vertices))
    ring.sum_duplicates()
    ring.data[:] = 1.0  # an edge listed twice still counts once
    degree = np.asarray(ring.sum(axis=1)).ravel()
    on = degree > 0
    along = sp.diags(np.where(on, 1.0 / np.maximum(degree, 1.0), 0.0)) @ ring
    boundary = (sp.diags(np.full(n_vertices, 1.0 - lam)) + lam * along).tocsr()
    keep = sp.diags((~on).astype(np.float64))
    return (keep @ interior + sp.diags(on.astype(np.float64)) @ boundary).tocsr()


def normal_detail(
    displacements: np.ndarray,
    triangles: np.ndarray,
    neutral: np.ndarray,
    steps: int = DETAIL_SMOOTHING_STEPS,
) -> np.ndarray:
    """(F, V) ``hn(d)``: the high-pass of ``displacements : (F, V, 3)`` by ``steps`` steps of
    :func:`detail_smoothing_operator` on the mesh ``(neutral (V, 3), triangles)``, along the
    neutral's unit vertex normals (the module docstring's *fine-scale detail*)."""
    from ..geometry.mesh_ops import vertex_normals

    neutral = np.asarray(neutral, dtype=np.float64)
    smoother = detail_smoothing_operator(neutral.shape[0], np.asarray(triangles))
    normals = vertex_normals(neutral, np.asarray(triangles))
    return np.einsum(
        "fvd,vd->fv",
        high_pass(np.asarray(displacements, dtype=np.float64), smoother, steps),
        normals,
    )


def high_pass(
    displacements: np.ndarray, smoother: sp.spmatrix, steps: int = DETAIL_SMOOTHING_STEPS
) -> np.ndarray:
    """``d - S^steps d`` for ``displacements : (F, V, 3)`` with sparse ``smoother : (V, V)``."""
    f, v, _ = displacements.shape
    flat = np.moveaxis(displacements, 1, 0).reshape(v, f * 3)
    low = flat
    for _ in range(steps):
        low = smoother @ low
    return np.moveaxis((flat - low).reshape(v, f, 3), 0, 1)


# ---------------------------------------------------------------------------------------
# Applicability checks: each returns None or the reason
# ---------------------------------------------------------------------------------------
def _needs_truth(animation: Animation, case: Case) -> str | None:
    truth = getattr(case, "truth", None)
    if truth is None:
        return "the case has no ground truth"
    if tuple(np.shape(truth.vertices)) != tuple(np.shape(animation.vertices)):
        return f"result shape {np.shape(animation.vertices)} differs from the ground truth's {np.shape(truth.vertices)}"
    return None


def _needs_landmarks(animation: Animation, case: Case) -> str | None:
    if case.target.landmarks is None:
        return "the target has no landmarks"
    return None


def _frames(n: int) -> Check:
    def check(animation: Animation, case: Case) -> str | None:
        if animation.n_frames < n:
            return f"needs at least {n} frames; the result has {animation.n_frames}"
        return None

    return check


def _needs_weights(animation: Animation, case: Case) -> str | None:
    if animation.weights is None:
        return "the method outputs vertices, not blendshape weights"
    return None


def _needs_truth_weights(animation: Animation, case: Case) -> str | None:
    truth = getattr(case, "truth", None)
    if truth is None or truth.weights is None:
        return "the ground truth has no blendshape weights"
    if not set(animation.weight_names) & set(truth.weight_names):
        return "the result's weights name no shape of the ground truth's"
    return None


def _groups(case: Case) -> dict[str, tuple[np.ndarray, np.ndarray]]:
    return feature_groups(case.target.feature_lines, np.asarray(case.target.neutral.vertices))


def _needs_group(kind: str) -> Check:
    def check(animation: Animation, case: Case) -> str | None:
        found = [g for g in _groups(case) if g.startswith(kind)]
        if not found:
            return f"the target has no {kind} feature lines (names containing {'lip/mouth' if kind == 'mouth' else 'eye/lid'})"
        return None

    return check


def _needs_upper_face(animation: Animation, case: Case) -> str | None:
    neutral = np.asarray(case.target.neutral.vertices)
    upper = upper_face_vertices(_groups(case), neutral)
    if upper is None or upper.size == 0:
        return _NO_UPPER_FACE
    return None


def _needs_regions(animation: Animation, case: Case) -> str | None:
    if not regions(case.target):
        return "the target has neither layer region masks nor eye and mouth feature lines"
    return None


def _needs_triangles(animation: Animation, case: Case) -> str | None:
    if case.target.neutral.n_vertices != animation.vertices.shape[1]:
        return "the result is not on the target's topology"
    return None


# ---------------------------------------------------------------------------------------
# The metrics (docstring = pinned definition)
# ---------------------------------------------------------------------------------------
def vertex_error_mean(v: _Views) -> float:
    """Mean over frames and vertices of ||X - Y||, in % of H."""
    return float(v.distances.mean())


def vertex_error_rms(v: _Views) -> float:
    """sqrt(mean over frames and vertices of ||X - Y||^2), in % of H (the fidelity check's measure)."""
    return float(np.sqrt(np.mean(v.distances**2)))


def vertex_error_max(v: _Views) -> float:
    """Max over frames and vertices of ||X - Y||, in % of H."""
    return float(v.distances.max())


def vertex_error_region(v: _Views) -> dict[str, float]:
    """Per region (layer masks >= 0.5, else upper / lower face): mean over frames and the region's vertices of ||X - Y||, in % of H."""
    return {name: float(v.distances[:, ids].mean()) for name, ids in regions(v.target).items()}


def _landmark_distances(v: _Views) -> np.ndarray:
    def make() -> np.ndarray:
        lm, tri = v.landmarks, v.target.neutral.triangles
        return (
            100.0
            * np.linalg.norm(lm.positions(v.X, tri) - lm.positions(v.Y, tri), axis=-1)
            / v.height
        )

    return v.get("landmark_distances", make)


def marker_error_mean(v: _Views) -> float:
    """Mean over frames and target landmarks of ||P - Q|| (landmark positions on X and Y), in % of H."""
    return float(_landmark_distances(v).mean())


def marker_error_max(v: _Views) -> float:
    """Max over frames and target landmarks of ||P - Q||, in % of H."""
    return float(_landmark_distances(v).max())


def velocity_error(v: _Views) -> float:
    """Seol et al. 2012 fig. 11: ||D P - D Q||_F^2 / H^2 summed over frames, where D is the forward difference in time and P, Q the landmarks of X and Y in the head frame (the ground truth's landmarks stand in for the paper's warped source markers). Dimensionless."""
    return float(landmark_velocity_curve(v.X, v.truth, v.target).sum())


def acceleration_error(v: _Views) -> float:
    """RMS over frames t = 1..F-2 and vertices of ||A X - A Y|| in the head frame, A x_t = x_{t+1} - 2 x_t + x_{t-1}, in % of H per frame^2."""
    diff = second_difference(v.X_local) - second_difference(v.Y_local)
    return float(100.0 * np.sqrt(np.mean(np.einsum("fvd,fvd->fv", diff, diff))) / v.height)


def jitter_excess(v: _Views) -> float:
    """Mean over frames and vertices of ||A X|| minus the same of ||A Y|| (head frame, A the second difference), in % of H per frame^2; > 0 means the result shakes more than the truth."""
    ax = np.linalg.norm(second_difference(v.X_local), axis=-1).mean()
    ay = np.linalg.norm(second_difference(v.Y_local), axis=-1).mean()
    return float(100.0 * (ax - ay) / v.height)


def _closure_error(v: _Views, kind: str) -> float:
    neutral = np.asarray(v.target.neutral.vertices)
    errors = []
    for name, (upper, lower) in feature_groups(v.target.feature_lines, neutral).items():
        if name.startswith(kind):
            pairs = closure_pairs(upper, lower, neutral)
            errors.append(np.abs(opening(v.X, pairs) - opening(v.Y, pairs)).mean())
    return float(100.0 * np.mean(errors) / v.height)


def lip_closure_error(v: _Views) -> float:
    """Mean over frames of |d_X(t) - d_Y(t)|, d(t) = mean over closure pairs (u, l(u)) of the mouth of ||x_u - x_l(u)||, in % of H."""
    return _closure_error(v, "mouth")


def eyelid_closure_error(v: _Views) -> float:
    """Mean over eyes and frames of |d_X(t) - d_Y(t)|, d(t) = mean over the eye's closure pairs (u, l(u)) of ||x_u - x_l(u)||, in % of H."""
    return _closure_error(v, "eye")


def _mouth_vertices(v: _Views) -> np.ndarray:
    groups = feature_groups(v.target.feature_lines, np.asarray(v.target.neutral.vertices))
    return np.unique(np.concatenate(groups["mouth"]))


def lve(v: _Views) -> float:
    """Lip vertex error: for each frame the max over lip vertices (the mouth feature-line vertices) of the Euclidean distance ||X - Y||, averaged over frames, in % of H (FaceFormer's code uses the squared distance; here it is the distance)."""
    return float(v.distances[:, _mouth_vertices(v)].max(axis=1).mean())


def _motion_std(
    local: np.ndarray, neutral: np.ndarray, ids: np.ndarray, squared: bool
) -> np.ndarray:
    disp = local[:, ids] - neutral[ids]
    mag = np.einsum("fvd,fvd->fv", disp, disp)
    return (mag if squared else np.sqrt(mag)).std(axis=0)


def _upper_face(v: _Views, neutral: np.ndarray) -> np.ndarray:
    """The upper-face vertex ids of ``v``'s target (:func:`_needs_upper_face` keeps cases
    without them away from the metrics that use this)."""
    ids = upper_face_vertices(_groups(v.case), neutral)
    if ids is None:
        from ..errors import InputError

        raise InputError(_NO_UPPER_FACE)
    return ids


def fdd(v: _Views) -> float:
    """Upper-face dynamics deviation as in the speech-driven literature (CodeTalker, Xing et al. 2023): for each upper-face vertex, the std over time of its squared displacement magnitude ||x_t - x_neutral||^2 (head frame); the mean of it over the upper face for Y minus the same for X, in (% of H)^2. Signed: > 0 means the result's upper face moves less than the truth's."""
    neutral = np.asarray(v.target.neutral.vertices, dtype=np.float64)
    ids = _upper_face(v, neutral)
    sy = _motion_std(v.Y_local, neutral, ids, squared=True).mean()
    sx = _motion_std(v.X_local, neutral, ids, squared=True).mean()
    return float((sy - sx) * (100.0 / v.height) ** 2)


def fdd_abs(v: _Views) -> float:
    """Upper-face dynamics deviation, absolute variant: for each upper-face vertex the std over time of its displacement magnitude ||x_t - x_neutral|| (head frame, not squared), the absolute difference between Y and X per vertex, averaged over the upper face, in % of H."""
    neutral = np.asarray(v.target.neutral.vertices, dtype=np.float64)
    ids = _upper_face(v, neutral)
    diff = _motion_std(v.Y_local, neutral, ids, squared=False) - _motion_std(
        v.X_local, neutral, ids, squared=False
    )
    return float(100.0 * np.abs(diff).mean() / v.height)


def _normal_details(v: _Views) -> tuple[np.ndarray, np.ndarray]:
    """(hn(X - N), hn(Y - N)), each (F, V), in the head frame: the first cached per run, the
    second per truth and target mesh (the same for every run scored against them)."""
    import hashlib

    neutral = np.ascontiguousarray(v.target.neutral.vertices, dtype=np.float64)
    triangles = np.ascontiguousarray(v.target.neutral.triangles)

    def of(local: Callable[[], np.ndarray]) -> Callable[[], np.ndarray]:
        return lambda: normal_detail(local() - neutral, triangles, neutral)

    mesh = hashlib.blake2b(neutral.tobytes() + triangles.tobytes(), digest_size=16).hexdigest()
    truth = _TRUTH.get(v.truth, f"normal_detail {mesh}", of(lambda: v.Y_local))
    return v.get("normal_details", of(lambda: v.X_local)), truth


def detail_error(v: _Views) -> float:
    """Fine-scale (wrinkle) error: sqrt(mean over frames and vertices of (hn(X - N) - hn(Y - N))^2) in the head frame, in % of H, where N is the target neutral and hn(d) the component along the neutral's vertex normal of the high-pass h(d) = d - S^5 d, S = 0.5 I + 0.5 D^-1 A one step of uniform Laplacian smoothing on the target mesh (a boundary vertex averages its boundary neighbours only). Blind to smooth (low-frequency) and tangential errors; dropping the truth's wrinkles costs their whole high-pass."""
    hx, hy = _normal_details(v)
    return float(100.0 * np.sqrt(np.mean((hx - hy) ** 2)) / v.height)


def detail_correlation(v: _Views) -> float:
    """Detail preservation: Pearson correlation, pooled over frames and vertices, of hn(X - N) and hn(Y - N) (the fine-scale normal motion of detail_error: the high-pass by 5 steps of uniform Laplacian smoothing on the target mesh, along the neutral's normals, head frame). 1 = the truth's fine-scale motion reproduced up to a factor; 0 = none of it."""
    hx, hy = _normal_details(v)
    hx, hy = hx.ravel(), hy.ravel()
    sx, sy = hx.std(), hy.std()
    if sy <= 1e-12 * v.height:
        raise NotApplicable("the ground truth has no fine-scale motion to preserve")
    if sx == 0.0:
        return 0.0
    return float(np.mean((hx - hx.mean()) * (hy - hy.mean())) / (sx * sy))


def _weights(v: _Views) -> np.ndarray:
    return np.asarray(v.animation.weights, dtype=np.float64)


def weight_min(v: _Views) -> float:
    """Smallest blendshape weight over frames and shapes (descriptive, not ranked)."""
    return float(_weights(v).min())


def weight_max(v: _Views) -> float:
    """Largest blendshape weight over frames and shapes (descriptive, not ranked)."""
    return float(_weights(v).max())


def weight_outside_share(v: _Views) -> float:
    """Share (0..1) of (frame, shape) weights outside their artist range by more than 1e-6: the rig's bounds when the animation's rig has them, else [0, 1]."""
    w = _weights(v)
    rig = v.animation.rig
    if rig is not None and rig.bounds is not None and rig.n_shapes == w.shape[1]:
        lo, hi = np.asarray(rig.bounds)[:, 0], np.asarray(rig.bounds)[:, 1]
    else:
        lo, hi = np.zeros(w.shape[1]), np.ones(w.shape[1])
    return float(np.mean((w < lo - RANGE_TOLERANCE) | (w > hi + RANGE_TOLERANCE)))


def weight_sparsity(v: _Views) -> float:
    """Share (0..1) of (frame, shape) weights with |w| < 0.01 (inactive shapes); higher = sparser, easier to edit."""
    return float(np.mean(np.abs(_weights(v)) < SPARSITY_THRESHOLD))


def weight_error_rms(v: _Views) -> float:
    """RMS over frames and the shapes named in both the result and the ground truth of w_result - w_truth (weights are unitless)."""
    truth = v.truth
    common = [n for n in v.animation.weight_names if n in truth.weight_names]
    wr = _weights(v)[:, [v.animation.weight_names.index(n) for n in common]]
    wt = np.asarray(truth.weights, dtype=np.float64)[
        :, [truth.weight_names.index(n) for n in common]
    ]
    return float(np.sqrt(np.mean((wr - wt) ** 2)))


def _from_context(key: str) -> Callable[[_Views, Context], float]:
    def compute(v: _Views, context: Context) -> float:
        value = (context or {}).get(key)
        if value is None:
            raise NotApplicable(
                f"not measured: run through faceretarget.evaluation.compare, which records {key!r}"
            )
        return float(value)

    return compute


def time_fit(v: _Views, context: Context) -> float:
    """Wall-clock seconds of fit(source, target), measured by the harness."""
    return _from_context("fit_s")(v, context)


def time_retarget(v: _Views, context: Context) -> float:
    """Wall-clock seconds of retarget(source), measured by the harness."""
    return _from_context("retarget_s")(v, context)


def time_total(v: _Views, context: Context) -> float:
    """Wall-clock seconds of fit + retarget, measured by the harness."""
    return _from_context("total_s")(v, context)


def peak_memory(v: _Views, context: Context) -> float:
    """Peak traced memory (tracemalloc: Python and numpy allocations) during fit + retarget, in MiB."""
    return _from_context("peak_memory_mib")(v, context)


# name, function, unit, better, checks
_TABLE: list[tuple[Callable, str, str, tuple]] = [
    (vertex_error_mean, PERCENT, "lower", (_needs_truth,)),
    (vertex_error_rms, PERCENT, "lower", (_needs_truth,)),
    (vertex_error_max, PERCENT, "lower", (_needs_truth,)),
    (vertex_error_region, PERCENT, "lower", (_needs_truth, _needs_regions)),
    (marker_error_mean, PERCENT, "lower", (_needs_truth, _needs_landmarks)),
    (marker_error_max, PERCENT, "lower", (_needs_truth, _needs_landmarks)),
    (velocity_error, "÷ H^2", "lower", (_needs_truth, _needs_landmarks, _frames(2))),
    (acceleration_error, "% face height/frame^2", "lower", (_needs_truth, _frames(3))),
    (jitter_excess, "% face height/frame^2", "lower", (_needs_truth, _frames(3))),
    (lip_closure_error, PERCENT, "lower", (_needs_truth, _needs_group("mouth"))),
    (eyelid_closure_error, PERCENT, "lower", (_needs_truth, _needs_group("eye"))),
    (lve, PERCENT, "lower", (_needs_truth, _needs_group("mouth"))),
    (fdd, "(% face height)^2", "none", (_needs_truth, _needs_upper_face, _frames(2))),
    (fdd_abs, PERCENT, "lower", (_needs_truth, _needs_upper_face, _frames(2))),
    (detail_error, PERCENT, "lower", (_needs_truth, _needs_triangles)),
    (detail_correlation, "Pearson r", "higher", (_needs_truth, _needs_triangles)),
    (weight_min, "weight", "none", (_needs_weights,)),
    (weight_max, "weight", "none", (_needs_weights,)),
    (weight_outside_share, "share", "lower", (_needs_weights,)),
    (weight_sparsity, "share", "higher", (_needs_weights,)),
    (weight_error_rms, "weight", "lower", (_needs_weights, _needs_truth_weights)),
    (time_fit, "s", "lower", ()),
    (time_retarget, "s", "lower", ()),
    (time_total, "s", "lower", ()),
    (peak_memory, "MiB", "lower", ()),
]

#: Metrics that enter the default ranking (accuracy and motion fidelity).
RANKED_METRICS = (
    "vertex_error_rms",
    "vertex_error_max",
    "marker_error_mean",
    "velocity_error",
    "acceleration_error",
    "lip_closure_error",
    "eyelid_closure_error",
    "lve",
    "fdd_abs",
    "detail_error",
    "detail_correlation",
)

_CONTEXT_METRICS = {time_fit, time_retarget, time_total, peak_memory}


def _make(fn: Callable, unit: str, better: str, checks: tuple) -> Metric:
    name = fn.__name__

    def structural(animation: Animation, case: Case) -> str | None:
        for check in checks:
            reason = check(animation, case)
            if reason:
                return reason
        return None

    def compute(
        animation: Animation, case: Case, context: Context = None
    ) -> float | dict[str, float] | None:
        reason = structural(animation, case)
        if reason is None:
            views = _views(animation, case, context)
            try:
                return fn(views, context) if fn in _CONTEXT_METRICS else fn(views)
            except NotApplicable as exc:
                reason = str(exc)
        if context is not None:
            context.setdefault("reasons", {})[name] = reason
        return None

    def why_not(animation: Animation, case: Case) -> str | None:
        reason = structural(animation, case)
        if reason is None:
            context: dict = {}
            if compute(animation, case, context) is None:
                reason = context["reasons"][name]
        return reason

    description = " ".join((fn.__doc__ or "").split())
    return Metric(
        name=fn.__name__,
        compute=compute,
        description=description,
        better=better,
        unit=unit,
        why_not=why_not,
    )


def builtin_metrics() -> list[Metric]:
    """The built-in metrics, in report order."""
    return [_make(*row) for row in _TABLE]


METRICS = {m.name: m for m in builtin_metrics()}


@hookimpl
def faceretarget_metrics() -> list[Metric]:
    return builtin_metrics()
