"""The ring with the default command, mesh in to G-code out, in fresh stores (another fTetWild cage each run:
``cage.seed`` = the run's number).

    .venv/bin/python benchmarks/bench_ring_default.py [RUNS]

For each run: wall time of `neuralslicer slice ring.tet --up y` (Prefect start-up included), the
optimisation steps, nozzle collisions of the first print, whether a retry or the planar blend was
needed, the overhang area fraction against planar layers, and each step's wall time. Writes
benchmarks/results/bench_ring_default.json and prints a table. Run it on a quiet machine: it is the
figure behind the ring rows of docs/results.md.
"""
from __future__ import annotations

import json
import os
import platform
import subprocess
import sys
import tempfile
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parent
RING = ROOT.parent / "neuralslicer" / "data" / "ring.tet"
RESULTS = ROOT / "results" / "bench_ring_default.json"


def one_run(tmp: Path, seed: int = 0) -> dict:
    """One default ring slice in a fresh store, its cage seeded with ``seed``: its figures."""
    # the cage cache off and a cage seed per run: every run meets another fTetWild cage, as a new model would
    env = {**os.environ, "PREFECT_HOME": str(tmp / "prefect"), "NEURALSLICER_CACHE_DIR": "off"}
    config = tmp / "seed.yaml"
    config.write_text(f"cage: {{seed: {seed}}}\n")
    out = tmp / "ring"
    load = os.getloadavg()[0]
    start = time.perf_counter()
    done = subprocess.run([sys.executable, "-m", "neuralslicer.cli", "slice", str(RING), "--up", "y", "--out", str(out),
                           "--config", str(config)],
                          env=env, capture_output=True, text=True, cwd=ROOT.parent)
    wall = time.perf_counter() - start
    if done.returncode != 0:
        raise SystemExit(f"the ring slice failed ({done.returncode}): {done.stderr[-2000:]}")
    m = json.loads((out / "metrics.json").read_text())
    prints = _prints(out / "store.zarr")
    stages = sorted({int(k.split(".")[1]) for k in m if k.startswith("collision_resolution.")})
    return {
        "wall_s": wall, "steps": m["field.steps"], "layers": m["n_layers"], "waypoints": m["n_waypoints"],
        "first_print_collisions": m["collision_resolution.0.collisions"] if stages else m["n_collisions"],
        "printed_collisions": m["n_collisions"], "fields_printed": max(1, len(stages)),
        "blend_planar": m["field.blend_planar"], "overhang": m["sf.overhang_area_fraction"],
        "overhang_planar": m["sf.overhang_area_fraction_planar"],
        "steps_s": {k.split(".", 1)[1]: v for k, v in m.items() if k.startswith("wall_s.")},
        "tilt": {k.split(".", 1)[1]: v for k, v in m.items() if k.startswith("tilt.")},
        "reach": {k.split(".", 1)[1]: v for k, v in m.items() if k.startswith("reach.")},
        "travel_collisions": m.get("n_travel_collisions"), "load_avg_1min_at_start": load,
        "overhang_heldout": m.get("sf.heldout.overhang_area_fraction"),
        "overhang_heldout_layers": m.get("sf.heldout.overhang_area_fraction_layers"),
        "overhang_heldout_planar": m.get("sf.heldout.overhang_area_fraction_planar"),
        "beads_outside_range": m.get("beads.fraction_outside_range"),
        "estimated_print_time_s": m.get("estimated_print_time_s"),
        "prints": prints,
    }


def _prints(store: Path) -> list[dict]:
    """Every print of the run, in the order made: collisions by kind and what the travel lift and tilt did."""
    from neuralslicer.storage import ArtifactStore

    st = ArtifactStore(store)
    rows = []
    made = sorted(st.children("ring/motion"), key=lambda d: (store / "ring" / "motion" / d).stat().st_mtime)
    for d in made:
        a = st.attrs(f"ring/motion/{d}")
        pm = a["metrics"]
        rows.append({"made_at_s": a.get("wall_s"), **{k: pm.get(k) for k in (
            "n_collisions", "n_part_collisions", "n_platform_collisions", "n_travel_collisions", "n_waypoints",
            "travel_lift", "axis_tilt", "axis_reach", "timings_s")}})
    return rows


def main(runs: int = 3) -> None:
    """Run the ring `runs` times and write the JSON."""
    rows = []
    for i in range(runs):
        with tempfile.TemporaryDirectory() as tmp:
            rows.append(one_run(Path(tmp), seed=i))
        r = rows[-1]
        print(f"run {i + 1}: {r['wall_s']:.0f} s, {r['steps']} steps, first print {r['first_print_collisions']} "
              f"collisions, {r['fields_printed']} field(s) printed, blend {r['blend_planar']:g}, overhang "
              f"{100 * r['overhang']:.3f} % (planar {100 * r['overhang_planar']:.2f} %), field "
              f"{r['steps_s'].get('field', 0):.0f} s, toolpaths {r['steps_s'].get('toolpaths', 0):.0f} s, tilt {r['tilt']}, "
              f"reach {r['reach']}, load {r['load_avg_1min_at_start']:.1f}, held-out overhang "
              f"{r['overhang_heldout']} (layers {r['overhang_heldout_layers']}, planar {r['overhang_heldout_planar']}), "
              f"beads outside range {r['beads_outside_range']}")
        for pr in r["prints"]:
            print("   print:", {k: pr[k] for k in ("n_collisions", "n_part_collisions", "n_platform_collisions",
                                                   "n_travel_collisions", "travel_lift", "axis_tilt")})
    RESULTS.parent.mkdir(exist_ok=True)
    RESULTS.write_text(json.dumps({"runs": rows, "machine": {"cpus": os.cpu_count(), "python": platform.python_version(),
                                                             "platform": platform.platform()}}, indent=2))


if __name__ == "__main__":
    main(int(sys.argv[1]) if len(sys.argv) > 1 else 3)
