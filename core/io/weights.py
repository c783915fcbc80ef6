"""Blendshape weight curves as CSV, including the iPhone Live Link Face layout.

Read: one header row; ``Timecode``, ``BlendShapeCount``, ``Frame`` and ``Time`` columns
are recognised (case-insensitively), every other column is a weight curve named by its
header (names are kept exactly; matching them to a rig is :mod:`faceretarget.naming`'s
job). ``BlendShapeCount`` must equal the number of columns after it. The frame rate is
``fps=`` if given, else from a ``Time`` column (seconds), else from the ``Timecode``
``HH:MM:SS:FF[.sub]`` fields (the frame field counts at the smallest standard rate above
its largest value), else 60 (Live Link Face's default) for timecoded files and 30.

Live Link Face's nine rotation columns (:data:`LIVE_LINK_EXTRA`: ``HeadYaw``,
``HeadPitch``, ``HeadRoll`` and the eyes' yaw/pitch/roll, in radians) are not blendshape
weights: they are set aside on the returned sequence as

- ``weights.head_motion``: ``(F, 4, 4)`` rigid transforms, rotation
  ``R = Ry(yaw) @ Rx(pitch) @ Rz(roll)`` (Y up, ARKit's axes), no translation;
- ``weights.extras["channels"]``: every rotation column as read, name -> ``(F,)`` array;
- ``weights.extras["live_link"]``: the timecode of every row and the column order,

so a take read and written back is the same file (timecodes such as
``00:32:09:07.867`` and a 59.96 fps rate included).

Write (the Live Link Face layout Unreal's importer reads): ``Timecode, BlendShapeCount``,
then one column per weight, then the rotation columns when the sequence has them (from
``extras["channels"]``, or derived from ``head_motion``), shortest round-trip decimals.
Timecodes are the ones read when the frame count is unchanged; otherwise they count
frames at the nominal rate ``round(fps)`` with a millisecond sub-frame field (so a rate
such as 59.96 is kept) and start at frame ``round(fps) - 1`` of second 0, so the nominal
rate can be read back from the frame field even for short takes.
"""

from __future__ import annotations

import csv
import io
import re
from collections.abc import Iterable
from pathlib import Path
from typing import Any

import numpy as np

from .._types import PathLike
from ..errors import InputError
from ..model import WeightSequence
from ._atomic import write_bytes
from ._common import bad, fmt_float, fps_from_times, guarded_reader
from .markers import csv_table

__all__ = ["read_weights_csv", "write_weights_csv", "LIVE_LINK_EXTRA", "timecode", "parse_timecode"]

#: the non-blendshape columns a Live Link Face take ends with (head and eye rotations)
LIVE_LINK_EXTRA = (
    "HeadYaw",
    "HeadPitch",
    "HeadRoll",
    "LeftEyeYaw",
    "LeftEyePitch",
    "LeftEyeRoll",
    "RightEyeYaw",
    "RightEyePitch",
    "RightEyeRoll",
)
_STANDARD_RATES = (24, 25, 30, 48, 50, 60, 72, 90, 100, 120, 240)
_TIMECODE = re.compile(r"^(\d+):(\d{1,2}):(\d{1,2})[:;.](\d+)(?:\.(\d+))?$")
_LIVE_LINK_FPS = 60.0
_DEFAULT_FPS = 30.0


def parse_timecode(text: str, path: PathLike, row: int) -> tuple[int, float]:
    """(whole seconds, frame field with its sub-frame fraction) of ``HH:MM:SS:FF[.sub]``."""
    m = _TIMECODE.match(text.strip())
    if not m:
        raise bad(path, f"row {row}: timecode {text[:30]!r} is not HH:MM:SS:FF[.sub]")
    h, mi, s, ff, sub = m.groups()
    frame = int(ff) + (float("0." + sub) if sub else 0.0)
    return int(h) * 3600 + int(mi) * 60 + int(s), frame


def timecode(frame: float, nominal: int) -> str:
    """``HH:MM:SS:FF.mmm`` of (possibly fractional) frame ``frame`` counted at ``nominal`` fps."""
    milli = int(round(float(frame) * 1000.0))
    whole, sub = divmod(milli, 1000)
    seconds, ff = divmod(whole, nominal)
    h, rest = divmod(seconds, 3600)
    m, s = divmod(rest, 60)
    return f"{h:02d}:{m:02d}:{s:02d}:{ff:02d}.{sub:03d}"


def _rotation(yaw: np.ndarray, pitch: np.ndarray, roll: np.ndarray) -> np.ndarray:
    """(F, 4, 4): ``Ry(yaw) @ Rx(pitch) @ Rz(roll)`` (radians), no translation."""
    n = yaw.shape[0]
    cy, sy, cp, sp, cr, sr = (
        np.cos(yaw),
        np.sin(yaw),
        np.cos(pitch),
        np.sin(pitch),
        np.cos(roll),
        np.sin(roll),
    )
    ry = np.zeros((n, 3, 3))
    ry[:, 0, 0] = cy
    ry[:, 0, 2] = sy
    ry[:, 1, 1] = 1
    ry[:, 2, 0] = -sy
    ry[:, 2, 2] = cy
    rx = np.zeros((n, 3, 3))
    rx[:, 0, 0] = 1
    rx[:, 1, 1] = cp
    rx[:, 1, 2] = -sp
    rx[:, 2, 1] = sp
    rx[:, 2, 2] = cp
    rz = np.zeros((n, 3, 3))
    rz[:, 0, 0] = cr
    rz[:, 0, 1] = -sr
    rz[:, 1, 0] = sr
    rz[:, 1, 1] = cr
    rz[:, 2, 2] = 1
    out = np.tile(np.eye(4), (n, 1, 1))
    out[:, :3, :3] = ry @ rx @ rz
    return out


def _yaw_pitch_roll(head: np.ndarray) -> np.ndarray:
    """(F, 3) yaw, pitch, roll of ``Ry @ Rx @ Rz`` rotations (the inverse of :func:`_rotation`)."""
    r = np.asarray(head, dtype=np.float64)[:, :3, :3]
    pitch = np.arcsin(np.clip(-r[:, 1, 2], -1.0, 1.0))
    yaw = np.arctan2(r[:, 0, 2], r[:, 2, 2])
    roll = np.arctan2(r[:, 1, 0], r[:, 1, 1])
    return np.stack([yaw, pitch, roll], axis=1)


def _fps_from_timecodes(codes: list[tuple[int, float]]) -> float:
    max_field = max(int(ff) for _, ff in codes)
    nominal = next((r for r in _STANDARD_RATES if r > max_field), max_field + 1)
    times = np.array([s + ff / nominal for s, ff in codes])
    if np.any(np.diff(times) <= 0):
        return float(nominal)
    return fps_from_times(times, nominal)


@guarded_reader
def read_weights_csv(path: Path, *, fps: float | None = None, **options: Any) -> WeightSequence:
    """Weight curves from a CSV (Live Link Face or ``frame, time, name...`` layouts)."""
    meta = {"timecode", "blendshapecount", "frame", "frame#", "time", "timestamp"}
    layout: dict[str, Any] = {}

    def pick(header: list[str]) -> list[int]:
        lower = [h.lower() for h in header]
        weight_cols = [i for i, h in enumerate(lower) if h not in meta]
        if not weight_cols:
            raise bad(
                path, "no weight columns: every column is Timecode/BlendShapeCount/Frame/Time"
            )
        for i in weight_cols:
            if not header[i]:
                raise bad(path, f"column {i + 1} has an empty name")
        count_col = lower.index("blendshapecount") if "blendshapecount" in lower else None
        time_col = (
            lower.index("time")
            if "time" in lower
            else (lower.index("timestamp") if "timestamp" in lower else None)
        )
        layout.update(lower=lower, weight_cols=weight_cols, count_col=count_col, time_col=time_col)
        extra = [c for c in (count_col, time_col) if c is not None]
        return weight_cols + extra

    def text_cols(header: list[str]) -> tuple[int, ...]:
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
        raise bad(
            path,
            f"row {r + 2}, column {header[weight_cols[j]]!r}: {weights[r, j]} is not a finite weight (an empty cell is not a weight)",
        )
    k = n
    if layout["count_col"] is not None:
        declared = table[:, k]
        after = len(header) - layout["count_col"] - 1
        wrong = np.flatnonzero(declared != after)
        if wrong.size:
            raise bad(
                path,
                f"row {int(wrong[0]) + 2}: BlendShapeCount is '{declared[wrong[0]]:g}' but {after} weight columns follow it",
            )
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
            fps = (
                _fps_from_timecodes(codes) if len(codes) > 1 or codes[0][1] > 0 else _LIVE_LINK_FPS
            )
    rot_idx = [j for j, name in enumerate(names) if name in LIVE_LINK_EXTRA]
    channels: dict[str, np.ndarray] = {}
    if rot_idx:
        keep = [j for j in range(n) if j not in set(rot_idx)]
        if not keep:
            raise bad(
                path,
                f"holds only head/eye rotation columns ({', '.join(names[j] for j in rot_idx)}), no blendshape weights",
            )
        channels = {names[j]: np.array(weights[:, j]) for j in rot_idx}
        weights = weights[:, keep]
        names = [names[j] for j in keep]
    if weights.base is not None and not weights.flags.c_contiguous:
        weights = np.ascontiguousarray(weights)
    seq = WeightSequence(weights, names, fps=fps)
    extras: dict = {}
    if channels:
        extras["channels"] = channels
        if all(h in channels for h in LIVE_LINK_EXTRA[:3]):
            seq.head_motion = _rotation(
                channels["HeadYaw"], channels["HeadPitch"], channels["HeadRoll"]
            )
    if "timecode" in lower:
        extras["live_link"] = {
            "timecodes": [c.strip() for c in texts[lower.index("timecode")]],
            "columns": [header[i] for i in layout["weight_cols"]],
        }
    if extras:
        seq.extras = extras
    return seq


def write_weights_csv(
    weights: WeightSequence,
    path: PathLike,
    *,
    force: bool = False,
    inputs: Iterable = (),
    **options: Any,
) -> None:
    """Write weight curves in the Live Link Face CSV layout (atomic)."""
    if not isinstance(weights, WeightSequence):
        raise InputError(
            f"the weights CSV writer takes a WeightSequence, got {type(weights).__name__}"
        )
    bad_names = [
        n
        for n in weights.names
        if n.strip().lower() in ("timecode", "blendshapecount", "frame", "time") or "\n" in n
    ]
    if bad_names:
        raise InputError(
            f"weights CSV: shape names {bad_names} clash with the layout's own columns; rename them"
        )
    n_frames = weights.n_frames
    extras = getattr(weights, "extras", None) or {}
    channels = {
        k: np.asarray(v, dtype=np.float64).reshape(-1)
        for k, v in (extras.get("channels") or {}).items()
    }
    channels = {
        k: v
        for k, v in channels.items()
        if k in LIVE_LINK_EXTRA and v.shape == (n_frames,) and k not in weights.names
    }
    head = getattr(weights, "head_motion", None)
    if head is not None:
        head = np.asarray(head, dtype=np.float64)
        if head.shape != (n_frames, 4, 4):
            raise InputError(
                f"weights CSV: head_motion has shape {head.shape}; expected ({n_frames}, 4, 4) for {n_frames} frames"
            )
        yaw, pitch, roll = (channels.get(h) for h in LIVE_LINK_EXTRA[:3])
        same = (
            yaw is not None
            and pitch is not None
            and roll is not None
            and np.array_equal(_rotation(yaw, pitch, roll), head)
        )
        if (
            not same
        ):  # the head moved since it was read (or was never a column): write what it is now
            ypr = _yaw_pitch_roll(head)
            channels.update({h: ypr[:, i] for i, h in enumerate(LIVE_LINK_EXTRA[:3])})
    if channels:  # Live Link Face always has all nine; the missing ones are zero
        channels = {k: channels.get(k, np.zeros(n_frames)) for k in LIVE_LINK_EXTRA}
    live = extras.get("live_link") or {}
    order = list(weights.names) + [k for k in LIVE_LINK_EXTRA if k in channels]
    stored_order = live.get("columns")
    if isinstance(stored_order, list) and sorted(stored_order) == sorted(order):
        order = list(stored_order)  # the columns as they were read
    columns = {name: np.asarray(weights.weights)[:, j] for j, name in enumerate(weights.names)}
    columns.update(channels)
    codes = live.get("timecodes")
    if not (
        isinstance(codes, list)
        and len(codes) == n_frames
        and all(isinstance(c, str) and _TIMECODE.match(c) for c in codes)
    ):
        nominal = max(1, int(round(weights.fps)))
        step = nominal / float(weights.fps)
        codes = [timecode(nominal - 1 + f * step, nominal) for f in range(n_frames)]
    buf = io.StringIO()
    w = csv.writer(buf, lineterminator="\n")
    w.writerow(["Timecode", "BlendShapeCount"] + order)
    count = str(len(order))
    table = np.stack([columns[name] for name in order], axis=1).tolist()
    for code, row in zip(codes, table):
        w.writerow([code, count] + [fmt_float(v) for v in row])
    write_bytes(path, buf.getvalue().encode("utf-8"), inputs=inputs, force=force)
