"""Cold start: a fresh ``faceretarget demo`` (empty numba cache: every kernel compiles)
against the same command with a warm cache, each in its own process (issue 16 item 6:
within 60 s on this machine).

Each run takes minutes, so the runs are counted by ``--cold-runs`` (default 1; the other
scripts use >= 5 repeats) and ``--quick`` does not run the demo at all: its row reads
"not run". The numba cache of a cold run is a new temporary folder (``NUMBA_CACHE_DIR``);
the warm run reuses it.

    python benchmarks/bench_coldstart.py [--quick] [--json] [--cold-runs N] [-- DEMO ARGS]
"""

from __future__ import annotations

import os
import shutil
import subprocess
import sys
import tempfile
import time
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parent))

import _common as C  # noqa: E402


def demo(cache: Path, out: Path, extra: list[str]) -> float:
    env = dict(os.environ, NUMBA_CACHE_DIR=str(cache))
    cmd = [
        sys.executable,
        "-c",
        "import sys; from faceretarget.cli import main; sys.exit(main())",
        "demo",
        "--quiet",
        "--out",
        str(out),
        *extra,
    ]
    t0 = time.perf_counter()
    proc = subprocess.run(cmd, env=env, stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True)
    wall = time.perf_counter() - t0
    if proc.returncode != 0:
        print(
            f"  demo exited with {proc.returncode}; last output:\n"
            + "\n".join(proc.stdout.splitlines()[-5:])
        )
    shutil.rmtree(out, ignore_errors=True)
    return wall


def main(argv=None) -> dict:
    ap = C.parser(__doc__)
    ap.add_argument("--cold-runs", type=int, default=1)
    ap.add_argument("demo_args", nargs="*", help="extra arguments of faceretarget demo")
    args = ap.parse_args(argv)
    result = {
        "script": "bench_coldstart",
        "machine": C.print_machine("bench_coldstart"),
        "rows": [],
        "scaling": [],
    }
    name = "fresh faceretarget demo (empty numba cache)"
    if args.quick:
        print("--quick: the demo is not run (minutes per run)")
        result["rows"].append(
            {
                "name": name,
                "unit": "s",
                "better": "lower",
                "goal": 60.0,
                "best": None,
                "median": None,
                "n": 0,
                "source": "issue 16 item 6",
                "note": "not run with --quick",
            }
        )
        return C.finish(result, args)
    cold, warm = [], []
    for _ in range(max(1, args.cold_runs)):
        tmp = Path(tempfile.mkdtemp(prefix="bench_coldstart_"))
        try:
            cold.append(demo(tmp / "numba", tmp / "cold", args.demo_args))
            warm.append(demo(tmp / "numba", tmp / "warm", args.demo_args))
        finally:
            shutil.rmtree(tmp, ignore_errors=True)
        print(f"  cold {cold[-1]:.1f} s, warm {warm[-1]:.1f} s", flush=True)
    import statistics

    c = {"min_s": min(cold), "median_s": statistics.median(cold), "times_s": cold}
    w = {"min_s": min(warm), "median_s": statistics.median(warm), "times_s": warm}
    result["rows"].append(
        C.time_row(
            name, c, 60.0, baseline=("the same demo, warm numba cache", w), source="issue 16 item 6"
        )
    )
    C.print_rows(result["rows"])
    return C.finish(result, args)


if __name__ == "__main__":
    main()
