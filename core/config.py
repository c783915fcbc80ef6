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
        if unit in scale:
            return int(float(raw[:-1]) * scale[unit])
        return int(float(raw))
    except ValueError:
        raise ConfigError(
            f"{ENV_MEMORY_BUDGET}={raw!r} is not a size; use bytes or a number with K, M or G (e.g. 2G)"
        ) from None


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
        raise ConfigError(f"{name}={raw!r} is not a number of seconds; use e.g. {name}=600 (0 for no limit)") from None
    return check_timeout(value, f"{name}={raw!r}")


def check_timeout(value, what: str = "timeout") -> float | None:
    """``value`` as a time limit in seconds (None or 0 = no limit); ConfigError otherwise."""
    from .errors import ConfigError

    if value is None:
        return None
    if isinstance(value, bool) or not isinstance(value, (int, float)) or not 0 <= value <= MAX_TIMEOUT:
        raise ConfigError(f"{what} must be a number of seconds from 0 to {MAX_TIMEOUT:g} (30 days; 0 or None for no limit), got {value!r}")
    return float(value) or None
