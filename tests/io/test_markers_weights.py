"""Markers (C3D, TRC, CSV) and weight curves (CSV incl. Live Link Face)."""

from __future__ import annotations

import io
import warnings

import numpy as np
import pytest

import faceretarget as fr
from faceretarget.errors import FileFormatError
from faceretarget.model import MarkerSequence, WeightSequence
from faceretarget.naming import LIVE_LINK_NAMES


@pytest.mark.parametrize("ext", ["csv", "trc", "npz"])
def test_marker_text_formats_round_trip_exactly(tmp_path, markers, ext):
    fr.save(markers, tmp_path / f"a.{ext}")
    once = fr.load(tmp_path / f"a.{ext}")
    assert (
        isinstance(once, MarkerSequence) and once.names == markers.names and once.fps == markers.fps
    )
    np.testing.assert_array_equal(once.positions, markers.positions)  # NaN where missing
    np.testing.assert_array_equal(once.reference, markers.reference)
    fr.save(once, tmp_path / f"b.{ext}")
    assert (tmp_path / f"b.{ext}").read_bytes().replace(b"b." + ext.encode(), b"") == (
        tmp_path / f"a.{ext}"
    ).read_bytes().replace(b"a." + ext.encode(), b"")


def test_c3d_float32_round_trip_with_missing_samples(tmp_path, markers):
    fr.save(markers, tmp_path / "a.c3d")
    once = fr.load(tmp_path / "a.c3d")
    assert once.names == markers.names and once.fps == markers.fps
    np.testing.assert_array_equal(np.isnan(once.positions), np.isnan(markers.positions))
    np.testing.assert_allclose(once.positions, markers.positions, atol=1e-4, equal_nan=True)
    fr.save(once, tmp_path / "b.c3d")
    np.testing.assert_array_equal(fr.load(tmp_path / "b.c3d").positions, once.positions)


def test_c3d_written_by_the_c3d_package_in_integer_format(tmp_path):
    """A file from another writer: scaled int16 points, residual -1 marks missing samples."""
    import c3d

    writer = c3d.Writer(point_rate=60.0, point_scale=0.1)
    writer.set_point_labels(["A", "B"])
    frames = []
    for f in range(3):
        pts = np.zeros((2, 5), np.float32)
        pts[:, :3] = [[10 * f, 1, 2], [3, 4, 5]]
        if f == 1:
            pts[1, 3] = -1
        frames.append((pts, np.zeros((0, 0), np.float32)))
    writer.add_frames(frames)
    buf = io.BytesIO()
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        writer.write(buf)
    (tmp_path / "int.c3d").write_bytes(buf.getvalue())
    read = fr.load(tmp_path / "int.c3d")
    assert read.names == ("A", "B") and read.fps == 60.0
    assert np.isnan(read.positions[1, 1]).all() and not np.isnan(read.positions[1, 0]).any()
    np.testing.assert_allclose(read.positions[2, 0], [20, 1, 2], atol=0.1)


TRC = (
    "PathFileType\t4\t(X/Y/Z)\tface.trc\n"
    "DataRate\tCameraRate\tNumFrames\tNumMarkers\tUnits\tOrigDataRate\tOrigDataStartFrame\tOrigNumFrames\n"
    "100.00\t100.00\t3\t2\tmm\t100.00\t1\t3\n"
    "Frame#\tTime\tBrowL\t\t\tChin\t\t\n"
    "\t\tX1\tY1\tZ1\tX2\tY2\tZ2\n"
    "\n"
    "1\t0.000\t1.0\t2.0\t3.0\t4.0\t5.0\t6.0\n"
    "2\t0.010\t1.1\t2.1\t3.1\t\t\t\n"
    "3\t0.020\t1.2\t2.2\t3.2\n"
)


def test_trc_missing_and_trailing_cells_become_nan(tmp_path):
    (tmp_path / "face.trc").write_text(TRC)
    m = fr.load(tmp_path / "face.trc")
    assert m.names == ("BrowL", "Chin") and m.fps == 100.0
    assert np.isnan(m.positions[1:, 1]).all()
    np.testing.assert_array_equal(m.positions[2, 0], [1.2, 2.2, 3.2])


@pytest.mark.parametrize(
    "text,needle",
    [
        (TRC.replace("100.00\t100.00\t3", "100.00\t100.00\t5"), "NumFrames is 5"),
        (TRC.replace("\t2\tmm", "\t3\tmm"), "NumMarkers is 3"),
        (TRC.replace("1.1\t2.1", "1.1\tx"), "expected a number"),
        (TRC.replace("1.1\t2.1\t3.1", "1.1\t\t3.1"), "some coordinates NaN"),
        (TRC.replace("4.0\t5.0\t6.0", "\t\t").replace("\t\t\t\n", "\t\t\t\n"), "Chin"),
    ],
)
def test_bad_trc(tmp_path, text, needle):
    (tmp_path / "bad.trc").write_text(text)
    with pytest.raises(FileFormatError, match=needle):
        fr.load(tmp_path / "bad.trc")


def test_marker_csv_header_variants_and_2d_tracks(tmp_path):
    (tmp_path / "m.csv").write_text(
        "Frame,Time,nose.X,nose.Y,nose.Z,chin:x,chin:y,chin:z\n0,0,1,2,3,4,5,6\n1,0.04,1,2,3,,,\n"
    )
    m = fr.load(tmp_path / "m.csv")
    assert m.names == ("nose", "chin") and m.fps == 25.0 and np.isnan(m.positions[1, 1]).all()
    (tmp_path / "t.csv").write_text("a_x,a_y,b_x,b_y\n1,2,3,4\n5,6,7,8\n")
    t = fr.load(tmp_path / "t.csv", kind="markers")
    assert t.dim == 2 and t.names == ("a", "b")
    fr.save(t, tmp_path / "t2.csv")
    np.testing.assert_array_equal(fr.load(tmp_path / "t2.csv").positions, t.positions)


def _live_link(rows: int, count: int = 61, fps_field: int = 60) -> str:
    header = "Timecode,BlendShapeCount," + ",".join(LIVE_LINK_NAMES)
    lines = [header]
    rng = np.random.default_rng(0)
    for r in range(rows):
        s, f = divmod(r, fps_field)
        values = ",".join(f"{v:.8f}" for v in rng.random(61))
        lines.append(f"14:03:{52 + s:02d}:{f:02d}.{r % 7}00,{count},{values}")
    return "\n".join(lines) + "\n"


def test_live_link_face_csv(tmp_path):
    path = tmp_path / "take.csv"
    path.write_text(_live_link(130))
    w = fr.load(path)
    # the 9 head/eye rotation columns are not blendshape weights
    assert isinstance(w, WeightSequence) and w.names == LIVE_LINK_NAMES[:52] and w.n_frames == 130
    assert sorted(w.extras["channels"]) == sorted(LIVE_LINK_NAMES[52:]) and w.head_motion.shape == (
        130,
        4,
        4,
    )
    assert w.fps == pytest.approx(60.0, rel=1e-2)
    fr.save(w, tmp_path / "out.csv")
    assert (
        (tmp_path / "out.csv")
        .read_text()
        .splitlines()[0]
        .startswith("Timecode,BlendShapeCount,EyeBlinkLeft,")
    )
    again = fr.load(tmp_path / "out.csv")
    np.testing.assert_array_equal(again.weights, w.weights)
    np.testing.assert_array_equal(again.head_motion, w.head_motion)
    assert again.names == w.names and again.fps == w.fps


def test_live_link_wrong_blendshape_count(tmp_path):
    path = tmp_path / "take.csv"
    path.write_text(_live_link(3, count=52))
    with pytest.raises(FileFormatError, match="BlendShapeCount is '52' but 61"):
        fr.load(path)


@pytest.mark.parametrize("fps", [24.0, 30.0, 60.0])
def test_weights_csv_round_trip_keeps_fps_even_for_short_takes(tmp_path, weights, fps):
    short = WeightSequence(weights.weights[:5], weights.names, fps=fps)
    fr.save(short, tmp_path / "w.csv")
    once = fr.load(tmp_path / "w.csv")
    assert once.fps == fps and once.names == short.names
    np.testing.assert_array_equal(once.weights, short.weights)


@pytest.mark.parametrize(
    "text,needle",
    [
        ("frame,jawOpen,smile\n0,0.1,0.2\n1,0.3\n", "row 3 has 2 cells"),
        ("frame,jawOpen,smile\n0,0.1,nan\n", "not a finite weight"),
        ("frame,jawOpen,smile\n0,0.1,abc\n", "expected a number"),
        ("frame,jawOpen,jawOpen\n0,0.1,0.2\n", "duplicate name"),
        ("Timecode,BlendShapeCount,jawOpen\n12:00:00,1,0.5\n", "timecode"),
    ],
)
def test_bad_weight_csv(tmp_path, text, needle):
    (tmp_path / "w.csv").write_text(text)
    with pytest.raises(FileFormatError, match=needle):
        fr.load(tmp_path / "w.csv", kind="weights")


def test_plain_weights_csv_with_time_column(tmp_path):
    (tmp_path / "w.csv").write_text("time,jawOpen\n0,0\n0.5,1\n1.0,0.5\n")
    w = fr.load(tmp_path / "w.csv")
    assert w.fps == 2.0 and w.names == ("jawOpen",)
