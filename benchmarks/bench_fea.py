"""Benchmark of the voxel FEA: assembly + solve time and peak memory against voxel count.

Cases (each run in its own process so that the peak resident memory is its own):
  beam_10k, beam_100k   cantilever 100x10x10 mm (analytic box), clamped at x=0, 10 N down at the
                        tip; the tip deflection is compared with Euler-Bernoulli (2.0 mm)
  ring_100k             neuralslicer/data/ring.tet (up y), platform support, 100 N down on the top
                        2 mm; max von Mises, |T|, and the anisotropic check with planar layers
  beam_1m               (with --large) the cantilever at 1M voxels

The isotropic solves use the default solver (``auto``: matrix-free geometric multigrid + CG above
``direct_max_dofs``); the anisotropic check of the ring uses the assembled AMG path.

Usage: python benchmarks/bench_fea.py [--large] [--cases beam_10k,ring_100k] [--out DIR]
Prints a table and writes benchmarks/results/bench_fea.json (and the figures of the ring).
"""
from __future__ import annotations

import argparse
import json
import os
import platform
import resource
import subprocess
import sys
import time
from pathlib import Path

import numpy as np

HERE = Path(__file__).resolve().parent
RESULTS = HERE / "results"
RING = Path(os.environ.get("NEURALSLICER_DATA", Path(__file__).resolve().parents[1] / "neuralslicer" / "data")) / "ring.tet"


def _beam(voxels: int) -> dict:
    """Cantilever 100x10x10 at about ``voxels`` voxels."""
    from neuralslicer.fea import FEASpec, run_fea
    from neuralslicer.fea.grid import voxelize
    from neuralslicer.fea.shapes import BoxSolid

    spec = FEASpec.model_validate(dict(
        supports=[dict(box=[[-1, -1, -1], [1e-6, 11, 11]])],
        loads=[dict(box=[[100 - 1e-6, -1, -1], [101, 11, 11]], force_n=[0, 0, -10])],
        voxels=voxels))
    solid = BoxSolid((0, 0, 0), (100, 10, 10))
    t0 = time.perf_counter()
    voxelize(solid, voxels)                       # voxelisation alone (cheap for a box)
    t_vox = time.perf_counter() - t0
    t0 = time.perf_counter()
    res = run_fea(solid, spec)
    total = time.perf_counter() - t0
    tip = res.grid.nodes[:, 0] > res.grid.nodes[:, 0].max() - 1e-6
    # the voxel model is n*h thick: compare with Euler-Bernoulli of that section
    g = res.grid
    thick = (g.ijk[:, 2].max() + 1) * g.spacing
    width = (g.ijk[:, 1].max() - g.ijk[:, 1].min() + 1) * g.spacing
    length = (g.ijk[:, 0].max() - g.ijk[:, 0].min() + 1) * g.spacing
    eb = 10 * length ** 3 / (3 * 2000 * width * thick ** 3 / 12)
    d = float(-res.displacement[tip, 2].mean())
    return {"voxels": g.n_voxels, "voxel_mm": g.spacing, "dofs": res.info["n_dofs"],
            "nnz": res.info["nnz"], "solver": res.info["solver"],
            "iterations": res.info["iterations"], "voxelize_s": t_vox,
            "assembly_s": res.info["assembly_s"], "solve_s": res.info["solve_s"],
            "total_s": total, "tip_mm": d, "euler_bernoulli_mm": eb, "tip_error": d / eb - 1,
            "max_von_mises_mpa": float(res.von_mises.max())}


def _ring(voxels: int, out: Path) -> dict:
    """Ring (up y) on the platform, 100 N down on the top 2 mm; isotropic and planar-layer runs."""
    from neuralslicer.fea import FEASpec, run_fea, stress_samples
    from neuralslicer.verify import verify_layers
    from neuralslicer.fea.io import plot_field, write_fea_outputs
    from neuralslicer.model import implicit_solid, spec_for_file

    solid = implicit_solid(spec_for_file(RING, up="y"))
    top = float(solid.bounds[1, 2])
    spec = FEASpec.model_validate(dict(
        supports=[dict(platform=True)],
        loads=[dict(box=[[-1e3, -1e3, top - 2.0], [1e3, 1e3, top + 1.0]], force_n=[0, 0, -100])],
        voxels=voxels))
    t0 = time.perf_counter()
    res = run_fea(solid, spec)
    total = time.perf_counter() - t0
    T = stress_samples(res, spec.top_fraction)
    metrics = write_fea_outputs(res, out / "ring")
    t1 = time.perf_counter()
    planar = verify_layers(solid, spec, lambda p: np.tile([0.0, 0.0, 1.0], (len(p), 1)),
                           reference=res)
    t_aniso = time.perf_counter() - t1
    plot_field(planar["result"], planar["strain"], RESULTS / "bench_fea_ring_planar_strain.png",
               label="max |principal strain| (planar layers)")
    plot_field(res, res.von_mises, RESULTS / "bench_fea_ring_von_mises.png")
    return {"voxels": res.grid.n_voxels, "voxel_mm": res.grid.spacing,
            "dofs": res.info["n_dofs"], "nnz": res.info["nnz"], "solver": res.info["solver"],
            "iterations": res.info["iterations"], "assembly_s": res.info["assembly_s"],
            "solve_s": res.info["solve_s"], "total_s": total,
            "max_von_mises_mpa": metrics["fea.max_von_mises_mpa"],
            "max_displacement_mm": metrics["fea.max_displacement_mm"],
            "T_size": len(T), "T_max_abs_stress_mpa": float(np.abs(T.stress).max()),
            "T_min_abs_stress_mpa": float(np.abs(T.stress).min()),
            "dropped_voxels": res.info["dropped_voxels"],
            "planar_max_strain": planar["max_strain"],
            "planar_max_strain_p99": planar["max_strain_p99"], "anisotropic_s": t_aniso}


CASES = {"beam_10k": lambda out: _beam(10_000), "beam_100k": lambda out: _beam(100_000),
         "ring_100k": lambda out: _ring(100_000, out), "beam_1m": lambda out: _beam(1_000_000)}


def _child(case: str, out: Path) -> None:
    """Run one case and print its JSON line with the peak resident memory."""
    row = CASES[case](out)
    row["peak_rss_mb"] = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024.0
    print("RESULT " + json.dumps(row))


def main() -> None:
    """Run the cases in subprocesses, print the table, write the JSON."""
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--large", action="store_true", help="also run 1M voxels")
    ap.add_argument("--cases", default=None, help="comma-separated subset of " + ",".join(CASES))
    ap.add_argument("--out", default="runs/bench_fea", help="folder for the .vtu/.png outputs")
    ap.add_argument("--json", default=str(RESULTS / "bench_fea.json"))
    ap.add_argument("--child", default=None, help=argparse.SUPPRESS)
    args = ap.parse_args()
    out = Path(args.out)
    if args.child:
        _child(args.child, out)
        return
    names = args.cases.split(",") if args.cases else [c for c in CASES if c != "beam_1m"]
    if args.large and "beam_1m" not in names:
        names.append("beam_1m")
    rows = {}
    load_before = os.getloadavg()                 # the machine may be shared: record its load
    for name in names:
        if name.startswith("ring") and not RING.is_file():
            print(f"skip {name}: {RING} not found")
            continue
        p = subprocess.run([sys.executable, __file__, "--child", name, "--out", str(out)],
                           capture_output=True, text=True)
        line = [ln for ln in p.stdout.splitlines() if ln.startswith("RESULT ")]
        if p.returncode != 0 or not line:
            print(f"{name}: failed\n{p.stderr[-2000:]}")
            continue
        rows[name] = json.loads(line[-1][7:])
    head = f"{'case':<10} {'voxels':>8} {'dofs':>8} {'solver':>6} {'it':>3} {'assemble s':>10} " \
           f"{'solve s':>8} {'total s':>8} {'peak MB':>8}  result"
    print(head)
    print("-" * len(head))
    for name, r in rows.items():
        extra = (f"tip {r['tip_mm']:.4f} mm, E-B {r['euler_bernoulli_mm']:.4f} "
                 f"({100 * r['tip_error']:+.2f} %)" if "tip_mm" in r else
                 f"max VM {r['max_von_mises_mpa']:.3f} MPa, |T| {r['T_size']}, planar max "
                 f"strain {r['planar_max_strain']:.3g}")
        print(f"{name:<10} {r['voxels']:>8} {r['dofs']:>8} {r['solver']:>6} {r['iterations']:>3} "
              f"{r['assembly_s']:>10.2f} {r['solve_s']:>8.2f} {r['total_s']:>8.2f} "
              f"{r['peak_rss_mb']:>8.0f}  {extra}")
    meta = {"machine": platform.platform(), "python": platform.python_version(),
            "cpus": os.cpu_count(), "date": time.strftime("%Y-%m-%dT%H:%M:%SZ", time.gmtime()),
            "load_avg_before": list(load_before), "load_avg_after": list(os.getloadavg())}
    path = Path(args.json)
    path.parent.mkdir(parents=True, exist_ok=True)
    old = json.loads(path.read_text()) if path.is_file() else {}
    old.setdefault("cases", {}).update(rows)
    old["meta"] = meta
    tmp = path.with_suffix(".json.tmp")
    tmp.write_text(json.dumps(old, indent=2) + "\n")
    os.replace(tmp, path)


if __name__ == "__main__":
    main()
