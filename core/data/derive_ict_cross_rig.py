"""Derive ``ict_cross_rig_fixture.npz`` (the remeshed source of ``cases.cross_rig``; run once, by hand).

    pip install fast-simplification==0.2.0      # offline tool only; uninstall afterwards
    python core/data/derive_ict_cross_rig.py

Input: ``ict_face_fixture.npz`` beside this script (the ICT-FaceKit face region, 9409
vertices). The generic neutral is decimated by quadric edge collapse
(fast-simplification, ``target_count=4000`` triangles, ``agg=7``, borders free to
simplify) to about 2,070 vertices; every decimated vertex is then projected to its
closest point on the ICT mesh, so at run time any ICT shape (identity or expression)
is carried to the new topology by barycentric interpolation. Output keys:

- ``triangles`` (T, 3) int32: the source topology (same orientation as ICT);
- ``vertex_triangles`` (V,) int32 and ``vertex_barycentric`` (V, 3) float64: the ICT
  triangle and barycentric weights of each source vertex;
- ``landmark_triangles`` (68,) int32 and ``landmark_barycentric`` (68, 3) float64: the
  68 Multi-PIE landmarks as barycentric points on the *source* triangles (closest
  points to the ICT landmark vertices).

The script checks what run time relies on: 1,500-3,000 vertices, four boundary loops
(outline, two eyes, mouth) each near its ICT loop, no degenerate triangle, projection
error below 0.05 cm, and the source landmarks following the ICT landmarks under jawOpen
and the blinks (so no landmark sits on the wrong lip or lid).
"""

import argparse
import sys
from pathlib import Path

import numpy as np

HERE = Path(__file__).resolve().parent


def load_ict(path: Path) -> dict[str, np.ndarray]:
    with np.load(path) as d:
        out = {k: d[k] for k in d.files}
    out["expression_deltas"] = (
        out["expression_deltas_q"].astype(np.float64) * out["expression_scales"][:, None, None]
    )
    return out


def interpolate(
    values: np.ndarray, triangles: np.ndarray, tri_ids: np.ndarray, bary: np.ndarray
) -> np.ndarray:
    """Barycentric interpolation of per-vertex ``values (..., V, 3)`` at (triangle, weights) points."""
    return np.einsum("...pkd,pk->...pd", values[..., triangles[tri_ids], :], bary)


def main(
    out: str = str(HERE / "ict_cross_rig_fixture.npz"), target_count: int = 4000, agg: float = 7.0
) -> None:
    import fast_simplification

    from faceretarget.correspond.topology import boundary_loops
    from faceretarget.geometry.raycast import closest_points
    from faceretarget.model import Mesh

    d = load_ict(HERE / "ict_face_fixture.npz")
    ict_v = d["neutral"].astype(np.float64)
    ict_t = d["faces"].astype(np.int64)
    names = [str(n) for n in d["expression_names"]]
    deltas = d["expression_deltas"]
    lm = d["landmarks68"].astype(np.int64)

    dec_v, dec_t = fast_simplification.simplify(
        ict_v, ict_t.astype(np.int32), target_count=target_count, agg=agg
    )
    used = np.unique(dec_t)
    remap = np.full(len(dec_v), -1)
    remap[used] = np.arange(len(used))
    dec_v, dec_t = dec_v[used], remap[dec_t]

    hits = closest_points(ict_v, ict_t, dec_v)
    assert hits.hit.all()
    tri_ids, bary = hits.triangle, np.clip(hits.barycentric, 0.0, None)
    bary /= bary.sum(axis=1, keepdims=True)
    assert np.abs(hits.distance).max() < 0.05, np.abs(hits.distance).max()
    src_v = interpolate(ict_v, ict_t, tri_ids, bary)
    mesh = Mesh(src_v, dec_t)
    mesh.check_nondegenerate("derive_ict_cross_rig")
    assert 1500 <= len(src_v) <= 3000, len(src_v)

    # orientation kept: source triangle normals agree with the ICT normals under them
    n_src = mesh.face_normals
    n_ict = Mesh(ict_v, ict_t).face_normals[tri_ids[dec_t[:, 0]]]
    assert (np.einsum("ij,ij->i", n_src, n_ict) > 0).mean() > 0.99

    # the same holes: each ICT boundary loop has a source loop with nearly the same bounding box
    src_loops, ict_loops = boundary_loops(dec_t), boundary_loops(ict_t)
    assert len(src_loops) == len(ict_loops) == 4, (len(src_loops), len(ict_loops))

    def box(points: np.ndarray) -> np.ndarray:
        return np.concatenate([points.min(axis=0), points.max(axis=0)])

    for loop in ict_loops:
        b = box(ict_v[loop])
        best = min(src_loops, key=lambda s: np.abs(box(src_v[s]) - b).max())
        assert np.abs(box(src_v[best]) - b).max() < 0.35, np.abs(box(src_v[best]) - b)

    # landmarks: closest points on the source to the ICT landmark vertices
    lm_hits = closest_points(src_v, dec_t, ict_v[lm])
    lm_tri, lm_bary = lm_hits.triangle, np.clip(lm_hits.barycentric, 0.0, None)
    lm_bary /= lm_bary.sum(axis=1, keepdims=True)
    for shape in ("jawOpen", "eyeBlink_L", "eyeBlink_R", "mouthFunnel"):
        k = names.index(shape)
        moved_ict = deltas[k][lm]
        moved_src = interpolate(
            interpolate(deltas[k], ict_t, tri_ids, bary), dec_t, lm_tri, lm_bary
        )
        err = np.linalg.norm(moved_src - moved_ict, axis=1)
        assert err.max() < 0.25 * np.linalg.norm(moved_ict, axis=1).max() + 0.05, (shape, err.max())

    np.savez_compressed(
        out,
        triangles=dec_t.astype(np.int32),
        vertex_triangles=tri_ids.astype(np.int32),
        vertex_barycentric=bary,
        landmark_triangles=lm_tri.astype(np.int32),
        landmark_barycentric=lm_bary,
    )
    print(
        f"{out}: {len(src_v)} vertices, {len(dec_t)} triangles, loops {[len(s) for s in src_loops]}, "
        f"max projection {np.abs(hits.distance).max():.4f} cm, {Path(out).stat().st_size / 1024:.0f} KB"
    )


def _parse_args(argv: list[str]) -> argparse.Namespace:
    """The command line ``[out [target_count [agg]]]``, typed as :func:`main` takes them."""
    parser = argparse.ArgumentParser(description="Derive ict_cross_rig_fixture.npz.")
    parser.add_argument(
        "out", nargs="?", default=str(HERE / "ict_cross_rig_fixture.npz"), help="the .npz to write"
    )
    parser.add_argument(
        "target_count", nargs="?", type=int, default=4000, help="triangles after decimation"
    )
    parser.add_argument(
        "agg", nargs="?", type=float, default=7.0, help="fast-simplification aggressiveness"
    )
    return parser.parse_args(argv)


if __name__ == "__main__":
    args = _parse_args(sys.argv[1:])
    main(args.out, args.target_count, args.agg)
