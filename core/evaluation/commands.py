"""The ``faceretarget compare``, ``demo`` and ``batch`` sub-commands.

``core/cli.py`` attaches them: ``add_<name>_arguments(parser)`` fills the sub-parser and
``run_<name>(args) -> int`` runs it. Errors are raised as
:class:`~faceretarget.errors.FaceRetargetError` subclasses; the CLI prints them as one line.
"""

from __future__ import annotations

import argparse
import datetime as _dt
import sys
import time
from collections.abc import Callable, Iterable
from pathlib import Path
from typing import TYPE_CHECKING, TextIO

from .._args import parse_sets
from ..errors import ConfigError, OutputError

if TYPE_CHECKING:
    from .._types import PathLike
    from ..hookspecs import Writer
    from ..registry import Registry
    from .harness import ComparisonResult

__all__ = [
    "add_compare_arguments",
    "run_compare",
    "add_demo_arguments",
    "run_demo",
    "add_batch_arguments",
    "run_batch",
    "DEMO_CASES",
]

#: Cases of ``faceretarget demo`` (name -> case spec): modest sizes so the demo takes about
#: a minute on 2 cores (more on the very first run, while numba compiles the plugins' kernels).
DEMO_CASES = {
    "synthetic-human": "synthetic-human?resolution=1500&n_frames=60",
    "synthetic-stylized": "synthetic-stylized?resolution=1500&n_frames=60",
    "ict": "ict?n_frames=60",
}


def _add_timeout_argument(parser: argparse.ArgumentParser, what: str) -> None:
    parser.add_argument(
        "--timeout",
        type=float,
        metavar="SECONDS",
        help=f"time limit of {what}; one that overruns is stopped and reported with its plugin, the rest go on "
        "(default: $FACERETARGET_TIMEOUT or 3600; 0: no limit)",
    )


def _add_keep_going_argument(parser: argparse.ArgumentParser, what: str) -> None:
    parser.add_argument(
        "--keep-going",
        action="store_true",
        help=f"exit 0 even when some {what} failed (default: exit 1 after the summary when any failed)",
    )


def _failed_exit(n_failed: int, total: int, what: str, keep_going: bool) -> int:
    """Exit status of a command whose ``n_failed`` of ``total`` runs or jobs failed: 1 with a
    summary line on stderr unless ``--keep-going`` (then 0, with the same line as a note)."""
    if not n_failed:
        return 0
    note = f"faceretarget: {n_failed} of {total} {what} failed (listed above)"
    if keep_going:
        print(f"{note}; exit status 0 because of --keep-going", file=sys.stderr)
        return 0
    print(f"{note}; exit status 1 (--keep-going exits 0 in that case)", file=sys.stderr)
    return 1


def _failed_runs(result: ComparisonResult) -> int:
    from .harness import ERROR

    return sum(run.status == ERROR for run in result.runs)


def _timeout(value: float | None) -> float | None:
    """``--timeout`` as given, else ``FACERETARGET_TIMEOUT``, else the default; None = no limit."""
    from .. import config

    if value is None:
        return config.seconds_setting(config.ENV_RUN_TIMEOUT, config.DEFAULT_RUN_TIMEOUT)
    return config.check_timeout(value, "--timeout")


def _print_ranking(result: ComparisonResult, stream: TextIO | None = None) -> None:
    from .report import _fmt

    stream = stream or sys.stdout
    from ._summary import ranking_metric

    rows = result.ranking()
    print(
        f"ranked by {ranking_metric(result)} (mean rank over the cases; the report explains each case)",
        file=stream,
    )
    print(
        f"{'rank':>4}  {'method':<24} {'mean rank':>9} {'ok':>3} {'n/a':>3} {'fail':>4} {'vertex RMS %H':>13} {'time s':>8}",
        file=stream,
    )
    for r in rows:
        print(
            f"{r['rank'] if r['rank'] is not None else '-':>4}  {r['method']:<24} {_fmt(r['mean_rank']) or '-':>9} {r['ranked_cases']:>3} "
            f"{r['not_applicable']:>3} {r['failed']:>4} {_fmt(r['vertex_error_rms']) or '-':>13} {_fmt(r['time_total']) or '-':>8}",
            file=stream,
        )
    for run in result.runs:
        if run.status != "ok":
            print(f"  {run.case} / {run.method}: {run.status}: {run.reason}", file=stream)


def _new_folder(path: Path | None, prefix: str) -> Path:
    if path is not None:
        if path.exists() and (not path.is_dir() or any(path.iterdir())):
            raise OutputError(
                f"{path} already exists and is not an empty folder; the demo never overwrites, choose a new --out"
            )
        path.mkdir(parents=False, exist_ok=True)
        return path
    stamp = _dt.datetime.now().strftime("%Y%m%d-%H%M%S")
    base = Path.cwd() / f"{prefix}-{stamp}"
    candidate, k = base, 2
    while True:
        try:
            candidate.mkdir()
            return candidate
        except FileExistsError:
            candidate, k = Path(f"{base}-{k}"), k + 1


# ---------------------------------------------------------------------------------------
# compare
# ---------------------------------------------------------------------------------------
def add_compare_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument(
        "cases",
        nargs="*",
        metavar="CASE",
        help="case names (synthetic, synthetic-human, synthetic-stylized, ict, cross_rig, cross_topology; keywords as 'NAME?k=v&k=v'); default: synthetic-human synthetic-stylized ict",
    )
    parser.add_argument(
        "--cases",
        dest="case_options",
        nargs="+",
        default=[],
        metavar="CASE",
        help="the same cases as an option (added to any given before the options)",
    )
    parser.add_argument(
        "--methods",
        nargs="+",
        metavar="NAME",
        help="retargeters to compare (default: every registered one)",
    )
    parser.add_argument(
        "--set",
        dest="sets",
        action="append",
        default=[],
        metavar="METHOD.PARAM=VALUE",
        help="a constructor parameter of one method, e.g. METHOD.alpha=0.05 (repeatable)",
    )
    parser.add_argument(
        "--metrics",
        nargs="+",
        metavar="NAME",
        help="metrics to compute (default: every registered one)",
    )
    parser.add_argument(
        "--presets",
        nargs="*",
        metavar="NAME",
        help="also run the paper reproductions the plugins register (all when no name is given)",
    )
    parser.add_argument(
        "--out",
        type=Path,
        metavar="FOLDER",
        help="write report.html, results.csv and results.json into FOLDER",
    )
    parser.add_argument("--csv", type=Path, metavar="FILE", help="write the tidy table as CSV")
    parser.add_argument(
        "--json", type=Path, metavar="FILE", help="write the tidy table, ranking and runs as JSON"
    )
    parser.add_argument(
        "--jobs",
        type=int,
        default=1,
        metavar="N",
        help="run the methods in N worker processes (default 1)",
    )
    parser.add_argument(
        "--force",
        action="store_true",
        help="replace existing --csv/--json files and report files in --out (never an input)",
    )
    _add_timeout_argument(parser, "one run (fit + retarget of one method on one case)")
    _add_keep_going_argument(parser, "runs")
    parser.add_argument("--quiet", action="store_true", help="no progress bar")


def check_outputs(paths: Iterable[PathLike], *, force: bool, inputs: Iterable = ()) -> None:
    """The one destination check of :mod:`faceretarget.io._atomic` for every file a command
    will write, before any slow work: never an input (``inputs``, or a file read by this
    process), never an existing file without ``--force``, never two outputs on one file."""
    import os

    from ..io._atomic import check_destination

    seen: dict[str, str] = {}
    for p in paths:
        real = os.path.realpath(p)
        if real in seen:
            raise OutputError(
                f"{p}: given for two outputs ({seen[real]} and {p}); give each output its own file"
            )
        seen[real] = str(p)
        check_destination(p, inputs=inputs, force=force)


def run_compare(args: argparse.Namespace) -> int:
    from .harness import compare
    from .report import REPORT_FILES, check_report_folder, write_report

    outputs = [p for p in (args.csv, args.json) if p]
    if args.out:
        check_report_folder(args.out)
        outputs += [args.out / name for name in REPORT_FILES] if args.out.is_dir() else []
    check_outputs(outputs, force=args.force)  # before the comparison runs
    cases = list(args.cases) + list(getattr(args, "case_options", None) or [])
    result = compare(
        cases or None,
        methods=args.methods,
        params=parse_sets(args.sets, per_method=True) or None,
        metrics=args.metrics,
        progress=not args.quiet,
        n_jobs=_jobs(args.jobs, 1),
        timeout=_timeout(args.timeout),
        presets=False if args.presets is None else (args.presets or True),
    )
    _print_ranking(result)
    if args.csv:
        print(f"wrote {result.to_csv(args.csv, force=args.force)}")
    if args.json:
        print(f"wrote {result.to_json(args.json, force=args.force)}")
    if args.out:
        paths = write_report(result, args.out, force=args.force)
        print(f"report: {paths['html']}")
    return _failed_exit(_failed_runs(result), len(result.runs), "runs", args.keep_going)


# ---------------------------------------------------------------------------------------
# demo
# ---------------------------------------------------------------------------------------
def add_demo_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument(
        "--out",
        type=Path,
        metavar="FOLDER",
        help="new folder for the results (default: ./faceretarget-demo-YYYYmmdd-HHMMSS)",
    )
    parser.add_argument(
        "--methods", nargs="+", metavar="NAME", help="retargeters (default: every registered one)"
    )
    parser.add_argument(
        "--frames", type=int, default=None, metavar="N", help="frames per case (default 60)"
    )
    parser.add_argument("--no-presets", action="store_true", help="skip the paper reproductions")
    parser.add_argument("--no-glb", action="store_true", help="do not write a GLB per method")
    parser.add_argument(
        "--jobs",
        type=int,
        metavar="N",
        help="methods run in parallel worker processes (default: 2, at most the CPU count)",
    )
    _add_timeout_argument(parser, "one run (fit + retarget of one method on one case)")
    _add_keep_going_argument(parser, "runs")
    parser.add_argument("--quiet", action="store_true", help="no progress bar")


def demo_cases(frames: int | None = None) -> dict[str, str]:
    """The demo's ``{name: case spec}``, with ``frames`` frames per case if given."""
    if frames is None:
        return dict(DEMO_CASES)
    if frames < 3:
        raise ConfigError(f"--frames must be at least 3, got {frames}")
    return {
        name: spec.replace("n_frames=60", f"n_frames={frames}") for name, spec in DEMO_CASES.items()
    }


def _jobs(value: int | None, default: int) -> int:
    import os

    jobs = default if value is None else value
    if jobs < 1:
        raise ConfigError(f"--jobs must be at least 1, got {jobs}")
    return min(jobs, os.cpu_count() or 1) if value is None else jobs


def run_demo(args: argparse.Namespace) -> int:
    from ..registry import registry
    from .batch import write_animation, writer_for
    from .harness import compare
    from .report import write_report

    start = time.perf_counter()
    timeout = _timeout(args.timeout)  # checked before the folder is made
    folder = _new_folder(args.out, "faceretarget-demo")
    print(f"faceretarget demo: writing into {folder}", file=sys.stderr)
    result = compare(
        demo_cases(args.frames),
        methods=args.methods,
        progress=not args.quiet,
        n_jobs=_jobs(args.jobs, 2),
        timeout=timeout,
        presets=not args.no_presets,
    )
    paths = write_report(result, folder, title="faceretarget demo")
    glb_note = ""
    if not args.no_glb:
        glb_note = _write_glbs(result, folder / "glb", registry(), write_animation, writer_for)
    _print_ranking(result)
    print(f"report:  {paths['html']}")
    print(f"table:   {paths['csv']}")
    print(f"json:    {paths['json']}")
    if glb_note:
        print(glb_note)
    print(f"done in {time.perf_counter() - start:.1f} s")
    return _failed_exit(_failed_runs(result), len(result.runs), "runs", args.keep_going)


# ---------------------------------------------------------------------------------------
# warmup
# ---------------------------------------------------------------------------------------
def add_warmup_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument(
        "--methods", nargs="+", metavar="NAME", help="only these methods (default: every built-in)"
    )


def warmup_cases() -> list:
    """Tiny cases that take every built-in method through its kernels: blendshape and dense
    targets, marker and mesh sources, same and different topology."""
    from .. import cases

    return [
        cases.synthetic(n_frames=6, resolution=300),
        cases.synthetic(n_frames=6, resolution=300, target="stylized"),
        cases.ict(n_frames=6),
        cases.cross_rig(n_frames=6, source_kind="markers"),
        cases.cross_rig(n_frames=6, source_kind="mesh"),
        cases.cross_topology(n_frames=3),
    ]


def run_warmup(args: argparse.Namespace) -> int:
    import warnings

    import numpy as np

    import faceretarget as fr

    from ..registry import registry

    reg = registry()
    names = args.methods or sorted(n for n, info in reg.retargeters.items() if info.plugin.builtin)
    start = time.perf_counter()
    tiny = warmup_cases()
    failed = []
    for name in names:
        began, ran = time.perf_counter(), 0
        for case in tiny:
            method = fr.get(name)
            if method.why_not(case.source, case.target):
                continue
            try:
                with (
                    warnings.catch_warnings()
                ):  # tiny cases, only to compile: their data warnings mean nothing
                    warnings.simplefilter("ignore")
                    animation = method.fit(case.source, case.target).retarget(case.source)
                    np.asarray(animation.vertices)
                ran += 1
            except Exception as exc:  # report and go on: warming up must not stop at one method
                failed.append(f"{name} on {case.name}: {type(exc).__name__}: {exc}")
        print(f"{name:28s} {ran} case(s) {time.perf_counter() - began:6.1f} s")
    for line in failed:
        print(f"failed: {line}", file=sys.stderr)
    print(
        f"warm in {time.perf_counter() - start:.1f} s; later runs load the compiled kernels from numba's cache"
    )
    return 1 if failed else 0


def _write_glbs(
    result: ComparisonResult,
    folder: Path,
    reg: Registry,
    write_animation: Callable[..., Path],
    writer_for: Callable[[Path, Registry, str], Writer],
) -> str:
    try:
        writer = writer_for(Path("x.glb"), reg, "demo")
    except ConfigError as exc:
        return f"glb:     not written: {exc}"
    folder.mkdir(exist_ok=True)
    written, failed = 0, []
    for run in result.runs:
        if run.status != "ok" or run.animation is None:
            continue
        try:
            write_animation(run.animation, folder / f"{run.case}-{run.method}.glb", writer.write)
            written += 1
        except Exception as exc:  # one bad export must not lose the report
            failed.append(f"{run.case}/{run.method}: {type(exc).__name__}: {exc}")
    note = f"glb:     {written} file(s) in {folder}"
    return note + ("".join(f"\n  not written: {f}" for f in failed) if failed else "")


# ---------------------------------------------------------------------------------------
# batch
# ---------------------------------------------------------------------------------------
def add_batch_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument(
        "manifest",
        type=Path,
        help="TOML manifest of [[job]] entries (shot, character, method, params, out); see docs/evaluation.md",
    )
    parser.add_argument(
        "--dask",
        action="store_true",
        help="run on dask.distributed (a local cluster on 127.0.0.1 unless --scheduler is given)",
    )
    parser.add_argument(
        "--scheduler",
        metavar="ADDRESS",
        help="address of a running Dask scheduler, e.g. tcp://10.0.0.5:8786 (implies --dask)",
    )
    parser.add_argument(
        "--workers",
        type=int,
        metavar="N",
        help="parallel jobs / local Dask workers (default: CPU count)",
    )
    parser.add_argument(
        "--redo",
        action="store_true",
        help="run jobs whose output already exists (default: skip them)",
    )
    parser.add_argument(
        "--summary",
        type=Path,
        metavar="FILE",
        help="write the per-job results as JSON (never over a file of the run)",
    )
    parser.add_argument(
        "--force",
        action="store_true",
        help="replace an existing --summary file (job outputs are replaced only with --redo)",
    )
    _add_timeout_argument(parser, "one job, unless its manifest entry sets timeout")
    parser.add_argument(
        "--check", action="store_true", help="only check the manifest and list the jobs"
    )
    _add_keep_going_argument(parser, "jobs")
    parser.add_argument("--quiet", action="store_true", help="no progress bar")


def run_batch(args: argparse.Namespace) -> int:
    from . import batch

    jobs = batch.load_manifest(args.manifest)
    run_files = batch.run_inputs(jobs, args.manifest)
    if args.summary:
        check_outputs([args.summary], force=args.force, inputs=run_files)  # before any job runs
    if args.check:
        for job in jobs:
            state = "exists" if Path(job.out).exists() else "to do"
            print(f"{job.name}: {job.method} {job.shot} -> {job.out} ({state})")
        print(f"{len(jobs)} job(s); manifest OK")
        return 0
    executor = "dask" if (args.dask or args.scheduler) else "local"
    summary = batch.run_batch(
        jobs,
        executor=executor,
        scheduler=args.scheduler,
        workers=args.workers,
        redo=args.redo,
        progress=not args.quiet,
        timeout=_timeout(args.timeout),
    )
    print(batch.format_summary(summary))
    if args.summary:
        print(
            f"wrote {batch.write_summary(summary, args.summary, force=args.force, inputs=run_files)}"
        )
    return _failed_exit(len(summary.failed), len(summary.results), "jobs", args.keep_going)
