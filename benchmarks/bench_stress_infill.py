"""Benchmark: what stress-following infill costs the toolpath step (toolpaths, beads, collision check, tilt, motion).

    .venv/bin/python benchmarks/bench_stress_infill.py [--cases bracket,bridge,ring] [--run bracket=runs/demo,ring=runs/ring]
                                                       [--repeats 3]

For each case the model's FEA gives the stress field, and the same layers are planned (``plan_print``) with the
zig-zag and with the stress-following infill, alternately, ``--repeats`` times each; the best wall and CPU time of
each is kept. Layers: planar (G = z on a default cage), and with ``--run CASE=DIR`` the curved layers a slice of that
case wrote to its output folder (``layers/*.ply``: ``make demo``'s ``runs/demo`` for the bracket, a default
``neuralslicer slice neuralslicer/data/ring.tet --up y --out runs/ring`` for the ring). The ring
(shipped in neuralslicer/data) gets a load case: the platform held, 100 N down on its top 2 mm.

Prints a table with the load average and writes ``benchmarks/results/bench_stress_infill.json``.
"""
from __future__ import annotations

import argparse
import json
import os
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parent
EXAMPLES = ROOT.parent / "neuralslicer" / "examples"
DATA = ROOT.parent / "neuralslicer" / "data"
RESULTS = ROOT / "results" / "bench_stress_infill.json"


def case_spec(name: str):  # noqa: ANN201
    """The model spec of a case (the ring's with a load case added), or None when its data is missing."""
    from neuralslicer.fea import FEASpec
    from neuralslicer.model import implicit_solid, load_spec, spec_for_file

    if name in ("bracket", "bridge"):
        return load_spec(EXAMPLES / name / "model.yaml")
    ring = DATA / "ring.tet"
    if not ring.is_file():
        return None
    spec = spec_for_file(ring, up="y")
    top = float(implicit_solid(spec).bounds[1, 2])
    fea = FEASpec.model_validate(dict(supports=[dict(platform=True)],
                                      loads=[dict(box=[[-1e3, -1e3, top - 2.0], [1e3, 1e3, top + 1.0]],
                                                  force_n=[0, 0, -100])]))
    return spec.model_copy(update={"fea": fea})


def planar_layers(solid, cfg):  # noqa: ANN001, ANN201
    """Planar layers (G = z) of the solid on a default cage."""
    from neuralslicer.cage import make_cage
    from neuralslicer.layers import slice_layers
    from neuralslicer.samples import surface_samples
    from neuralslicer.scalar_field import ScalarField

    samples = surface_samples(solid, cfg.samples.n_samples, k=cfg.samples.k, seed=cfg.samples.seed)
    cage = make_cage(solid, samples.points, cfg.cage)
    return slice_layers(solid, ScalarField.height(cage.vertices, cage.tets), cfg.layers).meshes


def exported_layers(run: Path):  # noqa: ANN201
    """The layers a slice exported to ``run/layers`` (PLY, vertex normals = LPD), in print order."""
    import trimesh

    layers = []
    for path in sorted((run / "layers").glob("layer_*.ply")):
        mesh = trimesh.load(path, process=False)
        mesh.vertex_attributes["lpd"] = mesh.vertex_normals.copy()
        layers.append(mesh)
    return layers


def time_plans(layers, solid, stress, repeats: int) -> dict:  # noqa: ANN001
    """Best wall / CPU time of plan_print with each infill (alternating), as the toolpaths step calls it (the
    solid's H counts waypoints outside the part), and the prints' figures."""
    from neuralslicer.motion.plan import plan_print
    from neuralslicer.toolpath import ToolpathConfig

    best: dict[str, dict] = {}
    for _ in range(repeats):
        for infill in ("zigzag", "stress"):
            t0, c0 = time.perf_counter(), time.process_time()
            tp, _, metrics, _ = plan_print(layers, platform_z=solid.platform_z, solid_H=solid.H, toolpath_cfg=ToolpathConfig(infill=infill),
                                           stress=stress if infill == "stress" else None)
            wall, cpu = time.perf_counter() - t0, time.process_time() - c0
            row = best.setdefault(infill, {"wall_s": wall, "cpu_s": cpu})
            row["wall_s"], row["cpu_s"] = min(row["wall_s"], wall), min(row["cpu_s"], cpu)
            row.update(toolpaths_s=metrics["timings_s"]["toolpaths"], n_waypoints=len(tp), n_paths=metrics["n_paths"],
                       print_time_s=metrics["estimated_print_time_s"], collisions=metrics.get("n_collisions", 0),
                       stress_infill_fraction=tp.attrs.get("stress_infill_fraction"))
    z, s = best["zigzag"], best["stress"]
    return {"zigzag": z, "stress": s, "added_wall": s["wall_s"] / z["wall_s"] - 1,
            "added_cpu": s["cpu_s"] / z["cpu_s"] - 1}


def run_case(name: str, run: Path | None, repeats: int) -> list[dict]:
    """The rows of one case: planar layers, and the curved layers a slice of it exported to ``run``."""
    from neuralslicer.config import SliceConfig
    from neuralslicer.fea import run_fea
    from neuralslicer.fea.samples import stress_field
    from neuralslicer.model import implicit_solid

    spec = case_spec(name)
    if spec is None:
        print(f"{name}: skipped (no {DATA / 'ring.tet'})")
        return []
    solid = implicit_solid(spec)
    stress = stress_field(run_fea(solid, spec.fea), spec.fea.top_fraction)
    rows = [{"case": name, "layers": "planar", **time_plans(planar_layers(solid, SliceConfig()), solid, stress, repeats)}]
    if run is not None:
        rows.append({"case": name, "layers": f"curved ({run})",
                     **time_plans(exported_layers(run), solid, stress, repeats)})
    return rows


def main() -> None:
    """Run the cases, print the table, write the JSON."""
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--cases", default="bracket,bridge,ring")
    ap.add_argument("--run", default="", help="CASE=DIR,...: output folders of slices of the cases (curved layers)")
    ap.add_argument("--repeats", type=int, default=3)
    args = ap.parse_args()
    runs = {k: Path(v) for k, v in (item.split("=", 1) for item in args.run.split(",") if item)}
    rows = [r for name in args.cases.split(",") for r in run_case(name, runs.get(name), args.repeats)]
    load = os.getloadavg()
    print(f"load average {load[0]:.1f} {load[1]:.1f} {load[2]:.1f} on {os.cpu_count()} CPUs")
    print(f"{'case':8} {'layers':10} {'zig-zag s':>10} {'stress s':>9} {'added':>7} {'added CPU':>9} {'paths z/s':>12}")
    for r in rows:
        print(f"{r['case']:8} {r['layers'][:10]:10} {r['zigzag']['wall_s']:10.2f} {r['stress']['wall_s']:9.2f} "
              f"{100 * r['added_wall']:6.1f}% {100 * r['added_cpu']:8.1f}% "
              f"{r['zigzag']['n_paths']:>5}/{r['stress']['n_paths']:<6}")
    RESULTS.parent.mkdir(exist_ok=True)
    RESULTS.write_text(json.dumps({"load_average": load, "rows": rows}, indent=2))


if __name__ == "__main__":
    main()
