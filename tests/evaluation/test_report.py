"""The HTML report: inline plots, decimation, self-containment, and a headless-Chromium load.

The browser test needs Debian's ``chromium`` (``apt-get install -y chromium``); CI installs it.
"""

import json
import os
import re
import struct
import subprocess
import tempfile
import xml.etree.ElementTree as ET
from pathlib import Path

import fake_retargeters as fakes
import numpy as np
import pytest

from faceretarget.evaluation.harness import compare
from faceretarget.evaluation.report import (
    Plot,
    Series,
    decimate,
    render_html,
    svg_plot,
    write_report,
)

CHROMIUM = "/usr/bin/chromium"


@pytest.fixture(scope="module")
def report(tmp_path_factory, fake_registry):
    case = fakes.tiny_case(n=21, n_frames=30)
    result = compare(
        [case],
        methods=["fake_oracle", "fake_transfer", "fake_neutral", "fake_broken", "fake_examples"],
        registry=fake_registry,
    )
    folder = tmp_path_factory.mktemp("report") / "out"
    return result, write_report(result, folder)


def test_svg_plots_are_valid_xml():
    line = Plot(
        "t <&>",
        [Series("a", [0, 1, 2], [1.0, np.nan, 3.0]), Series("b", [0, 1], [2.0, 2.0], dashed=True)],
        "x",
        "y",
    )
    root = ET.fromstring(svg_plot(line))
    assert (
        root.tag.endswith("svg") and len(root.findall("{http://www.w3.org/2000/svg}polyline")) == 2
    )
    bar = Plot("bars", [Series("p", [0], [2.0]), Series("q", [0], [-1.0])], ylabel="v", kind="bar")
    assert len(ET.fromstring(svg_plot(bar)).findall("{http://www.w3.org/2000/svg}rect")) == 2
    empty = ET.fromstring(svg_plot(Plot("none", [Series("a", [0], [np.nan])])))
    assert "no values" in "".join(empty.itertext())
    log = ET.fromstring(
        svg_plot(Plot("log", [Series("a", [0, 1, 2], [1e-6, 1e-3, 0.0])], log_y=True))
    )
    assert len(log.findall("{http://www.w3.org/2000/svg}polyline")) == 1


def test_decimation_keeps_holes_open():
    verts, tris = fakes.grid(41)
    centre = np.linalg.norm(verts[:, :2], axis=1) < 0.35  # a round hole (the "mouth")
    keep_tris = tris[~centre[tris].any(axis=1)]
    used = np.unique(keep_tris)
    remap = np.full(len(verts), -1)
    remap[used] = np.arange(len(used))
    verts, tris = verts[used], remap[keep_tris]
    keep, small, labels = decimate(verts, tris, 300)
    assert len(keep) <= 300 and small.max() < len(keep) and (labels >= 0).all()
    centroids = verts[keep][small].mean(axis=1)
    assert (np.linalg.norm(centroids[:, :2], axis=1) > 0.3).all()  # no triangle bridges the hole
    same, tris_same, _ = decimate(verts, tris, 10_000)
    assert len(same) == len(verts) and np.array_equal(tris_same, tris)


def test_report_files_are_self_contained(report):
    result, paths = report
    page = paths["html"].read_text()
    assert paths["csv"].exists() and json.loads(paths["json"].read_text())["columns"][0] == "case"
    external = re.findall(r"""(?:src|href)\s*=\s*["'](?!#)([^"']+)""", page)
    assert external == [], external
    assert "http://" not in page.replace('xmlns="http://www.w3.org/2000/svg"', "")
    assert "https://" not in page
    for needle in (
        "Ranking",
        "Case: tiny",
        "Viewer",
        "Per-vertex error",
        "Velocity error over time",
        "Weight curves",
        "Metric definitions",
        "boom in fit",
    ):
        assert needle in page, needle
    data = json.loads(
        re.search(
            r'<script type="application/json" id="report-data">(.*?)</script>', page, re.S
        ).group(1)
    )
    case = data["cases"][0]
    assert [s["label"] for s in case["seqs"]] == [
        "ground truth",
        "fake_oracle",
        "fake_transfer",
        "fake_neutral",
    ]
    assert (
        case["source"]["kind"] == "mesh"
        and len(case["frames"]) == 24
        and len(case["keyFrames"]) == 3
    )
    assert len(page) < 3_000_000


def test_report_budget_decimates(fake_registry):
    case = fakes.tiny_case(n=61, n_frames=40)  # 3721 vertices
    result = compare(
        [case],
        methods=["fake_oracle", "fake_transfer"],
        registry=fake_registry,
        metrics=["vertex_error_rms"],
    )
    page = render_html(result, max_bytes=200_000, max_frames=10)
    data = json.loads(re.search(r'id="report-data">(.*?)</script>', page, re.S).group(1))
    assert len(data["cases"][0]["frames"]) == 10
    assert data["cases"][0]["mesh"]["nv"] <= 1000


def _png_size(path):
    head = Path(path).read_bytes()[:24]
    assert head[:8] == b"\x89PNG\r\n\x1a\n"
    return struct.unpack(">II", head[16:24])


def _chromium(*args):
    with tempfile.TemporaryDirectory() as profile:
        cmd = [
            CHROMIUM,
            "--headless",
            "--no-sandbox",
            "--disable-gpu",
            "--disable-background-networking",
            "--disable-component-update",
            "--disable-sync",
            "--no-first-run",
            f"--user-data-dir={profile}",
            "--enable-logging=stderr",
            "--v=0",
            "--virtual-time-budget=5000",
            *args,
        ]
        return subprocess.run(
            cmd, capture_output=True, text=True, timeout=120, env={**os.environ, "HOME": profile}
        )


def test_report_loads_in_headless_chromium(report, tmp_path):
    if not os.path.exists(CHROMIUM):
        pytest.skip(
            "headless-browser check needs Debian's chromium at /usr/bin/chromium (apt-get install -y chromium)"
        )
    _, paths = report
    url = paths["html"].resolve().as_uri()
    dom = _chromium("--dump-dom", url)
    assert dom.returncode == 0, dom.stderr[-2000:]
    console = [line for line in dom.stderr.splitlines() if ":CONSOLE" in line]
    assert console == [], console
    body = re.search(r"<body([^>]*)>", dom.stdout).group(1)
    assert 'data-js-errors="0"' in body and 'data-report-ready="1"' in body, body
    assert int(re.search(r'data-faces-rendered="(\d+)"', body).group(1)) >= 10
    shot = tmp_path / "report.png"
    run = _chromium(f"--screenshot={shot}", "--window-size=1280,1600", url)
    assert run.returncode == 0 and shot.exists(), run.stderr[-2000:]
    assert _png_size(shot) == (1280, 1600) and shot.stat().st_size > 50_000


def _reproductions():
    from faceretarget.evaluation.presets import PresetResult

    disagreeing = PresetResult(
        "fake_disagree",
        "Fake 2099 fig. 1",
        "Nobody. A paper. 2099",
        "what it runs",
        claim="Method A has a lower error than method B.",
        setting="the paper's inputs, alpha = 0.5",
        agrees=False,
        evidence="DISAGREES: method A 0.731 > method B 0.412.",
    )
    agreeing = PresetResult(
        "fake_agree",
        "Fake 2099 fig. 2",
        "Nobody. A paper. 2099",
        "what it runs",
        claim="Method C is faster than method D.",
        setting="as published",
        agrees=True,
        evidence="agrees: C 1.5 s < D 9 s.",
    )
    failed = PresetResult(
        "fake_failed",
        "Fake 2099 fig. 3",
        "Nobody",
        "d",
        claim="Something holds.",
        status="error",
        reason="RuntimeError: boom",
    )
    return [disagreeing, agreeing, failed]


def test_report_flags_a_disagreeing_reproduction_in_red(fake_registry, tmp_path):
    """A reproduction whose measurement disagrees with its paper is shown in red with the measured
    numbers and the paper's claim; one that agrees in green; an undecided one in grey."""
    case = fakes.tiny_case(n=11, n_frames=6)
    result = compare(
        [case], methods=["fake_oracle"], registry=fake_registry, metrics=["vertex_error_rms"]
    )
    result.presets.extend(_reproductions())
    paths = write_report(result, tmp_path / "out")
    page = paths["html"].read_text()
    section = re.search(
        r'<section class="preset" id="preset-fake_disagree">(.*?)</section>', page, re.S
    ).group(1)
    verdict = re.search(
        r'<div class="verdict (\w+)" data-verdict="\w+"><strong>([^<]*)</strong>: ([^<]*)</div>',
        section,
    )
    assert verdict.groups() == (
        "disagree",
        "Disagrees with the paper",
        "DISAGREES: method A 0.731 &gt; method B 0.412.",
    )
    assert "Method A has a lower error than method B." in section and "alpha = 0.5" in section
    agree = re.search(r'id="preset-fake_agree">.*?<div class="verdict (\w+)"', page, re.S).group(1)
    failed = re.search(r'id="preset-fake_failed">.*?<div class="verdict (\w+)"', page, re.S).group(
        1
    )
    assert (agree, failed) == ("agree", "undecided")
    # the summary at the top of the reproductions, coloured the same way
    summary = re.search(r'<table class="metrics presets-summary">(.*?)</table>', page, re.S).group(
        1
    )
    cells = re.findall(r'<td class="verdict-cell (\w+)">([^<]*)</td>', summary)
    assert cells == [
        ("disagree", "Disagrees with the paper"),
        ("agree", "Agrees with the paper"),
        ("undecided", "Not decided"),
    ]
    # red is red: the stylesheet (inline in the page) colours a disagreement with the error colour
    css = re.search(r"<style>(.*?)</style>", page, re.S).group(1)
    assert re.search(r"--err:\s*#b42318", css)
    declarations = lambda selector: dict(  # noqa: E731
        tuple(part.strip() for part in d.split(":", 1))
        for d in re.search(selector + r"\s*\{([^}]*)\}", css).group(1).split(";")
        if d.strip()
    )
    disagree = declarations(r"\.verdict\.disagree")
    assert disagree["color"] == "var(--err)" and disagree["border-left-color"] == "var(--err)"
    assert declarations(r"\.verdict\.agree")["color"] == "var(--ok)"
    data = json.loads(paths["json"].read_text())["presets"]
    assert [(p["name"], p["agrees"], p["verdict"]) for p in data] == [
        ("fake_disagree", False, "disagrees"),
        ("fake_agree", True, "agrees"),
        ("fake_failed", None, "undecided"),
    ]
    assert data[0]["claim"] == "Method A has a lower error than method B." and data[0][
        "evidence"
    ].startswith("DISAGREES: method A 0.731")
