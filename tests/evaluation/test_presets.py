"""Paper reproductions: each registered preset runs on small cases and yields its plot and table."""

import xml.etree.ElementTree as ET

import numpy as np
import pytest

import faceretarget
from faceretarget import Preset
from faceretarget.errors import UnknownNameError
from faceretarget.evaluation import presets, reproduction
from faceretarget.evaluation.harness import resolve_case
from faceretarget.evaluation.report import svg_plot
from faceretarget.evaluation.reproduction import num as _num
from faceretarget.plugins.coating import presets as xu
from faceretarget.plugins.normalmesh import presets as najung
from faceretarget.plugins.spacetime import presets as seol


@pytest.fixture(scope="module")
def small_cases():
    return {
        "synthetic-human": resolve_case("synthetic-human?resolution=300&n_frames=20"),
        "synthetic-stylized": resolve_case("synthetic-stylized?resolution=300&n_frames=20"),
        "ict": resolve_case("ict?n_frames=4"),
    }


#: Smaller detail cases for the tests (60 frames: the wrinkle shapes are active).
SMALL_DETAIL_CASES = (
    ("human", "synthetic-human?resolution=600&n_frames=60"),
    ("stylized", "synthetic-stylized?resolution=600&n_frames=60"),
)
DENSE = ("najung_table1", "xu_fig4", "xu_fig6", "najung_fig14")


@pytest.fixture(scope="module")
def dense(small_cases):
    """The dense methods' reproductions, run once: name -> PresetResult."""
    with pytest.MonkeyPatch.context() as mp:
        mp.setattr(reproduction, "DETAIL_CASES", SMALL_DETAIL_CASES)
        return {name: presets.run_preset(name, small_cases) for name in DENSE}


def _plots_render(result):
    for plot in result.plots:
        assert ET.fromstring(svg_plot(plot)).tag.endswith("svg")


def _consistent_verdict(res, parts):
    """``res.agrees`` is True iff every part holds; the evidence names every part."""
    assert res.claim and res.setting and res.evidence
    assert res.agrees is all(parts), (res.agrees, parts, res.evidence)
    assert res.evidence.count("agrees:") + res.evidence.count("DISAGREES:") == len(parts)
    assert res.evidence.count("DISAGREES:") == sum(not p for p in parts)


def test_seol_fig11(small_cases):
    res = presets.run_preset("seol_fig11", small_cases)
    assert res.status == "ok", res.reason
    assert [row["method"] for row in res.table] == [
        "No Const",
        "Range PF",
        "Prior PF",
        "movement matching",
    ]
    assert res.table[0]["added over No Const"] == 0.0
    assert all(row["velocity error (vs truth)"] > 0 for row in res.table)
    assert [p.kind for p in res.plots] == ["bar", "line"]
    assert len(res.plots[1].series) == 3 and len(res.plots[1].series[0].x) == 19
    assert "movement matching adds less velocity error than both Range PF and Prior PF" in res.claim
    assert "0.01" in res.setting and "0.5" in res.setting and "noise" in res.setting
    added = {row["method"]: row["added over No Const"] for row in res.table}
    assert (
        res.table[0]["weights in range"] < 1.0
    )  # the stylized target: the range binds, as in the paper
    _consistent_verdict(
        res,
        [
            added["movement matching"] < added["Range PF"],
            added["movement matching"] < added["Prior PF"],
        ],
    )
    assert (
        _num(added["movement matching"]) in res.evidence and _num(added["Prior PF"]) in res.evidence
    )
    _plots_render(res)


def test_seol_fig11_passes_the_paper_parameters(small_cases, monkeypatch):
    """The reproduction runs the paper's settings whatever the methods' defaults are (only
    parameters the installed version accepts are passed)."""
    calls = []
    real_get = faceretarget.get

    def recording(name, **params):
        if params:
            calls.append((name, params))
        return real_get(name, **params)

    monkeypatch.setattr(faceretarget, "get", recording)
    res = presets.run_preset("seol_fig11", small_cases)
    assert res.status == "ok", res.reason
    used = dict(calls)
    assert set(used) == {"spacetime_noconst", "spacetime_rangepf", "spacetime_priorpf", "spacetime"}
    assert used["spacetime"]["alpha"] == 0.01 and used["spacetime_priorpf"]["alpha"] == 0.5
    for name, params in used.items():
        assert set(params) <= set(real_get(name).get_params()), name
        assert (
            params["prior_center"] == "mean" and "head_motion_refinement" not in params
        )  # head motion is given
        assert params["lower"] == -0.5 and params["upper"] == 1.5 and params["beta"] == 0.0
        for key, value in (
            ("bounds", None),
            ("transfer", "rbf"),
            ("samples", "landmarks"),
            ("sparsity", 0.0),
        ):
            if key in real_get(name).get_params():
                assert params[key] == value, (name, key)


def test_seol_head_motion_is_the_papers_procrustes(small_cases):
    """Sec. 3.1: per frame, the rotation aligning the neutral markers with the frame's (SVD of
    Y^T X), given to every method as a known head motion."""
    from naive import spacetime as naive

    source, sigma = reproduction.noisy_markers(
        small_cases["synthetic-stylized"].source, procrustes=True
    )
    markers, reference = source.performance.positions, source.performance.reference
    assert sigma > 0 and source.head_motion is not None
    for f in (0, 7, 19):
        rot = naive.procrustes_rotation(reference, markers[f])
        np.testing.assert_allclose(source.head_motion[f, :3, :3], rot, atol=1e-10)
        np.testing.assert_allclose(
            source.head_motion[f, :3, 3], markers[f].mean(0) - rot @ reference.mean(0), atol=1e-10
        )


def test_paper_params_keeps_only_accepted_parameters():
    known = faceretarget.get("spacetime").get_params()
    out = reproduction.paper_params(
        "spacetime", {"alpha": 0.01, "no_such_parameter": 1, "beta": 0.0}
    )
    assert out == {"alpha": 0.01, "beta": 0.0}
    assert set(seol.seol_params("spacetime")) <= set(known)


def test_kholgade_fig8(small_cases):
    res = presets.run_preset("kholgade_fig8", small_cases)
    assert res.status == "ok", res.reason
    assert [row["model"] for row in res.table] == [
        "layered",
        "emotion only",
        "speech only",
        "blink only",
    ]
    assert sum(row["frames where best"] for row in res.table) == 20
    mean = {row["model"]: row["mean RMS error (% face height)"] for row in res.table}
    assert mean["layered"] < mean["blink only"]  # a blink-only model cannot speak
    assert "layered < emotion < speech < blink" in res.claim
    best = res.table[0]["frames where best"]
    _consistent_verdict(
        res,
        [
            best > 10,
            mean["emotion only"] > mean["layered"],
            mean["speech only"] > mean["emotion only"],
            mean["blink only"] > max(mean["layered"], mean["emotion only"], mean["speech only"]),
        ],
    )
    _plots_render(res)


def test_xu_fig4(dense):
    res = dense["xu_fig4"]
    assert res.status == "ok", res.reason
    rows = {row["mode"]: row for row in res.table}
    assert (
        rows["weights only"]["mean change outside window"] == 0.0
    )  # fig. 4d: the edit stays in the window
    assert (
        rows["bases only"]["mean change outside window"] > 0.0
    )  # fig. 4b: similar expressions change too
    assert "updating the weights only does not change frames outside the window" in res.claim
    b, j, w = rows["bases only"], rows["bases and weights"], rows["weights only"]
    limit = 100 * xu.XU_CONSTRAINT_TOLERANCE * xu.XU_EDIT
    _consistent_verdict(
        res,
        [
            all(r["constraint error (% face height)"] <= limit for r in rows.values()),
            b["change of similar frames outside"] > b["change of dissimilar frames outside"],
            w["max change outside window"] <= 1e-9,
            j["mean change inside window"] > 0 and j["mean change outside window"] > 0,
        ],
    )
    _plots_render(res)


def test_najung_table1_counts_per_mesh(dense):
    res = dense["najung_table1"]
    assert res.status in ("ok", "error"), res.reason
    counted = [row for row in res.table if "%" in row]
    failed = [row for row in res.table if "error" in row]
    assert len(counted) + 2 * len(failed) == 6 and (counted or res.status == "error")
    for row in counted:
        assert 0 <= row["vertices with piercing error"] <= row["vertices"]
        assert row["%"] == pytest.approx(
            100 * row["vertices with piercing error"] / row["vertices"]
        )
    assert "under 0.1% on every mesh" in res.claim
    if counted:
        _consistent_verdict(res, [all(row["%"] < najung.NAJUNG_LIMIT_PERCENT for row in counted)])
        for row in counted:
            if row["%"] >= najung.NAJUNG_LIMIT_PERCENT:
                assert (
                    f"{row['mesh']} {_num(row['%'])}%" in res.evidence
                )  # the offending mesh, with its number


@pytest.mark.parametrize(
    "name, method, ablation",
    [
        ("xu_fig6", "coating", "coating without details"),
        ("najung_fig14", "normalmesh", "normalmesh without details"),
    ],
)
def test_detail_reproductions(dense, name, method, ablation):
    """Each wrinkled case: the method, its detail layer switched off, and deformation transfer,
    measured by the detail_error metric; the verdict holds iff every part does."""
    res = dense[name]
    assert res.status == "ok", res.reason
    rows = {(row["case"], row["retargeter"]): row for row in res.table}
    assert sorted(rows) == sorted(
        (case, m)
        for case, _ in SMALL_DETAIL_CASES
        for m in (method, ablation, "deformation_transfer")
    )
    assert all(
        row["wrinkle fine-scale motion (% face height)"] > reproduction.DETAIL_MIN_WRINKLE
        for row in res.table
    )
    # the wrinkles' own contribution, apart from the fine-scale error of the large-scale motion
    for row in res.table:
        assert (
            row["detail error without wrinkles (% face height)"] > 0
            and row["wrinkle transfer error (% face height)"] >= 0
        )
    if name == "xu_fig6":  # coating's detail layer is what carries the wrinkles
        for case, _ in SMALL_DETAIL_CASES:
            assert (
                rows[(case, ablation)]["wrinkle gain"] < 0.5 < rows[(case, method)]["wrinkle gain"]
            )
    assert "wrinkle" in res.claim and "deformation transfer" in res.claim
    parts = []
    for case, _ in SMALL_DETAIL_CASES:
        m, off, dt = (rows[(case, k)] for k in (method, ablation, "deformation_transfer"))
        parts += [
            m["detail error (% face height)"] < off["detail error (% face height)"],
            m["detail error (% face height)"] < dt["detail error (% face height)"],
        ]
        if name == "xu_fig6":
            parts.append(m["RMS error (% face height)"] <= dt["RMS error (% face height)"])
        assert (
            _num(m["detail error (% face height)"]) + "%" in res.evidence
            and _num(dt["detail error (% face height)"]) + "%" in res.evidence
        )
    _consistent_verdict(res, parts)
    assert res.plots[0].kind == "bar" and len(res.plots[0].series) == 6
    _plots_render(res)


def test_detail_reproductions_need_active_wrinkles(small_cases, monkeypatch):
    """20 frames of the synthetic performance hold no wrinkle shape: nothing to decide, nothing run."""
    monkeypatch.setattr(
        reproduction, "DETAIL_CASES", (("human", "synthetic-human?resolution=300&n_frames=20"),)
    )
    monkeypatch.setattr(
        faceretarget,
        "get",
        lambda name, **params: pytest.fail(f"{name} run on a case without wrinkles"),
    )
    res = presets.run_preset("xu_fig6", small_cases)
    assert res.status == "ok" and res.agrees is None and res.verdict == "undecided"
    assert res.evidence.startswith("not decided: human: no wrinkle is active"), res.evidence


def test_dense_reproductions_render_their_verdict(dense):
    """The dense methods' paper claims in the report: red with the numbers when the measurement
    disagrees, green when it agrees (whatever the methods measure today)."""
    import html
    import re

    from faceretarget.evaluation.harness import ComparisonResult
    from faceretarget.evaluation.report import render_html

    result = ComparisonResult([], [], {}, {}, presets=list(dense.values()))
    page = render_html(result)
    summary = dict(
        re.findall(
            r'<a href="#preset-(\w+)">\w+</a></th><td>[^<]*</td><td class="verdict-cell (\w+)">',
            page,
        )
    )
    for name, res in dense.items():
        expected = {True: "agree", False: "disagree", None: "undecided"}[res.agrees]
        section = re.search(
            rf'<section class="preset" id="preset-{name}">(.*?)</section>', page, re.S
        ).group(1)
        verdict = re.search(
            r'<div class="verdict (\w+)" data-verdict="\w+"><strong>[^<]*</strong>: ([^<]*)</div>',
            section,
        )
        assert verdict.group(1) == expected == summary[name], (
            name,
            verdict.group(1),
            summary.get(name),
        )
        assert verdict.group(2) == html.escape(res.evidence)
        assert html.escape(res.claim) in section
        if res.agrees is False:
            assert "DISAGREES" in verdict.group(2)


def test_missing_or_failing_retargeters_are_reported(small_cases, monkeypatch):
    with pytest.raises(UnknownNameError, match="valid presets"):
        presets.run_preset("nope")

    def broken(name, **params):
        if name == "spacetime":
            raise RuntimeError("spacetime exploded")
        return real_get(name, **params)

    real_get = faceretarget.get
    monkeypatch.setattr(faceretarget, "get", broken)
    res = presets.run_preset("seol_fig11", small_cases)
    assert res.status == "error" and res.reason == "RuntimeError: spacetime exploded"
    assert res.title.startswith("Seol 2012 fig. 11") and res.paper
    assert (
        res.agrees is None and res.verdict == "undecided" and res.claim
    )  # a failed run decides nothing

    def unknown(name, **params):
        raise UnknownNameError(f"no retargeter named {name!r}")

    monkeypatch.setattr(faceretarget, "get", unknown)
    res = presets.run_preset("xu_fig4", small_cases)
    assert res.status == "not applicable" and "no retargeter named 'coating'" in res.reason

    def decides_then_fails(cases, res):
        res.agrees, res.evidence = True, "agrees: something"
        raise RuntimeError("late failure")

    late = Preset(
        "late",
        "Late",
        "paper",
        "description",
        decides_then_fails,
        claim="A claim.",
        setting="A setting.",
    )
    res = presets.run_preset(late, small_cases)
    assert (
        res.status == "error" and res.agrees is None and "did not run" in res.evidence
    )  # a failed run decides nothing
    assert (res.claim, res.setting) == ("A claim.", "A setting.")


def test_run_presets_attaches_to_a_result(small_cases):
    from faceretarget.evaluation.harness import ComparisonResult

    result = ComparisonResult([], [], {"synthetic-human": small_cases["synthetic-human"]}, {})
    out = presets.run_presets(result, names=["seol_fig11"])
    assert result.presets == out and out[0].status == "ok"
    assert np.isfinite(out[0].as_dict()["table"][0]["velocity error (vs truth)"])


def test_preset_claims_are_in_the_json(small_cases, tmp_path):
    import json

    from faceretarget.evaluation.harness import ComparisonResult

    result = ComparisonResult([], [], dict(small_cases), {})
    out = presets.run_presets(result, names=["seol_fig11", "kholgade_fig8"])
    data = json.loads(result.to_json(tmp_path / "r.json").read_text())["presets"]
    for res, entry in zip(out, data):
        assert (
            entry["claim"] == res.claim
            and entry["setting"] == res.setting
            and entry["evidence"] == res.evidence
        )
        assert entry["agrees"] is res.agrees and entry["verdict"] == res.verdict
    assert all(p.claim and p.setting for p in presets.available_presets().values())


def test_run_presets_in_workers_matches_in_process(small_cases):
    """n_jobs=2: each preset a task of two worker processes, on the caller's cases (sent
    as they are); the same results as in this process, in the order asked."""
    names = ["kholgade_fig8", "seol_fig11"]
    here = presets.run_presets(names=names, cases=small_cases)
    there = presets.run_presets(names=names, cases=small_cases, n_jobs=2)
    assert [r.name for r in there] == names
    for a, b in zip(here, there):
        assert b.status == "ok" and (a.agrees, a.evidence) == (b.agrees, b.evidence)
        assert [sorted(row) for row in a.table] == [sorted(row) for row in b.table]
        for ra, rb in zip(a.table, b.table):
            for key, value in ra.items():
                if isinstance(value, float):
                    assert rb[key] == pytest.approx(value, rel=1e-9, abs=1e-12), key
                else:
                    assert rb[key] == value, key
    with pytest.raises(UnknownNameError, match="valid presets"):
        presets.run_presets(names=["nope"], n_jobs=2)
