"""Benchmark: preview.html of finished slices, its size, its decimation and how long a headless Chromium takes to draw
it (navigation to the part on screen), with the browser check of tests/preview/test_preview_browser.py.

    .venv/bin/python benchmarks/bench_preview.py [--run NAME=RUN_DIR ...] [--repeats 3] [--quick]

Without ``--run``, slices the ring (``ring.tet --up y``, about a minute) and the 200 mm bunny
(``bunny_closed_low_res.stl --objectives none``: planar layers, the bunny's full program, several minutes) into a
temporary folder first (``--quick``: the ring only). For each run: ``neuralslicer preview``'s page is written again
(timed), then opened ``--repeats`` times in one headless Chromium (Debian's chromium and chromium-driver, software
WebGL), started on a blank WebGL page first: the first load is a first visit in a running browser, the others
reloads. "Drawn" is navigation to the part on screen (the page's first plot presented and screenshotted). Prints a
table and writes ``benchmarks/results/bench_preview.json`` (the rows of the runs measured replace theirs).
"""
from __future__ import annotations

import argparse
import json
import os
import platform
import subprocess
import sys
import tempfile
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parent
sys.path.insert(0, str(ROOT.parent / "tests"))

from preview_browser import browser_missing, check_preview, start_browser  # noqa: E402

from neuralslicer.flows.preview import preview_run  # noqa: E402

DATA = ROOT.parent / "neuralslicer" / "data"
RESULTS = ROOT / "results" / "bench_preview.json"
#: the runs sliced when none is given: name -> the slice's arguments
SLICES = {"ring": ["ring.tet", "--up", "y"], "bunny": ["bunny_closed_low_res.stl", "--objectives", "none"]}
#: a page that starts the browser's renderer and WebGL before the first measured load
WARM_UP = "data:text/html,<canvas id=c></canvas><script>document.getElementById('c').getContext('webgl')</script>"
#: what the page must meet on the bunny (issue 41)
MAX_MB, MAX_DRAW_S = 25.0, 5.0


def slice_run(name: str, folder: Path) -> Path:
    """Slice a shipped model into ``folder/name`` with the command line; the output folder."""
    args = SLICES[name]
    out = folder / name
    exe = str(Path(sys.executable).with_name("neuralslicer"))
    cmd = [exe, "slice", str(DATA / args[0]), *args[1:], "--out", str(out)]
    print("slicing:", " ".join(cmd), flush=True)
    subprocess.run(cmd, check=True)
    return out


def measure(name: str, run_dir: Path, folder: Path, repeats: int) -> dict:
    """Write the run's preview and draw it ``repeats`` times: one row of the table."""
    start = time.perf_counter()
    page, data = preview_run(run_dir, folder / f"preview_{name}.html")
    row = {"case": name, "run": run_dir.name, "write_s": time.perf_counter() - start,
           "size_mb": page.stat().st_size / 1e6, **data.summary(), "load_before": os.getloadavg()[0]}
    driver = start_browser()
    try:
        driver.get(WARM_UP)                                # a running browser: its GPU process and WebGL started
        time.sleep(1.0)
        checks = [check_preview(driver, page, timeout=300) for _ in range(repeats)]
    finally:
        driver.quit()
    loads = [c.load_s for c in checks]
    row.update({"draw_s": loads, "draw_first_s": loads[0], "draw_min_s": min(loads),
                "draw_median_s": sorted(loads)[len(loads) // 2], "load_after": os.getloadavg()[0],
                "console_errors": sum(len(c.errors) for c in checks), "external_requests": len(checks[0].external),
                "pixels_all": checks[0].pixels_all, "pixels_first_third": checks[0].pixels_range,
                "changed_by_slider": checks[0].changed, "level_drawn": checks[0].state.get("level"),
                "page_draw_ms": [c.state.get("drawMs") for c in checks],
                "moves_drawn": checks[0].state.get("drawn", {}).get("1")})
    row["passed"] = (row["console_errors"] == 0 and row["external_requests"] == 0 and row["pixels_all"] > 2000
                     and row["pixels_first_third"] < 0.9 * row["pixels_all"] and row["changed_by_slider"] > 0.005)
    return row


def print_table(rows: list[dict]) -> None:
    """The rows as a table."""
    cols = [("case", "{}"), ("n_moves", "{:,}"), ("n_drawn", "{:,}"), ("factor", "{:.1f}"),
            ("max_deviation_mm", "{:.3f}"), ("size_mb", "{:.1f}"), ("write_s", "{:.1f}"), ("moves_drawn", "{:,}"),
            ("draw_first_s", "{:.2f}"), ("draw_median_s", "{:.2f}"), ("draw_min_s", "{:.2f}"), ("passed", "{}")]
    print(" | ".join(c for c, _ in cols))
    for r in rows:
        print(" | ".join(f.format(r[c]) if r.get(c) is not None else "-" for c, f in cols))


def main() -> None:
    """Measure the runs given (or sliced here) and record them."""
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--run", action="append", default=[], metavar="NAME=RUN_DIR",
                        help="a finished slice's output folder (repeatable; default: slice the ring and the bunny)")
    parser.add_argument("--repeats", type=int, default=3,
                        help="loads of each page (default 3; the first is a first visit, the others reloads)")
    parser.add_argument("--quick", action="store_true", help="without --run: the ring only")
    args = parser.parse_args()
    missing = browser_missing()
    if missing:
        sys.exit(f"bench_preview: {missing}")
    with tempfile.TemporaryDirectory(prefix="bench_preview_") as tmp:
        folder = Path(tmp)
        runs = dict(r.split("=", 1) for r in args.run) if args.run else {
            name: str(slice_run(name, folder)) for name in (("ring",) if args.quick else SLICES)}
        rows = [measure(name, Path(d), folder, args.repeats) for name, d in runs.items()]
    print_table(rows)
    kept = json.loads(RESULTS.read_text()) if RESULTS.exists() else {}
    by_case = {r["case"]: r for r in kept.get("rows", [])}
    by_case.update({r["case"]: r for r in rows})
    kept.update({"machine": platform.processor() or platform.machine(), "cpus": os.cpu_count(),
                 "python": platform.python_version(), "browser": "chromium (headless=new, software WebGL)",
                 "limits": {"size_mb": MAX_MB, "draw_s": MAX_DRAW_S}, "rows": list(by_case.values())})
    RESULTS.parent.mkdir(exist_ok=True)
    RESULTS.write_text(json.dumps(kept, indent=2, default=float) + "\n")
    print(f"written: {RESULTS}")


if __name__ == "__main__":
    main()
