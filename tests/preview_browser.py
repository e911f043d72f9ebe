"""preview.html in a real headless Chromium (Debian's chromium and chromium-driver, driven by selenium): shared by
tests/preview/test_preview_browser.py and benchmarks/bench_preview.py."""
from __future__ import annotations

import io
import shutil
import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

#: the system browser and its driver (Debian/Ubuntu packages chromium, chromium-driver): nothing is downloaded
CHROMIUM = "/usr/bin/chromium"
CHROMEDRIVER = "/usr/bin/chromedriver"
#: the page's state object (page.js)
STATE = "window.neuralslicerPreview"


def browser_missing() -> str | None:
    """Why the browser test cannot run here (None when it can)."""
    try:
        import selenium  # noqa: F401
    except ImportError:
        return "selenium is not installed (the dev extra)"
    for path, package in ((CHROMIUM, "chromium"), (CHROMEDRIVER, "chromium-driver")):
        if not Path(path).is_file() and shutil.which(Path(path).name) is None:
            return f"{path} not found: install Debian's {package} (apt-get install chromium chromium-driver)"
    return None


def start_browser(width: int = 1280, height: int = 900) -> Any:
    """A headless Chromium with the browser console logged (software WebGL: no GPU needed)."""
    from selenium import webdriver
    from selenium.webdriver.chrome.service import Service

    opts = webdriver.ChromeOptions()
    opts.binary_location = CHROMIUM if Path(CHROMIUM).is_file() else shutil.which("chromium")
    for arg in ("--headless=new", "--no-sandbox", "--disable-dev-shm-usage", f"--window-size={width},{height}",
                "--enable-unsafe-swiftshader", "--disable-extensions", "--no-first-run"):
        opts.add_argument(arg)
    opts.set_capability("goog:loggingPrefs", {"browser": "ALL"})
    driver_path = CHROMEDRIVER if Path(CHROMEDRIVER).is_file() else shutil.which("chromedriver")
    return webdriver.Chrome(service=Service(executable_path=driver_path), options=opts)


def wait_for(driver: Any, script: str, timeout: float) -> Any:
    """Poll a script until it returns something true; its value (an AssertionError after ``timeout`` s)."""
    end = time.monotonic() + timeout
    while True:
        value = driver.execute_script(script)
        if value:
            return value
        if time.monotonic() > end:
            raise AssertionError(f"timed out after {timeout:g} s waiting for: {script}")
        time.sleep(0.02)


def plot_pixels(driver: Any) -> np.ndarray:
    """The plot's area of a screenshot (h, w, 3) uint8, the colour bar at its right edge cut off."""
    from PIL import Image

    img = np.asarray(Image.open(io.BytesIO(driver.get_screenshot_as_png())).convert("RGB"))
    r = driver.execute_script("var r = document.getElementById('plot').getBoundingClientRect();"
                              "return [r.left, r.top, r.width, r.height, window.devicePixelRatio];")
    s = r[4] or 1.0
    x0, y0, w, h = (int(round(v * s)) for v in r[:4])
    return img[y0:y0 + h, x0:max(x0 + w - int(130 * s), x0 + 1)]


def coloured(pixels: np.ndarray) -> np.ndarray:
    """Pixels (h, w) bool of a saturated colour: the printed part (the colour scale), not the grey axes, head or
    background."""
    p = pixels.astype(np.int16)
    return (p.max(axis=2) - p.min(axis=2)) > 60


def console_errors(driver: Any) -> list[dict]:
    """The browser console's errors (level SEVERE) since the last call."""
    return [e for e in driver.get_log("browser") if e.get("level") == "SEVERE"]


def set_layer_range(driver: Any, lo: int, hi: int, timeout: float = 120.0) -> None:
    """Move the layer range sliders as a user would (input events) and wait for the redraw."""
    draws = driver.execute_script(f"return {STATE}.draws")
    driver.execute_script(
        "var f = function (id, v) { var el = document.getElementById(id); el.value = v;"
        " el.dispatchEvent(new Event('input', {bubbles: true})); };"
        " f('layer-lo', arguments[0]); f('layer-hi', arguments[1]);",
        lo, hi)
    wait_for(driver, f"return {STATE}.draws > {draws}", timeout)


@dataclass
class PageCheck:
    """What a headless Chromium saw of a preview: load time (navigation to drawn), console errors, coloured pixels
    of the whole part and of a narrower layer range, the share of the plot's pixels that changed, what it drew."""

    load_s: float
    errors: list[dict]
    pixels_all: int
    pixels_range: int
    changed: float
    state: dict[str, Any]
    external: list[str] = field(default_factory=list)


def check_preview(driver: Any, path: Path, timeout: float = 120.0) -> PageCheck:
    """Open a preview.html, wait until it is drawn, screenshot it, move the layer slider, screenshot it again."""
    console_errors(driver)                                # empty the log of anything before
    start = time.perf_counter()
    driver.get(Path(path).resolve().as_uri())
    wait_for(driver, f"return {STATE} && {STATE}.ready", timeout)
    before = plot_pixels(driver)                          # a screenshot waits for the frame to be drawn
    load_s = time.perf_counter() - start
    state = driver.execute_script(f"return {STATE}")
    external = driver.execute_script(
        "return performance.getEntriesByType('resource').map(function (e) { return e.name; })"
        ".filter(function (u) { return !u.startsWith('file:') && !u.startsWith('data:'); })")
    lo, hi = (int(v) for v in driver.execute_script(
        "return [document.getElementById('layer-lo').min, document.getElementById('layer-hi').max]"))
    set_layer_range(driver, lo, lo + max((hi - lo) // 3, 0), timeout)
    after = plot_pixels(driver)
    h, w = min(before.shape[0], after.shape[0]), min(before.shape[1], after.shape[1])
    changed = float(np.mean(np.any(before[:h, :w] != after[:h, :w], axis=2)))
    return PageCheck(load_s, console_errors(driver), int(coloured(before).sum()), int(coloured(after).sum()), changed,
                     state, external)
