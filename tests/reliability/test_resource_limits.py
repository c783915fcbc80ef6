"""Readers refuse files whose declared sizes exceed the memory budget, before allocating.

Two kinds of test:

- crafted headers that declare enormous sizes (PC2, MDD, npy, npz, C3D, PLY, OFF, STL,
  glTF, TRC) in a tiny file: the reader must refuse with a typed error
  (ResourceLimitError, or FileFormatError for a file shorter than it claims) while
  allocating almost nothing (measured with tracemalloc, which sees numpy's buffers);
- consistent files larger than a small ``FACERETARGET_MEMORY_BUDGET`` (every registered
  reader, seeds from the registered writers, plus an npz "zip bomb"): the reader must
  raise ResourceLimitError naming the variable, or return data that is memory-mapped
  rather than allocated.
"""

import io
import json
import mmap
import struct
import tracemalloc
import zipfile
from pathlib import Path

import numpy as np
import pytest
from reliability import samples
from reliability.fuzzkit import count, failed, typed

import faceretarget as fr
from faceretarget import errors
from faceretarget.io import _atomic

AREA = "memory budget"
#: bytes a refusal may allocate
ALLOWANCE = 32 * 2**20
HUGE = 2**31 - 1


def npy_bytes(shape, dtype="<f8", payload=b"\0" * 64) -> bytes:
    buf = io.BytesIO()
    np.lib.format.write_array_header_1_0(
        buf, {"descr": dtype, "fortran_order": False, "shape": tuple(shape)}
    )
    return buf.getvalue() + payload


def gltf_text(count_: int) -> str:
    return json.dumps(
        {
            "asset": {"version": "2.0"},
            "buffers": [
                {"byteLength": 36, "uri": "data:application/octet-stream;base64," + "A" * 48}
            ],
            "bufferViews": [{"buffer": 0, "byteLength": 36}],
            "accessors": [
                {"bufferView": 0, "componentType": 5126, "count": count_, "type": "VEC3"}
            ],
            "meshes": [{"primitives": [{"attributes": {"POSITION": 0}}]}],
            "nodes": [{"mesh": 0}],
            "scenes": [{"nodes": [0]}],
        }
    )


def c3d_bytes(seed_of) -> bytes:
    """A valid C3D file of a few frames whose header then declares 65535 frames."""
    data = bytearray(seed_of("c3d")[0].read_bytes())
    data[8:10] = struct.pack("<H", 65535)  # header word 5: last frame
    return bytes(data)


@pytest.fixture(scope="module")
def seed_of(tmp_path_factory):
    """``seed_of(name, n=3)``: (path, options) of a file the registered writers made for
    reader ``name`` (samples.seed), in a folder of the test session."""
    folder = tmp_path_factory.mktemp("budget_seeds")
    return lambda name, n=3: samples.seed(name, str(folder / f"n{n}"), n)


CRAFTED = {
    "pc2": (
        ".pc2",
        lambda: struct.pack("<12siiffi", b"POINTCACHE2\0", 1, HUGE, 0.0, 30.0, HUGE) + b"\0" * 24,
    ),
    "mdd": (".mdd", lambda: struct.pack(">ii", HUGE, HUGE) + b"\0" * 24),
    "npy": (".npy", lambda: npy_bytes((10**6, 10**6, 3))),
    "npz-sequence": (".npz", None),  # built in the test (a zip)
    "c3d": (".c3d", "seed"),  # c3d_bytes(seed_of), built in the test
    "ply": (
        ".ply",
        lambda: (
            b"ply\nformat ascii 1.0\nelement vertex 100000000000\nproperty float x\nproperty float y\nproperty float z\n"
            b"element face 100000000000\nproperty list uchar int vertex_indices\nend_header\n0 0 0\n"
        ),
    ),
    "off": (".off", lambda: b"OFF\n100000000000 100000000000 0\n0 0 0\n"),
    "stl": (".stl", lambda: b"\0" * 80 + struct.pack("<I", 4_000_000_000) + b"\0" * 50),
    "gltf-mesh": (".gltf", lambda: gltf_text(10**12).encode()),
    "trc": (
        ".trc",
        lambda: (
            b"PathFileType\t4\t(X/Y/Z)\tx.trc\nDataRate\tCameraRate\tNumFrames\tNumMarkers\tUnits\tOrigDataRate\tOrigDataStartFrame\tOrigNumFrames\n"
            b"30\t30\t10000000000\t100000\tmm\t30\t1\t10000000000\nFrame#\tTime\tm0\n\t\tX1\tY1\tZ1\n1\t0\t0\t0\t0\n"
        ),
    ),
}


def npz_declaring_huge(path: Path) -> None:
    with zipfile.ZipFile(path, "w") as zf:
        zf.writestr("vertices.npy", npy_bytes((10**6, 10**6, 3)))
        zf.writestr("triangles.npy", npy_bytes((1, 3), "<i8", b"\0" * 24))


def read_measured(path: Path, reader_name: str):
    """Read with the named reader; returns (result or typed error, peak bytes allocated)."""
    tracemalloc.start()
    try:
        tracemalloc.reset_peak()
        result = typed(AREA, fr.load, path, format=reader_name)
        peak = tracemalloc.get_traced_memory()[1]
    finally:
        tracemalloc.stop()
    _atomic.clear_inputs()
    return result, peak


@pytest.mark.parametrize("reader_name", sorted(CRAFTED))
def test_crafted_header_declaring_huge_sizes(reader_name, tmp_path, monkeypatch, seed_of):
    ext, make = CRAFTED[reader_name]
    if reader_name == "c3d":
        monkeypatch.setenv("FACERETARGET_MEMORY_BUDGET", "1M")  # 65535 frames x 5 markers ~ 7.5 MiB
    path = tmp_path / f"huge{ext}"
    if make is None:
        npz_declaring_huge(path)
    elif make == "seed":
        path.write_bytes(c3d_bytes(seed_of))
    else:
        path.write_bytes(make())
    result, peak = read_measured(path, reader_name)
    if reader_name == "c3d" and not isinstance(result, errors.FaceRetargetError):
        # read as ezc3d does: POINT:FRAMES and the frames present, never the header's last frame
        assert result.n_frames == fr.load(seed_of("c3d")[0], format="c3d").n_frames, result
    else:
        assert isinstance(result, (errors.ResourceLimitError, errors.FileFormatError)), (
            f"{reader_name}: {result!r}"
        )
        assert str(path) in str(result), "the error names the file"
    assert peak < ALLOWANCE, f"{reader_name} allocated {peak / 2**20:.1f} MiB before refusing"


def test_npz_zip_bomb_is_refused_before_inflating(tmp_path, monkeypatch):
    """64 MiB of zeros deflate to ~64 KiB; the declared size is what counts."""
    path = tmp_path / "bomb.npz"
    with zipfile.ZipFile(path, "w", compression=zipfile.ZIP_DEFLATED) as zf:
        with zf.open("vertices.npy", "w", force_zip64=True) as fh:
            fh.write(npy_bytes((2**20, 8, 1), "<f8", b""))
            zeros = b"\0" * 2**20
            for _ in range(64):
                fh.write(zeros)
        zf.writestr("triangles.npy", npy_bytes((1, 3), "<i8", b"\0" * 24))
    assert path.stat().st_size < 2**20
    monkeypatch.setenv("FACERETARGET_MEMORY_BUDGET", "16M")
    result, peak = read_measured(path, "npz-sequence")
    assert isinstance(result, errors.ResourceLimitError), result
    assert "FACERETARGET_MEMORY_BUDGET" in str(result)
    assert peak < ALLOWANCE


def mapped(arr) -> bool:
    """Whether ``arr`` views a memory map (not a buffer in memory)."""
    while arr is not None:
        if isinstance(arr, (np.memmap, mmap.mmap)):
            return True
        arr = getattr(arr, "base", None)
    return False


def data_arrays(obj):
    for name in ("vertices", "positions", "weights", "deltas"):
        value = getattr(obj, name, None)
        if isinstance(value, np.ndarray) and value.ndim >= 2:
            yield name, value


READERS = samples.readers()


@pytest.mark.parametrize("reader, info", READERS, ids=[r.name for r, _ in READERS])
def test_small_budget_refuses_or_maps(reader, info, monkeypatch, seed_of):
    found = seed_of(reader.name, n=12)
    if found is None:
        pytest.skip(f"no registered writer produces a file {reader.name} reads")
    path, options = found
    monkeypatch.setenv("FACERETARGET_MEMORY_BUDGET", "512")
    count(AREA)
    result = typed(AREA, reader.read, path, **options)
    _atomic.clear_inputs()
    if failed(result):
        assert isinstance(result, errors.ResourceLimitError), (
            f"{reader.name}: over budget must be ResourceLimitError, got {result!r}"
        )
        assert "FACERETARGET_MEMORY_BUDGET" in str(result)
        return
    big = [(name, a) for name, a in data_arrays(result) if a.nbytes > 512]
    assert big, f"{reader.name}: the seed is too small for this test"
    for name, arr in big:
        assert mapped(arr), (
            f"{reader.name} loaded {arr.nbytes} bytes of {name} into memory under a 512-byte budget"
        )


def test_budget_variable_is_validated(monkeypatch, tmp_path):
    monkeypatch.setenv("FACERETARGET_MEMORY_BUDGET", "lots")
    path = tmp_path / "m.obj"
    path.write_text("v 0 0 0\nv 1 0 0\nv 0 1 0\nf 1 2 3\n")
    result = typed(AREA, fr.load, path)
    assert isinstance(result, errors.ConfigError) and "FACERETARGET_MEMORY_BUDGET" in str(result)
    _atomic.clear_inputs()
