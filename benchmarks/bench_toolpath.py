"""Benchmark: toolpaths, motion planning, collisions and G-code, stage by stage, with peak memory.

    .venv/bin/python benchmarks/bench_toolpath.py [--quick] [--cases caps,box,part] [--part bunny|coin]

Cases:
- ``caps``: a curved part (80 concentric spherical caps, rotary motion);
- ``box``: a planar box sized to about one million waypoints;
- ``part``: a 200 mm tall closed part from the shipped data (default the Stanford bunny,
  ``bunny_closed_low_res.stl``, 203 x 156 x 200 mm; ``--part coin`` the overhang coin), sliced with planar
  layers (G = z) at 0.5 mm by the layer step (``slice_layers`` on a 10k-tet cage, not timed as a stage):
  391 layers for the bunny, 400 for the coin, full infill.

Each case runs in a fresh process. Each stage (toolpaths, ``plan_motion``, ``check_collisions``,
``write_gcode``, waypoint CSV) is timed on its own, with the peak resident memory of the process while it
runs (sampled every 20 ms) and what the stage added over its start; the process's CPU time per stage is
recorded too (``*_cpu_s``: on a shared machine it moves less than the wall time). Prints a table and the
load average, and writes ``benchmarks/results/bench_toolpath.json`` (the rows of the cases run replace
theirs; not with ``--quick``, a smoke run on small sizes).
"""
from __future__ import annotations

import argparse
import json
import multiprocessing
import os
import platform
import tempfile
import threading
import time
from concurrent.futures import ProcessPoolExecutor
from pathlib import Path

import psutil

from neuralslicer.gcode import write_gcode
from neuralslicer.motion import check_collisions, load_profile, plan_motion, program_metrics
from neuralslicer.toolpath import ToolpathConfig, toolpaths, write_waypoints_csv
from neuralslicer.toolpath.synthetic import cap_stack, planar_stack

ROOT = Path(__file__).resolve().parent
DATA = ROOT.parent / "neuralslicer" / "data"
PARTS = {"bunny": "bunny_closed_low_res.stl", "coin": "overhang_coin_closed_low_res.stl"}
RESULTS = ROOT / "results" / "bench_toolpath.json"
STAGES = ("toolpaths", "motion", "collisions", "gcode", "csv")


class Stage:
    """Context manager: wall and CPU time, peak resident memory (sampled every 20 ms) and load of one stage."""

    def __init__(self, row: dict, name: str) -> None:
        """Record into ``row`` under ``name``."""
        self.row, self.name = row, name
        self.proc = psutil.Process()

    def __enter__(self) -> "Stage":
        self.base = self.peak = self.proc.memory_info().rss
        self.stop = threading.Event()
        self.thread = threading.Thread(target=self._sample, daemon=True)
        self.thread.start()
        self.t0, self.c0 = time.perf_counter(), time.process_time()
        return self

    def _sample(self) -> None:
        while not self.stop.wait(0.02):
            self.peak = max(self.peak, self.proc.memory_info().rss)

    def __exit__(self, *exc: object) -> None:
        wall, cpu = time.perf_counter() - self.t0, time.process_time() - self.c0
        self.stop.set()
        self.thread.join()
        self.peak = max(self.peak, self.proc.memory_info().rss)
        self.row[f"{self.name}_s"] = wall
        self.row[f"{self.name}_cpu_s"] = cpu
        self.row[f"{self.name}_peak_gb"] = self.peak / 2**30
        self.row[f"{self.name}_added_gb"] = (self.peak - self.base) / 2**30
        self.row[f"{self.name}_load"] = os.getloadavg()[0]


def part_layers(name: str, layer_height: float = 0.5) -> tuple[list, float, float]:
    """Planar layers (G = z) of a shipped 200 mm part by the layer step: (meshes, platform_z, t_max)."""
    from neuralslicer.cage import CageConfig, make_cage
    from neuralslicer.layers import LayerConfig, slice_layers
    from neuralslicer.model.solid import implicit_solid
    from neuralslicer.model.spec import spec_for_file
    from neuralslicer.samples import surface_samples
    from neuralslicer.scalar_field import ScalarField

    solid = implicit_solid(spec_for_file(DATA / PARTS[name], "z"))
    samples = surface_samples(solid, 4000, k=10, seed=0)
    cage = make_cage(solid, samples.points, CageConfig(n_elements=10_000))
    field = ScalarField(cage.vertices, cage.tets, cage.vertices[:, 2].copy(), {})
    config = LayerConfig(layer_height=layer_height)
    layers = slice_layers(solid, field, config)
    return layers.meshes, float(solid.platform_z), float(config.t_max)


def run_case(name: str, layers: list, platform_z: float, cfg: ToolpathConfig, t_max: float = 1.0,
             csv: bool = True) -> dict:
    """Time every stage for one part; returns a row of the table."""
    profile = load_profile("table_bc_linuxcnc")
    row: dict = {"case": name, "layers": len(layers), "layer_area_m2": sum(m.area for m in layers) / 1e6}
    with Stage(row, "toolpaths"):
        tp = toolpaths(layers, platform_z=platform_z, config=cfg, t_max=t_max)
    with Stage(row, "motion"):
        prog = plan_motion(tp, profile, platform_z=platform_z)
    with Stage(row, "collisions"):
        rep = check_collisions(tp, profile.nozzle, platform_z)
    with tempfile.TemporaryDirectory() as tmp:
        with Stage(row, "gcode"):
            g = write_gcode(Path(tmp) / "print.ngc", prog)
        row["gcode_mb"] = g.stat().st_size / 1e6
        if csv:
            with Stage(row, "csv"):
                write_waypoints_csv(Path(tmp) / "waypoints.csv", tp)
    met = program_metrics(prog)
    on = tp.path >= 0
    row.update(waypoints=len(tp), moves=len(prog), collisions=rep.count, paths=int(tp.attrs["n_paths"]),
               path_length_m=float(tp.segment_lengths()[on & tp.extrude].sum() / 1e3),
               inserted_rotary=prog.attrs["n_inserted_rotary"],
               c_range_deg=prog.attrs["c_range_deg"], material_mm3=met["material_mm3"],
               print_time_h=met["estimated_print_time_s"] / 3600.0,
               peak_gb=max(row[f"{s}_peak_gb"] for s in STAGES if f"{s}_s" in row))
    row["total_s"] = sum(row.get(f"{s}_s", 0.0) for s in STAGES)
    row["toolpaths_gcode_s"] = row["toolpaths_s"] + row["gcode_s"]
    return row


def run_named_case(case: str, part: str = "bunny", quick: bool = False) -> dict:
    """Build the layers of one case (``caps``, ``box`` or ``part``) and time its stages."""
    t = time.perf_counter()
    if case == "caps":
        layers = (cap_stack(10, r0=10.0, theta_max_deg=40.0, subdivisions=4) if quick
                  else cap_stack(80, r0=10.0, theta_max_deg=30.0, subdivisions=5))
        name, pz, t_max = f"curved caps ({len(layers)} layers)", -30.0, 1.0
    elif case == "box":
        layers = planar_stack(10, size=20.0, n=21) if quick else planar_stack(160, size=40.0, n=41)
        name, pz, t_max = f"planar box ({len(layers)} layers)", 0.0, 1.0
    elif case == "part":
        layers, pz, t_max = part_layers(part)
        if quick:
            layers = layers[::40]
        name = f"{part} 200 mm, planar 0.5 mm ({len(layers)} layers)"
    else:
        raise SystemExit(f"unknown case {case!r}: caps, box or part")
    setup_s = time.perf_counter() - t
    row = run_case(name, layers, pz, ToolpathConfig(), t_max)
    row["layers_setup_s"] = setup_s
    return row


def main() -> None:
    """Run the benchmark cases and print the table."""
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--quick", action="store_true", help="small sizes (smoke test)")
    ap.add_argument("--cases", default="caps,box,part", help="comma-separated: caps, box, part")
    ap.add_argument("--part", default="bunny", choices=sorted(PARTS), help="the 200 mm part")
    args = ap.parse_args()
    rows = []
    # each case in a fresh process, so that one case's peak memory is not another's
    with ProcessPoolExecutor(max_workers=1, mp_context=multiprocessing.get_context("spawn"),
                             max_tasks_per_child=1) as pool:
        for case in args.cases.split(","):
            rows.append(pool.submit(run_named_case, case, args.part, args.quick).result())
            print(f"done {rows[-1]['case']}: {rows[-1]['total_s']:.1f} s, load {os.getloadavg()[0]:.2f}", flush=True)
    cols = ["case", "layers", "waypoints", "moves"] + [f"{s}_s" for s in STAGES] + ["total_s"] + \
        [f"{s}_cpu_s" for s in STAGES] + [f"{s}_peak_gb" for s in STAGES] + ["gcode_mb", "collisions"]
    print("| " + " | ".join(cols) + " |")
    print("|" + "---|" * len(cols))
    for r in rows:
        print("| " + " | ".join(f"{r.get(c, float('nan')):.2f}" if isinstance(r.get(c, 0.0), float)
                                else str(r[c]) for c in cols) + " |")
    print("load (1 min) during toolpaths / motion / collisions / G-code:",
          ", ".join("/".join(f"{r.get(f'{s}_load', float('nan')):.2f}" for s in STAGES[:4]) for r in rows))
    if not args.quick:
        RESULTS.parent.mkdir(parents=True, exist_ok=True)
        kept = json.loads(RESULTS.read_text()) if RESULTS.exists() else {}      # e.g. "before": earlier code
        names = {r["case"] for r in rows}
        kept.update({"machine": platform.processor() or platform.machine(), "cpus": os.cpu_count(),
                     "python": platform.python_version(),
                     "rows": [r for r in kept.get("rows", []) if r["case"] not in names] + rows})
        RESULTS.write_text(json.dumps(kept, indent=2))


if __name__ == "__main__":
    main()
