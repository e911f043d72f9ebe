"""Every shipped example and every model of ../shared/data sliced with the default command: is the optimised
field printed itself, collision-free, without the planar blend?

    .venv/bin/python benchmarks/bench_examples.py [NAME ...]             # slice these (default: all), fresh stores
    .venv/bin/python benchmarks/bench_examples.py --collect NAME=DIR ...  # record runs made by hand (the CLI's DIR)

For each model: wall time, the load at the start, optimisation steps and what stopped them, nozzle collisions of
the first print and of the printed program, every field printed on the way (refinements of L_GC, smoothing
retries, blends), the overhang of B and on held-out points of the surface (field and exported layers) against
planar layers, SR where the model has a load case. Results are merged by name into
benchmarks/results/bench_examples.json (so subsets can be run at different times) and printed as a table.
"""
from __future__ import annotations

import json
import os
import subprocess
import sys
import tempfile
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parent
REPO = ROOT.parent
DATA = REPO.parent / "shared" / "data"
EXAMPLES = REPO / "neuralslicer" / "examples"
RESULTS = ROOT / "results" / "bench_examples.json"

#: name -> (model, extra CLI arguments); the .tet models are y-up
MODELS: dict[str, tuple[Path, list[str]]] = {
    "bracket": (EXAMPLES / "bracket" / "model.yaml", []),
    "bracket-demo": (EXAMPLES / "bracket" / "model.yaml", ["--max-steps", "200", "--verify"]),
    "fea_beam": (EXAMPLES / "fea_beam" / "spec.yaml", []),
    "tubes": (EXAMPLES / "tubes" / "model.yaml", []),
    "shell": (EXAMPLES / "shell" / "model.yaml", []),
    "hybrid": (EXAMPLES / "hybrid" / "model.yaml", []),
    "lattice": (EXAMPLES / "lattice" / "model.yaml", []),
    "points": (EXAMPLES / "points" / "spec.yaml", []),
    "points-scan": (EXAMPLES / "points" / "part_scan.pcd", []),
    "ring": (DATA / "ring.tet", ["--up", "y"]),
    "topopt_new4": (DATA / "topopt_new4.tet", ["--up", "y"]),
    "bunny": (DATA / "bunny_closed_low_res.stl", []),
    "coin": (DATA / "overhang_coin_closed_low_res.stl", []),
}


def summary(out: Path) -> dict:
    """The figures of one finished run from its output folder."""
    m = json.loads((out / "metrics.json").read_text())
    stages = sorted({int(k.split(".")[1]) for k in m if k.startswith("collision_resolution.")})
    prints = [{f: m[f"collision_resolution.{i}.{f}"] for f in ("stage", "collisions", "overhang_area_fraction")}
              for i in stages]
    row = {
        "steps": m.get("field.steps"), "stop": m.get("field.stop"), "layers": m.get("n_layers"),
        "waypoints": m.get("n_waypoints"),
        "first_print_collisions": prints[0]["collisions"] if prints else m.get("collisions"),
        "printed_collisions": m.get("collisions"), "prints": prints or [{"stage": "optimised",
                                                                          "collisions": m.get("collisions"),
                                                                          "overhang_area_fraction": m.get("sf.overhang_area_fraction")}],
        "blend_planar": m.get("field.blend_planar"), "overhang": m.get("sf.overhang_area_fraction"),
        "overhang_planar": m.get("sf.overhang_area_fraction_planar"),
        "overhang_heldout": m.get("sf.heldout.overhang_area_fraction"),
        "overhang_heldout_layers": m.get("sf.heldout.overhang_area_fraction_layers"),
        "overhang_heldout_planar": m.get("sf.heldout.overhang_area_fraction_planar"),
        "sr": m.get("sr.satisfied_fraction"), "sr_planar": m.get("sr.satisfied_fraction_planar"),
        "part_collisions": m.get("n_part_collisions"), "platform_collisions": m.get("n_platform_collisions"),
        "travel_collisions": m.get("n_travel_collisions"),
        "tilt_cleared": m.get("tilt.n_collisions_cleared"), "travels_lifted": m.get("travel.n_travels_lifted"),
        "travels_by_clearance_plane": m.get("travel.n_travels_by_clearance_plane"),
        "wall_s_steps": {k.split(".", 1)[1]: v for k, v in m.items() if k.startswith("wall_s.")},
        "commit": m.get("provenance.code.git_commit"),
    }
    run = out / "run.json"
    if run.is_file():
        row["wall_s"] = json.loads(run.read_text()).get("wall_s")
    return row


def slice_one(name: str, tmp: Path) -> dict:
    """Slice one model with the default command in a fresh store under tmp; its figures."""
    model, extra = MODELS[name]
    env = {**os.environ, "PREFECT_HOME": str(tmp / "prefect")}
    out = tmp / name
    load = os.getloadavg()[0]
    start = time.perf_counter()
    done = subprocess.run([sys.executable, "-m", "cli", "slice", str(model), *extra, "--out", str(out)],
                          env=env, capture_output=True, text=True, cwd=REPO)
    if done.returncode != 0:
        raise SystemExit(f"{name}: the slice failed ({done.returncode}): {done.stderr[-2000:]}")
    row = summary(out)
    row.update(wall_s=time.perf_counter() - start, load_avg_1min_at_start=load, command=" ".join(
        ["neuralslicer slice", str(model.relative_to(REPO.parent) if model.is_relative_to(REPO.parent) else model),
         *extra]))
    return row


def fmt(name: str, r: dict) -> str:
    """One table row."""
    pct = lambda v: "-" if v is None else f"{100 * v:.2f} %"  # noqa: E731
    way = " -> ".join(str(p["collisions"]) for p in r["prints"])
    return (f"| {name} | {r['steps']} ({r.get('stop')}) | {way} | {r['blend_planar']:g} | {pct(r['overhang'])} "
            f"({pct(r['overhang_planar'])}) | {pct(r['overhang_heldout_layers'])} ({pct(r['overhang_heldout_planar'])}) "
            f"| {pct(r['sr'])} | {r.get('wall_s', 0):.0f} s |")


def main(argv: list[str]) -> None:
    """Slice or collect, merge into the JSON, print the table."""
    results = json.loads(RESULTS.read_text()) if RESULTS.is_file() else {"models": {}}
    if argv[:1] == ["--collect"]:
        for item in argv[1:]:
            name, folder = item.split("=", 1)
            results["models"][name] = {**summary(Path(folder)), "collected_from": folder}
    else:
        for name in argv or list(MODELS):
            with tempfile.TemporaryDirectory() as tmp:
                results["models"][name] = slice_one(name, Path(tmp))
            print(fmt(name, results["models"][name]), flush=True)
    results["machine"] = {"cpus": os.cpu_count()}
    RESULTS.parent.mkdir(exist_ok=True)
    tmp = RESULTS.with_suffix(".json.tmp")
    tmp.write_text(json.dumps(results, indent=2))
    tmp.replace(RESULTS)
    print("| model | steps (stop) | collisions of each print | blend t | overhang on B (planar) | held out, layers "
          "(planar) | SR | wall |")
    print("| --- | --- | --- | --- | --- | --- | --- | --- |")
    for name, r in results["models"].items():
        print(fmt(name, r))


if __name__ == "__main__":
    main(sys.argv[1:])
