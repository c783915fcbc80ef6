"""Derive ``ict_cross_topology_fixture.npz`` (the closed-eye source of ``cases.cross_topology``; run once, by hand).

    pip install --target /tmp/fsimp fast-simplification==0.2.0   # offline tool only, kept out of the env
    FSIMP=/tmp/fsimp python core/data/derive_ict_cross_topology.py

Input: ``ict_face_fixture.npz`` beside this script (the ICT-FaceKit face region, 9409
vertices, centimetres). A head mesh of another topology is built from it, the way a
scanned or sculpted head differs from the ICT face:

1. **Eyes closed, eyelid holes filled.** The generic neutral with both ``eyeBlink`` shapes
   at 1 closes the outer lids; every eye-region vertex hidden behind the closed lids (a
   ray towards the viewer, +z, hits the face) is removed, and the slit left between the
   lid margins is filled (ear clipping in the x-y plane). No eye holes remain.
2. **A mouth bag.** The lip loop is continued by a pocket 3 cm deep into the mouth
   (8 rings and a cap), so the source has no mouth hole; the ICT face has no bag.
3. **Different boundaries.** The forehead is cut at y = 8 cm (the ICT face reaches
   12.4 cm) and a 3-ring skirt (2.4 cm, curling back) continues the outline below
   y = 2 cm (sides, jaw line and neck), beyond the ICT face.
4. **Remeshed.** Quadric edge collapse (fast-simplification, ``target_count=4600``
   triangles, ``agg=7``) to about 2,400 vertices; every decimated vertex is then put on
   its closest point of the built surface.

Every source vertex is stored as an affine combination of ICT vertices plus a fixed
offset (cm): ``x = W @ ict_vertices + offset``. On the face, ``W`` is a barycentric point
of an ICT triangle and the offset is 0, so any ICT identity or expression is carried to
the new topology by the same weights; filled-eye vertices combine lid vertices, bag and
skirt vertices follow a lip / outline vertex rigidly. Output keys:

- ``triangles`` (T, 3) int32: the source topology (same orientation as ICT);
- ``w_indptr``, ``w_indices`` (int32), ``w_data`` (float64): ``W`` as CSR (V, 9409);
- ``offset`` (V, 3) float64: the fixed offsets (cm; 0 on the face);
- ``region`` (V,) int8: 0 face (on an ICT triangle), 1 closed eye fill, 2 mouth bag, 3 skirt;
- ``landmark_triangles`` (68,) int32 and ``landmark_barycentric`` (68, 3) float64: the
  68 Multi-PIE landmarks on the *source* triangles (closest points to the ICT landmarks
  of the closed-eye face).

The script checks what run time relies on: 2,000-3,000 vertices, a single boundary loop
(the new outline), no degenerate or flipped triangle against the built surface, every
face vertex within 0.05 cm of the ICT surface, and the file under 300 KB.
"""

import argparse
import os
import sys
from pathlib import Path
from typing import TYPE_CHECKING

import numpy as np

if TYPE_CHECKING:
    import scipy.sparse as sp

HERE = Path(__file__).resolve().parent
#: Region codes of the source vertices.
FACE, EYE, BAG, SKIRT = 0, 1, 2, 3
FOREHEAD_CUT = 8.0
SKIRT_ABOVE = 2.0
SKIRT_RINGS = 3
SKIRT_STEP = 0.8
BAG_RINGS = 8
BAG_DEPTH = 3.0


def load_ict(path: Path) -> dict[str, np.ndarray]:
    with np.load(path) as d:
        out = {k: d[k] for k in d.files}
    out["expression_deltas"] = (
        out["expression_deltas_q"].astype(np.float64) * out["expression_scales"][:, None, None]
    )
    return out


class Builder:
    """A triangle mesh whose vertices are affine combinations of ICT vertices + offsets."""

    def __init__(self, ict_v: np.ndarray, ict_t: np.ndarray) -> None:
        import scipy.sparse as sp

        n = len(ict_v)
        self.base = ict_v
        self.rows = sp.identity(n, format="csr")
        self.offset = np.zeros((n, 3))
        self.region = np.full(n, FACE, dtype=np.int8)
        self.tri = ict_t.copy()

    @property
    def vertices(self) -> np.ndarray:
        return self.rows @ self.base + self.offset

    def add(self, rows: "sp.spmatrix", offset: np.ndarray, region: int) -> np.ndarray:
        import scipy.sparse as sp

        start = self.rows.shape[0]
        self.rows = sp.vstack([self.rows, rows]).tocsr()
        self.offset = np.vstack([self.offset, offset])
        self.region = np.concatenate([self.region, np.full(rows.shape[0], region, dtype=np.int8)])
        return np.arange(start, start + rows.shape[0])

    def compact(self) -> None:
        used = np.zeros(self.rows.shape[0], dtype=bool)
        used[self.tri] = True
        remap = np.cumsum(used) - 1
        self.tri = remap[self.tri]
        self.rows = self.rows[used]
        self.offset = self.offset[used]
        self.region = self.region[used]


def fill_polygon(loop: np.ndarray, xy: np.ndarray) -> list:
    """Ear clipping of the closed polygon ``loop`` (vertex ids) with 2D points ``xy[loop]``;
    triangles oriented like the loop (counter-clockwise loops give counter-clockwise triangles)."""
    ids = list(loop)
    pts = {i: xy[i] for i in ids}
    area = sum(
        pts[a][0] * pts[b][1] - pts[b][0] * pts[a][1] for a, b in zip(ids, ids[1:] + ids[:1])
    )
    sign = 1.0 if area > 0 else -1.0
    out = []

    def cross(o: np.ndarray, a: np.ndarray, b: np.ndarray) -> float:
        return (a[0] - o[0]) * (b[1] - o[1]) - (a[1] - o[1]) * (b[0] - o[0])

    guard = 0
    while len(ids) > 3 and guard < 100000:
        guard += 1
        best: int | None = None
        best_q: float | np.floating = -np.inf
        for k in range(len(ids)):
            a, b, c = ids[k - 1], ids[k], ids[(k + 1) % len(ids)]
            if sign * cross(pts[a], pts[b], pts[c]) <= 0:
                continue
            if any(
                _inside(pts[p], pts[a], pts[b], pts[c], sign) for p in ids if p not in (a, b, c)
            ):
                continue
            # prefer fat ears (smallest angle largest)
            q = (
                sign
                * cross(pts[a], pts[b], pts[c])
                / (np.linalg.norm(pts[a] - pts[c]) ** 2 + 1e-12)
            )
            if q > best_q:
                best, best_q = k, q
        if best is None:
            raise RuntimeError("ear clipping failed")
        a, b, c = ids[best - 1], ids[best], ids[(best + 1) % len(ids)]
        out.append((a, b, c))
        ids.pop(best)
    out.append(tuple(ids))
    return out


def _inside(p: np.ndarray, a: np.ndarray, b: np.ndarray, c: np.ndarray, sign: float) -> bool:
    def cross(o: np.ndarray, u: np.ndarray, v: np.ndarray) -> float:
        return (u[0] - o[0]) * (v[1] - o[1]) - (u[1] - o[1]) * (v[0] - o[0])

    return sign * cross(a, b, p) > 0 and sign * cross(b, c, p) > 0 and sign * cross(c, a, p) > 0


def close_eyes(b: Builder, closed: np.ndarray, lm: np.ndarray) -> None:
    """Remove the eye-region vertices hidden behind the closed lids and fill the slits."""
    from faceretarget.correspond.topology import boundary_loops
    from faceretarget.geometry.raycast import RayCaster

    caster = RayCaster(closed, b.tri, backend="bvh")
    hidden = np.zeros(len(closed), dtype=bool)
    for eye in (lm[36:42], lm[42:48]):
        lo, hi = (
            closed[eye].min(axis=0) - [0.4, 0.6, 0.0],
            closed[eye].max(axis=0) + [0.4, 0.6, 0.0],
        )
        near = np.flatnonzero(np.all((closed[:, :2] >= lo[:2]) & (closed[:, :2] <= hi[:2]), axis=1))
        hits = caster.cast(
            closed[near] + [0.0, 0.0, 1e-4],
            np.tile([0.0, 0.0, 1.0], (len(near), 1)),
            both_directions=False,
        )
        hidden[near[hits.hit & (hits.distance > 1e-3)]] = True
    keep_tri = ~hidden[b.tri].any(axis=1)
    b.tri = b.tri[keep_tri]
    # drop what hangs by a vertex only (triangles with two boundary... keep it simple: faces whose
    # every edge is a boundary edge)
    for _ in range(3):
        from faceretarget.geometry.mesh_ops import boundary_edges

        be = boundary_edges(b.tri)
        keys = set(map(tuple, np.sort(be, axis=1).tolist()))
        lonely = np.array(
            [
                sum(tuple(sorted((t[i], t[(i + 1) % 3]))) in keys for i in range(3)) >= 2
                for t in b.tri
            ]
        )
        if not lonely.any():
            break
        b.tri = b.tri[~lonely]
    loops = boundary_loops(b.tri)
    for eye in (lm[36:42], lm[42:48]):
        c = closed[eye].mean(axis=0)
        loop = min(loops[1:], key=lambda lp: np.linalg.norm(closed[lp].mean(axis=0) - c))
        # the loop runs along its triangles' edges; new triangles must run the other way
        new = fill_polygon(loop[::-1], closed[:, :2])
        b.tri = np.vstack([b.tri, np.array(new, dtype=np.int64)])
        b.region[loop] = EYE


def mouth_bag(b: Builder, closed: np.ndarray, lm: np.ndarray) -> None:
    """A pocket continuing the lip loop into the mouth."""
    import scipy.sparse as sp

    from faceretarget.correspond.topology import boundary_loops

    loops = boundary_loops(b.tri)
    c = closed[lm[60:68]].mean(axis=0)
    loop = min(loops[1:], key=lambda lp: np.linalg.norm(closed[lp].mean(axis=0) - c))
    p = closed[loop]
    centre = p.mean(axis=0)
    n = len(loop)
    prev = loop[::-1]  # ring order so that new triangles oppose the loop's edges
    for k in range(1, BAG_RINGS + 1):
        s = k / BAG_RINGS
        depth = BAG_DEPTH * s
        # widen a little behind the lips, then close towards the cap
        radial = 1.0 + 0.5 * np.sin(np.pi * s) - 0.9 * s**3
        ring = (
            centre
            + (p[::-1] - centre) * np.array([radial, radial * (1.0 + 1.5 * np.sin(np.pi * s)), 1.0])
            + [0.0, -0.3 * s, -depth]
        )
        rows = sp.csr_matrix((np.ones(n), (np.arange(n), loop[::-1])), shape=(n, b.rows.shape[0]))
        rows = rows @ b.rows  # composed with the lip vertex's own weights
        new = b.add(rows, ring - rows @ b.base, BAG)
        tris = []
        for i in range(n):
            j = (i + 1) % n
            tris += [(prev[i], prev[j], new[j]), (prev[i], new[j], new[i])]
        b.tri = np.vstack([b.tri, np.array(tris)])
        prev = new
    cap_pts = b.vertices[prev].mean(axis=0)
    upper, lower = loop[np.argmax(p[:, 1])], loop[np.argmin(p[:, 1])]
    rows = (
        sp.csr_matrix(([0.5, 0.5], ([0, 0], [upper, lower])), shape=(1, b.rows.shape[0])) @ b.rows
    )
    cap = b.add(rows, cap_pts[None] - rows @ b.base, BAG)[0]
    b.tri = np.vstack([b.tri, np.array([(prev[i], prev[(i + 1) % n], cap) for i in range(n)])])


def crop_and_skirt(b: Builder) -> None:
    """Cut the forehead at FOREHEAD_CUT and continue the outline below SKIRT_ABOVE by a skirt."""
    import scipy.sparse as sp

    from faceretarget.correspond.topology import boundary_loops
    from faceretarget.geometry.mesh_ops import vertex_normals

    v = b.vertices
    b.tri = b.tri[~(v[b.tri][:, :, 1] > FOREHEAD_CUT).any(axis=1)]
    b.compact()
    v = b.vertices
    loops = boundary_loops(b.tri)
    assert len(loops) == 1, [len(lp) for lp in loops]
    loop = loops[0]
    normals = vertex_normals(v, b.tri)
    pts = v[loop]
    tangent = np.roll(pts, -1, axis=0) - np.roll(pts, 1, axis=0)
    # the loop runs along its triangles' edges (interior on the left seen from the normal): outward = tangent x normal
    out = np.cross(tangent, normals[loop])
    out /= np.linalg.norm(out, axis=1, keepdims=True)
    low = pts[:, 1] < SKIRT_ABOVE
    # one contiguous run of the loop below SKIRT_ABOVE
    start = int(np.flatnonzero(low & ~np.roll(low, 1))[0])
    order = np.roll(np.arange(len(loop)), -start)
    run = order[low[order]]
    run = run[: np.argmax(~low[order]) if (~low[order]).any() else len(run)]
    # smooth the outward directions along the run (a jagged outline would fold the skirt)
    d = out[run]
    for _ in range(20):
        d[1:-1] = 0.5 * d[1:-1] + 0.25 * (d[:-2] + d[2:])
    d /= np.linalg.norm(d, axis=1, keepdims=True)
    nrm = normals[loop][run]
    prev = loop[run]
    m = len(run)
    for k in range(1, SKIRT_RINGS + 1):
        ring = v[loop[run]] + k * SKIRT_STEP * d - (0.15 * k * k * SKIRT_STEP) * nrm
        rows = (
            sp.csr_matrix((np.ones(m), (np.arange(m), loop[run])), shape=(m, b.rows.shape[0]))
            @ b.rows
        )
        new = b.add(rows, ring - rows @ b.base, SKIRT)
        tris = []
        for i in range(m - 1):
            # the loop edge prev[i] -> prev[i+1] belongs to a face triangle: oppose it
            tris += [(prev[i + 1], prev[i], new[i]), (prev[i + 1], new[i], new[i + 1])]
        b.tri = np.vstack([b.tri, np.array(tris)])
        prev = new


def main(
    out: str = str(HERE / "ict_cross_topology_fixture.npz"),
    target_count: int = 4600,
    agg: float = 7.0,
) -> None:
    if os.environ.get("FSIMP"):
        sys.path.append(os.environ["FSIMP"])
    import fast_simplification
    import scipy.sparse as sp

    from faceretarget.correspond.topology import boundary_loops
    from faceretarget.geometry.raycast import closest_points
    from faceretarget.model import Mesh

    d = load_ict(HERE / "ict_face_fixture.npz")
    ict_v = d["neutral"].astype(np.float64)
    ict_t = d["faces"].astype(np.int64)
    names = [str(n) for n in d["expression_names"]]
    deltas = d["expression_deltas"]
    lm = d["landmarks68"].astype(np.int64)
    blink = deltas[names.index("eyeBlink_L")] + deltas[names.index("eyeBlink_R")]
    closed = ict_v + blink

    b = Builder(closed, ict_t)
    close_eyes(b, closed, lm)
    mouth_bag(b, closed, lm)
    crop_and_skirt(b)
    b.compact()
    built_v, built_t = b.vertices, b.tri
    built = Mesh(built_v, built_t)
    assert len(boundary_loops(built_t)) == 1

    dec_v, dec_t = fast_simplification.simplify(
        built_v, built_t.astype(np.int32), target_count=target_count, agg=agg
    )
    used = np.unique(dec_t)
    remap = np.full(len(dec_v), -1)
    remap[used] = np.arange(len(used))
    dec_v, dec_t = dec_v[used], remap[dec_t].astype(np.int64)
    hits = closest_points(built_v, built_t, dec_v)
    assert hits.hit.all()
    tri_ids, bary = hits.triangle, np.clip(hits.barycentric, 0.0, None)
    bary /= bary.sum(axis=1, keepdims=True)
    corners = built_t[tri_ids]
    n_src = len(dec_v)
    pick = sp.csr_matrix(
        (bary.ravel(), (np.repeat(np.arange(n_src), 3), corners.ravel())),
        shape=(n_src, len(built_v)),
    )
    rows = (pick @ b.rows).tocsr()
    rows.eliminate_zeros()
    offset = pick @ b.offset
    # a vertex is on the face only if all three corners are
    region = np.where(
        (b.region[corners] == FACE).all(axis=1), FACE, b.region[corners].max(axis=1)
    ).astype(np.int8)
    offset[region == FACE] = 0.0
    src_v = rows @ closed + offset
    assert np.abs(src_v - hits.points).max() < 1e-9
    mesh = Mesh(src_v, dec_t)
    mesh.check_nondegenerate("derive_ict_cross_topology")
    assert 2000 <= n_src <= 3000, n_src
    assert len(boundary_loops(dec_t)) == 1, [len(lp) for lp in boundary_loops(dec_t)]
    n_built = built.face_normals[tri_ids[dec_t].T].transpose(1, 0, 2).mean(axis=1)
    agree = np.einsum("ij,ij->i", mesh.face_normals, n_built)
    assert (agree > 0).mean() > 0.99, (agree <= 0).sum()
    # face vertices lie on ICT triangles
    on_face = region == FACE
    ict_hits = closest_points(closed, ict_t, src_v[on_face])
    assert np.abs(ict_hits.distance).max() < 0.05, np.abs(ict_hits.distance).max()

    lm_hits = closest_points(src_v, dec_t, closed[lm])
    lm_bary = np.clip(lm_hits.barycentric, 0.0, None)
    lm_bary /= lm_bary.sum(axis=1, keepdims=True)
    np.savez_compressed(
        out,
        triangles=dec_t.astype(np.int32),
        w_indptr=rows.indptr.astype(np.int32),
        w_indices=rows.indices.astype(np.int32),
        w_data=rows.data.astype(np.float64),
        offset=offset,
        region=region,
        landmark_triangles=lm_hits.triangle.astype(np.int32),
        landmark_barycentric=lm_bary,
    )
    size = Path(out).stat().st_size / 1024
    counts = np.bincount(region, minlength=4)
    print(
        f"{out}: {n_src} vertices, {len(dec_t)} triangles (built {len(built_v)} / {len(built_t)}), regions face/eye/bag/skirt "
        f"{counts.tolist()}, {rows.nnz} weights, outline {len(boundary_loops(dec_t)[0])}, {size:.0f} KB"
    )
    assert size < 300, size


def _parse_args(argv: list[str]) -> argparse.Namespace:
    """The command line ``[out [target_count [agg]]]``, typed as :func:`main` takes them."""
    parser = argparse.ArgumentParser(description="Derive ict_cross_topology_fixture.npz.")
    parser.add_argument(
        "out",
        nargs="?",
        default=str(HERE / "ict_cross_topology_fixture.npz"),
        help="the .npz to write",
    )
    parser.add_argument(
        "target_count", nargs="?", type=int, default=4600, help="triangles after decimation"
    )
    parser.add_argument(
        "agg", nargs="?", type=float, default=7.0, help="fast-simplification aggressiveness"
    )
    return parser.parse_args(argv)


if __name__ == "__main__":
    args = _parse_args(sys.argv[1:])
    main(args.out, args.target_count, args.agg)
