"""The random long mode over the classes of fault of issue 15 ("close the ten holes").

Each property runs a few examples in CI mode and ``FACERETARGET_FUZZ_EXAMPLES`` random
ones in long mode (``fuzzkit.fuzz``); inputs are counted per class in the session summary:

- ``glTF content sizes``: a GLB whose stored frame rate, key times and accessor counts are
  random, read under a small memory budget: a typed error, or a result whose peak memory
  (tracemalloc) stays within the budget;
- ``text reader memory``: OBJ, OFF, ASCII PLY/STL, TRC, marker and weights CSV made of a
  random line repeated up to 20,000 times: a typed error, or a peak within what the
  reader checked against the budget and within 4x the file plus one chunk's work;
- ``non-regular inputs``: a FIFO, a link to /dev/zero or /dev/null, a socket, a folder, a
  dangling or looping link where every reader expects a file: a typed error, at once;
- ``destinations``: an input spelled differently (relative, ``./``, ``a/../``, a symbolic
  or hard link, another case) or an existing file, written by ``save``, ``write_bytes`` or
  ``faceretarget convert`` with and without ``--force``: inputs never change, an existing
  file is replaced only with force, nothing is left behind;
- ``temp leftovers``: folders of random temporary names (the scheme, the former batch
  scheme, nested, moved-aside folders, look-alikes a user may own) of dead, live-locked
  and reused pids: cleanup removes every dead writer's file and nothing else;
- ``plugin hook results``: hooks returning values of random types (and objects whose
  ``repr``, iteration or attributes raise): the registry skips and names the plugin;
- ``exit codes``: random command lines over garbage files: 0, 1 or 2 with one message,
  never an internal error or a traceback.
"""

import os
import socket
import threading
import types
from pathlib import Path

import numpy as np
import pytest
from hypothesis import assume, given
from hypothesis import strategies as st
from memtools import traced_memory
from reliability import fuzzkit, samples
from reliability.fuzzkit import any_floats, count, failed, fuzz, junk, typed

import faceretarget as fr
from faceretarget import cli, errors
from faceretarget.hookspecs import Reader, Writer
from faceretarget.io import _atomic, _common
from faceretarget.io.gltf import glb_bytes, glb_document
from faceretarget.registry import Registry, registry

BUDGET = "FACERETARGET_MEMORY_BUDGET"
MiB = 1 << 20


@pytest.fixture(autouse=True)
def _forget_inputs():
    _atomic.clear_inputs()
    yield
    _atomic.clear_inputs()


@pytest.fixture(scope="module", autouse=True)
def _warm():
    registry()  # the registry's own memory is not a reader's


def traced(call):
    """(outcome of ``call`` through typed(), peak bytes, largest size checked against the budget)."""
    return traced_memory(call)


# =======================================================================================
# glTF frame rates, key times and accessor counts
# =======================================================================================
GLTF_AREA = "glTF content sizes"


def glb_any(doc: dict, blob: bytes) -> bytes:
    """:func:`glb_bytes`, but NaN and infinity may be written into the JSON (as Python does)."""
    import json
    import struct

    raw = json.dumps(doc, separators=(",", ":"), allow_nan=True).encode("utf-8")
    raw += b" " * ((-len(raw)) % 4)
    head = glb_bytes({}, b"")[:4]
    total = 12 + 8 + len(raw) + 8 + len(blob)
    return b"".join(
        [
            head,
            struct.pack("<II", 2, total),
            struct.pack("<II", len(raw), 0x4E4F534A),
            raw,
            struct.pack("<II", len(blob), 0x004E4942),
            blob,
        ]
    )


def _times_accessor(doc) -> int:
    return doc["animations"][0]["samplers"][0]["input"]


@given(
    fps=st.one_of(
        st.sampled_from([24.0, 30, 60.0, 1e3, 1e6]),
        any_floats(),
        st.integers(-10, 10**15),
        st.sampled_from(["30", None, True, [30], {"a": 1}]),
    ),
    fps_option=st.one_of(
        st.none(), st.none(), st.sampled_from([24.0, 1e5]), any_floats(), st.integers(-5, 10**9)
    ),
    keep_times=st.booleans(),
    times=st.lists(
        st.one_of(
            st.floats(-1e6, 1e6, width=32),
            st.sampled_from([0.0, 1e-7, 1e-30, 3.4e38, float("nan"), float("inf")]),
        ),
        min_size=4,
        max_size=4,
    ),
    count_change=st.sampled_from([0, 0, 0, -1, 1, 10**9, -(10**9)]),
    drop_exact=st.booleans(),
    kind=st.sampled_from(["animation", "mesh_sequence", "weights"]),
    budget=st.sampled_from(["64K", "1M", "4M"]),
)
@fuzz(25)
def test_gltf_frame_rates_key_times_and_counts(
    fps,
    fps_option,
    keep_times,
    times,
    count_change,
    drop_exact,
    kind,
    budget,
    tmp_path_factory,
    monkeypatch,
):
    anim = samples.sample("animation")
    doc, blob = glb_document(anim)
    info = doc["asset"]["extras"]["faceretarget"]
    info["fps"] = fps
    if drop_exact:
        info["arrays"] = {}
    acc = doc["accessors"][_times_accessor(doc)]
    view = doc["bufferViews"][acc["bufferView"]]
    start = view.get("byteOffset", 0) + acc.get("byteOffset", 0)
    blob = bytearray(blob)
    if not keep_times:
        blob[start : start + 16] = np.asarray(times, dtype="<f4").tobytes()
        acc.pop("min", None), acc.pop("max", None)
        acc["count"] = max(0, acc["count"] + count_change) if count_change > -(10**9) else -5
    path = tmp_path_factory.mktemp("gltf") / "anim.glb"
    path.write_bytes(glb_any(doc, bytes(blob)))
    monkeypatch.setenv(BUDGET, budget)
    limit = _common.config.memory_budget()
    options = {} if fps_option is None else {"fps": fps_option}
    result, peak, checked = traced(lambda: typed(GLTF_AREA, fr.load, path, kind=kind, **options))
    if not failed(result):
        assert peak <= limit + MiB, (
            f"read within a budget of {limit >> 10} KiB but peaked at {peak >> 10} KiB"
        )
        assert np.isfinite(result.fps) and result.fps > 0


# =======================================================================================
# text readers: memory of a random line repeated
# =======================================================================================
TEXT_AREA = "text reader memory"
_FMT = st.sampled_from(["{!r}", "{:.3e}", "{:g}", "{:.0f}", " {} ", "{}\t"])


def _num(draw):
    value = draw(
        st.one_of(
            st.floats(-1e6, 1e6),
            st.sampled_from([0.0, -0.0, 1e-300, 1e300, float("nan"), float("inf")]),
        )
    )
    return draw(_FMT).format(value)


@st.composite
def text_files(draw):
    """(extension, load options, file text) of a random line repeated ``n`` times."""
    kind = draw(st.sampled_from(["obj", "off", "ply", "stl", "trc", "markers_csv", "weights_csv"]))
    n = draw(st.sampled_from([1, 7, 300, 4000, 20000]))
    a, b, c = _num(draw), _num(draw), _num(draw)
    end = draw(st.sampled_from(["\n", "\r\n", " \n", "\t\n"]))
    odd = draw(st.sampled_from(["", "", "# note", "\t", "x", "1 2", '"q"', ",,", "\u00e9"]))

    def rows(template):
        body = template.replace("{a}", a).replace("{b}", b).replace("{c}", c).replace("{odd}", odd)
        return end.join(body.replace("{i}", str(i)) for i in range(n)) + end

    if kind == "obj":
        line = draw(
            st.sampled_from(
                [
                    "v {a} {b} {c}",
                    "v {a} {b} {c} 1",
                    "vt {a} {b}",
                    "v {i} {a} {b}",
                    "{odd}",
                    "v {a} {b}{odd}",
                    "vn 0 0 1",
                    "g g{i}",
                ]
            )
        )
        return ".obj", {}, rows(line) + "v 1 0 0\nv 0 1 0\nv 0 0 1\nf -1 -2 -3\n"
    if kind in ("off", "ply"):
        line = draw(
            st.sampled_from(
                ["{a} {b} {c}", "{i} {a} {b}", "{a} {b} {c} 255 0 0", "{a} {b}{odd}", "{odd}"]
            )
        )
        declared = n + 3 + draw(st.sampled_from([0, 0, -1, 1]))
        head = (
            f"OFF\n{declared} 1 0\n"
            if kind == "off"
            else f"ply\nformat ascii 1.0\nelement vertex {declared}\nproperty float x\nproperty float y\nproperty float z\n"
            "element face 1\nproperty list uchar int vertex_indices\nend_header\n"
        )
        return f".{kind}", {}, head + rows(line) + f"1 0 0\n0 1 0\n0 0 1\n3 {n} {n + 1} {n + 2}\n"
    if kind == "stl":
        vertex = draw(
            st.sampled_from(
                [
                    "vertex {i} {a} {b}",
                    "vertex {a} {b} {c}",
                    "vertex {i} {a}",
                    "vertex {i} {a} {b}{odd}",
                ]
            )
        )
        facet = (
            " facet normal 0 0 1\n  outer loop\n   "
            + "\n   ".join(vertex.replace("{i}", "{i}" + s) for s in ("1", "2", "3"))
            + "\n  endloop\n endfacet"
        )
        return ".stl", {}, "solid fuzz\n" + rows(facet) + "endsolid fuzz\n"
    if kind == "trc":
        line = draw(
            st.sampled_from(
                [
                    "{i}\t0\t{a}\t{b}\t{c}",
                    "{i}\t0\t\t\t",
                    "{i}\t0\t{a}",
                    "{i}\t0\t{a}\t{b}\t{c}\t{odd}",
                    "\t\t{a}\t{b}\t{c}",
                ]
            )
        )
        declared = n + draw(st.sampled_from([0, 0, -1, 1]))
        head = (
            f"PathFileType\t4\t(X/Y/Z)\tf.trc\nDataRate\tCameraRate\tNumFrames\tNumMarkers\tUnits\n60\t60\t{declared}\t1\tmm\n"
            "Frame#\tTime\tm\t\t\n\t\tX1\tY1\tZ1\n\n"
        )
        return ".trc", {}, head + rows(line)
    if kind == "markers_csv":
        line = draw(
            st.sampled_from(
                [
                    "{a},{b},{c}",
                    ",,",
                    "{a},,{c}",
                    "{a};{b};{c}",
                    '"{a}",{b},{c}',
                    "{a},{b},{c},{odd}",
                    "{odd}",
                ]
            )
        )
        return ".csv", {"kind": "markers"}, "m_x,m_y,m_z" + end + rows(line)
    line = draw(
        st.sampled_from(["{a},{b}", "0.5,0.25", ",", "{a},{odd}", "00:00:{i}:01.000,2,0.1,0.2"])
    )
    head = "Timecode,BlendShapeCount,a,b" if line.startswith("00:") else "a,b"
    return ".csv", {"kind": "weights"}, head + end + rows(line)


@given(spec=text_files(), budget=st.sampled_from(["256K", "2M", "8M", "64M"]))
@fuzz(25)
def test_text_readers_stay_within_what_they_checked(spec, budget, tmp_path_factory, monkeypatch):
    ext, options, text = spec
    path = tmp_path_factory.mktemp("text") / f"f{ext}"
    path.write_bytes(text.encode("utf-8"))
    size = path.stat().st_size
    monkeypatch.setenv(BUDGET, budget)
    result, peak, checked = traced(lambda: typed(TEXT_AREA, fr.load, path, **options))
    if failed(result):
        return
    slack = 256 * 1024  # the model object, names, the reader's own frame: not sized by the file
    assert peak <= checked + slack, (
        f"peak {peak >> 10} KiB, but only {checked / 1024:.0f} KiB was checked against the budget"
    )
    work = _common.CHUNK_FACTOR * min(size, 2 * _common.CHUNK_BYTES)
    assert peak <= 4 * size + work + slack, f"{size >> 10} KiB file peaked at {peak >> 10} KiB"


# =======================================================================================
# inputs that are not regular files
# =======================================================================================
SPECIAL_AREA = "non-regular inputs"
SPECIALS = ["fifo", "dev_zero", "dev_null", "socket", "folder", "dangling", "loop", "link_to_fifo"]


def make_special(path: Path, what: str):
    """Make ``path`` a ``what``; returns a closer (the socket's) or None."""
    if what in ("fifo", "link_to_fifo"):
        target = path if what == "fifo" else path.with_name("real_fifo")
        os.mkfifo(target)
        if what == "link_to_fifo":
            path.symlink_to(target)
    elif what == "dev_zero":
        path.symlink_to("/dev/zero")
    elif what == "dev_null":
        path.symlink_to("/dev/null")
    elif what == "socket":
        s = socket.socket(socket.AF_UNIX, socket.SOCK_STREAM)
        try:
            s.bind(str(path))
        except OSError:  # path too long for a socket name
            s.close()
            return "skip"
        return s.close
    elif what == "folder":
        path.mkdir()
        (path / "frame_0001.obj").write_text("v 0 0 0\n")
    elif what == "dangling":
        path.symlink_to(path.with_name("missing_target"))
    elif what == "loop":
        path.symlink_to(path)
    return None


def within(seconds: float, call):
    box = {}

    def run():
        try:
            box["r"] = call()
        except BaseException as exc:  # noqa: BLE001 - reported by the caller
            box["e"] = exc

    t = threading.Thread(target=run, daemon=True)
    t.start()
    t.join(seconds)
    assert not t.is_alive(), "hung on a non-regular input"
    if "e" in box:
        raise box["e"]
    return box["r"]


READER_CALLS = [(r.name, r) for r, _ in samples.readers() if "/" not in r.extensions]


@given(
    which=st.sampled_from(
        [name for name, _ in READER_CALLS]
        + ["landmarks", "feature_lines", "gltf_buffer", "mesh_folder", "convert"]
    ),
    what=st.sampled_from(SPECIALS),
)
@fuzz(40)
def test_non_regular_inputs_are_refused_at_once(which, what, tmp_path_factory, capsys):
    folder = tmp_path_factory.mktemp("special")
    if which in ("landmarks", "feature_lines"):
        path = folder / ("lm.json" if which == "landmarks" else "lines.json")
        call = (
            (lambda: fr.io.read_landmarks(path))
            if which == "landmarks"
            else (lambda: fr.io.read_feature_lines(path))
        )
    elif which == "gltf_buffer":
        doc, _ = glb_document(samples.sample("mesh"))
        doc["buffers"][0]["uri"] = "data.bin"
        (folder / "m.gltf").write_text(__import__("json").dumps(doc))
        path = folder / "data.bin"
        call = lambda: fr.load(folder / "m.gltf")  # noqa: E731
    elif which == "mesh_folder":
        seq = folder / "seq"
        seq.mkdir()
        for k in range(2):
            fr.save(samples.grid_mesh(), seq / f"frame_{k:04d}.obj")
        path = seq / "frame_0002.obj"
        call = lambda: fr.load(seq)  # noqa: E731
    elif which == "convert":
        path = folder / "in.obj"

        def call():
            code = cli.main(["convert", str(path), str(folder / "out.obj")])
            err = capsys.readouterr().err
            assert (
                code == cli.EXIT_ERROR
                and len(err.strip().splitlines()) == 1
                and "Traceback" not in err
            ), (code, err)
            return errors.FileFormatError(err)
    else:
        reader = dict(READER_CALLS)[which]
        path = folder / f"x{reader.extensions[0]}"
        call = lambda: reader.read(path)  # noqa: E731
    closer = make_special(path, what)
    assume(closer != "skip")
    try:
        if which == "convert":
            count(SPECIAL_AREA)
            result = within(20, call)
            fuzzkit.REJECTED[SPECIAL_AREA] += 1
        else:
            result = within(20, lambda: typed(SPECIAL_AREA, call))
    finally:
        if callable(closer):
            closer()
    if which == "mesh_folder":
        return  # a folder reader skips what is not a regular file (or refuses it): both typed
    if which == "gltf_buffer" and what == "folder":
        assert failed(result)
        return
    assert failed(result), f"{which} read a {what}: {result!r}"
    assert not (folder / "out.obj").exists()


# =======================================================================================
# destinations: inputs spelled differently, existing files, --force
# =======================================================================================
DEST_AREA = "destinations"
SPELLINGS = [
    "same",
    "relative",
    "dot",
    "dotdot",
    "symlink",
    "hardlink",
    "case",
    "other_existing",
    "new",
    "folder_of_input",
]


def spelled(folder: Path, src: Path, how: str) -> tuple[str, bool]:
    """A spelling of an output path and whether it names the input ``src``."""
    name = src.name
    if how == "same":
        return str(src), True
    if how == "relative":
        return name, True
    if how == "dot":
        return f"./{name}", True
    if how == "dotdot":
        (folder / "sub").mkdir(exist_ok=True)
        return f"sub/../{name}", True
    if how == "symlink":
        link = folder / f"link{src.suffix}"
        link.symlink_to(src)
        return str(link), True
    if how == "hardlink":
        link = folder / f"hard{src.suffix}"
        os.link(src, link)
        return str(link), True
    if how == "case":
        other = folder / name.upper()
        same = other.exists() and os.path.samefile(other, src)  # a case-insensitive file system
        return str(other), same
    if how == "other_existing":
        other = folder / f"precious{src.suffix}"
        other.write_bytes(b"precious")
        return str(other), False
    if how == "folder_of_input":
        return str(folder), True
    return str(folder / f"new{src.suffix}"), False


@given(
    ext=st.sampled_from([".obj", ".off", ".ply", ".npz", ".glb"]),
    how=st.sampled_from(SPELLINGS),
    force=st.booleans(),
    via=st.sampled_from(["save", "write_bytes", "convert"]),
)
@fuzz(40)
def test_destinations_never_an_input_never_an_existing_file_without_force(
    ext, how, force, via, tmp_path_factory, monkeypatch, capsys
):
    folder = tmp_path_factory.mktemp("dest")
    monkeypatch.chdir(folder)
    src = folder / f"in{ext}"
    fr.save(samples.grid_mesh(), src)
    before = src.read_bytes()
    out, is_src = spelled(folder, src, how)
    out_path = folder / out if not os.path.isabs(out) else Path(out)
    existed = os.path.lexists(out_path)
    old = out_path.read_bytes() if existed and out_path.is_file() and not is_src else None
    listing = sorted(p.name for p in folder.iterdir())
    if via == "convert":
        count(DEST_AREA)
        code = cli.main(
            ["convert", str(src) if how != "relative" else src.name, out]
            + (["--force"] if force else [])
        )
        err = capsys.readouterr().err
        assert code in (0, cli.EXIT_ERROR) and "Traceback" not in err, (code, err)
        ok = code == 0
        fuzzkit.REJECTED[DEST_AREA] += not ok
    else:
        obj = fr.load(src)  # the input of this "run"

        if via == "save":
            result = typed(DEST_AREA, fr.save, obj, out, force=force)
        else:
            result = typed(DEST_AREA, _atomic.write_bytes, out, b"new bytes", force=force)
        ok = not failed(result)
    assert src.read_bytes() == before, f"the input was replaced through {how!r} ({via})"
    if is_src or how == "folder_of_input":
        assert not ok, f"writing {out!r} over the input succeeded ({via})"
    elif existed and not force:
        assert not ok and out_path.read_bytes() == old, (
            "an existing file was replaced without force"
        )
    if not ok:
        assert sorted(p.name for p in folder.iterdir()) == listing, (
            "a refused write left something behind"
        )
    leftovers = [p.name for p in folder.iterdir() if _atomic.temp_owner(p.name)]
    assert not leftovers, leftovers


# =======================================================================================
# temporary files: cleanup finds every dead writer's file, and nothing else
# =======================================================================================
TEMP_AREA = "temp leftovers"
DEAD = 2**22 + 4321  # above the default pid_max


@st.composite
def temp_entries(draw):
    dest = draw(st.sampled_from(["hero.npz", "a.b.glb", "x", ".hidden.obj", "t\u00e9.csv", "rig"]))
    ext = Path(dest).suffix
    who = draw(
        st.sampled_from(
            [
                "dead",
                "dead",
                "reused_unlocked",
                "reused_locked",
                "huge_pid",
                "pid_zero",
                "self_inactive",
            ]
        )
    )
    pid = {
        "dead": DEAD,
        "reused_unlocked": os.getppid(),
        "reused_locked": os.getppid(),
        "huge_pid": 10**25,
        "pid_zero": 0,
        "self_inactive": os.getpid(),
    }[who]
    token = draw(st.text("0123456789abcdef", min_size=8, max_size=8))
    scheme = draw(
        st.sampled_from(
            ["new", "new_noext", "old_folder", "legacy", "nested", "user", "user", "user"]
        )
    )
    if scheme == "new":
        name = f".{dest}.{pid}.{token}.frtmp{ext}"
    elif scheme == "new_noext":
        name = f".{dest}.{pid}.{token}.frtmp"
    elif scheme == "old_folder":
        name = f".{dest}.{pid}.{token}.frold"
    elif scheme == "legacy":
        name = f".{dest}.frbatch-{pid}-{token}{ext}"
    elif scheme == "nested":
        name = f"..{dest}.frbatch-{pid}-{token}{ext}.{pid}.{token}.frtmp"
    else:  # names a user may own: never a temporary
        dest = dest.lstrip(".") or "x"
        name = draw(
            st.sampled_from(
                [
                    f"{dest}.{pid}.{token}.frtmp",
                    f".{dest}.frtmp",
                    f".{dest}.{pid}.{token.upper()}.frtmp"
                    if token.upper() != token
                    else f".{dest}.x.frtmp",
                    f".{dest}.frbatch-{ext}",
                    f"{dest}~",
                    f".{dest}.{pid}.{token}.frtmpx",
                    f".{dest}.{pid}.{token}",
                    f"{dest}.frold",
                ]
            )
        )
    folder_entry = (
        scheme == "old_folder" or draw(st.booleans()) and scheme != "user" and draw(st.booleans())
    )
    return dest, name, who, scheme, folder_entry


@given(
    entries=st.lists(temp_entries(), min_size=1, max_size=10, unique_by=lambda e: e[1]),
    live_writer=st.booleans(),
)
@fuzz(40)
def test_cleanup_removes_every_dead_writers_file_and_nothing_else(
    entries, live_writer, tmp_path_factory
):
    import fcntl

    folder = tmp_path_factory.mktemp("temps")
    locks = []
    expect_gone, expect_kept = set(), set()
    for _dest, name, who, scheme, is_folder in entries:
        path = folder / name
        if is_folder:
            path.mkdir()
            (path / "part").write_bytes(b"x")
        else:
            path.write_bytes(b"x" * 10)
        if who == "reused_locked":
            fd = os.open(path, os.O_RDONLY)
            fcntl.flock(fd, fcntl.LOCK_EX)
            locks.append(fd)
        dead = who in ("dead", "huge_pid", "pid_zero") or (
            who == "reused_unlocked" and scheme in ("new", "new_noext")
        )
        (expect_gone if dead and scheme != "user" else expect_kept).add(name)
    try:
        found = typed(TEMP_AREA, _atomic.leftovers, folder)
        assert not failed(found), found
        found_names = {p.name for p in found}
        users = {e[1] for e in entries if e[3] == "user"}
        assert not (found_names & users), (
            f"a user's file taken for a temporary: {found_names & users}"
        )
        assert found_names == expect_gone, (
            f"missed {expect_gone - found_names}, wrongly found {found_names - expect_gone}"
        )
        cm = None
        if live_writer:  # a writer at work in this process: its temporary is never touched
            cm = _atomic.atomic_file(folder / "live.bin", force=True)
            cm.__enter__().write(b"live")
            expect_kept |= {p.name for p in folder.iterdir() if p.name in _atomic._ACTIVE}
        for dest in {e[0] for e in entries} | {"live.bin"}:
            assert not failed(typed(TEMP_AREA, _atomic.remove_leftovers, folder / dest))
        present = {p.name for p in folder.iterdir()}
        assert not (present & expect_gone), f"not removed: {present & expect_gone}"
        assert expect_kept <= present, f"removed what it must keep: {expect_kept - present}"
        if cm is not None:
            cm.__exit__(None, None, None)
            assert (folder / "live.bin").read_bytes() == b"live"
    finally:
        for fd in locks:
            os.close(fd)


# =======================================================================================
# plugin hook results of random types
# =======================================================================================
HOOK_AREA = "plugin hook results"


class Hostile:
    """An object whose repr, iteration, length and attributes raise."""

    def __repr__(self):
        raise RuntimeError("repr exploded")

    def __iter__(self):
        raise RuntimeError("iteration exploded")

    def __len__(self):
        raise RuntimeError("len exploded")

    def __getattr__(self, name):
        raise RuntimeError(f"attribute {name} exploded")


class HostileList(list):
    def __iter__(self):
        raise RuntimeError("list iteration exploded")

    def __repr__(self):
        raise RuntimeError("list repr exploded")


def _read(path, **options):
    raise errors.FileFormatError(f"{path}: fuzz reader")


def records():
    reader = st.builds(
        Reader,
        name=st.one_of(st.sampled_from(["fz", "", " ", "obj"]), junk()),
        kind=st.one_of(st.sampled_from(["mesh", "markers", "nope"]), junk()),
        extensions=st.one_of(st.sampled_from([(".fz",), (), ("",), [".fz"], (".fz", 3)]), junk()),
        read=st.sampled_from([_read, None, 42]),
        description=st.one_of(st.text(max_size=5), junk()),
    )
    writer = st.builds(
        Writer,
        name=st.sampled_from(["fzw", ""]),
        kind=st.sampled_from(["mesh", "x"]),
        extensions=st.sampled_from([(".fzw",), ()]),
        write=st.sampled_from([_read, None]),
        description=st.just(""),
    )
    return st.one_of(
        junk(),
        reader,
        writer,
        st.builds(Hostile),
        st.builds(lambda: HostileList([1])),
        st.just(type("NotARetargeter", (), {})),
    )


@given(
    results=st.fixed_dictionaries(
        {
            hook: st.one_of(
                st.none(), records(), st.lists(records(), max_size=3), st.tuples(records())
            )
            for hook in (
                "faceretarget_readers",
                "faceretarget_writers",
                "faceretarget_metrics",
                "faceretarget_retargeters",
            )
        }
    )
)
@fuzz(40)
def test_hook_results_of_any_type_skip_the_plugin_by_name(results):
    module = types.ModuleType("fuzz_plugin")
    for hook, value in results.items():

        def impl(value=value):
            return value

        impl.__name__ = hook
        setattr(module, hook, fr.hookimpl(impl))

    def load():
        reg = Registry()
        reg.load(extra=[("fuzzplug", module)])
        return reg

    reg = typed(HOOK_AREA, load)
    assert not failed(reg), reg
    mine = [p for p in reg.plugins if p.name == "fuzzplug"]
    skipped = [p for p in reg.failures if p.name == "fuzzplug"]
    assert len(mine) + len(skipped) == 1
    if skipped:
        fuzzkit.REJECTED[HOOK_AREA] += 1  # skipped and named: the clean rejection
        message = skipped[0].error
        assert isinstance(message, str) and "fuzzplug" in message and "hook" in message, message
    else:  # everything it returned was valid: its readers work through load()
        for r, info in reg.readers:
            if info.name == "fuzzplug":
                assert isinstance(r.extensions, (tuple, list)) and r.kind in fr.hookspecs.DATA_KINDS


# =======================================================================================
# exit codes: random command lines over garbage files
# =======================================================================================
EXIT_AREA = "exit codes"


@st.composite
def command_lines(draw, folder: Path):
    files = [
        str(folder / n)
        for n in (
            "garbage.obj",
            "garbage.csv",
            "empty.glb",
            "missing.npz",
            "fifo.obj",
            "m.toml",
            "out.obj",
            "dir",
        )
    ]
    words = st.one_of(
        st.sampled_from(files),
        st.sampled_from(
            [
                "--force",
                "--fps",
                "nan",
                "-1",
                "1e400",
                "0",
                "--timeout",
                "--jobs",
                "--methods",
                "--summary",
                "--csv",
                "--kind",
                "mesh",
                "--keep-going",
                "--check",
                "--redo",
                "--quiet",
                "--format",
                "x",
                "--",
                "-",
                "\u00e9",
                "",
            ]
        ),
        st.text(max_size=4),
    )
    cmd = draw(
        st.sampled_from(
            ["convert", "run", "batch", "info", "formats", "list", "cases", "compare", "nope"]
        )
    )
    return [cmd] + draw(st.lists(words, max_size=6))


@pytest.fixture(scope="module")
def garbage(tmp_path_factory):
    folder = tmp_path_factory.mktemp("argv")
    (folder / "garbage.obj").write_bytes(b"v 1 2\nf 9 9 9\n\x00")
    (folder / "garbage.csv").write_text("a,b\n1,x\n")
    (folder / "empty.glb").write_bytes(b"")
    os.mkfifo(folder / "fifo.obj")
    (folder / "m.toml").write_text(
        '[[job]]\nshot = "garbage.obj"\nmethod = "nope"\nout = "o.npz"\n'
    )
    (folder / "dir").mkdir()
    return folder


@given(data=st.data())
@fuzz(40)
def test_exit_codes_over_random_command_lines(garbage, data, capsys):
    argv = data.draw(command_lines(garbage))
    if argv[0] == "compare":  # never a real comparison here: only refusals
        argv = argv[:1] + ["--cases", "no-such-case"] + argv[1:]
    before = sorted(p.name for p in garbage.iterdir())
    count(EXIT_AREA)
    try:
        code = within(60, lambda: cli.main(argv))
    except SystemExit as exc:  # argparse: a usage error
        code = exc.code
    out = capsys.readouterr()
    assert code in (0, cli.EXIT_FAILED, cli.EXIT_ERROR), f"{argv}: exit {code}: {out.err}"
    assert "Traceback" not in out.err and "internal error" not in out.err, out.err
    if code == cli.EXIT_ERROR:
        fuzzkit.REJECTED[EXIT_AREA] += 1
        assert out.err.strip(), f"{argv}: exit 2 without a message"
    assert set(before) <= {p.name for p in garbage.iterdir()}, "an input went missing"
    for p in garbage.iterdir():
        if p.name.startswith(".") and _atomic.temp_owner(p.name):
            pytest.fail(f"{argv}: left {p.name}")


@pytest.mark.parametrize(
    "value",
    [Hostile, lambda: HostileList([1]), lambda: [Hostile()]],
    ids=["repr_raises", "list_iteration_raises", "item_raises"],
)
def test_a_hook_result_whose_repr_or_iteration_raises_skips_the_plugin(value):
    """Found by the long fuzz mode (issue 15): a hook result whose ``repr`` or iteration
    raised escaped the registry (every command exited 3)."""
    module = types.ModuleType("fuzz_plugin")

    def faceretarget_readers():
        return value()

    module.faceretarget_readers = fr.hookimpl(faceretarget_readers)
    reg = Registry().load(extra=[("hostile", module)])
    (skipped,) = [p for p in reg.failures if p.name == "hostile"]
    assert "hostile" in skipped.error, skipped.error
    assert not [p for p in reg.plugins if p.name == "hostile"]
