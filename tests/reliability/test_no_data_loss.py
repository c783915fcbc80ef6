"""No data loss: writers are atomic, never replace an input, and a killed writer leaves the old output.

- Every registered writer is killed (SIGKILL) in a child process half-way through its
  first write, and again after the data is complete but before the rename; the previous
  output must be byte-for-byte intact, nothing partial may be visible, and the next
  write cleans up what the dead writer left.
- A write that fails (the file-size limit ``RLIMIT_FSIZE`` stands in for a full disk)
  raises a typed error and leaves the previous output and no temporary file.
- Inputs are never overwritten: ``--force`` is needed to replace an existing output,
  and even ``--force`` never replaces the input (same path, symlink, hard link,
  ``..`` spelling, a folder holding the input).
"""

import json
import os
import select
import signal
import subprocess
import sys
from pathlib import Path

import pytest
from hypothesis import given
from hypothesis import strategies as st
from reliability import samples
from reliability.fuzzkit import count, fuzz, typed

import faceretarget as fr
from faceretarget import cli, errors
from faceretarget.io import _atomic

AREA = "writers and outputs"
HERE = Path(__file__).resolve().parent
CHILD = HERE / "_kill_writer.py"


def distinct_writers():
    """One (writer, plugin) per distinct write function (the npz-* writers share one, as do the glTF ones)."""
    seen, out = set(), []
    for w, info in samples.writers():
        if id(w.write) not in seen:
            seen.add(id(w.write))
            out.append((w, info))
    return out


WRITERS = distinct_writers()
WRITER_IDS = [w.name for w, _ in WRITERS]
ALL_WRITERS = [w for w, _ in samples.writers()]
MODES = ("mid", "commit")
#: child processes run at once by the kill tests
CONCURRENCY = 4


def out_path(folder: Path, writer) -> Path:
    ext = writer.extensions[0]
    return folder / ("out" if ext == "/" else f"out{ext}")


def snapshot(path: Path):
    """Bytes of a file, {name: bytes} of a folder, None if absent."""
    if path.is_dir():
        return {p.name: p.read_bytes() for p in sorted(path.iterdir())}
    return path.read_bytes() if path.exists() else None


def write_old(writer, path: Path):
    writer.write(samples.sample(writer.kind, frames=2, n=3), path, force=True)
    return snapshot(path)


def child_env(scratch: Path):
    """The child's environment; its temporary files (a SIGKILLed writer cannot remove its
    scratch folders) go to ``scratch``, a folder of the test session, not the user's /tmp."""
    return dict(
        os.environ,
        PYTHONPATH=os.pathsep.join([str(HERE.parent)] + sys.path),
        TMPDIR=str(scratch),
        TEMP=str(scratch),
        TMP=str(scratch),
    )


def kill_when_stopped(procs, timeout: float = 180.0):
    """Wait for each child's MID/COMMIT line and SIGKILL it; returns [(line, stderr)]."""
    out = []
    for proc in procs:
        try:
            ready, _, _ = select.select([proc.stdout], [], [], timeout)
            line = proc.stdout.readline().strip() if ready else "TIMEOUT"
            if line in ("MID", "COMMIT"):
                os.kill(proc.pid, signal.SIGKILL)
            proc.wait(timeout=timeout)
            err = proc.stderr.read()
        finally:
            if proc.poll() is None:
                proc.kill()
                proc.wait()
            proc.stdout.close()
            proc.stderr.close()
        out.append((line, err))
    return out


@pytest.fixture(scope="module")
def killed(tmp_path_factory):
    """Every distinct writer, killed in each mode: {(name, mode): (line, stderr, folder, out, old)}."""
    jobs = []
    for writer, info in WRITERS:
        for mode in MODES:
            folder = tmp_path_factory.mktemp(f"kill_{mode}_{writer.name}")
            out = out_path(folder, writer)
            jobs.append((writer, info, mode, folder, out, write_old(writer, out)))
    jobs.append(
        (WRITERS[0][0], WRITERS[0][1], "first", tmp_path_factory.mktemp("kill_first"), None, None)
    )
    results = {}
    scratch = tmp_path_factory.mktemp("kill_scratch")
    for start in range(0, len(jobs), CONCURRENCY):
        batch = jobs[start : start + CONCURRENCY]
        procs = []
        for writer, _info, mode, folder, out, _old in batch:
            target = out if out is not None else out_path(folder, writer)
            procs.append(
                subprocess.Popen(
                    [
                        sys.executable,
                        str(CHILD),
                        writer.name,
                        str(target),
                        "mid" if mode == "first" else mode,
                        "builtin" if info.builtin else "plugin",
                    ],
                    stdout=subprocess.PIPE,
                    stderr=subprocess.PIPE,
                    text=True,
                    env=child_env(scratch),
                )
            )
        for (writer, _info, mode, folder, out, old), (line, err) in zip(
            batch, kill_when_stopped(procs)
        ):
            results[(writer.name, mode)] = (
                line,
                err,
                folder,
                out if out is not None else out_path(folder, writer),
                old,
            )
    return results


@pytest.mark.parametrize("writer, info", WRITERS, ids=WRITER_IDS)
@pytest.mark.parametrize("mode", MODES)
def test_sigkill_keeps_previous_output(writer, info, mode, killed):
    line, err, folder, out, old = killed[(writer.name, mode)]
    count(AREA)
    assert line in ("MID", "COMMIT"), (
        f"the child writer was not stopped mid-write ({line}): {err[-2000:]}"
    )
    assert snapshot(out) == old, (
        f"{writer.name}: after SIGKILL ({mode}) the previous output is not intact (now: {type(snapshot(out)).__name__})"
    )
    visible = [
        p.name for p in folder.iterdir() if p.name != out.name and not p.name.startswith(".")
    ]
    assert not visible, f"{writer.name}: a killed write left visible files {visible}"
    # the next write removes what the dead writer left and succeeds
    writer.write(samples.sample(writer.kind), out, force=True)
    assert sorted(p.name for p in folder.iterdir()) == [out.name], (
        f"{writer.name}: leftovers of the killed writer were not cleaned"
    )


def test_sigkill_before_first_output_leaves_nothing(killed):
    writer = WRITERS[0][0]
    line, err, folder, out, _ = killed[(writer.name, "first")]
    assert line == "MID", err[-2000:]
    assert not out.exists(), "a killed first write must not leave an output"
    assert all(p.name.startswith(".") for p in folder.iterdir())


FSIZE_CHILD = """
import json, os, resource, signal, sys
sys.path.insert(0, {tests!r})
from reliability import samples
from faceretarget.registry import registry
from faceretarget.errors import FaceRetargetError
jobs = json.loads(sys.argv[1])
writers = {{w.name: w for w, _ in registry().writers}}
signal.signal(signal.SIGXFSZ, signal.SIG_IGN)
resource.setrlimit(resource.RLIMIT_FSIZE, (64, 64))
for name, out in jobs:
    try:
        writers[name].write(samples.sample(writers[name].kind), out, force=True)
        verdict = "OK"
    except FaceRetargetError as exc:
        verdict = f"TYPED {{type(exc).__name__}}: {{exc}}"
    except Exception as exc:
        verdict = f"UNTYPED {{type(exc).__name__}}: {{exc}}"
    print(json.dumps([name, verdict]), flush=True)
"""


@pytest.fixture(scope="module")
def disk_full(tmp_path_factory):
    """Each distinct writer replacing an old output under a 64-byte file-size limit (one child)."""
    jobs = {}
    for writer, _ in WRITERS:
        folder = tmp_path_factory.mktemp(f"fsize_{writer.name}")
        out = out_path(folder, writer)
        jobs[writer.name] = (folder, out, write_old(writer, out))
    code = FSIZE_CHILD.format(tests=str(HERE.parent))
    arg = json.dumps([[name, str(out)] for name, (_, out, _) in jobs.items()])
    run = subprocess.run(
        [sys.executable, "-c", code, arg],
        capture_output=True,
        text=True,
        timeout=300,
        env=child_env(tmp_path_factory.mktemp("fsize_scratch")),
    )
    verdicts = dict(json.loads(line) for line in run.stdout.splitlines() if line.startswith("["))
    return {
        name: (verdicts.get(name, "NO RESULT " + run.stderr[-500:]),) + job
        for name, job in jobs.items()
    }


@pytest.mark.parametrize("writer, info", WRITERS, ids=WRITER_IDS)
def test_failed_write_is_typed_and_keeps_previous_output(writer, info, disk_full):
    """A write that fails half-way (disk full; here the file-size limit) is an OutputError."""
    verdict, folder, out, old = disk_full[writer.name]
    count(AREA)
    assert snapshot(out) == old, f"{writer.name}: a failed write changed the previous output"
    assert sorted(p.name for p in folder.iterdir()) == [out.name], (
        f"{writer.name}: a failed write left files behind"
    )
    assert verdict.startswith("TYPED OutputError"), (
        f"{writer.name}: a write that fails with 'file too large' must raise OutputError, got: {verdict}"
    )


# ---------------------------------------------------------------------------------------
# inputs are never overwritten
# ---------------------------------------------------------------------------------------
@pytest.mark.parametrize("writer", ALL_WRITERS, ids=[w.name for w in ALL_WRITERS])
def test_existing_output_needs_force(writer, tmp_path):
    out = out_path(tmp_path, writer)
    old = write_old(writer, out)
    refused = typed(AREA, writer.write, samples.sample(writer.kind), out)
    assert isinstance(refused, errors.OutputError), (
        f"{writer.name} replaced an existing output without force"
    )
    assert snapshot(out) == old
    missing_folder = typed(
        AREA, writer.write, samples.sample(writer.kind), tmp_path / "no" / "such" / out.name
    )
    assert isinstance(missing_folder, errors.OutputError)
    assert not (tmp_path / "no").exists()


RELATIONS = ["same", "dotdot", "symlink", "hardlink", "relative", "folder_with_input"]


@st.composite
def spellings(draw):
    return draw(st.sampled_from(RELATIONS)), draw(st.booleans())


def spell_output(relation: str, src: Path, tmp: Path) -> Path:
    """Another path for (or holding) the file ``src``."""
    if relation == "same":
        return src
    if relation == "dotdot":
        return src.parent / "sub" / ".." / src.name
    if relation == "symlink":
        link = tmp / f"link{src.suffix}"
        if not link.exists():
            link.symlink_to(src)
        return link
    if relation == "hardlink":
        link = tmp / f"hard{src.suffix}"
        if not link.exists():
            os.link(src, link)
        return link
    if relation == "relative":
        return Path(os.path.relpath(src))
    return src.parent  # a folder output that holds the input


@given(rel=spellings())
@fuzz(24)
def test_convert_never_overwrites_its_input(rel, tmp_path_factory, capsys):
    relation, force = rel
    tmp = tmp_path_factory.mktemp("inputs")
    (tmp / "sub").mkdir()
    src = tmp / "in.obj"
    fr.save(samples.grid_mesh(), src)
    before = src.read_bytes()
    out = spell_output(relation, src, tmp)
    count(AREA)
    code = cli.main(["convert", str(src), str(out)] + (["--force"] if force else []))
    err = capsys.readouterr().err
    assert code == cli.EXIT_ERROR, f"convert {relation} (force={force}) was not refused: {err}"
    assert "Traceback" not in err and len(err.strip().splitlines()) == 1
    assert src.read_bytes() == before, "the input changed"


def test_save_refuses_a_file_read_in_this_process(tmp_path):
    path = tmp_path / "mesh.obj"
    fr.save(samples.grid_mesh(), path)
    fr.load(path)
    before = path.read_bytes()
    result = typed(AREA, fr.save, samples.grid_mesh(4), path, force=True)
    assert isinstance(result, errors.OutputError), "force must not lift the input protection"
    assert path.read_bytes() == before
    _atomic.clear_inputs()


def test_convert_force_replaces_only_a_non_input(tmp_path, capsys):
    src, out = tmp_path / "in.obj", tmp_path / "out.obj"
    fr.save(samples.grid_mesh(), src)
    out.write_text("old")
    assert cli.main(["convert", str(src), str(out)]) == cli.EXIT_ERROR
    assert out.read_text() == "old"
    assert cli.main(["convert", str(src), str(out), "--force"]) == 0
    assert out.read_text() != "old"
    capsys.readouterr()
