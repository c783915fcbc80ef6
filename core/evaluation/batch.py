"""Batch runs: many (shot, character, method) jobs from a TOML manifest, locally or on Dask.

Manifest (``faceretarget batch shots.toml``)::

    [defaults]                       # optional; every job inherits these keys
    method = "NAME"                  # a name or alias from faceretarget list
    params = { alpha = 0.02 }
    character = "characters/hero.glb"

    [[job]]
    shot = "shots/sh010.c3d"         # performance file, or "case:NAME?k=v" (its source)
    character = "characters/hero.glb"  # target rig file, or "case:NAME?k=v" (its target)
    landmarks = "characters/hero_landmarks.json"   # optional, passed to io.load_target
    method = "NAME"                  # registered name or alias
    params = { alpha = 0.05 }        # merged over the defaults' params
    out = "out/sh010_hero.glb"       # extension picks the registered writer
    name = "sh010-hero"              # optional id (default: out)
    timeout = 600                    # optional: seconds this job may run (0: no limit)

Every path is relative to the manifest's folder and is refused (:class:`ConfigError`)
if it resolves (symlinks followed) outside that folder. The whole manifest is checked
before anything runs: unknown keys, methods, parameters, duplicate outputs, outputs
without a registered writer.

Execution: supervised local worker processes by default (``workers`` of them, spawn
start method; :mod:`faceretarget.evaluation._workers`);
``executor="dask"`` runs the same jobs on ``dask.distributed`` (a scheduler at
``scheduler`` such as ``tcp://10.0.0.5:8786``, or a local cluster on 127.0.0.1). Workers
must see the same file system. Each job writes its output atomically (a temporary file
in the output folder, then ``os.replace``), so an output that exists is complete: a rerun
skips it (``redo=True`` runs everything again). A failing job is reported with its error
and does not stop the others. A job that overruns its time limit (``timeout`` in the
manifest or the ``timeout`` argument, seconds) has its worker process killed and is
reported as failed with its plugin and distribution; nothing is written for it. Progress is shown with tqdm on stderr.
"""

from __future__ import annotations

import json
import os
import secrets
import sys
import time
import tomllib
from collections.abc import Callable, Hashable, Iterable, Mapping
from dataclasses import asdict, dataclass, field
from pathlib import Path
from typing import TYPE_CHECKING, Any

from ..errors import ConfigError, UnknownNameError

if TYPE_CHECKING:
    from tqdm import tqdm

    from .._types import PathLike
    from ..hookspecs import Writer
    from ..model import Animation, Source, TargetRig
    from ..registry import Registry
    from ._workers import Outcome

__all__ = [
    "Job",
    "JobResult",
    "BatchSummary",
    "load_manifest",
    "run_batch",
    "run_job",
    "CASE_PREFIX",
]

#: Prefix of a shot / character given as a built-in case (``case:synthetic-human?n_frames=40``).
CASE_PREFIX = "case:"
_JOB_KEYS = {"shot", "character", "landmarks", "method", "params", "out", "name", "timeout"}


#: :attr:`Job.timeout` of a job whose manifest entry sets none: the run's time limit applies.
RUN_DEFAULT = "run default"


@dataclass
class Job:
    """One job, with paths resolved and the retargeter class and writer looked up."""

    name: str
    shot: str
    character: str
    method: str
    params: dict
    out: str
    landmarks: str | None = None
    cls: Any = None
    writer: Callable | None = None
    writer_name: str = ""
    origin: str = ""  # "plugin <entry point> (<distribution> <version>)", for error messages
    #: seconds, None: no limit (as everywhere: faceretarget.config.check_timeout); RUN_DEFAULT:
    #: the manifest does not say, run_batch's ``timeout`` applies
    timeout: float | None | str = RUN_DEFAULT
    replace: bool = False  # replace an existing output (run_batch(redo=True)); never an input
    #: who answers for the job in a worker (:func:`._workers.plugin_owner`); None: its module
    owner: Hashable = None


@dataclass
class JobResult:
    name: str
    status: str  # "done" | "skipped" | "failed"
    out: str
    seconds: float = 0.0
    error: str = ""
    method: str = ""


@dataclass
class BatchSummary:
    results: list[JobResult] = field(default_factory=list)

    def count(self, status: str) -> int:
        return sum(r.status == status for r in self.results)

    @property
    def failed(self) -> list[JobResult]:
        return [r for r in self.results if r.status == "failed"]

    def as_dict(self) -> dict:
        return {
            "done": self.count("done"),
            "skipped": self.count("skipped"),
            "failed": self.count("failed"),
            "jobs": [asdict(r) for r in self.results],
        }


# ---------------------------------------------------------------------------------------
# Manifest
# ---------------------------------------------------------------------------------------
def _inside(root: Path, value: str, what: str, where: str) -> str:
    if not isinstance(value, str) or not value.strip():
        raise ConfigError(f"{where}: {what} must be a non-empty path string, got {value!r}")
    if value.startswith(CASE_PREFIX):
        return value
    path = (root / value).resolve()
    if not path.is_relative_to(root):
        raise ConfigError(
            f"{where}: {what} {value!r} resolves to {path}, outside the manifest's folder {root}; paths must stay inside it"
        )
    return str(path)


def writer_for(out: Path, registry: Registry, where: str) -> Writer:
    """The registered animation :class:`~faceretarget.Writer` for ``out``'s extension."""
    suffix = out.suffix.lower()
    candidates = [
        w
        for w, _ in registry.writers
        if suffix and suffix in w.extensions and w.kind == "animation"
    ]
    if not candidates:
        valid = sorted(
            {
                e
                for w, _ in registry.writers
                if w.kind == "animation"
                for e in w.extensions
                if e != "/"
            }
        )
        raise ConfigError(
            f"{where}: no registered writer for animations with extension {suffix or '(none)'!r} "
            f"(out = {out.name}); available: {', '.join(valid) or 'none registered'}"
        )
    return candidates[0]


def load_manifest(path: PathLike, *, registry: Registry | None = None) -> list[Job]:
    """Parse and check a manifest; returns its jobs (nothing runs).

    Raises :class:`ConfigError` (malformed, unsafe paths, duplicate outputs, no writer)
    or :class:`UnknownNameError` (method or parameter) naming the job.
    """
    from ..errors import FileFormatError
    from ..io._atomic import note_input
    from ..io._common import check_regular, open_regular
    from ..registry import registry as _registry
    from ._workers import plugin_owner
    from .harness import parse_case_spec

    registry = registry or _registry()
    path = Path(path)
    try:
        check_regular(path)  # a FIFO or device is refused, never read
        with open_regular(path) as fh:
            text = fh.read(16 * 2**20 + 1).decode("utf-8")
    except (OSError, UnicodeError, FileFormatError) as exc:
        raise ConfigError(f"cannot read manifest {path}: {exc}") from None
    if len(text) > 16 * 2**20:
        raise ConfigError(f"manifest {path}: larger than 16 MiB; split it into several manifests")
    note_input(path)  # nothing this process writes may replace it
    try:
        data = tomllib.loads(text)
    except tomllib.TOMLDecodeError as exc:
        raise ConfigError(f"manifest {path}: not valid TOML ({exc})") from None
    root = path.parent.resolve()
    unknown_top = set(data) - {"defaults", "job", "jobs"}
    if unknown_top:
        raise ConfigError(
            f"manifest {path}: unknown table(s) {sorted(unknown_top)}; use [defaults] and [[job]]"
        )
    defaults = data.get("defaults", {})
    job, jobs_ = data.get("job", []), data.get("jobs", [])
    if not isinstance(job, list) or not isinstance(jobs_, list):
        raise ConfigError(
            f"manifest {path}: [[job]] must be an array of tables (one [[job]] header per job)"
        )
    entries = job + jobs_
    if not isinstance(defaults, dict) or not all(isinstance(e, dict) for e in entries):
        raise ConfigError(
            f"manifest {path}: [defaults] must be a table and [[job]] an array of tables"
        )
    for where, table in (
        ("[defaults]", defaults),
        *((f"job #{i + 1}", e) for i, e in enumerate(entries)),
    ):
        if not isinstance(table.get("params", {}), dict):
            raise ConfigError(
                f"manifest {path}, {where}: params must be a table, e.g. params = {{ alpha = 0.05 }}"
            )
    if not entries:
        raise ConfigError(f"manifest {path}: no [[job]] entries")
    jobs: list[Job] = []
    outs: dict[str, str] = {}
    for i, entry in enumerate(entries):
        where = f"manifest {path.name}, job #{i + 1}"
        merged = {
            **defaults,
            **entry,
            "params": {**defaults.get("params", {}), **entry.get("params", {})},
        }
        unknown = set(merged) - _JOB_KEYS
        if unknown:
            raise ConfigError(
                f"{where}: unknown key(s) {sorted(unknown)}; valid keys: {sorted(_JOB_KEYS)}"
            )
        missing = [k for k in ("shot", "method", "out") if k not in merged]
        if "character" not in merged and not str(merged.get("shot", "")).startswith(CASE_PREFIX):
            missing.append("character")
        if missing:
            raise ConfigError(f"{where}: missing {', '.join(missing)}")
        merged.setdefault("character", merged["shot"])
        for key in ("shot", "character"):
            if str(merged[key]).startswith(CASE_PREFIX):
                parse_case_spec(merged[key][len(CASE_PREFIX) :])
        if not isinstance(merged["params"], dict):
            raise ConfigError(f"{where}: params must be a table, e.g. params = {{ alpha = 0.05 }}")
        info = registry.resolve(str(merged["method"]))
        defaults_of = info.cls.default_params()
        bad = sorted(set(merged["params"]) - set(defaults_of))
        if bad:
            raise UnknownNameError(
                f"{where}: {info.name} has no parameter(s) {', '.join(bad)}; valid: {', '.join(sorted(defaults_of)) or '(none)'}"
            )
        out = _inside(root, merged["out"], "out", where)
        if str(merged["out"]).startswith(CASE_PREFIX):
            raise ConfigError(f"{where}: out must be a file path")
        shot = _inside(root, merged["shot"], "shot", where)
        character = _inside(root, merged["character"], "character", where)
        landmarks = (
            _inside(root, merged["landmarks"], "landmarks", where)
            if "landmarks" in merged
            else None
        )
        if out in (shot, character, landmarks):
            raise ConfigError(
                f"{where}: out {merged['out']!r} is also an input; choose another output path"
            )
        name = str(merged.get("name") or merged["out"])
        if out in outs:
            raise ConfigError(
                f"{where}: out {merged['out']!r} is already written by {outs[out]!r}; every job needs its own output"
            )
        outs[out] = name
        writer = writer_for(Path(out), registry, where)
        from .. import config

        timeout = (
            config.check_timeout(merged["timeout"], f"{where}: timeout")
            if "timeout" in merged
            else RUN_DEFAULT
        )
        jobs.append(
            Job(
                name,
                shot,
                character,
                info.name,
                dict(merged["params"]),
                out,
                landmarks,
                cls=info.cls,
                writer=writer.write,
                writer_name=writer.name,
                origin=f"plugin {info.plugin.name} ({info.plugin.origin})",
                timeout=timeout,
                owner=plugin_owner(info.plugin.name, info.plugin.builtin),
            )
        )
    inputs = {str(Path(v).resolve()): j.name for j in jobs for v in job_inputs(j)}
    for j in jobs:
        if str(Path(j.out).resolve()) in inputs:
            raise ConfigError(
                f"manifest {path.name}: job {j.name!r} would write {j.out!r}, an input of job {inputs[str(Path(j.out).resolve())]!r}; "
                "outputs must never overwrite inputs"
            )
    names = [j.name for j in jobs]
    if len(set(names)) != len(names):
        dup = sorted({n for n in names if names.count(n) > 1})
        raise ConfigError(f"manifest {path}: job names must be unique; repeated: {dup}")
    return jobs


def job_inputs(job: Job) -> list[str]:
    """The files ``job`` reads: its shot, character and landmarks, and the files their
    readers open on their own (the same-stem mesh a point cache takes its triangles from)."""
    from ..io.sequences import POINTS_ONLY, sibling_topology

    out = []
    for value in (job.shot, job.character, job.landmarks):
        if not value or str(value).startswith(CASE_PREFIX):
            continue
        out.append(str(value))
        if Path(value).suffix.lower() in POINTS_ONLY:
            sibling = sibling_topology(value)
            if sibling is not None:
                out.append(str(sibling))
    return out


def run_inputs(jobs: list[Job], manifest: PathLike | None = None) -> list[str]:
    """Every file a batch run reads (the manifest, each job's inputs) or writes (each
    job's output): what a summary or any other file of the run must never replace."""
    found = [str(manifest)] if manifest is not None else []
    for job in jobs:
        found.extend(job_inputs(job))
        found.append(job.out)
    return found


# ---------------------------------------------------------------------------------------
# One job (runs in a worker process or thread)
# ---------------------------------------------------------------------------------------
def _load_source(spec: str) -> Source:
    from .harness import cached_case

    if spec.startswith(CASE_PREFIX):
        return cached_case(spec[len(CASE_PREFIX) :]).source
    from .. import io

    if not hasattr(io, "load_source"):
        raise ConfigError(
            f"reading {spec} needs faceretarget.io.load_source, which this installation does not provide"
        )
    return io.load_source(spec)


def _load_target(spec: str, landmarks: str | None) -> TargetRig:
    from .harness import cached_case

    if spec.startswith(CASE_PREFIX):
        return cached_case(spec[len(CASE_PREFIX) :]).target
    from .. import io

    if not hasattr(io, "load_target"):
        raise ConfigError(
            f"reading {spec} needs faceretarget.io.load_target, which this installation does not provide"
        )
    return io.load_target(spec, landmarks=landmarks)


def write_animation(
    animation: Animation,
    out: Path,
    writer: Callable[[Animation, Path], object],
    *,
    force: bool = True,
    inputs: Iterable = (),
) -> Path:
    """Write through ``writer`` into a temporary beside ``out`` (faceretarget's one naming
    scheme, :func:`faceretarget.io._atomic.temp_path`), then replace ``out``.

    The destination check is the one every writer uses: never a file read as an input
    by this process (including files a reader opened on its own, such as a sibling
    topology) or listed in ``inputs``; an existing ``out`` only with ``force``.
    Leftovers of killed writers of ``out`` are removed first.
    """
    from ..io._atomic import atomic_path

    out = Path(out)
    out.parent.mkdir(parents=True, exist_ok=True)
    with atomic_path(out, inputs=inputs, force=force) as tmp:
        writer(animation, tmp)
    return out


def remove_leftovers(out: PathLike) -> list[Path]:
    """Temporaries of killed writers of ``out`` removed (see :mod:`faceretarget.io._atomic`)."""
    from ..io._atomic import remove_leftovers as remove

    return remove(Path(out))


def _registered_writer(name: str) -> Callable:
    from ..registry import registry

    for writer, _ in registry().writers:
        if writer.name == name:
            return writer.write
    raise ConfigError(
        f"no writer named {name!r} is registered in this worker; install the plugin that provides it on every worker"
    )


def _portable(jobs: list[Job]) -> list[Job]:
    """Jobs for other processes: a writer callable that does not pickle is looked up by name there."""
    import pickle
    from dataclasses import replace

    out = []
    for job in jobs:
        try:
            pickle.dumps(job.writer)
            out.append(job)
        except Exception:
            out.append(replace(job, writer=None))
    return out


def _who(job: Job) -> str:
    """The method of ``job`` with its plugin and distribution, for error messages."""
    return f"{job.method} [{job.origin}]" if job.origin else job.method


def run_job(job: Job) -> JobResult:
    """Run one job and write its output atomically; never raises (errors are returned)."""
    start = time.perf_counter()
    out = Path(job.out)
    try:
        source = _load_source(job.shot)
        target = _load_target(job.character, job.landmarks)
        retargeter = job.cls(**job.params)
        animation = retargeter.fit(source, target).retarget(
            source
        )  # checked by Retargeter.check_output
        write_animation(
            animation,
            out,
            job.writer or _registered_writer(job.writer_name),
            force=job.replace,
            inputs=job_inputs(job),
        )
        return JobResult(job.name, "done", job.out, time.perf_counter() - start, method=job.method)
    except (
        Exception,
        SystemExit,
    ) as exc:  # reported per job (sys.exit in a plugin too); the batch goes on
        message = " ".join(str(exc).split()) or type(exc).__name__
        return JobResult(
            job.name,
            "failed",
            job.out,
            time.perf_counter() - start,
            f"{_who(job)}: {type(exc).__name__}: {message}",
            job.method,
        )


# ---------------------------------------------------------------------------------------
# Executors
# ---------------------------------------------------------------------------------------
def _job_timeout(job: Job, default: float | None) -> float | None:
    if job.timeout == RUN_DEFAULT:
        return default
    if isinstance(job.timeout, str):  # only RUN_DEFAULT is text
        raise ConfigError(
            f"{_who(job)}: timeout must be seconds, None or RUN_DEFAULT, got {job.timeout!r}"
        )
    return job.timeout


def _failed_run(job: Job, outcome: Outcome) -> JobResult:
    """The result of a job whose worker failed it (time limit, crash, task not movable)."""
    remove_leftovers(job.out)
    error = outcome.error()
    return JobResult(
        job.name,
        "failed",
        job.out,
        outcome.seconds,
        f"{_who(job)}: {type(error).__name__}: {error}; no partial output is left",
        job.method,
    )


def _supervised(
    jobs: list[Job],
    workers: int,
    timeout: float | None,
    on_result: Callable[[JobResult], None],
    env: Mapping[str, str] | None = None,
) -> None:
    """Jobs in supervised worker processes, each killed when it overruns its time limit."""
    from ._workers import DONE, Task, run_supervised

    by_name: dict[Hashable, Job] = {job.name: job for job in jobs}  # by task key

    def on_outcome(outcome: Outcome) -> None:
        job = by_name[outcome.key]
        on_result(outcome.value if outcome.status == DONE else _failed_run(job, outcome))

    groups = (
        [
            Task(
                job.name,
                run_job,
                (job,),
                _job_timeout(job, timeout),
                owner=job.owner
                if job.owner is not None
                else getattr(job.cls, "__module__", job.method),
            )
        ]
        for job in jobs
    )
    run_supervised(groups, workers=workers, on_outcome=on_outcome, env=env)


def run_job_supervised(job: Job, timeout: float | None) -> JobResult:
    """:func:`run_job` in a worker process of its own, stopped after ``timeout`` seconds
    (how a Dask worker enforces a job's time limit)."""
    results: list[JobResult] = []
    _supervised([job], 1, timeout, results.append)
    return results[0]


def _run_local(jobs: list[Job], workers: int, timeout: float | None, bar: tqdm) -> list[JobResult]:
    from ._workers import single_threaded_environ

    results = []

    def on_result(result: JobResult) -> None:
        results.append(result)
        bar.update()
        bar.set_postfix_str(f"{result.name}: {result.status}")

    _supervised(jobs, workers, timeout, on_result, env=single_threaded_environ())
    return results


def _run_dask(
    jobs: list[Job],
    workers: int,
    scheduler: str | None,
    processes: bool,
    timeout: float | None,
    bar: tqdm,
) -> list[JobResult]:
    from .harness import single_threaded_children

    try:
        from distributed import Client, LocalCluster, as_completed
    except ImportError as exc:
        raise ConfigError(
            f"--dask / --scheduler need dask.distributed, in the cluster extra: pip install 'faceretarget[cluster]' ({exc})"
        ) from None
    cluster = None
    try:
        if scheduler:
            try:
                client = Client(scheduler, timeout="20s")
            except (OSError, TimeoutError) as exc:
                raise ConfigError(
                    f"cannot reach the Dask scheduler at {scheduler!r}: {exc}"
                ) from None
        else:
            with single_threaded_children():
                cluster = LocalCluster(
                    n_workers=workers,
                    threads_per_worker=1,
                    processes=processes,
                    host="127.0.0.1",
                    protocol="tcp://",
                    dashboard_address=None,
                    silence_logs=40,
                )
            client = Client(cluster)
        results = []
        token = secrets.token_hex(4)
        futures = {}
        for i, job in enumerate(jobs):
            limit = _job_timeout(job, timeout)
            call: tuple[Any, ...]
            if limit is None:
                call = (run_job, job)
            else:  # the job goes on to a worker process (with dask_processes, run_batch made it portable already)
                call = (run_job_supervised, job if processes else _portable([job])[0], limit)
            futures[client.submit(*call, key=f"faceretarget-job-{i}-{token}", pure=False)] = job
        for future in as_completed(list(futures)):
            job = futures[future]
            try:
                result = future.result()
            except Exception as exc:  # e.g. KilledWorker
                result = JobResult(
                    job.name,
                    "failed",
                    job.out,
                    0.0,
                    f"{_who(job)}: the Dask worker failed: {type(exc).__name__}: {exc}",
                    job.method,
                )
            results.append(result)
            bar.update()
            bar.set_postfix_str(f"{result.name}: {result.status}")
        client.close()
        return results
    finally:
        if cluster is not None:
            cluster.close()


def run_batch(
    manifest: PathLike | list[Job],
    *,
    executor: str = "local",
    scheduler: str | None = None,
    workers: int | None = None,
    redo: bool = False,
    dask_processes: bool = True,
    registry: Registry | None = None,
    progress: bool = True,
    timeout: float | None = None,
) -> BatchSummary:
    """Run the jobs of ``manifest`` (a path, or a list of :class:`Job` from :func:`load_manifest`).

    executor : "local" (process pool) or "dask" (``scheduler`` address, or a local cluster
        of ``workers`` workers on 127.0.0.1; ``dask_processes=False`` uses threads)
    workers : parallel jobs (default: the CPU count)
    redo : run jobs whose output already exists (default: skip them)
    timeout : seconds a job may take unless its manifest entry sets ``timeout``; a job over
        its limit has its worker process killed and is reported failed (None or 0: no limit).
        Local jobs always run in supervised worker processes; on Dask, a job with a limit
        runs in a child process of the Dask worker.
    """
    from tqdm import tqdm

    if executor not in ("local", "dask"):
        raise ConfigError(f"executor must be 'local' or 'dask', got {executor!r}")
    jobs = manifest if isinstance(manifest, list) else load_manifest(manifest, registry=registry)
    from .. import config

    timeout = config.check_timeout(timeout, "batch: timeout")
    workers = int(workers or os.cpu_count() or 1)
    if workers < 1:
        raise ConfigError(f"workers must be >= 1, got {workers}")
    from dataclasses import replace as _with

    summary = BatchSummary()
    pending = []
    for job in jobs:
        remove_leftovers(job.out)  # what killed runs left, also for outputs skipped below
        if redo:
            job = _with(job, replace=True)
        if not redo and Path(job.out).exists():
            summary.results.append(JobResult(job.name, "skipped", job.out, method=job.method))
        else:
            pending.append(job)
    bar = tqdm(total=len(pending), desc="batch", unit="job", disable=not progress, file=sys.stderr)
    try:
        if pending:
            if executor == "dask":
                summary.results.extend(
                    _run_dask(
                        pending if not dask_processes else _portable(pending),
                        workers,
                        scheduler,
                        dask_processes,
                        timeout,
                        bar,
                    )
                )
            else:
                summary.results.extend(_run_local(_portable(pending), workers, timeout, bar))
    finally:
        bar.close()
    order = {j.name: i for i, j in enumerate(jobs)}
    summary.results.sort(key=lambda r: order.get(r.name, 0))
    return summary


def write_summary(
    summary: BatchSummary, path: PathLike, *, force: bool = False, inputs: Iterable = ()
) -> Path:
    """The summary as JSON (atomically); never over a file of the run (``inputs``: see
    :func:`run_inputs`), an existing file only with ``force``."""
    from ..io._atomic import write_bytes

    return write_bytes(
        path,
        (json.dumps(summary.as_dict(), indent=1) + "\n").encode("utf-8"),
        inputs=inputs,
        force=force,
    )


def format_summary(summary: BatchSummary) -> str:
    lines = [
        f"batch: {summary.count('done')} done, {summary.count('skipped')} skipped (output exists), {summary.count('failed')} failed"
    ]
    for r in summary.failed:
        lines.append(f"  FAILED {r.name} ({r.method}): {r.error}")
    return "\n".join(lines)
