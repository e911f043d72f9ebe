"""Benchmark: toolpaths, motion planning, collisions and G-code for synthetic multi-layer parts.

Cases: a curved part (concentric spherical caps, rotary motion) with many layers, and a planar
box sized to about one million waypoints. Prints a table and writes
``benchmarks/results/bench_toolpath.json``. ``--quick`` runs small sizes (smoke test).
"""
from __future__ import annotations

import argparse
import json
import platform
import resource
import tempfile
import time
from pathlib import Path


from neuralslicer.gcode import write_gcode
from neuralslicer.motion import check_collisions, load_profile, plan_motion, program_metrics
from neuralslicer.toolpath import ToolpathConfig, toolpaths, write_waypoints_csv
from neuralslicer.toolpath.synthetic import cap_stack, planar_stack

RESULTS = Path(__file__).parent / "results" / "bench_toolpath.json"


def _peak_rss_mb() -> float:
    return resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024.0


def run_case(name: str, layers: list, platform_z: float, cfg: ToolpathConfig) -> dict:
    """Time every stage for one part; returns a row of the table."""
    profile = load_profile("table_bc_linuxcnc")
    rss0 = _peak_rss_mb()
    row: dict = {"case": name, "layers": len(layers)}
    t = time.perf_counter()
    tp = toolpaths(layers, platform_z=platform_z, config=cfg)
    row["toolpaths_s"] = time.perf_counter() - t
    t = time.perf_counter()
    prog = plan_motion(tp, profile, platform_z=platform_z)
    row["motion_s"] = time.perf_counter() - t
    t = time.perf_counter()
    rep = check_collisions(tp, profile.nozzle, platform_z)
    row["collisions_s"] = time.perf_counter() - t
    with tempfile.TemporaryDirectory() as tmp:
        t = time.perf_counter()
        g = write_gcode(Path(tmp) / "print.ngc", prog)
        row["gcode_s"] = time.perf_counter() - t
        row["gcode_mb"] = g.stat().st_size / 1e6
        t = time.perf_counter()
        write_waypoints_csv(Path(tmp) / "waypoints.csv", tp)
        row["csv_s"] = time.perf_counter() - t
    met = program_metrics(prog)
    row.update(waypoints=len(tp), moves=len(prog), collisions=rep.count,
               inserted_rotary=prog.attrs["n_inserted_rotary"],
               c_range_deg=prog.attrs["c_range_deg"], material_mm3=met["material_mm3"],
               print_time_h=met["estimated_print_time_s"] / 3600.0,
               peak_rss_mb=_peak_rss_mb(), rss_growth_mb=_peak_rss_mb() - rss0)
    row["total_s"] = sum(row[k] for k in ("toolpaths_s", "motion_s", "collisions_s", "gcode_s", "csv_s"))
    return row


def main() -> None:
    """Run the benchmark cases and print the table."""
    ap = argparse.ArgumentParser(description=__doc__)
    ap.add_argument("--quick", action="store_true", help="small sizes (smoke test)")
    args = ap.parse_args()
    cfg = ToolpathConfig()
    if args.quick:
        cases = [("curved caps", cap_stack(10, r0=10.0, theta_max_deg=40.0, subdivisions=4), -20.0),
                 ("planar box", planar_stack(10, size=20.0, n=21), 0.0)]
    else:
        cases = [("curved caps (80 layers)", cap_stack(80, r0=10.0, theta_max_deg=30.0, subdivisions=5), -30.0),
                 ("planar box 40 mm (~1M wp)", planar_stack(160, size=40.0, n=41), 0.0)]
    rows = []
    for n, layers, pz in cases:
        rows.append(run_case(n, layers, pz, cfg))
        print(f"done {n}: {rows[-1]['total_s']:.1f} s", flush=True)
    cols = ["case", "layers", "waypoints", "moves", "toolpaths_s", "motion_s", "collisions_s", "gcode_s",
            "csv_s", "total_s", "peak_rss_mb", "gcode_mb", "collisions"]
    print("| " + " | ".join(cols) + " |")
    print("|" + "---|" * len(cols))
    for r in rows:
        print("| " + " | ".join(f"{r[c]:.2f}" if isinstance(r[c], float) else str(r[c]) for c in cols) + " |")
    if not args.quick:
        RESULTS.parent.mkdir(parents=True, exist_ok=True)
        RESULTS.write_text(json.dumps({"machine": platform.processor() or platform.machine(),
                                       "python": platform.python_version(), "rows": rows}, indent=2))


if __name__ == "__main__":
    main()
