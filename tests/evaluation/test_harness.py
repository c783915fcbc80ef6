"""The comparison harness with fake retargeters on the tiny hand-built case."""

import csv
import json
import math

import fake_retargeters as fakes
import numpy as np
import pytest

from faceretarget.errors import ConfigError, OutputError, UnknownNameError
from faceretarget.evaluation.harness import COLUMNS, compare, parse_case_spec, resolve_case
from faceretarget.hookspecs import Metric, hookimpl
from faceretarget.registry import Registry


@pytest.fixture(scope="module")
def result(tiny, fake_registry):
    names = [
        "fake_oracle",
        "fake_transfer",
        "fake_neutral",
        "fake_broken",
        "fake_wrongshape",
        "fake_examples",
        "fake_badcheck",
    ]
    return compare([tiny], methods=names, registry=fake_registry)


def test_statuses_reasons_and_errors(result):
    runs = {r.method: r for r in result.runs}
    assert {m: r.status for m, r in runs.items()} == {
        "fake_oracle": "ok",
        "fake_transfer": "ok",
        "fake_neutral": "ok",
        "fake_broken": "error",
        "fake_wrongshape": "error",
        "fake_examples": "not applicable",
        "fake_badcheck": "error",
    }
    assert (
        runs["fake_badcheck"].error["stage"] == "why_not"
        and "why_not is broken" in runs["fake_badcheck"].reason
    )
    assert (
        runs["fake_examples"].reason
        == "fake_examples needs a TargetRig with example poses; this one lacks it"
    )
    broken = runs["fake_broken"]
    assert (
        broken.error["type"] == "RuntimeError"
        and broken.error["message"] == "boom in fit"
        and broken.error["stage"] == "fit"
    )
    assert "plugin 'fakes'" in broken.reason and "distribution local" in broken.reason
    wrong = runs["fake_wrongshape"]
    # Retargeter.retarget itself refuses a result off the target's vertices
    assert wrong.error["type"] == "PluginOutputError" and wrong.error["stage"] == "retarget"
    assert "returned 80 vertices per frame but the target has 81" in wrong.reason
    assert runs["fake_oracle"].fit_s >= 0 and runs["fake_oracle"].peak_memory_mib > 0


def test_every_row_has_a_value_or_a_reason(result):
    assert result.rows and all(set(row) == set(COLUMNS) for row in result.rows)
    for row in result.rows:
        if row["status"] == "ok":
            assert math.isfinite(row["value"]) and row["reason"] == ""
        else:
            assert row["value"] is None and row["reason"], row
    oracle = {r["metric"]: r for r in result.rows if r["method"] == "fake_oracle"}
    assert all(r["status"] == "ok" for r in oracle.values()), [
        r for r in oracle.values() if r["status"] != "ok"
    ]
    assert {"vertex_error_region[upper]", "vertex_error_region[lower]"} <= set(oracle)
    transfer = {r["metric"]: r for r in result.rows if r["method"] == "fake_transfer"}
    assert transfer["weight_min"]["status"] == "not applicable"
    assert transfer["weight_min"]["reason"] == "the method outputs vertices, not blendshape weights"


def test_values_and_ranking(result):
    assert result.value("tiny", "fake_oracle", "vertex_error_max") < 1e-9
    assert result.value("tiny", "fake_oracle", "detail_correlation") == pytest.approx(1.0)
    assert result.value("tiny", "fake_transfer", "vertex_error_rms") > 0.1
    assert result.value("tiny", "fake_neutral", "weight_sparsity") == 1.0
    ranking = result.ranking()
    assert [r["method"] for r in ranking[:3]] == ["fake_oracle", "fake_transfer", "fake_neutral"]
    assert [r["rank"] for r in ranking] == [1, 2, 3, None, None, None, None]
    assert {r["method"]: (r["failed"], r["not_applicable"]) for r in ranking[3:]} == {
        "fake_badcheck": (1, 0),
        "fake_broken": (1, 0),
        "fake_examples": (0, 1),
        "fake_wrongshape": (1, 0),
    }


def test_csv_and_json(result, tmp_path):
    with open(result.to_csv(tmp_path / "t.csv"), newline="") as fh:
        rows = list(csv.DictReader(fh))
    assert len(rows) == len(result.rows) and list(rows[0]) == list(COLUMNS)
    first = next(
        r for r in rows if r["method"] == "fake_transfer" and r["metric"] == "vertex_error_rms"
    )
    assert float(first["value"]) == result.value("tiny", "fake_transfer", "vertex_error_rms")
    data = json.loads((result.to_json(tmp_path / "t.json")).read_text())
    assert data["columns"] == list(COLUMNS) and len(data["rows"]) == len(result.rows)
    assert (
        data["metrics"]["lve"]["unit"] == "% face height"
        and "Lip vertex error" in data["metrics"]["lve"]["description"]
    )
    broken = next(r for r in data["runs"] if r["method"] == "fake_broken")
    assert broken["error"]["distribution"] == "local" and broken["error"]["plugin"] == "fakes"
    with pytest.raises(OutputError, match="does not exist"):
        result.to_csv(tmp_path / "missing" / "t.csv")


def test_explicit_classes_and_params(tiny):
    res = compare(
        [tiny],
        methods=[fakes.TransferFake],
        params={"fake_transfer": {"gain": 2.0}},
        metrics=["vertex_error_rms", "time_total"],
    )
    run = res.runs[0]
    assert (
        run.status == "ok"
        and run.parameters == {"gain": 2.0, "delay": 0.0}
        and run.distribution == "local"
    )
    base = compare([tiny], methods=[fakes.TransferFake], metrics=["vertex_error_rms"])
    assert res.value("tiny", "fake_transfer", "vertex_error_rms") > base.value(
        "tiny", "fake_transfer", "vertex_error_rms"
    )
    assert [r["metric"] for r in res.rows] == ["vertex_error_rms", "time_total"]
    with pytest.raises(UnknownNameError, match="no parameter"):
        compare([tiny], methods=[fakes.TransferFake], params={"fake_transfer": {"gian": 2}})
    with pytest.raises(UnknownNameError, match="not among the compared"):
        compare([tiny], methods=[fakes.TransferFake], params={"spacetime": {"alpha": 1}})
    with pytest.raises(UnknownNameError, match="no metric"):
        compare([tiny], methods=[fakes.TransferFake], metrics=["nope"])
    with pytest.raises(UnknownNameError, match="valid choices"):
        compare([tiny], methods=["no_such_method"])
    with pytest.raises(ConfigError, match="each retargeter once"):
        compare([tiny], methods=[fakes.TransferFake, fakes.TransferFake])
    assert (
        compare([tiny], methods=[fakes.TransferFake], keep_animations=False).runs[0].animation
        is None
    )


class _MetricPlugin:
    """A third-party metrics plugin: one good metric, one that raises."""

    @hookimpl
    def faceretarget_metrics(self):
        def boom(animation, case, context):
            raise ValueError("metric exploded")

        return [
            Metric(
                "frames_count",
                lambda a, c, ctx: float(a.n_frames),
                "number of frames",
                unit="frames",
            ),
            Metric("exploding", boom, "raises"),
        ]


def test_metric_plugins_and_failing_metrics(tiny):
    reg = Registry().load(extra=[("metrics3p", _MetricPlugin())])
    res = compare([tiny], methods=[fakes.OracleFake], registry=reg)
    rows = {r["metric"]: r for r in res.rows}
    assert rows["frames_count"]["value"] == 12.0
    assert (
        rows["exploding"]["status"] == "error"
        and rows["exploding"]["reason"] == "ValueError: metric exploded"
    )
    assert rows["vertex_error_rms"]["status"] == "ok"


def test_case_names_and_duplicates(tiny):
    assert parse_case_spec("ict?n_frames=40&seed=2&head_motion=false") == (
        "ict",
        {"n_frames": 40, "seed": 2, "head_motion": False},
    )
    with pytest.raises(UnknownNameError, match="valid cases"):
        parse_case_spec("nope")
    with pytest.raises(ConfigError, match="key=value"):
        parse_case_spec("ict?40")
    case = resolve_case("synthetic-stylized?resolution=80&n_frames=3")
    assert case.name == "synthetic-stylized" and case.source.n_frames == 3
    res = compare(
        [tiny, tiny, "synthetic?resolution=80&n_frames=3"],
        methods=[fakes.TransferFake],
        metrics=["vertex_error_max"],
    )
    assert list(res.cases) == ["tiny", "tiny#2", "synthetic?resolution=80&n_frames=3"]
    assert [r.status for r in res.runs] == ["ok", "ok", "ok"]
    with pytest.raises(UnknownNameError):
        resolve_case(42)


def test_the_output_check_catches_non_finite_and_non_animation(tiny):
    """The one output check (Retargeter.check_output, made by retarget) that the harness, batch
    and the command line rely on."""
    from faceretarget.errors import PluginOutputError

    method = fakes.TransferFake().fit(tiny.source, tiny.target)
    with pytest.raises(PluginOutputError, match="not an Animation"):
        method.check_output(np.zeros((12, 81, 3)), tiny.source)
    rig = fakes.BlendshapeRig(tiny.target.neutral, np.full((2, 81, 3), 10.0), ["a", "b"])
    big = fakes.Animation(
        weights=np.full((12, 2), 1e308), rig=rig
    )  # finite weights, vertices overflow to inf
    with pytest.raises(PluginOutputError, match="NaN or infinite vertex"):
        method.check_output(big, tiny.source)
    assert big._vertices is None  # checked a chunk at a time, not kept
    with pytest.raises(PluginOutputError, match="frames for a source"):
        method.check_output(fakes.Animation(vertices=tiny.truth.vertices[:5]), tiny.source)
    method.check_output(tiny.truth, tiny.source)
    method.check_output(fakes.Animation(weights=np.ones((12, 2)), rig=rig), tiny.source)


def test_builtin_retargeters_on_synthetic_and_ict():
    """Every registered retargeter on small synthetic and ICT cases: each metric is filled or says why not."""
    from faceretarget.registry import registry

    result = compare(["synthetic?resolution=300&n_frames=8", "ict?n_frames=5"])
    assert {r.method for r in result.runs} == set(registry().retargeters)
    for run in result.runs:
        assert run.status in ("ok", "not applicable", "error")
        assert (run.status == "ok") == (run.reason == ""), run
    for row in result.rows:
        assert (row["status"] == "ok" and math.isfinite(row["value"])) or (
            row["value"] is None and row["reason"]
        ), row
    ok = [r for r in result.runs if r.status == "ok"]
    assert len(ok) >= 2 * len(result.runs) // 3
    for run in (
        ok
    ):  # on a successful run only the weight statistics may be missing, and only for vertex outputs
        missing = {
            r["metric"]
            for r in result.rows
            if r["case"] == run.case and r["method"] == run.method and r["status"] != "ok"
        }
        expected = (
            set()
            if run.animation.weights is not None
            else {
                "weight_min",
                "weight_max",
                "weight_outside_share",
                "weight_sparsity",
                "weight_error_rms",
            }
        )
        assert missing == expected, (run.case, run.method, missing)
    ranked = [r for r in result.ranking() if r["rank"] is not None]
    assert len(ranked) >= 5 and ranked[0]["mean_rank"] <= ranked[-1]["mean_rank"]


def test_parallel_compare_matches_sequential(tiny, fake_registry):
    names = [
        "fake_oracle",
        "fake_transfer",
        "fake_broken",
        "fake_examples",
        "deformation_transfer",
    ]  # two modules: two tasks
    cases = {"first": tiny, "second": "synthetic?resolution=80&n_frames=3"}
    metrics = ["vertex_error_rms", "lve", "weight_min"]
    seq = compare(cases, methods=names, registry=fake_registry, metrics=metrics)
    par = compare(cases, methods=names, registry=fake_registry, metrics=metrics, n_jobs=2)
    strip = lambda rows: [{k: v for k, v in r.items() if k != "value"} for r in rows]  # noqa: E731
    assert strip(par.rows) == strip(seq.rows)
    for a, b in zip(seq.rows, par.rows):
        assert (a["value"] is None and b["value"] is None) or a["value"] == pytest.approx(
            b["value"], abs=1e-12
        )
    assert [(r.case, r.method, r.status) for r in par.runs] == [
        (r.case, r.method, r.status) for r in seq.runs
    ]
    assert par.run("first", "fake_oracle").animation.extras == {}
    with pytest.raises(ConfigError, match="n_jobs"):
        compare([tiny], methods=names, registry=fake_registry, n_jobs=0)


def test_compare_runs_presets_with_its_runs(tiny, fake_registry):
    """presets=: the reproductions get the comparison's cases, in this process without
    workers and as tasks of the worker pool with them (same results, in the order asked)."""
    import os

    cases = {"first": tiny, "second": "synthetic?resolution=80&n_frames=3"}
    kw = dict(methods=["fake_oracle"], registry=fake_registry, metrics=["vertex_error_rms"])
    seq = compare(cases, presets=["fake_frames"], **kw)
    par = compare(cases, presets=["fake_frames"], n_jobs=2, **kw)
    for result, here in ((seq, True), (par, False)):
        (res,) = result.presets
        assert res.name == "fake_frames" and res.status == "ok" and res.agrees is True
        assert [(r["case"], r["frames"]) for r in res.table] == [
            ("first", len(tiny.truth.vertices)),
            ("second", 3),
        ]
        assert all((r["pid"] == os.getpid()) is here for r in res.table)
        assert [r.status for r in result.runs] == ["ok", "ok"]
    assert compare(cases, **kw).presets == []


def test_compare_reports_presets_that_overrun_or_crash(tiny, fake_registry):
    result = compare(
        {"first": tiny, "second": tiny},
        methods=["fake_oracle"],
        registry=fake_registry,
        metrics=["vertex_error_rms"],
        timeout=2.0,
        presets=["fake_sleeper", "fake_crash", "fake_frames"],
    )
    sleeper, crash, frames = result.presets
    assert [p.name for p in result.presets] == ["fake_sleeper", "fake_crash", "fake_frames"]
    for res, what in ((sleeper, "2 s"), (crash, "exit")):
        assert res.status == "error" and res.agrees is None, res.reason
        assert what in res.reason and "preset of plugin 'fakes'" in res.reason, res.reason
        assert "did not run" in res.evidence
    assert frames.status == "ok" and [r.status for r in result.runs] == ["ok", "ok"]


def test_compare_checks_preset_names_before_running(tiny, fake_registry, monkeypatch):
    import faceretarget.evaluation.harness as harness

    monkeypatch.setattr(harness, "_run_one", lambda *a: pytest.fail("ran before the check"))
    with pytest.raises(UnknownNameError, match="'fake_frame'.*did you mean 'fake_frames'"):
        compare([tiny], methods=["fake_oracle"], registry=fake_registry, presets=["fake_frame"])
    with pytest.raises(ConfigError, match="list of preset names"):
        compare([tiny], methods=["fake_oracle"], registry=fake_registry, presets="fake_frames")
