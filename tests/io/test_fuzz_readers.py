"""Mutated files of every format end in a typed error or a clean result, never anything else.

Valid files are written by our writers (and by hand for foreign layouts), then cut,
overwritten, spliced and edited at random (seeded); each mutant is read with and
without an explicit kind. The number of inputs tried is printed (run with -s).
"""

from __future__ import annotations

import numpy as np
import pytest

import faceretarget as fr
from faceretarget.errors import FaceRetargetError
from faceretarget.io._atomic import clear_inputs

TOKENS = [
    b"-1",
    b"99999999999",
    b"nan",
    b"inf",
    b"1e308",
    b",",
    b"\n",
    b'"',
    b"0",
    b"\t",
    b"{",
    b"]",
    b"/",
    b"-2147483648",
]


def _mutate(data: bytes, rng: np.random.Generator) -> bytes:
    buf = bytearray(data)
    op = int(rng.integers(5))
    if op == 0 or not buf:
        return bytes(buf[: int(rng.integers(len(buf) + 1))])
    if op == 1:
        for _ in range(int(rng.integers(1, 10))):
            buf[int(rng.integers(len(buf)))] = int(rng.integers(256))
    elif op == 2:
        at = int(rng.integers(len(buf)))
        buf[at:at] = rng.integers(0, 256, int(rng.integers(1, 64)), dtype=np.uint8).tobytes()
    elif op == 3:
        at = int(rng.integers(len(buf)))
        buf[at : at + 1] = TOKENS[int(rng.integers(len(TOKENS)))]
    else:
        a, b = int(rng.integers(len(buf))), int(rng.integers(len(buf)))
        buf[a : a + 8] = buf[b : b + 8]
    return bytes(buf)


def _seed_files(tmp_path, mesh, rig, seq, animation, markers, weights):
    objs = [(mesh, e) for e in ("obj", "ply", "off", "stl", "glb", "gltf", "npz")]
    objs += [
        (rig, "glb"),
        (rig, "npz"),
        (seq, "pc2"),
        (seq, "mdd"),
        (seq, "npy"),
        (seq, "glb"),
        (animation, "glb"),
        (animation, "gltf"),
    ]
    objs += [
        (animation, "npz"),
        (markers, "csv"),
        (markers, "trc"),
        (markers, "c3d"),
        (weights, "csv"),
    ]
    seeds = []
    for i, (obj, ext) in enumerate(objs):
        path = tmp_path / f"seed{i}.{ext}"
        fr.save(obj, path)
        seeds.append((ext, path.read_bytes()))
    seeds.append(
        (
            "ply",
            b"ply\nformat ascii 1.0\nelement vertex 3\nproperty float x\nproperty float y\nproperty float z\n"
            b"element face 1\nproperty list uchar int vertex_indices\nend_header\n0 0 0\n1 0 0\n0 1 0\n3 0 1 2\n",
        )
    )
    return seeds


def test_mutated_files_of_every_format(tmp_path, mesh, rig, seq, animation, markers, weights):
    rng = np.random.default_rng(20240601)
    seeds = _seed_files(tmp_path, mesh, rig, seq, animation, markers, weights)
    tried = rejected = 0
    untyped = []
    for n in range(40 * len(seeds)):
        ext, data = seeds[n % len(seeds)]
        mutant = tmp_path / f"mutant.{ext}"
        clear_inputs()
        mutant.write_bytes(_mutate(data, rng))
        for kind in (None, "mesh_sequence" if ext in ("pc2", "mdd", "npy", "glb") else None):
            tried += 1
            try:
                fr.load(mutant, kind=kind, topology=mesh)
            except FaceRetargetError as exc:
                rejected += 1
                assert str(mutant) in str(exc), str(exc)
            except Exception as exc:  # noqa: BLE001 - the point of the test
                untyped.append(f".{ext}: {type(exc).__name__}: {exc}"[:200])
    print(
        f"\nreader fuzz: {tried} mutated inputs tried, {rejected} rejected with typed errors, {len(untyped)} untyped"
    )
    assert not untyped, untyped[:5]
    assert rejected > tried // 3  # most mutants are broken and said so


@pytest.mark.parametrize(
    "ext",
    ["obj", "ply", "off", "stl", "glb", "gltf", "c3d", "trc", "csv", "npz", "npy", "pc2", "mdd"],
)
@pytest.mark.parametrize("content", [b"", b"v 0 0 0\nv 1 0 0\nf 1 2 7\n", bytes(range(256)) * 20])
def test_empty_truncated_and_random_files(tmp_path, mesh, ext, content):
    path = tmp_path / f"in.{ext}"
    path.write_bytes(content)
    with pytest.raises(FaceRetargetError) as info:
        fr.load(path, topology=mesh)
    assert str(path) in str(info.value)
