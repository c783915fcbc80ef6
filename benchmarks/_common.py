"""Shared helpers of the benchmark scripts: timing (min and median of repeats), machine
description (load, BLAS threads, versions), peak memory, log-log exponents and the one JSON
line that ``run_all.py`` reads.

Every script's ``main(argv)`` returns a dict ``{"script", "machine", "rows", "scaling"}``:

- a *row* is one measured figure against its goal: ``name``, ``goal`` (number, in ``unit``),
  ``better`` ("lower" or "higher"), ``best`` and ``median`` (in ``unit``: for a time the min
  and the median of the repeats; for a rate or a speed-up the value from the min and from
  the median time), ``n`` (repeats), optional ``baseline`` (``name``, ``min_s``,
  ``median_s``) timed in the same process, ``source`` (which issue set the goal) and ``note``;
- a *scaling* entry lists sizes with min / median times and peak memory per size and the
  fitted log-log exponent.

With ``--json`` a script prints that dict as the last line of its output, prefixed
with ``BENCH_JSON ``.
"""

from __future__ import annotations

import argparse
import json
import math
import os
import platform
import statistics
import sys
import time
import tracemalloc
from pathlib import Path

JSON_PREFIX = "BENCH_JSON "
ROOT = Path(__file__).resolve().parents[1]


# ---- machine ----------------------------------------------------------------------------


def load_average() -> list[float]:
    try:
        return [round(x, 2) for x in os.getloadavg()]
    except (AttributeError, OSError):  # pragma: no cover - not on POSIX
        return [float("nan")] * 3


def blas_info() -> list[dict]:
    """The BLAS / OpenMP libraries loaded in this process and their thread counts (threadpoolctl)."""
    try:
        import numpy  # noqa: F401  (load the BLAS numpy uses)
        import scipy.linalg  # noqa: F401
        from threadpoolctl import threadpool_info
    except ImportError:
        return [
            {"user_api": "?", "internal_api": "threadpoolctl not installed", "num_threads": None}
        ]
    return [
        {
            k: i.get(k)
            for k in ("user_api", "internal_api", "num_threads", "version", "threading_layer")
        }
        for i in threadpool_info()
    ]


def blas_threads_text(info: list[dict] | None = None) -> str:
    info = blas_info() if info is None else info
    parts = [
        f"{i['internal_api']} {i.get('version') or ''} x{i['num_threads']}".replace("  ", " ")
        for i in info
        if i.get("user_api") == "blas"
    ]
    return ", ".join(parts) or "no BLAS found by threadpoolctl"


def versions() -> dict:
    out = {"python": platform.python_version()}
    for name in ("numpy", "scipy", "numba", "threadpoolctl"):
        try:
            out[name] = __import__(name).__version__
        except ImportError:
            out[name] = None
    try:
        from importlib.metadata import version

        out["faceretarget"] = version("faceretarget")
    except Exception:  # noqa: BLE001 - informative only
        out["faceretarget"] = None
    return out


def cpu_model() -> str:
    try:
        for line in Path("/proc/cpuinfo").read_text().splitlines():
            if line.startswith("model name"):
                return line.split(":", 1)[1].strip()
    except OSError:
        pass
    return platform.processor() or platform.machine()


def machine() -> dict:
    return {
        "date": time.strftime("%Y-%m-%d %H:%M:%S %z"),
        "cpu_count": os.cpu_count(),
        "cpu": cpu_model(),
        "platform": platform.platform(),
        "load_average": load_average(),
        "blas": blas_info(),
        "versions": versions(),
        "env_threads": {
            k: os.environ[k]
            for k in (
                "OPENBLAS_NUM_THREADS",
                "OMP_NUM_THREADS",
                "MKL_NUM_THREADS",
                "NUMBA_NUM_THREADS",
            )
            if k in os.environ
        },
    }


def print_machine(title: str) -> dict:
    m = machine()
    print(f"== {title}")
    print(
        f"machine: {m['cpu_count']} CPUs ({m['cpu']}), load average {m['load_average'][0]:.2f} / "
        f"{m['load_average'][1]:.2f} / {m['load_average'][2]:.2f} (1 / 5 / 15 min); "
        f"BLAS: {blas_threads_text(m['blas'])}"
        + (f"; environment {m['env_threads']}" if m["env_threads"] else "")
    )
    print(
        "wall times: min and median of the repeats (warm: one untimed call first); CPU time only where stated"
    )
    sys.stdout.flush()
    return m


# ---- timing -----------------------------------------------------------------------------


def timeit(fn, repeat: int, *, warmup: int = 1, cpu: bool = False) -> dict:
    """Wall time of ``fn()`` over ``repeat`` calls after ``warmup`` untimed calls:
    ``{"min_s", "median_s", "times_s", "result"}`` (+ ``cpu_min_s``, ``cpu_median_s``)."""
    out = None
    for _ in range(warmup):
        out = fn()
    walls, cpus = [], []
    for _ in range(max(1, repeat)):
        c0, t0 = time.process_time(), time.perf_counter()
        out = fn()
        walls.append(time.perf_counter() - t0)
        cpus.append(time.process_time() - c0)
    res = {
        "min_s": min(walls),
        "median_s": statistics.median(walls),
        "times_s": walls,
        "result": out,
    }
    if cpu:
        res["cpu_min_s"], res["cpu_median_s"] = min(cpus), statistics.median(cpus)
    return res


def peak_memory(fn) -> tuple[int, object]:
    """Peak traced memory (tracemalloc: Python and numpy allocations) of one ``fn()`` call, in bytes."""
    was = tracemalloc.is_tracing()
    if not was:
        tracemalloc.start()
    tracemalloc.reset_peak()
    base = tracemalloc.get_traced_memory()[0]
    out = fn()
    peak = tracemalloc.get_traced_memory()[1] - base
    if not was:
        tracemalloc.stop()
    return peak, out


def max_rss_bytes() -> int:
    try:
        import resource

        return int(resource.getrusage(resource.RUSAGE_SELF).ru_maxrss) * 1024
    except ImportError:  # pragma: no cover
        return 0


def fit_exponent(sizes, values) -> float:
    """Least-squares slope of log(value) against log(size)."""
    pts = [(math.log(s), math.log(v)) for s, v in zip(sizes, values) if s > 0 and v and v > 0]
    if len(pts) < 2:
        return float("nan")
    mx = sum(p[0] for p in pts) / len(pts)
    my = sum(p[1] for p in pts) / len(pts)
    sxx = sum((p[0] - mx) ** 2 for p in pts)
    return sum((p[0] - mx) * (p[1] - my) for p in pts) / sxx if sxx else float("nan")


# ---- rows -------------------------------------------------------------------------------


def time_row(
    name: str,
    t: dict,
    goal_s: float | None,
    *,
    per: float = 1.0,
    baseline: tuple[str, dict] | None = None,
    source: str = "",
    note: str = "",
    unit: str = "s",
) -> dict:
    """A lower-is-better time row; ``per`` divides the times (e.g. frames, for a per-frame cost)."""
    row = {
        "name": name,
        "unit": unit,
        "better": "lower",
        "goal": goal_s,
        "best": t["min_s"] / per,
        "median": t["median_s"] / per,
        "n": len(t["times_s"]),
        "source": source,
        "note": note,
    }
    if "cpu_min_s" in t:
        row["cpu_best"], row["cpu_median"] = t["cpu_min_s"] / per, t["cpu_median_s"] / per
    if baseline is not None:
        row["baseline"] = {
            "name": baseline[0],
            "min_s": baseline[1]["min_s"] / per,
            "median_s": baseline[1]["median_s"] / per,
            "n": len(baseline[1]["times_s"]),
        }
    return row


def rate_row(
    name: str,
    count: float,
    t: dict,
    goal: float | None,
    *,
    unit: str = "frames/s",
    baseline: tuple[str, dict] | None = None,
    baseline_count: float | None = None,
    source: str = "",
    note: str = "",
) -> dict:
    """A higher-is-better rate ``count / time`` (best from the min time, median from the median)."""
    row = {
        "name": name,
        "unit": unit,
        "better": "higher",
        "goal": goal,
        "best": count / t["min_s"],
        "median": count / t["median_s"],
        "n": len(t["times_s"]),
        "source": source,
        "note": note,
    }
    if "cpu_min_s" in t:
        row["cpu_best"], row["cpu_median"] = count / t["cpu_min_s"], count / t["cpu_median_s"]
    if baseline is not None:
        c = baseline_count if baseline_count is not None else count
        row["baseline"] = {
            "name": baseline[0],
            "min_s": baseline[1]["min_s"] / c,
            "median_s": baseline[1]["median_s"] / c,
            "n": len(baseline[1]["times_s"]),
            "per": "per item",
        }
    return row


def value_row(
    name: str,
    best: float,
    median: float,
    goal: float | None,
    unit: str,
    better: str = "lower",
    *,
    n: int = 1,
    source: str = "",
    note: str = "",
    baseline: dict | None = None,
) -> dict:
    row = {
        "name": name,
        "unit": unit,
        "better": better,
        "goal": goal,
        "best": best,
        "median": median,
        "n": n,
        "source": source,
        "note": note,
    }
    if baseline is not None:
        row["baseline"] = baseline
    return row


def scaling_entry(
    name: str,
    size_label: str,
    sizes,
    timings: list[dict],
    peaks: list[int],
    *,
    per_label: str = "",
    note: str = "",
    extra: dict | None = None,
) -> dict:
    mins = [t["min_s"] for t in timings]
    meds = [t["median_s"] for t in timings]
    entry = {
        "name": name,
        "size_label": size_label,
        "sizes": list(sizes),
        "min_s": mins,
        "median_s": meds,
        "n": [len(t["times_s"]) for t in timings],
        "peak_bytes": list(peaks),
        "exponent_min": fit_exponent(sizes, mins),
        "exponent_median": fit_exponent(sizes, meds),
        "memory_exponent": fit_exponent(sizes, peaks),
        "note": note,
    }
    if extra:
        entry.update(extra)
    return entry


def print_rows(rows: list[dict]) -> None:
    for r in rows:
        base = r.get("baseline")
        text = f"  {r['name']}: best {fmt(r['best'], r['unit'])}, median {fmt(r['median'], r['unit'])} (n={r['n']})"
        if r.get("goal") is not None:
            text += f"; goal {'<' if r['better'] == 'lower' else '>='} {fmt(r['goal'], r['unit'])}"
        if "cpu_best" in r:
            text += f"; CPU time: best {fmt(r['cpu_best'], r['unit'])}, median {fmt(r['cpu_median'], r['unit'])}"
        if base:
            text += f"; baseline {base['name']}: min {fmt(base['min_s'], 's')}, median {fmt(base['median_s'], 's')} (n={base['n']})"
        print(text)
    sys.stdout.flush()


def print_scaling(entry: dict) -> None:
    print(
        f"  scaling of {entry['name']} ({entry['size_label']}): exponent {entry['exponent_min']:.2f} (min times), "
        f"{entry['exponent_median']:.2f} (medians), memory exponent {entry['memory_exponent']:.2f}"
    )
    for s, a, b, p in zip(entry["sizes"], entry["min_s"], entry["median_s"], entry["peak_bytes"]):
        print(
            f"    {s:>9,}: min {fmt(a, 's')}, median {fmt(b, 's')}, peak memory {p / 2**20:,.1f} MiB"
        )
    sys.stdout.flush()


def fmt(value: float | None, unit: str) -> str:
    if value is None or (isinstance(value, float) and math.isnan(value)):
        return "n/a"
    if unit == "s":
        if value < 1e-3:
            return f"{value * 1e6:.0f} us"
        if value < 1.0:
            return f"{value * 1e3:.3g} ms" if value * 1e3 < 100 else f"{value * 1e3:.0f} ms"
        return f"{value:.3g} s" if value < 100 else f"{value:.0f} s"
    if unit == "B":
        if value < 2**20:
            return f"{value / 1024:.3g} KB"
        return f"{value / 2**20:,.0f} MiB"
    if unit == "x":
        return f"{value:,.3g}x" if value < 1000 else f"{value:,.0f}x"
    if unit == "frames/s":
        return f"{value:,.0f} frames/s"
    return f"{value:.3g} {unit}"


# ---- command line -----------------------------------------------------------------------


def parser(doc: str | None) -> argparse.ArgumentParser:
    p = argparse.ArgumentParser(description=(doc or "").strip().splitlines()[0] if doc else None)
    p.add_argument(
        "--quick",
        action="store_true",
        help="fewer sizes, frames and repeats (what run_all.py --quick uses)",
    )
    p.add_argument(
        "--json",
        action="store_true",
        help=f"print the results as one last line starting with {JSON_PREFIX!r}",
    )
    p.add_argument(
        "--repeat",
        type=int,
        default=None,
        help="timed repeats per figure (at least 5; default 5, 7 without --quick)",
    )
    return p


def repeats(args) -> int:
    return max(5, args.repeat if args.repeat is not None else (5 if args.quick else 7))


def finish(result: dict, args) -> dict:
    if args.json:

        def clean(o):
            if isinstance(o, float) and (math.isnan(o) or math.isinf(o)):
                return None
            if isinstance(o, dict):
                return {k: clean(v) for k, v in o.items() if k != "result"}
            if isinstance(o, (list, tuple)):
                return [clean(v) for v in o]
            if hasattr(o, "item"):
                return clean(o.item())
            return o

        print(JSON_PREFIX + json.dumps(clean(result)))
        sys.stdout.flush()
    return result
