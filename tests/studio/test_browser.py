"""The studio as a person uses it: headless Chromium (Debian's /usr/bin/chromium, driven by
Playwright, no browser download) opens the printed URL, switches methods, edits a frame with
a slider and sees the curve change, undoes, turns on the heat map, exports; sees a failing
method's message; and watches a live stream from a simulated Live Link Face sender.

The page's Content-Security-Policy stays on: the tests read its state with
``page.evaluate`` (not ``wait_for_function``, which CSP forbids) and check screenshots."""

from __future__ import annotations

import os
import time
from pathlib import Path

import numpy as np
import pytest
from studio_helpers import colours

CHROMIUM = "/usr/bin/chromium"

pytestmark = [
    pytest.mark.timeout(180),
    pytest.mark.skipif(
        not os.access(CHROMIUM, os.X_OK),
        reason=f"the browser tests need Debian's chromium at {CHROMIUM} (apt-get install -y chromium)",
    ),
]
playwright_api = pytest.importorskip(
    "playwright.sync_api", reason="the browser tests need playwright (pip install -e '.[test]')"
)


@pytest.fixture(scope="module")
def browser():
    with playwright_api.sync_playwright() as p:
        chromium = p.chromium.launch(
            executable_path=CHROMIUM,
            args=["--no-sandbox", "--use-angle=swiftshader", "--enable-unsafe-swiftshader"],
        )
        yield chromium
        chromium.close()


@pytest.fixture(scope="module")
def studio(boom_registry, case, start_studio):
    lines: list[str] = []
    server = start_studio(case, live=lines)
    return server, lines


@pytest.fixture
def page(browser, studio):
    page = browser.new_page(viewport={"width": 1400, "height": 900})
    problems: list[str] = []
    page.on("pageerror", lambda e: problems.append(f"page error: {e}"))
    page.on(  # an HTTP error the page reports is checked by the tests that cause it
        "console",
        lambda m: (
            m.type == "error"
            and not m.text.startswith("Failed to load resource: the server responded")
            and problems.append(f"console: {m.text}")
        ),
    )
    page.goto(studio[0].url)
    wait(page, "window.studio && window.studio.ready && !window.studio.busy")
    yield page
    page.close()
    assert not problems, problems


def wait(page, expression: str, limit: float = 60.0) -> None:
    start = time.monotonic()
    while not page.evaluate(f"!!({expression})"):
        assert time.monotonic() - start < limit, f"waited {limit} s for {expression}"
        time.sleep(0.05)


def state(page, expression: str):
    return page.evaluate(f"window.studio.{expression}")


def drawn(png: bytes) -> float:
    """Share of pixels that are neither the view's background nor white."""
    pixels = colours(png)
    return sum(max(abs(c - b) for c, b in zip(p, (247, 248, 250))) > 12 for p in pixels) / len(
        pixels
    )


def test_open_switch_edit_undo_heat_map_export(page, studio, case):
    server = studio[0]
    assert state(page, "result.method") == "spacetime"  # the first method that edits curves
    target = page.locator("#view-target canvas")
    assert drawn(target.screenshot()) > 0.2, "the target face is not drawn"
    assert drawn(page.locator("#view-source canvas").screenshot()) > 0.2

    # switch method: another result, other edit tools; then back (from the cache)
    page.select_option("#method", "deformation_transfer")
    wait(page, "window.studio.result.method === 'deformation_transfer' && !window.studio.busy")
    assert page.locator("#edit-none").is_visible() and not page.locator("#sliders").is_visible()
    page.select_option("#method", "spacetime")
    wait(page, "window.studio.result.method === 'spacetime' && !window.studio.busy")
    assert "cached" in page.locator("#status").inner_text()
    params = page.locator("#params [name=alpha]")
    assert params.get_attribute("type") == "number" and params.input_value() == "0.01"

    # edit frame 30 with a slider
    page.locator("#frame").fill("30")
    page.locator("#frame").dispatch_event("input")
    assert state(page, "frame") == 30
    names = state(page, "result.weight_names")
    j, m = names.index("jawOpen"), len(names)
    before = np.array(state(page, "weights"))
    slider = page.locator("#sliders label[data-shape=jawOpen] input")
    slider.focus()  # the curve of the focused shape is drawn in red
    assert state(page, "focus") == "jawOpen"
    curves_before = page.locator("#curves").screenshot()
    version = state(page, "curvesVersion")
    slider.fill("1")  # fires input and change: one edit
    wait(page, f"window.studio.curvesVersion > {version} && !window.studio.busy")
    after = np.array(state(page, "weights"))
    assert after[30 * m + j] == pytest.approx(1.0, abs=1e-4) and before[30 * m + j] < 0.9
    assert page.locator("#curves").screenshot() != curves_before, "the curve did not change"
    assert state(page, "result.undo") == 1 and page.locator("#undo").is_enabled()
    assert "changed" in page.locator("#status").inner_text()
    shot = target.screenshot()

    # undo: the curves are back
    page.click("#undo")
    wait(page, "window.studio.result.undo === 0 && !window.studio.busy")
    np.testing.assert_array_equal(np.array(state(page, "weights")), before)
    page.click("#redo")
    wait(page, "window.studio.result.undo === 1 && !window.studio.busy")

    # heat map: the distance to the truth colours the face
    page.check("#heatmap")
    wait(page, "window.studio.errors !== null && !window.studio.busy")
    assert page.locator("#heat-legend").is_visible()
    heat = target.screenshot()
    assert heat != shot
    blue = sum(b > r + 40 for r, _, b in colours(heat))
    assert blue > 100, "no blue (small error) pixels on the heat map"

    # export: a new GLB in the output folder
    page.click("#export-glb")
    wait(page, "window.studio.lastExport !== '' && !window.studio.busy")
    path = Path(state(page, "lastExport"))
    assert path.is_file() and path.parent == server.session.out_dir.resolve()
    assert path.name in page.locator("#export-msg").inner_text()
    import faceretarget as fr

    exported = fr.load(path, kind="animation")
    assert exported.weights[30, j] == pytest.approx(1.0, abs=1e-4)


def test_a_failing_method_is_shown_and_the_page_goes_on(page):
    page.select_option("#method", "studio_boom")
    wait(page, "window.studio.lastError !== '' && !window.studio.busy")
    assert page.locator("#error").is_visible()
    assert "kaboom" in page.locator("#error-text").inner_text()
    page.click("#error-close")
    page.select_option("#method", "spacetime")
    wait(page, "window.studio.result.method === 'spacetime' && !window.studio.busy")
    assert page.locator("#error").is_hidden()


def test_the_parameter_panel_runs_with_the_values_set(page):
    page.locator("#params [name=alpha]").fill("0.05")
    page.click("#run")
    wait(page, "window.studio.result.params.alpha === 0.05 && !window.studio.busy")
    page.locator("#params [name=alpha]").fill("-3")
    page.click("#run")
    wait(page, "window.studio.lastError !== '' && !window.studio.busy")
    assert "alpha" in page.locator("#error-text").inner_text()


def test_live_stream_in_the_page(page, studio, case):
    from faceretarget.studio.live import send

    server, lines = studio
    link = server.session.live
    wait(page, "true")
    start = time.monotonic()
    while link.status != "waiting" and link.status != "streaming":
        assert time.monotonic() - start < 60 and link.status != "failed", link.error
        time.sleep(0.05)
    assert page.locator("#live-panel").is_visible()
    page.check("#live-on")
    neutral = page.locator("#view-target canvas").screenshot()
    frames = np.zeros((40, 61))
    frames[:, 17] = 0.8  # JawOpen
    send(link.port, frames, fps=60)
    wait(page, f"window.studio.liveSeq >= {max(1, link.frames)}")
    assert "ms" in page.locator("#live-info").inner_text()
    assert "live frame" in page.locator("#status").inner_text()
    assert page.locator("#view-target canvas").screenshot() != neutral
    assert any(
        line.startswith("live frame") and line.endswith("retargeted frame)") for line in lines
    )
    page.uncheck("#live-on")
