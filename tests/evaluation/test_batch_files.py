"""Batch jobs on real files: source and target bundles written by faceretarget.io."""

import numpy as np

import faceretarget as fr
from faceretarget.evaluation.batch import run_batch
from faceretarget.testing import tiny_case


def test_batch_runs_jobs_from_files_and_skips_them_on_rerun(tmp_path):
    case = tiny_case()
    fr.io.save_bundle(case.source, tmp_path / "shot.npz")
    fr.io.save_bundle(case.target, tmp_path / "hero.npz")
    manifest = tmp_path / "shots.toml"
    manifest.write_text(
        '[defaults]\ncharacter = "hero.npz"\nshot = "shot.npz"\n\n'
        '[[job]]\nmethod = "spacetime"\nout = "out/spacetime.glb"\n\n'
        '[[job]]\nmethod = "deformation_transfer"\nout = "out/dt.npz"\n'
    )
    first = run_batch(manifest, workers=1, progress=False)
    assert sorted(r.status for r in first.results) == ["done", "done"], [
        r.error for r in first.results
    ]
    anim = fr.load(tmp_path / "out" / "dt.npz", kind="animation")
    assert np.asarray(anim.vertices).shape == (
        case.source.n_frames,
        case.target.neutral.n_vertices,
        3,
    )
    glb = fr.load(tmp_path / "out" / "spacetime.glb", kind="animation")
    assert glb.weights is not None and glb.weights.shape[0] == case.source.n_frames
    again = run_batch(manifest, workers=1, progress=False)
    assert [r.status for r in again.results] == ["skipped", "skipped"]
