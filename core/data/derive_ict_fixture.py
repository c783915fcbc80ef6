"""Derive ``ict_face_fixture.npz`` from the ICT-FaceKit face region (run once, by hand).

    python core/data/derive_ict_fixture.py /path/to/ict_face.npz

Input: the face region of the ICT-FaceKit generic model (vertices 0..9408, quads
fan-triangulated, centimetres; see README.md here). Output keys:

- ``neutral`` (9409, 3) float32, ``faces`` (18461, 3) int32, ``landmarks68`` (68,) int32: copied;
- ``expression_names`` (45,): the 53 ICT expressions minus the 8 ``eyeLook*`` shapes
  (eye-ball rotations, which move no face-region vertex in a useful way);
- ``expression_deltas_q`` (45, 9409, 3) int16 and ``expression_scales`` (45,) float64:
  each delta quantized as ``round(delta / scale)`` with ``scale = max|delta| / 32767``
  (error below 6e-5 cm);
- ``identity_deltas_q`` (10, 9409, 3) int16 and ``identity_scales`` (10,): the same for the
  first 10 identity modes.
"""

import sys

import numpy as np


def quantize(deltas: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    scales = np.abs(deltas).reshape(len(deltas), -1).max(axis=1) / 32767.0
    scales[scales == 0] = 1.0
    q = np.round(deltas / scales[:, None, None]).astype(np.int16)
    return q, scales


def main(path: str, out: str = "core/data/ict_face_fixture.npz") -> None:
    d = np.load(path)
    names = np.array([str(n) for n in d["expression_names"]])
    keep = np.array([not n.startswith("eyeLook") for n in names])
    eq, es = quantize(d["expression_deltas"][keep].astype(np.float64))
    iq, is_ = quantize(d["identity_deltas"].astype(np.float64))
    np.savez_compressed(
        out,
        neutral=d["neutral"].astype(np.float32),
        faces=d["faces"].astype(np.int32),
        landmarks68=d["landmarks68"].astype(np.int32),
        expression_names=names[keep],
        expression_deltas_q=eq,
        expression_scales=es,
        identity_deltas_q=iq,
        identity_scales=is_,
    )


if __name__ == "__main__":
    main(*sys.argv[1:])
