"""The report explains itself and fits a 1280 px window.

- per case a sentence: who wins on the ranking metric, by how much, where else, why; paper
  methods and baselines labelled; the ranking metric named and defined;
- numbers for people (``12,934``, ``2.99×10⁻⁵``; never ``1.29e+04``);
- numba compile time measured apart from fit and retarget, and shown apart;
- in headless Chromium (Debian's ``chromium``) at 1280 px: no horizontal overflow, no table
  wider than the page or cut inside it, no overlapping chart labels; the screenshot is drawn.
"""

import html
import json
import os
import re
import shutil
import struct
import subprocess
import tempfile
import zlib
from pathlib import Path
from types import SimpleNamespace

import fake_retargeters as fakes
import numpy as np
import pytest

from faceretarget.errors import ConfigError, UnknownNameError
from faceretarget.evaluation._summary import (
    BASELINE,
    PAPER,
    MethodRole,
    case_summary,
    method_roles,
    ranking_metric,
    short_citation,
)
from faceretarget.evaluation.harness import compare
from faceretarget.evaluation.presets import PresetResult
from faceretarget.evaluation.report import (
    Plot,
    Series,
    format_number,
    render_html,
    svg_plot,
    write_report,
)

WIDTH = 1280
SCIENTIFIC = re.compile(r"\d[eE][+-]?\d")


def _chromium_binary() -> str | None:
    for name in ("chromium", "chromium-browser", "google-chrome"):
        found = shutil.which(name)
        if found:
            return found
    return "/usr/bin/chromium" if os.path.exists("/usr/bin/chromium") else None


def _variant(i: int) -> type:
    """A same-topology transfer under a long name (the demo's names are this long and longer)."""
    return type(
        f"LongNamedTransfer{i}",
        (fakes.TransferFake,),
        {"name": f"fake_transfer_with_long_name_{i}", "__module__": __name__},
    )


VARIANTS = [_variant(i) for i in range(5)]

#: Catalogue entries the report looks roles up in: a paper method, its baseline, a plugin.
CATALOGUE = SimpleNamespace(
    retargeters={
        "fake_transfer": SimpleNamespace(
            paper="Doe, Roe & Poe 2031, Transfer of Things, Journal 1(2)",
            summary="the paper's method",
            cls=fakes.TransferFake,
        ),
        "fake_oracle": SimpleNamespace(
            paper="Doe, Roe & Poe 2031, Transfer of Things, Journal 1(2)",
            summary="baseline: the exact solve",
            cls=fakes.OracleFake,
        ),
        "fake_neutral": SimpleNamespace(paper="", summary="zero weights", cls=fakes.NeutralFake),
    }
)


def _reproduction() -> PresetResult:
    """A reproduction with the kind of charts that overlapped: long bar labels, a large number, tiny values."""
    labels = [
        "synthetic-human source",
        "synthetic-human target",
        "synthetic-stylized source",
        "synthetic-stylized target",
        "ict source",
        "ict target",
    ]
    bars = Plot(
        "vertices with piercing error, % of the normal mesh",
        [
            Series(name, [0], [v])
            for name, v in zip(labels, [0.0104, 0.0104, 0.0106, 0.298, 0.187, 12934.0])
        ],
        ylabel="%",
        kind="bar",
    )
    frames = np.arange(60)
    tiny = Plot(
        "velocity error (tiny values)",
        [
            Series(f"method_with_a_long_name_{k}", frames, 1e-5 * (1 + np.sin(frames / (3 + k))))
            for k in range(6)
        ],
        xlabel="frame",
        ylabel="||DP - DQ||^2 / H^2",
    )
    return PresetResult(
        "fake_table1",
        "Fake 2031 table 1",
        "Doe, Roe & Poe. 2031",
        "piercing errors per mesh",
        plots=[bars, tiny],
        table=[{"mesh": name, "vertices": 10816, "%": 0.1} for name in labels],
        claim="Piercing errors stay below 0.1% of the vertices.",
        agrees=False,
        evidence="DISAGREES: 3 of 6 meshes at or above 0.1%.",
    )


@pytest.fixture(scope="module")
def explained(tmp_path_factory, fake_registry):
    cases = {
        "tiny": fakes.tiny_case(n=21, n_frames=30),
        "tiny-stylized-with-a-long-case-name": fakes.tiny_case(n=15, n_frames=20, name="other"),
    }
    methods = [
        "fake_oracle",
        "fake_transfer",
        "fake_neutral",
        "fake_broken",
        "fake_examples",
        *VARIANTS,
    ]
    params = {cls.name: {"gain": 0.8 + 0.05 * i} for i, cls in enumerate(VARIANTS)}
    result = compare(cases, methods=methods, params=params, registry=fake_registry)
    result.presets.append(_reproduction())
    folder = tmp_path_factory.mktemp("explained") / "report"
    paths = write_report(result, folder, registry=CATALOGUE)
    return result, paths


# ---------------------------------------------------------------------------------------
# Words
# ---------------------------------------------------------------------------------------
def test_each_case_gets_a_sentence_naming_the_winner_metric_and_why(explained):
    result, paths = explained
    page = paths["html"].read_text()
    summary = re.search(r'<section id="summary">(.*?)</section>', page, re.S).group(1)
    items = re.findall(r'<li class="summary" data-case="([^"]+)">(.*?)</li>', summary, re.S)
    assert [case for case, _ in items] == list(result.cases)
    tiny = html.unescape(re.sub(r"<[^>]+>", "", items[0][1])).strip()
    # fake_oracle drives the target's blendshapes with the source's exact weights: it wins, and the reason says so
    assert re.search(
        r"fake_oracle \(baseline of fake_transfer\) wins on vertex_error_rms: [0-9.,×⁻⁰¹²³⁴⁵⁶⁷⁸⁹]+ % face height",
        tiny,
    ), tiny
    assert "Why: fake_oracle's result is a mix of the target's own blendshapes" in tiny, tiny
    assert "more than 1,000 times lower than" in tiny  # an exact result against an inexact one
    # the paper method behind its own baseline is flagged
    assert (
        "the paper method fake_transfer is behind its baseline fake_oracle on vertex_error_rms"
        in tiny
    ), tiny
    # the same sentence heads the case's section
    case_section = re.search(
        r'<section class="case" id="case-0">(.*?)</section>', page, re.S
    ).group(1)
    assert tiny.endswith(" details")  # the top list links to the case
    assert tiny.removesuffix(" details") in html.unescape(re.sub(r"<[^>]+>", "", case_section))


def test_the_summary_flags_reproductions_that_disagree(explained):
    _, paths = explained
    page = paths["html"].read_text()
    summary = re.search(r'<section id="summary">(.*?)</section>', page, re.S).group(1)
    line = re.search(r'<p class="reproductions-line">(.*?)</p>', summary).group(1)
    assert line.startswith("Paper reproductions: 0 agree, 1 disagree, 0 not decided")
    assert (
        '<span class="disagree">disagreeing with their paper: <a class="disagree" href="#preset-fake_table1">fake_table1</a></span>'
        in line
    )
    assert (
        'id="preset-fake_table1"' in page
    )  # the link lands on the reproduction, shown in red there


def test_paper_methods_and_baselines_are_labelled(explained):
    _, paths = explained
    page = paths["html"].read_text()
    ranking = re.search(r'<table class="metrics ranking">(.*?)</table>', page, re.S).group(1)
    labels = dict(
        re.findall(
            r'<th class="method">(.*?)<span class="role [a-z]+" title="[^"]*">([^<]*)</span>',
            ranking,
        )
    )
    labels = {name.replace("<wbr>", ""): label for name, label in labels.items()}
    assert labels["fake_transfer"] == "paper method, Doe et al. 2031"
    assert labels["fake_oracle"] == "baseline of fake_transfer"  # same paper: its baseline
    assert labels["fake_neutral"] == "other"
    legend = re.search(r'<p class="note roles">(.*?)</p>', page).group(1)
    assert "paper methods (the retargeter a paper describes): fake_transfer" in legend


def test_roles_of_the_builtin_methods():
    roles = method_roles(
        [
            "coating",
            "deformation_transfer",
            "spacetime",
            "spacetime_noconst",
            "normalmesh",
            "not_registered",
        ]
    )
    assert (roles["coating"].kind, roles["coating"].citation) == (PAPER, "Xu et al. 2014")
    assert roles["deformation_transfer"].kind == BASELINE and roles[
        "deformation_transfer"
    ].baseline_of == ("coating",)
    assert roles["spacetime_noconst"].label == "baseline of spacetime / spacetime_paper"
    assert roles["normalmesh"].label == "paper method, Na & Jung 2004"
    assert roles["not_registered"].kind == "other"
    assert (
        short_citation("Kholgade, Matthews & Sheikh 2011, Content Retargeting")
        == "Kholgade et al. 2011"
    )
    assert short_citation("no year here") == ""


def test_the_ranking_names_its_one_metric(explained):
    result, paths = explained
    page = paths["html"].read_text()
    section = re.search(r'<section id="ranking">(.*?)</section>', page, re.S).group(1)
    assert "<strong>Ranked by vertex_error_rms</strong>" in section
    assert (
        html.escape(result.metrics["vertex_error_rms"].description) in section
    )  # its definition, not a list of 11 names
    assert "acceleration_error" not in section
    heads = re.findall(r'<th class="ranked">(.*?)<br>', section)
    assert [h.replace("<wbr>", "") for h in heads] == list(
        result.cases
    )  # one value column per case
    # the order and the mean ranks follow the chosen metric alone
    rows = re.findall(
        r'<th class="method">(.*?)<span.*?</th>(?:<td[^>]*>[^<]*</td>){%d}<td class="num">([^<]*)</td>'  # noqa: UP031
        % len(result.cases),
        section,
    )  # noqa: UP031
    shown = {name.replace("<wbr>", ""): rank for name, rank in rows}
    assert list(shown) == [r["method"] for r in result.ranking(metrics=["vertex_error_rms"])]
    assert shown == {
        m: format_number(rank) if rank is not None else "-"
        for m, rank in _mean_ranks_by(result, "vertex_error_rms").items()
    }
    other = render_html(result, rank_by="velocity_error", registry=CATALOGUE)
    assert (
        "<strong>Ranked by velocity_error</strong>" in other and "wins on velocity_error" in other
    )


def _mean_ranks_by(result, metric):
    """Each method's mean over cases of its rank (1 = lowest value) by ``metric`` alone."""
    ranks = {m: [] for m in result.methods}
    for case in result.cases:
        values = {
            r["method"]: r["value"]
            for r in result.rows
            if r["case"] == case and r["metric"] == metric and r["value"] is not None
        }
        if len(values) < 2:
            continue
        for method, value in values.items():
            below, tied = (
                sum(v < value for v in values.values()),
                sum(v == value for v in values.values()),
            )
            ranks[method].append(below + (tied + 1) / 2)
    return {m: (float(np.mean(r)) if r else None) for m, r in ranks.items()}


def test_console_and_json_rank_like_the_report(explained, capsys):
    """result.ranking() (results.json) and the console table use the report's one metric."""
    from faceretarget.evaluation.commands import _print_ranking

    result, _ = explained
    expected = _mean_ranks_by(result, "vertex_error_rms")
    assert {r["method"]: r["mean_rank"] for r in result.ranking()} == pytest.approx(expected)
    _print_ranking(result)
    assert capsys.readouterr().out.startswith("ranked by vertex_error_rms")


def test_ranking_metric_is_checked(explained, tmp_path):
    result, _ = explained
    assert ranking_metric(result) == "vertex_error_rms"
    with pytest.raises(UnknownNameError, match="vertex_error_rms"):
        ranking_metric(result, "vertex_eror_rms")
    with pytest.raises(UnknownNameError):
        write_report(result, tmp_path / "out", rank_by="vertex_eror_rms")
    assert not (tmp_path / "out").exists()
    with pytest.raises(ConfigError, match="descriptive"):
        ranking_metric(result, "fdd")


def test_summary_without_values_says_why(explained):
    result, _ = explained
    roles = {"fake_transfer": MethodRole(PAPER, "Doe et al. 2031")}
    s = case_summary(result, "tiny", "weight_error_rms", roles)
    assert s.winner == "fake_oracle" and "wins on weight_error_rms" in s.text
    none = case_summary(result, "tiny", None, roles)
    assert none.winner is None and "no ranking metric" in none.text


def test_summary_of_a_tie_names_no_winner():
    from faceretarget.evaluation.harness import ComparisonResult
    from faceretarget.evaluation.metrics import METRICS

    rows = [
        {
            "case": "c",
            "method": m,
            "metric": "vertex_error_rms",
            "value": 0.5,
            "unit": "% face height",
            "status": "ok",
            "reason": "",
        }
        for m in ("a", "b")
    ]
    result = ComparisonResult(
        rows, [], {"c": SimpleNamespace(meta={})}, {"vertex_error_rms": METRICS["vertex_error_rms"]}
    )
    s = case_summary(result, "c", "vertex_error_rms", {})
    assert (
        s.winner is None and s.text == "On c, a and b tie on vertex_error_rms: 0.5 % face height."
    )


# ---------------------------------------------------------------------------------------
# Numbers and charts
# ---------------------------------------------------------------------------------------
@pytest.mark.parametrize(
    "value, text",
    [
        (12934.4, "12,934"),
        (10816, "10,816"),
        (999.97, "1000"),
        (0.5468, "0.5468"),
        (0.001234, "0.001234"),
        (2.99e-5, "2.99×10⁻⁵"),
        (-3.1e-12, "-3.1×10⁻¹²"),
        (0.0, "0"),
        (None, ""),
        (float("nan"), ""),
    ],
)
def test_numbers_for_people(value, text):
    assert format_number(value) == text


def test_no_e_notation_in_the_page(explained):
    _, paths = explained
    page = paths["html"].read_text()
    page = re.sub(
        r'<section id="definitions">.*?</section>', "", page, flags=re.S
    )  # quotes constants as written
    visible = re.sub(r"<script.*?</script>|<style>.*?</style>|<[^>]+>", " ", page, flags=re.S)
    assert not SCIENTIFIC.findall(visible), SCIENTIFIC.findall(visible)[:5]
    assert "12,934" in page and "10,816" in page


def test_bar_charts_are_horizontal_with_one_row_per_label():
    names = [f"a rather long label number {i}" for i in range(6)]
    svg = svg_plot(
        Plot("bars", [Series(n, [0], [float(i + 1)]) for i, n in enumerate(names)], kind="bar")
    )
    rows = [
        float(y)
        for y in re.findall(
            r'<text x="[\d.]+" y="([\d.]+)" class="tick" text-anchor="end">a rather', svg
        )
    ]
    assert len(rows) == 6 and min(np.diff(rows)) >= 16  # each label on its own line


# ---------------------------------------------------------------------------------------
# Compile time
# ---------------------------------------------------------------------------------------
class CompilingFake(fakes.TransferFake):
    """Compiles a fresh numba kernel in every fit (never cached)."""

    name = "fake_compiling"

    def _fit(self, source, target):
        import numba

        kernel = numba.njit(lambda x: x * 2.0 + 1.0)
        kernel(np.ones(3))
        super()._fit(source, target)


def test_compile_time_is_measured_apart_and_shown(fake_registry, tmp_path):
    pytest.importorskip("numba")
    result = compare(
        [fakes.tiny_case(n=9, n_frames=6)],
        methods=[CompilingFake, "fake_transfer"],
        registry=fake_registry,
        metrics=["vertex_error_rms"],
    )
    compiling, plain = result.run("tiny", "fake_compiling"), result.run("tiny", "fake_transfer")
    assert 0 < compiling.compile_s <= compiling.fit_s + compiling.retarget_s
    assert plain.compile_s == 0.0
    assert (
        json.loads(result.to_json(tmp_path / "r.json").read_text())["runs"][0]["compile_s"]
        == compiling.compile_s
    )
    page = render_html(result, registry=CATALOGUE)
    runs = re.search(r'<table class="metrics runs">(.*?)</table>', page, re.S).group(1)
    assert "of which compile" in runs and "excl. compile" in runs
    row = re.search(r"fake_<wbr>compiling.*?</tr>", runs, re.S).group(0)
    cells = re.findall(r'<td class="num">([^<]*)</td>', row)
    _, _, compile_s, excl = cells[:4]  # fit, retarget, of which compile, excl. compile
    assert compile_s == format_number(compiling.compile_s)
    assert excl == format_number(compiling.fit_s + compiling.retarget_s - compiling.compile_s)
    ranking = re.search(r'<table class="metrics ranking">(.*?)</table>', page, re.S).group(1)
    assert "excl. compile" in ranking and "compile<br>" in ranking


class HoldingCompilingFake(fakes.TransferFake):
    """Holds 40 MiB across a numba compile, then takes 8 MiB more."""

    name = "fake_holding_compiling"

    def _fit(self, source, target):
        import numba

        held = np.ones(40 * 2**20 // 8)
        numba.njit(lambda x: x * 2.0 + 1.0)(np.ones(3))  # ~0.8 MiB traced if traced
        self.held = (held, np.ones(8 * 2**20 // 8))
        super()._fit(source, target)


def test_peak_memory_leaves_out_the_compiler_and_keeps_what_was_held_across_it(fake_registry):
    """tracemalloc is paused while numba compiles (it would run about twice as slow, and the
    compiler's allocations are not the method's): the peak still counts the 40 MiB held
    across the pause and the 8 MiB after it, and not the compiler's own allocations."""
    pytest.importorskip("numba")
    result = compare(
        [fakes.tiny_case(n=9, n_frames=6)],
        methods=[HoldingCompilingFake],
        registry=fake_registry,
        metrics=["vertex_error_rms"],
    )
    run = result.run("tiny", "fake_holding_compiling")
    assert run.compile_s > 0
    assert 48.0 <= run.peak_memory_mib < 48.5, run.peak_memory_mib


# ---------------------------------------------------------------------------------------
# Headless Chromium at 1280 px
# ---------------------------------------------------------------------------------------
#: Measures the page after load (every <details> opened) and writes JSON into <pre id="layout">.
MEASURE = r"""
<script>
window.addEventListener("load", function () { setTimeout(function () {
  document.querySelectorAll("details").forEach(function (d) { d.open = true; });
  var vw = window.innerWidth, out = {viewport: vw, scrollWidth: document.documentElement.scrollWidth, tables: [], overlaps: [], outside: [], svgs: 0};
  document.querySelectorAll("table").forEach(function (t) {
    var r = t.getBoundingClientRect(), p = t.parentElement;
    out.tables.push({cls: t.className, right: r.right, width: r.width, cut: p.scrollWidth > p.clientWidth + 1});
  });
  function box(e) { var r = e.getBoundingClientRect(); return {l: r.left, r: r.right, t: r.top, b: r.bottom, text: e.textContent}; }
  document.querySelectorAll("svg.plot").forEach(function (svg, k) {
    out.svgs += 1;
    var s = box(svg), texts = Array.prototype.map.call(svg.querySelectorAll("text"), box);
    texts.forEach(function (a, i) {
      if (a.l < s.l - 1 || a.r > s.r + 1 || a.t < s.t - 1 || a.b > s.b + 1) out.outside.push([k, a.text]);
      texts.slice(i + 1).forEach(function (b) {
        var w = Math.min(a.r, b.r) - Math.max(a.l, b.l), h = Math.min(a.b, b.b) - Math.max(a.t, b.t);
        if (w > 1 && h > 1) out.overlaps.push([k, a.text, b.text]);
      });
    });
  });
  out.scrollWidthOpen = document.documentElement.scrollWidth;
  // the report's own words and numbers (the metric definitions quote constants such as 1e-6 as written)
  out.text = Array.prototype.map.call(document.querySelectorAll("header, main > section:not(#definitions)"), function (e) { return e.innerText; }).join("\n");
  var pre = document.createElement("pre"); pre.id = "layout"; pre.textContent = JSON.stringify(out);
  document.body.appendChild(pre);
}, 0); });
</script>
"""


def _run_chromium(binary: str, *args: str) -> subprocess.CompletedProcess:
    with tempfile.TemporaryDirectory() as profile:
        cmd = [
            binary,
            "--headless",
            "--no-sandbox",
            "--disable-gpu",
            "--hide-scrollbars",
            "--no-first-run",
            "--disable-sync",
            "--disable-background-networking",
            "--disable-component-update",
            f"--user-data-dir={profile}",
            "--virtual-time-budget=10000",
            f"--window-size={WIDTH},2000",
            *args,
        ]
        return subprocess.run(
            cmd, capture_output=True, text=True, timeout=180, env={**os.environ, "HOME": profile}
        )


@pytest.fixture(scope="module")
def chromium():
    binary = _chromium_binary()
    if binary is None:
        pytest.skip(
            "the layout check needs a headless Chromium ('chromium' on PATH, e.g. apt-get install -y chromium)"
        )
    return binary


@pytest.fixture(scope="module")
def layout(explained, chromium, tmp_path_factory):
    _, paths = explained
    folder = tmp_path_factory.mktemp("layout")
    page = folder / "measured.html"
    page.write_text(paths["html"].read_text().replace("</body>", MEASURE + "</body>"))
    run = _run_chromium(chromium, "--dump-dom", page.as_uri())
    assert run.returncode == 0, run.stderr[-2000:]
    found = re.search(r'<pre id="layout">(.*?)</pre>', run.stdout, re.S)
    assert found, "the measuring script did not run: " + run.stderr[-2000:]
    return json.loads(html.unescape(found.group(1)))


def test_page_fits_1280_without_horizontal_overflow(layout):
    assert layout["viewport"] == WIDTH
    assert layout["scrollWidth"] == WIDTH and layout["scrollWidthOpen"] == WIDTH, (
        layout["scrollWidth"],
        layout["scrollWidthOpen"],
    )


def test_no_table_is_wider_than_the_page_or_cut(layout):
    tables = layout["tables"]
    assert {"metrics ranking", "metrics case-metrics", "metrics all-metrics", "metrics runs"} <= {
        t["cls"] for t in tables
    }
    wide = [t for t in tables if t["right"] > WIDTH or t["width"] > WIDTH or t["cut"]]
    assert wide == [], wide


def test_chart_labels_do_not_overlap(layout):
    assert layout["svgs"] >= 4
    assert layout["overlaps"] == [], layout["overlaps"][:5]
    assert layout["outside"] == [], layout["outside"][:5]


def test_rendered_text_explains_and_has_no_e_notation(layout):
    text = layout["text"]
    assert (
        "Ranked by vertex_error_rms" in text
        and "Why:" in text
        and "paper method, Doe et al. 2031" in text
    )
    assert not SCIENTIFIC.findall(text), SCIENTIFIC.findall(text)[:5]


def _png_rows(path: Path) -> tuple[int, int, list[bytes]]:
    """Width, height and the filtered scanlines (filter byte first) of an 8-bit RGB/RGBA PNG."""
    data = path.read_bytes()
    assert data[:8] == b"\x89PNG\r\n\x1a\n", "not a PNG"
    pos, idat, header = 8, b"", None
    while pos < len(data):
        length, kind = struct.unpack(">I4s", data[pos : pos + 8])
        body = data[pos + 8 : pos + 8 + length]
        if kind == b"IHDR":
            header = struct.unpack(">IIBBBBB", body)
        elif kind == b"IDAT":
            idat += body
        pos += 12 + length
    width, height, depth, color = header[:4]
    assert depth == 8 and color in (2, 6), header
    stride = width * (4 if color == 6 else 3)
    raw = zlib.decompress(idat)
    return width, height, [raw[i * (stride + 1) : (i + 1) * (stride + 1)] for i in range(height)]


def _rows_with_content(rows: list[bytes], bpp: int) -> int:
    """Scanlines that are not one repeated pixel. Every PNG filter turns a uniform image into
    rows that repeat with the pixel's period after the first pixel, so these rows prove content."""
    count = 0
    for row in rows:
        body = row[1 + bpp :]
        period = body[:bpp]
        if body != period * (len(body) // bpp):
            count += 1
    return count


def test_screenshot_is_drawn(explained, chromium, tmp_path):
    _, paths = explained
    shot = tmp_path / "report.png"
    run = _run_chromium(chromium, f"--screenshot={shot}", paths["html"].resolve().as_uri())
    assert run.returncode == 0 and shot.exists(), run.stderr[-2000:]
    width, height, rows = _png_rows(shot)
    assert (width, height) == (WIDTH, 2000)
    bpp = (len(rows[0]) - 1) // width
    assert _rows_with_content(rows, bpp) > 0.3 * height
