"""Benchmark: the exact nozzle collision check of a whole print, and how its time grows from 1M to 10M waypoints.

    .venv/bin/python benchmarks/bench_collision.py [--store OUT/store.zarr] [--sizes 1e6,2e6,5e6,1e7] [--workers N]

The print: the layers of the first run in ``--store`` (e.g. the 200 mm bunny's optimised field), or by default the
shipped 200 mm bunny (``bunny_closed_low_res.stl``) sliced with a curved field ``G = z + c r^2`` (r: the distance
from the part's vertical centre line; tool axes up to about 40 deg from vertical, the tilts of the bunny's
optimised fields) by the layer step. Toolpaths are planned as the toolpath step plans them up to the check (beads
held, short moves merged, axes turned up at the platform) and cached in the temporary folder. For each size the
print's first layers holding about that many waypoints are checked from scratch in a fresh process: the structure
of the printed material built (``PrintedMaterial.of_toolpaths``), then every waypoint and every pose inside the
travels (``check_collisions``). Per size: waypoints, travel poses, build and check wall time, the process's CPU
time, peak memory, collisions, the load. Prints a table and the growth exponent (slope of log time over log
waypoints), and writes ``benchmarks/results/bench_collision.json``.
"""
from __future__ import annotations

import argparse
import hashlib
import json
import multiprocessing
import os
import tempfile
import time
from concurrent.futures import ProcessPoolExecutor
from pathlib import Path

import numpy as np
import psutil

ROOT = Path(__file__).resolve().parent
DATA = ROOT.parent / "neuralslicer" / "data"
RESULTS = ROOT / "results" / "bench_collision.json"
FIELDS = ("layer", "path", "xyz", "axis", "thickness", "width", "extrude")
#: curvature of the default field G = z + CURVE r^2 (1/mm)
CURVE = 0.004


def shown(path: Path) -> str:
    """A path as the results record it: relative to the repository, else its last two parts (no machine path)."""
    path, repo = path.resolve(), ROOT.parent
    return (path.relative_to(repo).as_posix() if path.is_relative_to(repo)
            else f"<outside the repository>/{path.parent.name}/{path.name}")


def curved_bunny_layers() -> tuple[list, float]:
    """Layers of the shipped bunny under G = z + CURVE r^2 by the layer step, and the platform height."""
    from neuralslicer.cage import CageConfig, make_cage
    from neuralslicer.layers import LayerConfig, slice_layers
    from neuralslicer.model.solid import implicit_solid
    from neuralslicer.model.spec import spec_for_file
    from neuralslicer.samples import surface_samples
    from neuralslicer.scalar_field import ScalarField

    solid = implicit_solid(spec_for_file(DATA / "bunny_closed_low_res.stl", "z"))
    cage = make_cage(solid, surface_samples(solid, 4000, k=10, seed=0).points, CageConfig(n_elements=10_000))
    centre = solid.bounds.mean(axis=0)
    v = cage.vertices
    G = v[:, 2] + CURVE * ((v[:, 0] - centre[0]) ** 2 + (v[:, 1] - centre[1]) ** 2)
    layers = slice_layers(solid, ScalarField(v, cage.tets, G, {}), LayerConfig())
    return layers.meshes, float(solid.platform_z)


def stored_layers(store: Path) -> tuple[list, float]:
    """The layers and the platform height of the first run in a store."""
    from replan_store import first_ref
    from neuralslicer.tasks.codec import read_layers, read_solid

    return read_layers(first_ref(store, "layers")).meshes, float(read_solid(first_ref(store, "model")).platform_z)


def planned_print(store: Path | None) -> Path:
    """The print to check (cached .npz in the temporary folder): toolpaths as the toolpath step plans them up to
    the check."""
    from neuralslicer.motion import load_profile
    from neuralslicer.motion.planning import merge_short_moves
    from neuralslicer.motion.reorient import clamp_to_platform
    from neuralslicer.toolpath import ToolpathConfig, toolpaths
    from neuralslicer.toolpath.beads import hold_beads

    tag = hashlib.sha256(str(store.resolve() if store else f"bunny-curved-{CURVE}").encode()).hexdigest()[:12]
    cache = Path(tempfile.gettempdir()) / f"neuralslicer-bench-collision-{tag}.npz"
    if cache.is_file():
        return cache
    layers, platform_z = stored_layers(store) if store else curved_bunny_layers()
    profile, cfg = load_profile("table_bc_linuxcnc"), ToolpathConfig()
    tp = toolpaths(layers, platform_z=platform_z, config=cfg, t_max=1.0)
    tp, _ = hold_beads(tp, profile.nozzle.bead_thickness_mm)
    tp, _ = merge_short_moves(tp, profile)
    tp, _ = clamp_to_platform(tp, profile.nozzle, platform_z, cfg.collision_tilt_deg)
    np.savez(cache, platform_z=platform_z, **{k: getattr(tp, k) for k in FIELDS})
    return cache


def check_prefix(cache: Path, size: int, workers: int | None) -> dict:
    """Build the structure and check the first layers of the print holding about ``size`` waypoints (own process)."""
    from neuralslicer.motion import load_profile, scan
    from neuralslicer.motion.collision import check_collisions, travel_samples
    from neuralslicer.motion.material import PrintedMaterial
    from neuralslicer.toolpath.types import Toolpaths

    scan.WORKERS = workers
    data = np.load(cache)
    layer = data["layer"]
    cut = int(np.searchsorted(layer, layer[min(size, len(layer)) - 1], side="right"))
    tp = Toolpaths(**{k: data[k][:cut] for k in FIELDS})
    proc, peak, load = psutil.Process(), [0], os.getloadavg()[0]
    t0, c0 = time.perf_counter(), time.process_time()
    material = PrintedMaterial.of_toolpaths(tp)
    t1 = time.perf_counter()
    peak[0] = proc.memory_info().rss
    report = check_collisions(tp, load_profile("table_bc_linuxcnc").nozzle, float(data["platform_z"]), material=material)
    t2, c2 = time.perf_counter(), time.process_time()
    return {"waypoints": len(tp), "layers": tp.n_layers, "travel_poses": len(travel_samples(tp, 2.0)[2]),
            "material_points": len(material.points), "build_s": t1 - t0, "check_s": t2 - t1, "total_s": t2 - t0,
            "cpu_s": c2 - c0, "peak_gb": max(peak[0], proc.memory_info().rss) / 2**30,
            "collisions": report.count, "by_kind": report.summary(), "load_1min_at_start": load,
            "load_1min_at_end": os.getloadavg()[0], "workers": scan.workers()}


def main() -> None:
    """Plan (or reuse) the print, check each size in a fresh process, print the table, write the JSON."""
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--store", type=Path, default=None, help="a store whose first run's layers are checked")
    ap.add_argument("--sizes", default="1e6,2e6,5e6,1e7", help="waypoints (the print's first layers holding so many)")
    ap.add_argument("--workers", type=int, default=None, help="threads of the scans (default: the usable cores)")
    args = ap.parse_args()
    t = time.perf_counter()
    cache = planned_print(args.store)
    print(f"print: {cache} ({time.perf_counter() - t:.0f} s)", flush=True)
    rows = []
    for size in (int(float(s)) for s in args.sizes.split(",")):
        with ProcessPoolExecutor(1, mp_context=multiprocessing.get_context("spawn")) as pool:
            row = pool.submit(check_prefix, cache, size, args.workers).result()
        rows.append(row)
        print(f"{row['waypoints']:>11,} waypoints ({row['layers']} layers, {row['travel_poses']:,} travel poses): build "
              f"{row['build_s']:.1f} s, check {row['check_s']:.1f} s, {row['cpu_s']:.0f} s CPU, {row['peak_gb']:.1f} GB, "
              f"{row['collisions']:,} collisions, load {row['load_1min_at_start']:.2f}-{row['load_1min_at_end']:.2f}",
              flush=True)
    if len(rows) > 1:
        slope = np.polyfit(np.log([r["waypoints"] for r in rows]), np.log([r["total_s"] for r in rows]), 1)[0]
        print(f"growth: time ~ waypoints^{slope:.2f}")
    else:
        slope = None
    RESULTS.parent.mkdir(exist_ok=True)
    default_print = f"bunny_closed_low_res.stl, G = z + {CURVE} r^2"
    RESULTS.write_text(json.dumps({"print": shown(args.store) if args.store else default_print,
                                   "cpus": os.cpu_count(), "growth_exponent": slope, "rows": rows}, indent=2))


if __name__ == "__main__":
    main()
