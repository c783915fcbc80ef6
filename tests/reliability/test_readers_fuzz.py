"""Every registered reader answers random, empty, truncated and corrupted files with a typed error.

Readers are taken from ``registry().readers``, so formats added by plugins are fuzzed
too. For each reader a valid seed file is written by a registered writer of the same
extension (see ``samples.seed``); the fuzzer then truncates it, flips bytes, splices in
random bytes or repeats chunks. A reader may only raise a ``FaceRetargetError``
subclass, must not hang (hypothesis deadline + pytest-timeout), must return an object of
its declared kind when it succeeds, and must not create files.
"""

import shutil
from pathlib import Path

import pytest
from hypothesis import given
from hypothesis import strategies as st
from reliability import samples
from reliability.fuzzkit import count, failed, fuzz, typed

import faceretarget as fr
from faceretarget import cli, errors

AREA = "file readers"
KIND_TYPES = {
    "mesh": fr.Mesh,
    "mesh_sequence": fr.MeshSequence,
    "rig": fr.BlendshapeRig,
    "markers": fr.MarkerSequence,
    "weights": fr.WeightSequence,
    "animation": fr.Animation,
}
READERS = samples.readers()
IDS = [f"{r.name}[{info.distribution}]" for r, info in READERS]
FOLDER_NAMES = [
    "neutral.obj",
    "frame_0001.obj",
    "frame_0002.obj",
    "jawOpen.obj",
    "rig.json",
    "sequence.json",
    "x.ply",
]


@pytest.fixture(scope="module")
def seeds(tmp_path_factory):
    folder = tmp_path_factory.mktemp("seeds")
    return lambda reader: samples.seed(reader.name, str(folder))


def listing(folder: Path):
    return sorted(str(p.relative_to(folder)) for p in folder.rglob("*"))


def check_read(reader, path: Path, options=None):
    """Read ``path``: a typed error, or an object of the reader's kind; no file created next to it."""
    folder = path.parent
    before = listing(folder)
    result = typed(AREA, reader.read, path, **(options or {}))
    assert listing(folder) == before, (
        f"reader {reader.name} created or removed files: {set(listing(folder)) ^ set(before)}"
    )
    if not failed(result):
        want = KIND_TYPES.get(reader.kind)
        assert want is None or isinstance(result, want), (
            f"reader {reader.name} ({reader.kind}) returned {type(result).__name__}"
        )
    return result


def fresh(tmp_path_factory, reader, label):
    folder = tmp_path_factory.mktemp(f"{label}_{reader.name}")
    ext = reader.extensions[0]
    return folder, (folder / "input" if ext == "/" else folder / f"input{ext}")


def put(path: Path, data: bytes, folder_files=None):
    """Write ``data`` to ``path`` (a file), or fill folder ``path`` with ``folder_files``."""
    if path.is_dir():
        shutil.rmtree(path)
    elif path.exists():
        path.unlink()
    if folder_files is None:
        path.write_bytes(data)
        return
    path.mkdir()
    for name, content in folder_files.items():
        (path / name).write_bytes(content)


# ---------------------------------------------------------------------------------------
@pytest.mark.parametrize("reader, info", READERS, ids=IDS)
def test_empty_input_is_a_typed_error(reader, info, tmp_path):
    path = tmp_path / ("empty" if "/" in reader.extensions else f"empty{reader.extensions[0]}")
    if "/" in reader.extensions:
        path.mkdir()
    else:
        path.write_bytes(b"")
    result = check_read(reader, path)
    assert isinstance(result, errors.FaceRetargetError), (
        f"{reader.name} accepted an empty input: {result!r}"
    )
    missing = check_read(
        reader, tmp_path / f"missing{reader.extensions[0] if reader.extensions[0] != '/' else ''}"
    )
    assert isinstance(missing, errors.FaceRetargetError)


@pytest.mark.parametrize("reader, info", READERS, ids=IDS)
@given(
    data=st.binary(max_size=3000),
    names=st.lists(st.sampled_from(FOLDER_NAMES), min_size=1, max_size=3, unique=True),
)
@fuzz(12)
def test_random_bytes(reader, info, tmp_path_factory, data, names):
    folder, path = fresh(tmp_path_factory, reader, "random")
    if "/" in reader.extensions:
        put(path, b"", {n: data[i :: len(names)] for i, n in enumerate(names)})
    else:
        put(path, data)
    check_read(reader, path)


@st.composite
def mutations(draw, seed: bytes):
    """``seed`` truncated, with bytes flipped, random bytes spliced in, or a chunk repeated."""
    n = len(seed)
    kind = draw(st.sampled_from(["truncate", "flip", "splice", "repeat", "zero_tail"]))
    at = draw(st.integers(0, max(0, n - 1)))
    if kind == "truncate":
        return seed[:at]
    if kind == "flip":
        out = bytearray(seed)
        for pos in draw(st.lists(st.integers(0, max(0, n - 1)), min_size=1, max_size=8)):
            if n:
                out[pos] ^= draw(st.integers(1, 255))
        return bytes(out)
    if kind == "splice":
        junk = draw(st.binary(min_size=1, max_size=64))
        cut = draw(st.integers(0, 64))
        return seed[:at] + junk + seed[at + cut :]
    if kind == "repeat":
        length = draw(st.integers(1, 256))
        return seed[:at] + seed[at : at + length] * draw(st.integers(2, 4)) + seed[at + length :]
    return seed[:at] + b"\x00" * (n - at)


def seed_bytes(seed_path: Path) -> dict:
    """The seed as {relative name: bytes} (one entry '' for a file)."""
    if seed_path.is_dir():
        return {p.name: p.read_bytes() for p in sorted(seed_path.iterdir()) if p.is_file()}
    return {"": seed_path.read_bytes()}


@pytest.mark.parametrize("reader, info", READERS, ids=IDS)
@given(data=st.data())
@fuzz(20)
def test_truncated_and_corrupted_valid_files(reader, info, seeds, tmp_path_factory, data):
    found = seeds(reader)
    if found is None:
        pytest.skip(
            f"no registered writer produces a file {reader.name} reads; covered by the random-bytes test only"
        )
    seed_path, options = found
    parts = seed_bytes(seed_path)
    target = data.draw(st.sampled_from(sorted(parts)))
    parts = dict(parts, **{target: data.draw(mutations(parts[target]))})
    folder, path = fresh(tmp_path_factory, reader, "mutated")
    if seed_path.is_dir():
        put(path, b"", parts)
    else:
        put(path, parts[""])
    check_read(reader, path, options)


@pytest.mark.parametrize("reader, info", READERS, ids=IDS)
def test_seed_reads_back(reader, info, seeds):
    """Precondition of the mutation fuzzing: the seed itself is read cleanly."""
    found = seeds(reader)
    if found is None:
        pytest.skip(f"no registered writer produces a file {reader.name} reads")
    path, options = found
    result = check_read(reader, path, options)
    assert not failed(result), result


# ---------------------------------------------------------------------------------------
# the command line: one line on stderr, exit 2, no output written
# ---------------------------------------------------------------------------------------
CONVERT_OUT = [".glb", ".npz", ".obj", ".pc2", ".csv"]


@pytest.mark.parametrize("ext", sorted({e for r, _ in READERS for e in r.extensions if e != "/"}))
@given(data=st.data())
@fuzz(6)
def test_convert_garbage_leaves_no_output(ext, seeds, tmp_path_factory, data, capsys):
    folder = tmp_path_factory.mktemp("convert")
    src = folder / f"in{ext}"
    found = [f for f in (seeds(r) for r, _ in READERS if ext in r.extensions) if f is not None]
    if found and data.draw(st.booleans()):
        src.write_bytes(data.draw(mutations(found[0][0].read_bytes())))
    else:
        src.write_bytes(data.draw(st.binary(max_size=2000)))
    out = folder / f"out{data.draw(st.sampled_from(CONVERT_OUT))}"
    before = listing(folder)
    capsys.readouterr()
    count(AREA)
    code = cli.main(["convert", str(src), str(out)])
    err = capsys.readouterr().err
    assert code in (0, cli.EXIT_ERROR), f"convert exited {code}: {err}"
    assert "Traceback" not in err
    if code == 0:
        assert out.exists()
    else:
        assert len(err.strip().splitlines()) == 1, f"errors are one line: {err!r}"
        assert listing(folder) == before, (
            "a failed convert must leave nothing behind (no output, no temporary file)"
        )
