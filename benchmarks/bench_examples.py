"""Every shipped example and every sample model of neuralslicer/data sliced with the default command: is the optimised
field printed itself, collision-free, without the planar blend?

    .venv/bin/python benchmarks/bench_examples.py [NAME ...]             # slice these (default: all), fresh stores
    .venv/bin/python benchmarks/bench_examples.py --parts                 # the real parts of issue 30: bunny, coin,
                                                                          # topopt_new4, lattice, hybrid
    .venv/bin/python benchmarks/bench_examples.py --collect NAME=DIR ...  # record runs made by hand (the CLI's DIR)

For each model: wall time of the whole command (a fresh store and Prefect home, its own local server stopping with
it), the load at the start and the end, the peak memory of the command's processes (sampled every 0.5 s),
optimisation steps and what stopped them, nozzle collisions of the first print and of the printed program, every
field printed on the way (refinements of L_GC, smoothing retries, blends), the overhang of B and on held-out points
of the surface (field and exported layers) against planar layers and the share of planar's overhang the exported
layers remove, SR where the model has a load case. Results are merged by name into
benchmarks/results/bench_examples.json (so subsets can be run at different times) and printed as a table.
"""
from __future__ import annotations

import json
import os
import subprocess
import sys
import tempfile
import threading
import time
from pathlib import Path

import psutil

ROOT = Path(__file__).resolve().parent
REPO = ROOT.parent
DATA = REPO / "neuralslicer" / "data"
EXAMPLES = REPO / "neuralslicer" / "examples"
RESULTS = ROOT / "results" / "bench_examples.json"


def shown(path: Path | str) -> str:
    """A path as the results record it: relative to the repository, else only its name (no machine path)."""
    path = Path(path).resolve()
    return path.relative_to(REPO).as_posix() if path.is_relative_to(REPO) else f"<outside the repository>/{path.name}"

#: three_axis_reprap with the paper's 1.0 mm nozzle settings
THREE_AXIS_1MM = Path(__file__).parent / "machines" / "three_axis_1mm.yaml"
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
    # three-axis non-planar (issue 41): slope-limited layers on a vertical head, against planar on the same printer;
    # the shipped three-axis head with the paper's 1.0 mm nozzle settings, as docs/results.md measured them
    "ring-3axis": (DATA / "ring.tet", ["--up", "y", "--machine", str(THREE_AXIS_1MM)]),
    "bunny-3axis": (DATA / "bunny_closed_low_res.stl", ["--machine", str(THREE_AXIS_1MM)]),
    "bracket-3axis": (EXAMPLES / "bracket" / "model.yaml", ["--max-steps", "200", "--verify", "--machine",
                                                            str(THREE_AXIS_1MM)]),
    # the 0.4 mm nozzle of the shipped RepRap profiles at its 0.2 mm layers (issue 43)
    "ring-0.4mm": (DATA / "ring.tet", ["--up", "y", "--machine", "reprap_5axis"]),
}
#: the three-axis comparisons: the same model and printer with planar layers (``--objectives none``)
THREE_AXIS = ("ring-3axis", "bunny-3axis", "bracket-3axis")
#: the real parts whose default runs issue 30 sets targets for
PARTS = ("bunny", "coin", "topopt_new4", "lattice", "hybrid")


def summary(out: Path) -> dict:
    """The figures of one finished run from its output folder."""
    m = json.loads((out / "metrics.json").read_text())
    stages = sorted({int(k.split(".")[1]) for k in m if k.startswith("collision_resolution.")})
    prints = [{f: m[f"collision_resolution.{i}.{f}"] for f in ("stage", "collisions", "overhang_area_fraction")}
              for i in stages]
    row = {
        "steps": m.get("field.steps"), "stop": m.get("field.stop"), "layers": m.get("n_layers"),
        "waypoints": m.get("n_waypoints"),
        "first_print_collisions": prints[0]["collisions"] if prints else m.get("n_collisions"),
        "printed_collisions": m.get("n_collisions"), "prints": prints or [{"stage": "optimised",
                                                                          "collisions": m.get("n_collisions"),
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
        **{k: v for k, v in m.items() if k.startswith(("three_axis.", "fea."))},
    }
    run = out / "run.json"
    if run.is_file():
        row["wall_s"] = json.loads(run.read_text()).get("wall_s")
    return row


def peak_memory(proc: subprocess.Popen, stop: threading.Event, peak: list[int]) -> None:
    """The largest resident memory of a process and its descendants together, sampled every 0.5 s into peak[0]."""
    try:
        root = psutil.Process(proc.pid)
    except psutil.Error:
        return
    while not stop.wait(0.5):
        total = 0
        try:
            for p in [root, *root.children(recursive=True)]:
                try:
                    total += p.memory_info().rss
                except psutil.Error:
                    continue
        except psutil.Error:
            return
        peak[0] = max(peak[0], total)


def slice_one(name: str, tmp: Path) -> dict:
    """Slice one model with the default command in a fresh store under tmp; its figures."""
    model, extra = MODELS[name]
    env = {**os.environ, "PREFECT_HOME": str(tmp / "prefect"), "NEURALSLICER_API_IDLE_S": "0"}
    out = tmp / name
    load = os.getloadavg()[0]
    start = time.perf_counter()
    peak, stop = [0], threading.Event()
    with open(tmp / "stderr.txt", "w") as err:
        proc = subprocess.Popen([sys.executable, "-m", "neuralslicer.cli", "slice", str(model), *extra, "--out", str(out)],
                                env=env, stdout=subprocess.DEVNULL, stderr=err, cwd=REPO)
        watch = threading.Thread(target=peak_memory, args=(proc, stop, peak), daemon=True)
        watch.start()
        code = proc.wait()
    wall = time.perf_counter() - start
    stop.set()
    watch.join()
    if code != 0:
        raise SystemExit(f"{name}: the slice failed ({code}): {(tmp / 'stderr.txt').read_text()[-2000:]}")
    row = summary(out)
    row.update(wall_s=wall, load_avg_1min_at_start=load, load_avg_1min_at_end=os.getloadavg()[0],
               peak_memory_gb=peak[0] / 2**30, command=" ".join(
                   ["neuralslicer slice", shown(model), *extra]))
    return row


def reduction(r: dict) -> float | None:
    """The share of planar layers' held-out overhang the exported layers remove."""
    ours, planar = r.get("overhang_heldout_layers"), r.get("overhang_heldout_planar")
    return None if ours is None or not planar else 1.0 - ours / planar


def fmt(name: str, r: dict) -> str:
    """One table row."""
    pct = lambda v: "-" if v is None else f"{100 * v:.2f} %"  # noqa: E731
    way = " -> ".join(str(p["collisions"]) for p in r["prints"])
    mem = f"{r['peak_memory_gb']:.1f} GB" if r.get("peak_memory_gb") else "-"
    load = f"{r.get('load_avg_1min_at_start', float('nan')):.1f}"
    return (f"| {name} | {r.get('wall_s', 0):.0f} s | {r['steps']} ({r.get('stop')}) | {way} | {r['blend_planar']:g} | "
            f"{pct(r['overhang'])} ({pct(r['overhang_planar'])}) | {pct(r['overhang_heldout_layers'])} "
            f"({pct(r['overhang_heldout_planar'])}, {pct(reduction(r))} removed) | {pct(r['sr'])} | {mem} | {load} |")


def main(argv: list[str]) -> None:
    """Slice or collect, merge into the JSON, print the table."""
    results = json.loads(RESULTS.read_text()) if RESULTS.is_file() else {"models": {}}
    if argv[:1] == ["--collect"]:
        for item in argv[1:]:
            name, folder = item.split("=", 1)
            results["models"][name] = {**summary(Path(folder)), "collected_from": shown(folder)}
    else:
        for name in (list(PARTS) if argv == ["--parts"] else argv) or list(MODELS):
            with tempfile.TemporaryDirectory() as tmp:
                results["models"][name] = slice_one(name, Path(tmp))
            print(fmt(name, results["models"][name]), flush=True)
    results["machine"] = {"cpus": os.cpu_count()}
    RESULTS.parent.mkdir(exist_ok=True)
    tmp = RESULTS.with_suffix(".json.tmp")
    tmp.write_text(json.dumps(results, indent=2))
    tmp.replace(RESULTS)
    print("| model | wall | steps (stop) | collisions of each print | blend t | overhang on B (planar) | held out, "
          "layers (planar, share removed) | SR | peak memory | load |")
    print("| --- | --- | --- | --- | --- | --- | --- | --- | --- | --- |")
    for name, r in results["models"].items():
        print(fmt(name, r))


if __name__ == "__main__":
    main(sys.argv[1:])
