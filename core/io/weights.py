"""Blendshape weight curves as CSV, including the iPhone Live Link Face layout.

Read: one header row; ``Timecode``, ``BlendShapeCount``, ``Frame`` and ``Time`` columns
are recognised (case-insensitively), every other column is a weight curve named by its
header (names are kept exactly; matching them to a rig is :mod:`faceretarget.naming`'s
job). ``BlendShapeCount`` must equal the number of columns after it. The frame rate is
``fps=`` if given, else from a ``Time`` column (seconds), else from the ``Timecode``
``HH:MM:SS:FF[.sub]`` fields (the frame field counts at the smallest standard rate above
its largest value), else 60 (Live Link Face's default) for timecoded files and 30.

Write (the Live Link Face layout Unreal's importer reads): ``Timecode, BlendShapeCount``,
then one column per weight, shortest round-trip decimals. Timecodes count frames at the
nominal rate ``round(fps)`` and start at frame ``round(fps) - 1`` of second 0, so the
rate can be read back from the frame field even for short takes.
"""
from __future__ import annotations

import csv
import io
import re
from pathlib import Path

import numpy as np

from ..errors import InputError
from ..model import WeightSequence
from ._atomic import write_bytes
from ._common import bad, check_budget, fmt_float, fps_from_times, guarded_reader, parse_float
from .markers import csv_table

__all__ = ["read_weights_csv", "write_weights_csv", "LIVE_LINK_EXTRA", "timecode", "parse_timecode"]

#: the non-blendshape columns a Live Link Face take ends with (head and eye rotations)
LIVE_LINK_EXTRA = (
    "HeadYaw", "HeadPitch", "HeadRoll", "LeftEyeYaw", "LeftEyePitch", "LeftEyeRoll", "RightEyeYaw", "RightEyePitch", "RightEyeRoll",
)
_STANDARD_RATES = (24, 25, 30, 48, 50, 60, 72, 90, 100, 120, 240)
_TIMECODE = re.compile(r"^(\d+):(\d{1,2}):(\d{1,2})[:;.](\d+)(?:\.(\d+))?$")
_LIVE_LINK_FPS = 60.0
_DEFAULT_FPS = 30.0


def parse_timecode(text: str, path, row: int) -> tuple[int, float]:
    """(whole seconds, frame field with its sub-frame fraction) of ``HH:MM:SS:FF[.sub]``."""
    m = _TIMECODE.match(text.strip())
    if not m:
        raise bad(path, f"row {row}: timecode {text[:30]!r} is not HH:MM:SS:FF[.sub]")
    h, mi, s, ff, sub = m.groups()
    frame = int(ff) + (float("0." + sub) if sub else 0.0)
    return int(h) * 3600 + int(mi) * 60 + int(s), frame


def timecode(frame: int, nominal: int) -> str:
    seconds, ff = divmod(frame, nominal)
    h, rest = divmod(seconds, 3600)
    m, s = divmod(rest, 60)
    return f"{h:02d}:{m:02d}:{s:02d}:{ff:02d}.000"


def _fps_from_timecodes(codes: list[tuple[int, float]]) -> float:
    max_field = max(int(ff) for _, ff in codes)
    nominal = next((r for r in _STANDARD_RATES if r > max_field), max_field + 1)
    times = np.array([s + ff / nominal for s, ff in codes])
    if np.any(np.diff(times) <= 0):
        return float(nominal)
    return fps_from_times(times, nominal)


@guarded_reader
def read_weights_csv(path: Path, *, fps=None, **options) -> WeightSequence:
    """Weight curves from a CSV (Live Link Face or ``frame, time, name...`` layouts)."""
    meta = {"timecode", "blendshapecount", "frame", "frame#", "time", "timestamp"}
    layout = {}

    def pick(header):
        lower = [h.lower() for h in header]
        weight_cols = [i for i, h in enumerate(lower) if h not in meta]
        if not weight_cols:
            raise bad(path, "no weight columns: every column is Timecode/BlendShapeCount/Frame/Time")
        for i in weight_cols:
            if not header[i]:
                raise bad(path, f"column {i + 1} has an empty name")
        count_col = lower.index("blendshapecount") if "blendshapecount" in lower else None
        time_col = lower.index("time") if "time" in lower else (lower.index("timestamp") if "timestamp" in lower else None)
        layout.update(lower=lower, weight_cols=weight_cols, count_col=count_col, time_col=time_col)
        extra = [c for c in (count_col, time_col) if c is not None]
        return weight_cols + extra

    def text_cols(header):
        lower = [h.lower() for h in header]
        return (lower.index("timecode"),) if "timecode" in lower else ()

    header, table, texts = csv_table(path, pick, text_cols=text_cols)
    lower, weight_cols = layout["lower"], layout["weight_cols"]
    if table.shape[0] == 0:
        raise bad(path, "holds a header but no frames")
    n = len(weight_cols)
    names = [header[i] for i in weight_cols]
    weights = table[:, :n]
    if not np.all(np.isfinite(weights)):
        r, j = (int(x) for x in np.argwhere(~np.isfinite(weights))[0])
        raise bad(path, f"row {r + 2}, column {header[weight_cols[j]]!r}: {weights[r, j]} is not a finite weight (an empty cell is not a weight)")
    k = n
    if layout["count_col"] is not None:
        declared = table[:, k]
        after = len(header) - layout["count_col"] - 1
        wrong = np.flatnonzero(declared != after)
        if wrong.size:
            raise bad(path, f"row {int(wrong[0]) + 2}: BlendShapeCount is '{declared[wrong[0]]:g}' but {after} weight columns follow it")
        k += 1
    if fps is None:
        fps = _DEFAULT_FPS
        if layout["time_col"] is not None:
            times = table[:, k]
            if not np.all(np.isfinite(times)):
                raise bad(path, f"column {header[layout['time_col']]!r} must hold times in seconds")
            fps = fps_from_times(times, _DEFAULT_FPS)
        elif "timecode" in lower:
            cells = texts[lower.index("timecode")]
            codes = [parse_timecode(c, path, r + 2) for r, c in enumerate(cells)]
            fps = _fps_from_timecodes(codes) if len(codes) > 1 or codes[0][1] > 0 else _LIVE_LINK_FPS
    if weights.base is not None and not weights.flags.c_contiguous and k == n:
        weights = np.ascontiguousarray(weights)
    return WeightSequence(weights, names, fps=fps)


def write_weights_csv(weights: WeightSequence, path, *, force: bool = False, inputs=(), **options) -> None:
    """Write weight curves in the Live Link Face CSV layout (atomic)."""
    if not isinstance(weights, WeightSequence):
        raise InputError(f"the weights CSV writer takes a WeightSequence, got {type(weights).__name__}")
    bad_names = [n for n in weights.names if n.strip().lower() in ("timecode", "blendshapecount", "frame", "time") or "\n" in n]
    if bad_names:
        raise InputError(f"weights CSV: shape names {bad_names} clash with the layout's own columns; rename them")
    nominal = max(1, int(round(weights.fps)))
    buf = io.StringIO()
    w = csv.writer(buf, lineterminator="\n")
    w.writerow(["Timecode", "BlendShapeCount"] + list(weights.names))
    count = str(len(weights.names))
    for f, row in enumerate(np.asarray(weights.weights).tolist()):
        w.writerow([timecode(f + nominal - 1, nominal), count] + [fmt_float(v) for v in row])
    write_bytes(path, buf.getvalue().encode("utf-8"), inputs=inputs, force=force)
