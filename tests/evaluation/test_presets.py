"""Paper reproductions: each registered preset runs on small cases and yields its plot and table."""
import xml.etree.ElementTree as ET

import numpy as np
import pytest

import faceretarget
from faceretarget.errors import UnknownNameError
from faceretarget.evaluation import presets
from faceretarget.evaluation.harness import resolve_case
from faceretarget.evaluation.report import svg_plot


@pytest.fixture(scope="module")
def small_cases():
    return {
        "synthetic-human": resolve_case("synthetic-human?resolution=300&n_frames=20"),
        "synthetic-stylized": resolve_case("synthetic-stylized?resolution=300&n_frames=20"),
        "ict": resolve_case("ict?n_frames=4"),
    }


def _plots_render(result):
    for plot in result.plots:
        assert ET.fromstring(svg_plot(plot)).tag.endswith("svg")


def test_seol_fig11(small_cases):
    res = presets.run_preset("seol_fig11", small_cases)
    assert res.status == "ok", res.reason
    assert [row["method"] for row in res.table] == ["No Const", "Range PF", "Prior PF", "movement matching"]
    assert res.table[0]["added over No Const"] == 0.0
    assert all(row["velocity error (vs truth)"] > 0 for row in res.table)
    assert [p.kind for p in res.plots] == ["bar", "line"]
    assert len(res.plots[1].series) == 3 and len(res.plots[1].series[0].x) == 19
    _plots_render(res)


def test_kholgade_fig8(small_cases):
    res = presets.run_preset("kholgade_fig8", small_cases)
    assert res.status == "ok", res.reason
    assert [row["model"] for row in res.table] == ["layered", "emotion only", "speech only", "blink only"]
    assert sum(row["frames where best"] for row in res.table) == 20
    blink = res.table[3]["mean RMS error (% face height)"]
    assert res.table[0]["mean RMS error (% face height)"] < blink  # a blink-only model cannot speak
    _plots_render(res)


def test_xu_fig4(small_cases):
    res = presets.run_preset("xu_fig4", small_cases)
    assert res.status == "ok", res.reason
    rows = {row["mode"]: row for row in res.table}
    assert rows["weights only"]["mean change outside window"] == 0.0  # fig. 4d: the edit stays in the window
    assert rows["bases only"]["mean change outside window"] > 0.0  # fig. 4b: similar expressions change too
    _plots_render(res)


def test_najung_table1_counts_per_mesh(small_cases):
    res = presets.run_preset("najung_table1", small_cases)
    assert res.status in ("ok", "error"), res.reason
    counted = [row for row in res.table if "%" in row]
    failed = [row for row in res.table if "error" in row]
    assert len(counted) + 2 * len(failed) == 6 and (counted or res.status == "error")
    for row in counted:
        assert 0 <= row["vertices with piercing error"] <= row["vertices"]
        assert row["%"] == pytest.approx(100 * row["vertices with piercing error"] / row["vertices"])


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

    def unknown(name, **params):
        raise UnknownNameError(f"no retargeter named {name!r}")

    monkeypatch.setattr(faceretarget, "get", unknown)
    res = presets.run_preset("xu_fig4", small_cases)
    assert res.status == "not applicable" and "no retargeter named 'coating'" in res.reason


def test_run_presets_attaches_to_a_result(small_cases):
    from faceretarget.evaluation.harness import ComparisonResult

    result = ComparisonResult([], [], {"synthetic-human": small_cases["synthetic-human"]}, {})
    out = presets.run_presets(result, names=["seol_fig11"])
    assert result.presets == out and out[0].status == "ok"
    assert np.isfinite(out[0].as_dict()["table"][0]["velocity error (vs truth)"])
