"""preview.html in a real headless Chromium (Debian's chromium and chromium-driver, driven by selenium): the page
loads offline with no console error, draws the part, and the drawing changes when the layer slider moves.
Skipped, with the reason, where the browser, its driver or selenium is missing (.ci/run installs them as root)."""
from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
from conftest import fast_config
from preview_browser import PageCheck, browser_missing, check_preview, start_browser

from neuralslicer.motion import load_profile, plan_print
from neuralslicer.preview import PREVIEW_FILE
from neuralslicer.preview.page import write_preview
from neuralslicer.toolpath.synthetic import cap_stack

MISSING = browser_missing()
# a real Chromium (about 15 s for the module): end-to-end, so `make test` runs it and `make test-fast` leaves it out
pytestmark = [pytest.mark.skipif(MISSING is not None, reason=f"no headless browser: {MISSING}"), pytest.mark.slow]


@pytest.fixture(scope="module")
def browser():
    """One headless Chromium for the module."""
    driver = start_browser()
    yield driver
    driver.quit()


def assert_drawn(check: PageCheck) -> None:
    """No console error, nothing fetched, the part drawn (coloured pixels), and fewer of them after the slider
    narrowed the layer range to its first third."""
    assert check.errors == [], check.errors
    assert check.external == [], check.external
    assert check.state["ready"] and check.state["draws"] >= 1
    assert check.pixels_all > 2000, check
    assert check.pixels_range < 0.9 * check.pixels_all and check.changed > 0.005, check


def test_preview_of_a_planned_program(browser, tmp_path: Path) -> None:
    """A curved part printed with rotary motion, two of its waypoints colliding."""
    layers = cap_stack(6, r0=8.0, theta_max_deg=40.0, subdivisions=4)
    tp, prog, metrics, _ = plan_print(layers, platform_z=0.0, profile=load_profile("table_bc_linuxcnc"))
    write_preview(tmp_path / PREVIEW_FILE, prog, tp.width, np.array([10, len(tp) // 2]), "caps", metrics)
    check = check_preview(browser, tmp_path / PREVIEW_FILE)
    assert_drawn(check)
    assert browser.execute_script("return document.getElementById('figures').textContent").endswith(
        "2 colliding moves (red)")


def test_preview_of_a_slice(browser, planar_run: Path) -> None:
    """The page a slice writes beside print.gcode (the export of the Prefect flow)."""
    assert (planar_run / "print.gcode").is_file()
    assert_drawn(check_preview(browser, planar_run / PREVIEW_FILE))


def test_the_controls_redraw_without_errors(browser, planar_run: Path) -> None:
    """Every colour mode, travels on, the head at another move and the next-collision button: no console error; a
    move number typed in shows that move, the layer range widened to hold it."""
    from preview_browser import set_layer_range

    check_preview(browser, planar_run / PREVIEW_FILE)       # leaves the first third of the layers shown
    value = "return document.getElementById(arguments[0]).value"
    move, top = int(browser.execute_script(value, "move-number")), int(browser.execute_script(value, "layer-hi"))
    last = int(browser.execute_script("return document.getElementById('layer-hi').max"))
    set_layer_range(browser, last, last)
    browser.execute_script("var m = document.getElementById('move-number'); m.value = arguments[0];"
                           "m.dispatchEvent(new Event('change'));", move)
    assert browser.execute_script("return document.getElementById('move-info').textContent").startswith(f"#{move:,}:")
    assert int(browser.execute_script(value, "layer-lo")) <= top
    for mode in ("tilt", "feed", "width", "layer"):
        browser.execute_script("var s = document.getElementById('colour'); s.value = arguments[0];"
                               "s.dispatchEvent(new Event('change'));", mode)
    browser.execute_script("var t = document.getElementById('travels'); t.checked = true;"
                           "t.dispatchEvent(new Event('change'));"
                           "var m = document.getElementById('move'); m.value = m.min;"
                           "m.dispatchEvent(new Event('input'));"
                           "document.getElementById('next-collision').click();")
    info = browser.execute_script("return document.getElementById('move-info').textContent")
    assert info.startswith("#") and "layer" in info
    assert [e for e in browser.get_log("browser") if e.get("level") == "SEVERE"] == []


@pytest.mark.slow   # a ring slice in this process (a short optimisation): about a minute
def test_preview_of_the_ring(browser, ring_path: Path, tmp_path: Path) -> None:
    """The Ring of the paper, sliced with curved layers and tilted tool axes: its preview.html draws."""
    from neuralslicer.config import SliceConfig
    from neuralslicer.model.spec import spec_for_file
    from neuralslicer.run.in_process import slice_model

    config = SliceConfig.model_validate(fast_config(
        samples={"n_samples": 4000}, cage={"n_elements": 3000}, neural={"optim": {"max_steps": 60}},
        layers={"layer_height": 0.8}, toolpath={}))
    slice_model(spec_for_file(ring_path, "y"), config, tmp_path / "ring")
    page = tmp_path / "ring" / PREVIEW_FILE
    assert page.stat().st_size < 25e6
    check = check_preview(browser, page)
    assert_drawn(check)
