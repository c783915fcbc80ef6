"""Writes a small C3D file with ezc3d (the C++ library's Python binding), and what ezc3d reads back.

Run (with ezc3d installed): python make_ezc3d_file.py OUTDIR
"""
import json
import sys
from pathlib import Path

import ezc3d
import numpy as np

out = Path(sys.argv[1])
out.mkdir(parents=True, exist_ok=True)
rng = np.random.default_rng(7)
names = ["browL", "browR", "noseTip", "lipUpper", "lipLower", "jaw"]
n_frames = 12
c3d = ezc3d.c3d()
c3d["parameters"]["POINT"]["RATE"]["value"] = [120.0]
c3d["parameters"]["POINT"]["LABELS"]["value"] = names
c3d["parameters"]["POINT"]["UNITS"]["value"] = ["mm"]
points = np.ones((4, len(names), n_frames))
points[:3] = 100.0 * rng.normal(size=(3, len(names), n_frames))
c3d["data"]["points"] = points
residuals = np.zeros((1, len(names), n_frames))
residuals[0, 3, 5:7] = -1.0  # lipUpper occluded in frames 5 and 6
c3d["data"]["meta_points"] = {"residuals": residuals, "camera_masks": np.zeros((7, len(names), n_frames), dtype=bool)}
c3d.write(str(out / "ezc3d_face.c3d"))
back = ezc3d.c3d(str(out / "ezc3d_face.c3d"))
p = back["data"]["points"][:3]  # (3, N, F); ezc3d gives NaN for residual < 0
truth = {
    "ezc3d": ezc3d.__version__ if hasattr(ezc3d, "__version__") else "1.7.2",
    "labels": back["parameters"]["POINT"]["LABELS"]["value"],
    "rate": float(back["parameters"]["POINT"]["RATE"]["value"][0]),
    "units": back["parameters"]["POINT"]["UNITS"]["value"][0],
    "points": np.transpose(p, (2, 1, 0)).tolist(),  # (F, N, 3), NaN as null
}
(out / "ezc3d_face.truth.json").write_text(json.dumps(truth).replace("NaN", "null"))
print("wrote", truth["labels"], truth["rate"], np.isnan(p).sum())
