"""Numerical thresholds and environment settings, in one place.

Modules import the constants from here rather than hard-coding them, so a
threshold is documented and changed once.
"""

from __future__ import annotations

import os

#: Triangles whose area is below this fraction of the mean triangle area count as
#: degenerate (zero-area) for methods that need a well-defined triangle frame.
DEGENERATE_AREA_RATIO = 1e-12

#: Relative tolerance used to call a matrix rank deficient (times its largest singular value).
RANK_RTOL = 1e-10

#: Tikhonov term added (relative to the trace / size) when a least-squares system is
#: rank deficient (duplicate blendshapes, coincident RBF centres).
RIDGE_EPS = 1e-9

#: A Cholesky pivot at or below this fraction of the matrix's largest diagonal entry counts
#: as (numerically) singular: the system then gets the fallback ridge (``RIDGE_EPS``-sized;
#: spacetime's frame blocks with unseen shapes, ``geometry.nnls.bounded_lsq_frames``).
PIVOT_RTOL = 1e-13

#: Smoothing many frames through the column space of their displacements
#: (``geometry.smoothing.SmoothedDisplacements``): the fewest basis rows whose discarded
#: eigenvalues sum to at most ``LOW_RANK_TOL^2`` of their total, i.e. a truncation error of
#: at most ``LOW_RANK_TOL`` of the displacements' Frobenius norm over all frames together
#: (one frame up to ~2x that of its own). The coating's test holds the bases' smoothed
#: displacements within 2e-6 of a float64 smoothing; below ~1e-7 the rank starts to follow
#: the float32 rounding of the stored displacements (1e-9: 71 of 120 rows instead of 29).
LOW_RANK_TOL = 1e-6

#: The low-rank path is taken only when it smooths at most this share of the ``3C``
#: coordinate rows (its float64 rows then take no more memory than the float32 input),
#: and for at most ``LOW_RANK_MAX_ROWS`` rows (the ``(3C)^2`` eigenproblem: 750 rows for the
#: coating's default 250 candidates).
LOW_RANK_MAX_SHARE = 0.5
LOW_RANK_MAX_ROWS = 1500

#: Largest temporary of one step of the chunked loops that use it (the coating fit's
#: candidate frames, the deformation transfer's gradient blocks): glibc serves blocks of
#: 32 MiB and more from fresh pages every time (the kernel zeroes them: 18-23 ms to allocate
#: and fill 59 MiB on the project's machine), smaller ones from memory freed by the step
#: before (1.2-2.5 ms for 29 MiB).
SCRATCH_BLOCK_BYTES = 24 * 2**20


def scratch_items(item_bytes: int) -> int:
    """How many items of ``item_bytes`` one step of such a loop takes (at least one)."""
    return max(1, SCRATCH_BLOCK_BYTES // max(1, int(item_bytes)))


#: Largest ``[deltas; neutral]`` matrix a :class:`~faceretarget.model.BlendshapeRig` keeps
#: beside its deltas so that evaluating weights is one matrix product with no separate pass
#: adding the neutral (300 x 9,409 vertices: 17 -> 14 ms); a larger rig adds the neutral
#: inside the product instead (its deltas are not copied).
RIG_AFFINE_MAX_BYTES = 128 * 2**20


#: Variables from which ``geometry.banded_qp.nonneg_qp_block_tridiagonal`` factors its
#: steps by blocks (numba). Below, LAPACK's banded Cholesky takes about as long and a call
#: compiles nothing (the block kernels compile for ~1 s); the coating edit's 28-basis knot
#: problems ran as fast either way at 3,640 variables, 1.5x faster by blocks at 11,200.
BLOCK_QP_MIN_VARIABLES = 8192


#: Head-motion estimation (``geometry.head_motion``): rigidity weights ``1 / (eps^2 + m_i^2)``
#: of the markers, ``m_i`` = RMS displacement of marker i over the expression basis, with
#: ``eps`` this fraction of the face size (RMS radius of the neutral markers; 0.02 = 1.2 mm
#: on a human face). Smaller trusts the stillest markers more (less leakage of rig mismatch
#: into the head motion, more marker noise); measured on the ICT pairs 0.01-0.02 is best.
HEAD_MOTION_RIGIDITY = 0.02

#: Head-motion significance gate: the fitted rigid motion is kept only if, over some
#: ``HEAD_MOTION_WINDOW`` consecutive frames, it reduces the weighted marker residual left by
#: the expressions by more than this many times the residual that remains (plus the noise
#: floor below); otherwise the head motion is exactly the identity. Measured with
#: spacetime's shapes at the markers: sources without head motion 0.2-1.5 on animated
#: shots (synthetic, ICT, ICT with transferred expressions, cross_rig seeds 0-3), up to 2.3
#: with one expression held at full strength (cheekPuff, or mouthClose + jawOpen, on the
#: transferred ICT pair); real head motion 13-18 at 0.25 degrees, 50-70 at 0.5, 200-270 at
#: 1, over 20,000 at 10 (largest angle, smooth motion over the shot); a 20-frame yaw turn 8
#: at 1 degree, 30 at 2, 66 at 3. 20 leaves a factor 8 over the worst source without head
#: motion measured (real pairs mismatch more than these cases: an invented head wobble is
#: re-applied to the target, a missed half-degree is not).
HEAD_MOTION_SIGNIFICANCE = 20.0

#: Frames over which the head-motion gate sums (the largest ratio over any this many
#: consecutive frames decides; the whole shot if shorter): one second at 30 fps, so a short
#: head turn in a long still shot is not averaged away. spacetime passes one second of its
#: source's frames.
HEAD_MOTION_WINDOW = 30

#: Marker-noise floor of the head-motion gate, as a fraction of the face size (0.001 = 0.06 mm
#: on a human face): with exact rigs (nothing left unexplained) a rigid motion must still
#: move the markers by more than about this much to count.
HEAD_MOTION_NOISE_FLOOR = 1e-3

#: A rigid direction (rotation or translation combination) is estimated only if at least
#: this fraction of its effect on the visible markers cannot be mimicked by the expressions
#: (generalized eigenvalue of the expression-eliminated rigid normal matrix). Complete ICT
#: and synthetic marker sets give 0.09-0.25; with most markers missing it drops to 1e-5.
HEAD_MOTION_IDENTIFIABLE = 0.01

#: Environment variable: "1" disables third-party plugins (built-ins still load).
ENV_DISABLE_PLUGINS = "FACERETARGET_DISABLE_PLUGINS"

#: Environment variable: comma-separated entry-point names or distributions allowed to load
#: (empty or unset: every installed entry point).
ENV_PLUGIN_ALLOWLIST = "FACERETARGET_PLUGINS"

#: Environment variable: "1" prints every hook call and its result to stderr.
ENV_TRACE = "FACERETARGET_TRACE"

#: Environment variable: memory budget for readers, in bytes (suffixes K, M, G allowed).
ENV_MEMORY_BUDGET = "FACERETARGET_MEMORY_BUDGET"

#: Environment variable: time limit in seconds for one compare run or one batch job
#: (fit + retarget), used by the command line when ``--timeout`` is not given; 0 = none.
ENV_RUN_TIMEOUT = "FACERETARGET_TIMEOUT"

#: Default time limit of one compare run or batch job on the command line: 1 hour.
DEFAULT_RUN_TIMEOUT = 3600.0

#: Environment variable: time limit in seconds for importing one third-party plugin
#: (its entry point and its registration hooks); 0 = none.
ENV_IMPORT_TIMEOUT = "FACERETARGET_IMPORT_TIMEOUT"

#: Default time limit for importing one third-party plugin.
DEFAULT_IMPORT_TIMEOUT = 60.0

#: The longest time limit accepted (30 days); for none, give 0.
MAX_TIMEOUT = 30 * 24 * 3600.0

#: A worker process gets at least this long (seconds) to start and import a plugin's
#: module before its first call's own time limit begins.
WORKER_STARTUP_SECONDS = 60.0

#: Default memory budget for a single file read: 8 GiB.
DEFAULT_MEMORY_BUDGET = 8 * 1024**3


def memory_budget() -> int:
    """The reader memory budget in bytes, from ``FACERETARGET_MEMORY_BUDGET`` or the default."""
    from .errors import ConfigError

    raw = os.environ.get(ENV_MEMORY_BUDGET, "").strip()
    if not raw:
        return DEFAULT_MEMORY_BUDGET
    scale = {"K": 1024, "M": 1024**2, "G": 1024**3, "T": 1024**4}
    unit = raw[-1].upper()
    try:
        value = float(raw[:-1]) * scale[unit] if unit in scale else float(raw)
    except ValueError:
        value = float("nan")
    if not (1 <= value < 2**63):  # negative, zero, below one byte, NaN, infinite or absurd
        raise ConfigError(
            f"{ENV_MEMORY_BUDGET}={raw!r} is not a positive size; use bytes or a number with K, M, G or T "
            f"(e.g. 2G), or unset it for the default of {DEFAULT_MEMORY_BUDGET // 1024**3}G"
        )
    return int(value)


def env_flag(name: str) -> bool:
    """True when environment variable ``name`` is set to 1/true/yes/on."""
    return os.environ.get(name, "").strip().lower() in {"1", "true", "yes", "on"}


def seconds_setting(name: str, default: float) -> float | None:
    """A time limit in seconds from environment variable ``name`` (default ``default``);
    None when it is 0 (no limit)."""
    from .errors import ConfigError

    raw = os.environ.get(name, "").strip()
    try:
        value = float(raw) if raw else float(default)
    except ValueError:
        raise ConfigError(
            f"{name}={raw!r} is not a number of seconds; use e.g. {name}=600 (0 for no limit)"
        ) from None
    return check_timeout(value, f"{name}={raw!r}")


def check_timeout(value: object, what: str = "timeout") -> float | None:
    """``value`` as a time limit in seconds (None or 0 = no limit); ConfigError otherwise."""
    from .errors import ConfigError

    if value is None:
        return None
    if (
        isinstance(value, bool)
        or not isinstance(value, (int, float))
        or not 0 <= value <= MAX_TIMEOUT
    ):
        raise ConfigError(
            f"{what} must be a number of seconds from 0 to {MAX_TIMEOUT:g} (30 days; 0 or None for no limit), got {value!r}"
        )
    return float(value) or None


def check_jobs(value: object, what: str = "n_jobs") -> int:
    """``value`` as a count of worker processes (an integer >= 1); ConfigError otherwise."""
    from .errors import ConfigError

    if isinstance(value, bool) or not isinstance(value, int) or value < 1:
        raise ConfigError(f"{what} must be an integer >= 1, got {value!r}")
    return value


# ---------------------------------------------------------------------------------------
# Cross-topology correspondence (``correspond.resample_to_topology`` and its QualityReport)
# ---------------------------------------------------------------------------------------
#: A source boundary loop is pulled onto the nearest target boundary loop only if the mean
#: distance from each to the other (after the landmark warp, then at each stiffness stage)
#: is below this fraction of the face size (RMS radius of the target landmarks). Measured
#: after the warp: loops that correspond (synthetic eyes/mouth/outline, the cross-rig ICT
#: loops) 0.001-0.12; an outline cut elsewhere (cases.cross_topology: forehead cut, skirt
#: beyond the target) 0.44-0.46.
CORRESPONDENCE_LOOP_MATCH = 0.25

#: Flipped triangles of the face interior (every corner matched on the target) above this
#: count warn (CorrespondenceWarning) ...
CORRESPONDENCE_FLIPPED_WARN = 0
#: ... and above this share of the interior triangles raise CorrespondenceError.
CORRESPONDENCE_FLIPPED_ERROR = 0.02

#: Largest landmark distance after the fit, as a fraction of the target's bounding-box
#: diagonal (QualityReport.scale): warn above / raise above. Good fits: below 0.008.
CORRESPONDENCE_LANDMARK_WARN = 0.02
CORRESPONDENCE_LANDMARK_ERROR = 0.1

#: Mean distance of the matched source vertices to the target surface (fraction of the
#: bounding-box diagonal): warn above / raise above. After snapping, good fits: < 1e-4.
CORRESPONDENCE_RESIDUAL_WARN = 0.005
CORRESPONDENCE_RESIDUAL_ERROR = 0.03

#: A target vertex is "not reached" when it lies farther than this many mean target edge
#: lengths from the matched part of the resampled surface ...
CORRESPONDENCE_UNCOVERED_EDGES = 3.0
#: ... counted only more than this many edge rings inside the target's outline (a source
#: cut elsewhere leaves a band along it; that is reported, not warned about) ...
CORRESPONDENCE_OUTLINE_RINGS = 15
#: ... warn when that share of the target's vertices is not reached, raise above the second.
CORRESPONDENCE_UNCOVERED_WARN = 0.05
CORRESPONDENCE_UNCOVERED_ERROR = 0.5

#: The face interior of a cross-topology fit excludes source triangles whose closest target
#: points lie within this many edge rings of a target boundary (eye, mouth and outline rims:
#: a closed lid on an open one, or an outline cut elsewhere, cannot correspond vertex for
#: vertex there); their flips are counted apart (``details["flipped_rim"]``).
CORRESPONDENCE_RIM_RINGS = 2
