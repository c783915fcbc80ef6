"""Regression tests for the reliability holes of issue 15 owned by the readers and writers:

1. a glTF animation's sampling grid (stored fps x time range) is sized against the budget;
2. text readers (OBJ, marker CSV) stream: peak memory within 4x the file (tracemalloc);
3. a FIFO or a link to /dev/zero is refused with a typed error before anything is read;
4. a batch job never replaces a file a reader opened on its own (a PC2's sibling topology);
5. summaries and compare outputs are destination-checked (inputs, existing files, --force);
9. one temporary naming scheme, and a cleanup that finds every leftover (resume, --redo).
"""

import json
import os
import threading
import tracemalloc
from pathlib import Path

import numpy as np
import pytest
from reliability import samples

import faceretarget as fr
from faceretarget import cli, errors
from faceretarget.evaluation import batch
from faceretarget.io import _atomic
from faceretarget.io.gltf import glb_bytes, glb_document

BUDGET = "FACERETARGET_MEMORY_BUDGET"


@pytest.fixture(autouse=True)
def _forget_inputs():
    yield
    _atomic.clear_inputs()


def peak_of(call, *args, **kwargs):
    tracemalloc.start()
    try:
        tracemalloc.reset_peak()
        result = call(*args, **kwargs)
        return result, tracemalloc.get_traced_memory()[1]
    finally:
        tracemalloc.stop()


# ---------------------------------------------------------------------------------------
# 1. glTF animation memory bomb
# ---------------------------------------------------------------------------------------
def animation_glb(path: Path, fps) -> Path:
    anim = samples.sample("animation")
    doc, blob = glb_document(anim)
    doc["asset"]["extras"]["faceretarget"]["fps"] = fps
    doc["asset"]["extras"]["faceretarget"]["arrays"] = {}  # no exact copy: the keys are resampled
    path.write_bytes(glb_bytes(doc, blob))
    return path


@pytest.mark.parametrize("fps", [1e8, 1e12, 1e308, -30.0, 0.0, "30"])
def test_gltf_stored_frame_rate_that_is_not_one_is_refused(fps, tmp_path):
    path = animation_glb(tmp_path / "bomb.glb", fps)
    with pytest.raises(errors.FileFormatError, match="frame rate") as info:
        peak_of(fr.load, path, kind="animation")
    assert str(path) in str(info.value) and "too large" not in str(info.value)


def test_gltf_sampling_grid_is_checked_against_the_budget(tmp_path, monkeypatch):
    monkeypatch.setenv(BUDGET, "1M")
    path = animation_glb(tmp_path / "dense.glb", 1e6)  # 3 keys over 0.1 s resampled at 1 MHz
    with pytest.raises(errors.ResourceLimitError, match=BUDGET) as info:
        _, peak = peak_of(fr.load, path, kind="animation")
    assert "sampling the animation" in str(info.value)
    result, peak = peak_of(
        lambda: pytest.raises(errors.ResourceLimitError, fr.load, path, kind="mesh_sequence")
    )
    assert peak < 1 * 2**20
    monkeypatch.setenv(BUDGET, "8G")
    assert fr.load(animation_glb(tmp_path / "ok.glb", 240.0), kind="animation").fps == 240.0


# ---------------------------------------------------------------------------------------
# 2. text readers stream (peak within 4x the file)
# ---------------------------------------------------------------------------------------
def test_obj_of_minimal_vertex_lines_peaks_within_4x_the_file(tmp_path):
    path = tmp_path / "big.obj"
    with open(path, "w") as fh:
        fh.write("v 0 0 0\n" * 1_500_000 + "v 1 0 0\nv 0 1 0\nf 1 2 3\nf -1 -2 -3\n")
    mesh, peak = peak_of(fr.load, path)
    size = path.stat().st_size
    assert mesh.n_vertices == 1_500_002 and mesh.n_triangles == 2
    assert peak <= 4 * size, f"reading a {size >> 20} MiB OBJ peaked at {peak / size:.1f}x the file"


def test_marker_csv_peaks_within_4x_the_file_and_matches_the_writer(tmp_path):
    rng = np.random.default_rng(3)
    positions = rng.normal(size=(3000, 40, 3))
    positions[5, 3] = np.nan
    markers = fr.MarkerSequence(positions, names=[f"m{i}" for i in range(40)], fps=60.0)
    path = tmp_path / "take.csv"
    fr.save(markers, path)
    back, peak = peak_of(fr.load, path)
    np.testing.assert_array_equal(back.positions, markers.positions)
    assert back.fps == 60.0
    assert peak <= 4 * path.stat().st_size, f"peak {peak / path.stat().st_size:.1f}x the file"


def test_text_sizes_from_contents_are_checked_before_allocating(tmp_path, monkeypatch):
    obj = tmp_path / "m.obj"
    obj.write_text("v 0 0 0\n" * 200_000 + "f 1 2 3\n")
    csv = tmp_path / "m.csv"
    csv.write_text("a_x,a_y,a_z\n" + "1,2,3\n" * 200_000)
    monkeypatch.setenv(BUDGET, "2M")
    for path in (obj, csv):
        with pytest.raises(errors.ResourceLimitError, match=BUDGET):
            fr.load(path)


# ---------------------------------------------------------------------------------------
# 3. inputs that are not regular files
# ---------------------------------------------------------------------------------------
def refused_quickly(call, unblock=None):
    """``call()`` in a thread: its outcome, or a failure if it is still running after 20 s."""
    box = {}

    def run():
        try:
            box["result"] = call()
        except BaseException as exc:  # noqa: BLE001 - reported below
            box["error"] = exc

    t = threading.Thread(target=run, daemon=True)
    t.start()
    t.join(20)
    if t.is_alive():
        if unblock:
            unblock()
        t.join(5)
        pytest.fail("the reader hung on a non-regular input")
    return box.get("error", box.get("result"))


@pytest.mark.parametrize(
    "ext", [".obj", ".csv", ".glb", ".gltf", ".npz", ".pc2", ".npy", ".c3d", ".stl", ".json"]
)
def test_fifo_is_refused_without_hanging(ext, tmp_path):
    fifo = tmp_path / f"pipe{ext}"
    os.mkfifo(fifo)

    def unblock():
        fd = os.open(fifo, os.O_WRONLY | os.O_NONBLOCK)
        os.close(fd)

    reader = fr.io.read_landmarks if ext == ".json" else fr.load
    outcome = refused_quickly(lambda: reader(fifo), unblock)
    assert isinstance(outcome, errors.FileFormatError), outcome
    assert "FIFO" in str(outcome) and "regular file" in str(outcome)


@pytest.mark.skipif(not os.path.exists("/dev/zero"), reason="needs /dev/zero")
@pytest.mark.parametrize("ext", [".obj", ".csv", ".glb", ".npz", ".pc2", ".off"])
def test_symlink_to_dev_zero_is_refused(ext, tmp_path):
    link = tmp_path / f"zero{ext}"
    link.symlink_to("/dev/zero")
    outcome = refused_quickly(lambda: fr.load(link))
    assert isinstance(outcome, errors.FileFormatError), outcome
    assert "character device" in str(outcome)


def test_gltf_buffer_that_is_a_fifo_is_refused(tmp_path):
    doc, blob = glb_document(samples.sample("mesh"))
    os.mkfifo(tmp_path / "data.bin")
    doc["buffers"][0]["uri"] = "data.bin"
    path = tmp_path / "m.gltf"
    path.write_text(json.dumps(doc))
    outcome = refused_quickly(lambda: fr.load(path))
    assert isinstance(outcome, errors.FileFormatError) and "regular file" in str(outcome), outcome


def test_convert_from_a_fifo_exits_2_with_one_line(tmp_path, capsys):
    fifo = tmp_path / "in.obj"
    os.mkfifo(fifo)
    code = refused_quickly(lambda: cli.main(["convert", str(fifo), str(tmp_path / "out.obj")]))
    err = capsys.readouterr().err
    assert code == cli.EXIT_ERROR and "FIFO" in err and len(err.strip().splitlines()) == 1


# ---------------------------------------------------------------------------------------
# 4. batch never replaces a file a reader opened on its own
# ---------------------------------------------------------------------------------------
def pc2_with_sibling_topology(folder: Path):
    seq = samples.sample("mesh_sequence")
    fr.save(seq, folder / "take.pc2")
    fr.save(seq.reference, folder / "take.glb")  # the PC2's topology, found by its stem
    return folder / "take.pc2", folder / "take.glb"


def test_batch_output_over_a_sibling_topology_is_refused_by_the_manifest(tmp_path):
    shot, topo = pc2_with_sibling_topology(tmp_path)
    manifest = tmp_path / "m.toml"
    manifest.write_text(
        '[[job]]\nshot = "take.pc2"\ncharacter = "case:synthetic?resolution=60&n_frames=4"\nmethod = "deformation_transfer"\nout = "take.glb"\n'
    )
    with pytest.raises(errors.ConfigError, match="input"):
        batch.load_manifest(manifest)


def test_batch_writer_refuses_a_file_read_indirectly_even_with_redo(tmp_path):
    shot, topo = pc2_with_sibling_topology(tmp_path)
    before = topo.read_bytes()
    source = fr.io.load_source(shot)  # reads take.glb for the triangles
    writer = next(w for w, _ in fr.registry.registry().writers if w.name == "gltf-animation")
    anim = fr.Animation(
        vertices=source.performance.vertices, triangles=source.performance.triangles, fps=24.0
    )
    with pytest.raises(errors.OutputError, match="input"):
        batch.write_animation(anim, topo, writer.write, force=True)  # what --redo does
    assert topo.read_bytes() == before
    assert sorted(p.name for p in tmp_path.iterdir()) == ["take.glb", "take.pc2"], (
        "no temporary left"
    )


# ---------------------------------------------------------------------------------------
# 5. one destination check for summaries and compare outputs
# ---------------------------------------------------------------------------------------
def manifest_in(folder: Path) -> Path:
    path = folder / "m.toml"
    path.write_text(
        '[[job]]\nshot = "case:synthetic?resolution=60&n_frames=4"\nmethod = "deformation_transfer"\nout = "hero.npz"\n'
    )
    return path


@pytest.mark.parametrize("which", ["existing", "manifest", "job_output"])
@pytest.mark.parametrize("force", [False, True])
def test_batch_summary_never_replaces_a_file_without_force_or_a_file_of_the_run(
    which, force, tmp_path, capsys
):
    manifest = manifest_in(tmp_path)
    target = {
        "existing": tmp_path / "precious.glb",
        "manifest": manifest,
        "job_output": tmp_path / "hero.npz",
    }[which]
    if not target.exists():
        target.write_bytes(b"precious")
    before = target.read_bytes()
    code = cli.main(
        ["batch", str(manifest), "--check", "--summary", str(target)]
        + (["--force"] if force else [])
    )
    err = capsys.readouterr().err
    if which == "existing" and force:
        assert code == 0
        return
    assert code == cli.EXIT_ERROR, err
    assert target.read_bytes() == before
    assert ("input" in err) if (force or which != "existing") else ("already exists" in err)


def test_compare_outputs_are_checked_before_the_comparison(tmp_path, capsys):
    precious = tmp_path / "precious.glb"
    precious.write_bytes(b"precious")
    code = cli.main(
        [
            "compare",
            "synthetic?resolution=60&n_frames=4",
            "--methods",
            "deformation_transfer",
            "--csv",
            str(precious),
            "--quiet",
        ]
    )
    assert code == cli.EXIT_ERROR and "already exists" in capsys.readouterr().err
    assert precious.read_bytes() == b"precious"
    same = tmp_path / "t.csv"
    code = cli.main(["compare", "x", "--csv", str(same), "--json", str(same), "--quiet"])
    assert code == cli.EXIT_ERROR and "two outputs" in capsys.readouterr().err
    report = tmp_path / "report"
    report.mkdir()
    (report / "results.json").write_text("mine")
    code = cli.main(["compare", "x", "--out", str(report), "--quiet"])
    assert code == cli.EXIT_ERROR and (report / "results.json").read_text() == "mine"


def test_result_exports_need_force(tmp_path):
    from faceretarget.evaluation.harness import atomic_write_text

    path = tmp_path / "r.csv"
    path.write_text("old")
    with pytest.raises(errors.OutputError, match="already exists"):
        atomic_write_text(path, "new")
    assert path.read_text() == "old"
    atomic_write_text(path, "new", force=True)
    assert path.read_text() == "new"


# ---------------------------------------------------------------------------------------
# 9. one temporary naming scheme, every leftover found
# ---------------------------------------------------------------------------------------
DEAD = 2**22 + 12345  # above the default pid_max: no such process


def leftover_names(out: str) -> list[str]:
    ext = Path(out).suffix
    return [
        f".{out}.{DEAD}.0123abcd.frtmp{ext}",  # the scheme (killed mid-write)
        f".{out}.frbatch-{DEAD}-89abcdef{ext}",  # the batch runner's former scheme
        f"..{out}.frbatch-{DEAD}-89abcdef{ext}.{DEAD}.0a1b2c3d.frtmp",  # a writer's temporary of that one
    ]


def test_temp_names_have_one_scheme_and_name_their_destination(tmp_path):
    name = _atomic.temp_path(tmp_path / "j2.npz").name
    assert _atomic.temp_owner(name)[0] == "j2.npz" and name.endswith(".frtmp.npz")
    for leftover in leftover_names("j2.npz"):
        assert _atomic.temp_owner(leftover)[0] == "j2.npz", leftover
    assert _atomic.temp_owner("j2.npz") is None and _atomic.temp_owner(".hidden") is None


@pytest.mark.parametrize("redo", [False, True])
def test_batch_resume_and_redo_remove_every_leftover(redo, tmp_path):
    manifest = manifest_in(tmp_path)
    out = tmp_path / "hero.npz"
    fr.save(samples.sample("animation"), out)
    for name in leftover_names("hero.npz"):
        (tmp_path / name).write_bytes(b"x" * 1000)
    jobs = batch.load_manifest(manifest)
    summary = batch.run_batch(jobs, redo=redo, workers=1, progress=False, timeout=600)
    assert summary.count("done" if redo else "skipped") == 1, summary.as_dict()
    assert sorted(p.name for p in tmp_path.iterdir()) == ["hero.npz", "m.toml"]


def test_a_live_writers_temporary_is_kept_and_an_unlocked_one_of_a_reused_pid_is_removed(tmp_path):
    out = tmp_path / "x.bin"
    with _atomic.atomic_file(out) as fh:
        fh.write(b"data")
        live = [p for p in tmp_path.iterdir() if _atomic.temp_owner(p.name)]
        assert live and _atomic.leftovers(tmp_path) == []  # ours, being written
    # a temporary whose pid now belongs to another process (pid reuse) but nobody locks
    reused = tmp_path / f".x.bin.{os.getppid()}.0123abcd.frtmp.bin"
    reused.write_bytes(b"old")
    assert _atomic.leftovers(tmp_path) == [reused]
    fr.save(samples.sample("mesh"), tmp_path / "y.obj")
    assert reused.exists(), "a write to another destination leaves it"
    _atomic.remove_leftovers(out)
    assert not reused.exists()
