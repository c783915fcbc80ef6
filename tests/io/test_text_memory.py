"""Peak memory of every text reader, measured with tracemalloc.

- Realistic files of a few MB (what faceretarget's writers or common exporters write):
  the peak stays within 4x the file (issue 15).
- The smallest possible lines (``0 0 0``), where the parsed numbers alone take 4x the
  text: the peak is the result plus a constant (one chunk's work, ``CHUNK_FACTOR``
  times at most two chunks), and never more than the size the reader checked against
  ``FACERETARGET_MEMORY_BUDGET`` before allocating (so the budget is an upper bound).
- Small files parsed whole into Python objects (landmark lists, feature lines, the
  sidecar of a mesh folder): the peak stays within ``TEXT_TOKEN_FACTOR`` times the file,
  the factor their budget check uses.
"""

import json
from pathlib import Path

import numpy as np
import pytest
from memtools import TEXT_READER_MODULES, traced_memory

import faceretarget as fr
from faceretarget.io import _common, read_feature_lines, read_landmarks
from faceretarget.registry import registry

WORK = _common.CHUNK_FACTOR * 2 * _common.CHUNK_BYTES
#: a small chunk for the streaming test: a reader that holds more than one chunk's
#: lines at a time exceeds the (then small) chunk work at once
SMALL_CHUNK = 1 << 15


@pytest.fixture(autouse=True, scope="module")
def _warm():
    registry()  # loading the registry is not the reader's memory


def measured(call, monkeypatch=None):
    """(result, peak bytes, largest size checked against the budget: spied with ``monkeypatch``)."""
    return traced_memory(call, TEXT_READER_MODULES if monkeypatch is not None else ())


def grid(n: int, seed: int = 0) -> fr.Mesh:
    rng = np.random.default_rng(seed)
    xs, ys = np.meshgrid(np.arange(n, dtype=float), np.arange(n, dtype=float))
    v = (
        np.stack([xs.ravel(), ys.ravel(), 0.1 * xs.ravel() * ys.ravel()], 1)
        + rng.normal(size=(n * n, 3)) * 1e-3
    )
    i = np.arange(n * n).reshape(n, n)
    a, b, c, d = i[:-1, :-1].ravel(), i[:-1, 1:].ravel(), i[1:, :-1].ravel(), i[1:, 1:].ravel()
    return fr.Mesh(v, np.concatenate([np.stack([a, b, d], 1), np.stack([a, d, c], 1)]))


def ascii_ply(path: Path, mesh: fr.Mesh, fmt: str = "%.6f") -> Path:
    with open(path, "w") as fh:
        fh.write(
            f"ply\nformat ascii 1.0\nelement vertex {mesh.n_vertices}\nproperty float x\nproperty float y\nproperty float z\n"
            f"element face {mesh.n_triangles}\nproperty list uchar int vertex_indices\nend_header\n"
        )
        fh.write("\n".join(" ".join(fmt % x for x in r) for r in mesh.vertices.tolist()) + "\n")
        fh.write("\n".join("3 {} {} {}".format(*r) for r in mesh.triangles.tolist()) + "\n")
    return path


def ascii_stl(path: Path, mesh: fr.Mesh, fmt: str = "%.6e") -> Path:
    v = mesh.vertices.tolist()
    with open(path, "w") as fh:
        fh.write("solid grid\n")
        for t in mesh.triangles.tolist():
            fh.write("  facet normal 0.000000e+00 0.000000e+00 1.000000e+00\n    outer loop\n")
            for k in t:
                fh.write("      vertex " + " ".join(fmt % x for x in v[k]) + "\n")
            fh.write("    endloop\n  endfacet\n")
        fh.write("endsolid grid\n")
    return path


def realistic(kind: str, folder: Path) -> tuple[Path, dict]:
    rng = np.random.default_rng(1)
    if kind in ("obj", "off"):
        path = folder / f"grid.{kind}"
        fr.save(grid(180 if kind == "obj" else 130), path)  # OBJ: one chunk of work is ~7 MiB
        return path, {}
    if kind == "ply":
        return ascii_ply(folder / "grid.ply", grid(140)), {}
    if kind == "stl":
        return ascii_stl(folder / "grid.stl", grid(48)), {}
    if kind in ("trc", "markers_csv"):
        markers = fr.MarkerSequence(
            rng.normal(size=(700, 40, 3)), names=[f"m{i}" for i in range(40)], fps=120.0
        )
        path = folder / ("take.trc" if kind == "trc" else "take.csv")
        fr.save(markers, path)
        return path, {}
    if kind == "weights_csv":
        weights = fr.WeightSequence(
            rng.uniform(size=(1000, 61)), [f"shape{i}" for i in range(61)], fps=60.0
        )
        path = folder / "live_link.csv"
        fr.save(weights, path)
        return path, {"kind": "weights"}
    raise ValueError(kind)


TEXT_READERS = ["obj", "off", "ply", "stl", "trc", "markers_csv", "weights_csv"]


@pytest.mark.parametrize("kind", TEXT_READERS)
def test_realistic_text_files_peak_within_4x_the_file(kind, tmp_path):
    path, options = realistic(kind, tmp_path)
    size = path.stat().st_size
    assert size > 1_000_000  # a few MB: a chunk's work is small beside the file
    result, peak, _ = measured(lambda: fr.load(path, **options))
    assert result is not None
    print(f"\n{kind}: {size >> 10} KiB, peak {peak / size:.2f}x the file")
    assert peak <= 4 * size, (
        f"{kind}: reading {size >> 10} KiB peaked at {peak / size:.2f}x the file"
    )


def smallest_lines(kind: str, folder: Path, n: int) -> tuple[Path, dict, int]:
    """A file of about ``n`` of the smallest lines the format allows, and the bytes of its result."""
    if kind == "obj":
        path = folder / "min.obj"
        path.write_text("v 0 0 0\n" * n + "v 1 0 0\nv 0 1 0\nf 1 2 3\n")
        return path, {}, (n + 2) * 24 + 24
    if kind == "off":
        path = folder / "min.off"
        path.write_text(f"OFF\n{n + 3} 1 0\n" + "0 0 0\n" * n + "1 0 0\n0 1 0\n0 0 1\n3 0 1 2\n")
        return path, {}, (n + 3) * 24 + 24
    if kind == "ply":
        path = folder / "min.ply"
        path.write_text(
            f"ply\nformat ascii 1.0\nelement vertex {n + 3}\nproperty float x\nproperty float y\nproperty float z\n"
            "element face 1\nproperty list uchar int vertex_indices\nend_header\n"
            + "0 0 0\n" * n
            + "1 0 0\n0 1 0\n0 0 1\n3 0 1 2\n"
        )
        return path, {}, (n + 3) * 24 + 24
    if kind == "stl":
        m = n // 10
        path = folder / "min.stl"
        path.write_text(
            "solid\n"
            + "".join(
                f"facet\nouter loop\nvertex {i} 0 0\nvertex {i} 1 0\nvertex {i} 0 1\nendloop\nendfacet\n"
                for i in range(m)
            )
            + "endsolid\n"
        )
        return path, {}, m * 9 * 8
    if kind == "trc":
        path = folder / "min.trc"
        path.write_text(
            f"PathFileType\t4\t(X/Y/Z)\tmin.trc\nDataRate\tCameraRate\tNumFrames\tNumMarkers\tUnits\n60\t60\t{n}\t1\tmm\n"
            "Frame#\tTime\tm\t\t\n\t\tX1\tY1\tZ1\n\n" + "1\t0\t0\t0\t0\n" * n
        )
        return path, {}, n * 24
    if kind == "markers_csv":
        path = folder / "min.csv"
        path.write_text("m_x,m_y,m_z\n" + "0,0,0\n" * n)
        return path, {}, n * 24
    if kind == "weights_csv":
        path = folder / "min_w.csv"
        path.write_text("a,b\n" + "0,0\n" * (2 * n))
        return path, {"kind": "weights"}, 2 * n * 16
    raise ValueError(kind)


@pytest.mark.parametrize("chunk", [_common.CHUNK_BYTES, SMALL_CHUNK], ids=["chunk", "small_chunk"])
@pytest.mark.parametrize("kind", TEXT_READERS)
def test_smallest_lines_cost_the_result_plus_one_chunk_and_never_more_than_checked(
    kind, chunk, tmp_path, monkeypatch
):
    path, options, result_bytes = smallest_lines(
        kind, tmp_path, 100_000 if chunk == _common.CHUNK_BYTES else 40_000
    )
    for module in ("_common", "meshes", "markers"):
        monkeypatch.setattr(f"faceretarget.io.{module}.CHUNK_BYTES", chunk)
    work = _common.CHUNK_FACTOR * 2 * chunk
    size = path.stat().st_size
    assert size > 2 * chunk  # the chunk work is at its largest
    _, peak, checked = measured(lambda: fr.load(path, **options), monkeypatch)
    print(
        f"\n{kind} smallest lines, {chunk >> 10} KiB chunks: {size >> 10} KiB, peak {peak / size:.2f}x the file, result {result_bytes / size:.2f}x, "
        f"work beyond the result {(peak - result_bytes) >> 10} KiB of {work >> 10}, checked {checked / size:.2f}x"
    )
    assert peak <= result_bytes + work, (
        f"{kind}: peak {peak >> 10} KiB, result {result_bytes >> 10} KiB + chunk work {work >> 10} KiB"
    )
    assert result_bytes <= 4 * size
    assert peak <= checked, (
        f"{kind}: peak {peak >> 10} KiB but only {checked / 1024:.0f} KiB was checked against the budget"
    )


# ---------------------------------------------------------------------------------------
# small files parsed whole: landmarks, feature lines, a mesh folder's sidecar
# ---------------------------------------------------------------------------------------
def small_text(kind: str, folder: Path):
    ids = list(range(1000, 1000 + 40_000))
    if kind == "landmarks_json":
        path = folder / "lm.json"
        path.write_text(json.dumps(ids, separators=(",", ":")))
        return path, lambda: read_landmarks(path)
    if kind == "landmarks_named_json":
        path = folder / "lmn.json"
        path.write_text(json.dumps({f"p{i}": v for i, v in enumerate(ids)}, separators=(",", ":")))
        return path, lambda: read_landmarks(path)
    if kind == "landmarks_txt":
        path = folder / "lm.txt"
        path.write_text("\n".join(map(str, ids)) + "\n")
        return path, lambda: read_landmarks(path)
    if kind == "landmarks_named_txt":
        path = folder / "lmn.txt"
        path.write_text("\n".join(f"p{i} {v}" for i, v in enumerate(ids)) + "\n")
        return path, lambda: read_landmarks(path)
    if kind == "feature_lines":
        path = folder / "lines.json"
        path.write_text(
            json.dumps(
                {f"l{k}": ids[k * 4 : k * 4 + 4] for k in range(len(ids) // 4)},
                separators=(",", ":"),
            )
        )
        return path, lambda: read_feature_lines(path)
    if kind == "sidecar":
        seq = folder / "seq"
        seq.mkdir()
        mesh = grid(3)
        for k in range(2):
            fr.save(mesh, seq / f"f{k}.obj")
        from faceretarget.io.sequences import SEQUENCE_SIDECAR, _sidecar

        path = seq / SEQUENCE_SIDECAR
        path.write_text(
            json.dumps({"fps": 30, "notes": [str(i) for i in range(40_000)]}, separators=(",", ":"))
        )
        return path, lambda: _sidecar(seq, SEQUENCE_SIDECAR)
    raise ValueError(kind)


@pytest.mark.parametrize(
    "kind",
    [
        "landmarks_json",
        "landmarks_named_json",
        "landmarks_txt",
        "landmarks_named_txt",
        "feature_lines",
        "sidecar",
    ],
)
def test_small_text_files_peak_within_the_factor_their_budget_check_uses(kind, tmp_path):
    path, call = small_text(kind, tmp_path)
    size = path.stat().st_size
    _, peak, _ = measured(call)
    factor = _common.TEXT_TOKEN_FACTOR
    print(f"\n{kind}: {size >> 10} KiB, peak {peak / size:.2f}x the file")
    assert peak <= factor * size, (
        f"{kind}: {size >> 10} KiB peaked at {peak / size:.1f}x the file (TEXT_TOKEN_FACTOR = {factor})"
    )
