"""Benchmark of print-head-aware optimisation (the global collision term L_GC).

    python benchmarks/bench_head_collision.py cost       # ring: time per step with and without L_GC
    python benchmarks/bench_head_collision.py ablation   # ring + bracket through the CLI, four variants
    python benchmarks/bench_head_collision.py all

`cost` builds the ring's cage and pool once and times one optimisation step (loss + backward) for
SF + PO + CA and for SF + PO + CA + GC, the search for L_GC's pairs near collision (every
`check_every` steps) and the pool's size. `ablation` slices the ring and the bracket with the CLI
(fresh store each) for: SF only (no CA, no retries, no blend), + CA, + CA + GC (the default), and
today's former default (SF + PO, retries with smoother fields and CA, then the planar blend); each
row gives the nozzle collisions of the first print and of the printed program, the overhang, SR
where it applies, the optimisation steps and the wall time of the whole command. Figures go to
benchmarks/results/bench_head_collision.json; docs/results.md and docs/neural.md quote them.
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

import numpy as np
import torch

REPO = Path(__file__).resolve().parents[1]
DATA = REPO / "neuralslicer" / "data"
RESULTS = Path(__file__).parent / "results" / "bench_head_collision.json"


def _merge(key: str, value) -> None:
    """Merge one part's figures into the JSON results file."""
    data = json.loads(RESULTS.read_text()) if RESULTS.exists() else {}
    data[key] = value
    data["machine"] = {"platform": platform.platform(), "cpu_count": os.cpu_count(),
                       "torch_threads": torch.get_num_threads(), "torch": torch.__version__}
    RESULTS.parent.mkdir(parents=True, exist_ok=True)
    RESULTS.write_text(json.dumps(data, indent=2))


def _timed(fn, repeat: int) -> float:
    """Mean seconds per call of fn over repeat calls (after one warm-up call)."""
    fn()
    t0 = time.perf_counter()
    for _ in range(repeat):
        fn()
    return (time.perf_counter() - t0) / repeat


def cost() -> dict:
    """Ring: seconds per step without and with L_GC, seconds per pair search, pool and pair counts."""
    from neuralslicer.cage import CageConfig, build_cage, interior_points
    from neuralslicer.model.solid import implicit_solid
    from neuralslicer.model.spec import spec_for_file
    from neuralslicer.neural import NeuralConfig
    from neuralslicer.neural.head_collision import collision_pool
    from neuralslicer.neural.problem import FieldProblem
    from neuralslicer.samples import surface_samples

    solid = implicit_solid(spec_for_file(DATA / "ring.tet", up="y"))
    B = surface_samples(solid, 20_000, k=10, seed=0)
    check = np.concatenate([B.points, interior_points(solid.H, solid.bounds, 20_000, 0)])
    cage = build_cage(solid.H, solid.bounds, solid.volume(), CageConfig(), check)
    rows = {}
    for label, w_gc in (("SF + PO + CA", 0.0), ("SF + PO + CA + GC", 1.0)):
        cfg = NeuralConfig.model_validate({"loss": {"w_gc": w_gc}})
        t0 = time.perf_counter()
        pool = collision_pool(solid.H, solid.bounds, solid.volume(), B.points, cfg.loss.gc_points) if w_gc else None
        problem = FieldProblem(cage.vertices, cage.tets, B, None, cfg, solid.platform_z, pool)
        setup = time.perf_counter() - t0
        fields = problem.new_fields()
        with torch.no_grad():  # a tilted, colliding field: a few hundred random-direction steps
            for p in fields.parameters():
                p.add_(0.02 * torch.randn_like(p))

        def step() -> None:
            total, _ = problem.evaluate(fields)
            fields.zero_grad()
            total.backward()

        row = {"setup_s": setup, "step_s": _timed(step, 20), "n_cage_tets": int(len(cage.tets))}
        if problem.head is not None:
            row["pair_search_s"] = _timed(lambda: problem.refresh_collisions(fields), 5)
            row["active_pairs"] = problem.refresh_collisions(fields)
            row["pairs_within_reach"] = int(len(problem.head.near))
            row["pool_points"] = len(problem.head)
            row["pool_spacing_mm"] = problem.head.length
            row["step_with_search_amortised_s"] = row["step_s"] + row["pair_search_s"] / cfg.optim.check_every
        rows[label] = row
    base, gc = rows["SF + PO + CA"], rows["SF + PO + CA + GC"]
    print(f"ring cage {base['n_cage_tets']} tets, pool {gc['pool_points']} points at {gc['pool_spacing_mm']:.2f} mm, "
          f"{gc['pairs_within_reach']:,} pairs within the head's reach, {gc['active_pairs']:,} active")
    print("| objectives | s / step | pair search s (every 10 steps) | s / step amortised |")
    print("| --- | --- | --- | --- |")
    print(f"| SF + PO + CA | {base['step_s']:.4f} | - | {base['step_s']:.4f} |")
    print(f"| SF + PO + CA + GC | {gc['step_s']:.4f} | {gc['pair_search_s']:.3f} | {gc['step_with_search_amortised_s']:.4f} |")
    _merge("cost", rows)
    return rows


VARIANTS = {
    "SF only": ["--collision-retries", "0", "--collision-fallback", "none"],
    "+ CA": ["--collision-retries", "0", "--collision-fallback", "none"],
    "+ CA + GC (default)": [],
    "former default: retries + blend": [],
}


def _objectives(variant: str, strength: bool) -> str:
    """The --objectives of a variant (with sr for a model with loads)."""
    base = {"SF only": "sf,po", "+ CA": "sf,po,ca", "+ CA + GC (default)": "sf,po,gc,ca",
            "former default: retries + blend": "sf,po"}[variant]
    return base + (",sr" if strength else "")


def _printed_map(store: Path, metrics: dict):  # noqa: ANN202 - a CollisionMap
    """Where the head of the printed program hits (the print whose counts match the metrics)."""
    from neuralslicer.storage import ArtifactStore, ArtifactRef
    from neuralslicer.tasks.codec import read_collision_map

    st = ArtifactStore(store)
    for group in sorted(store.glob("*/motion/*")):
        path = str(group.relative_to(store))
        if st.exists(path):
            m = st.attrs(path)["metrics"]
            if m["n_collisions"] == metrics["n_collisions"] and m["n_waypoints"] == metrics["n_waypoints"]:
                return read_collision_map(ArtifactRef(str(store), path, ""))
    raise RuntimeError(f"{store}: no print matches the metrics")


def _slice(model: list[str], variant: str, strength: bool, extra: list[str], maps: dict) -> dict:
    """One CLI slice in a fresh folder: its metrics and wall time (and its collision map into maps)."""
    with tempfile.TemporaryDirectory() as tmp:
        cmd = [sys.executable, "-m", "neuralslicer.cli", "slice", *model, "--out", f"{tmp}/out",
               "--objectives", _objectives(variant, strength), *VARIANTS[variant], *extra]
        t0 = time.perf_counter()
        subprocess.run(cmd, check=True, stdout=subprocess.DEVNULL, cwd=REPO)
        wall = time.perf_counter() - t0
        m = json.loads(Path(tmp, "out", "metrics.json").read_text())
        maps[f"{variant}: {m['n_collisions']:,} collisions"] = _printed_map(Path(tmp, "out", "store.zarr"), m)
    first = m.get("collision_resolution.0.collisions", m.get("n_collisions"))
    return {"wall_s": wall, "first_print_collisions": first, "collisions": m.get("n_collisions"),
            "overhang": m.get("sf.overhang_area_fraction"), "overhang_planar": m.get("sf.overhang_area_fraction_planar"),
            "sr": m.get("sr.satisfied_fraction"), "sr_planar": m.get("sr.satisfied_fraction_planar"),
            "steps": m.get("field.steps"), "blend_planar": m.get("field.blend_planar"),
            "n_prints": sum(1 for k in m if k.startswith("collision_resolution.") and k.endswith(".stage")) or 1}


def ablation(models: list[str]) -> dict:
    """The four variants on the ring and the bracket (CLI, fresh store each)."""
    cases = {
        "ring": ([str(DATA / "ring.tet"), "--up", "y"], False, []),
        "bracket": (["neuralslicer/examples/bracket/model.yaml"], True, ["--max-steps", "200"]),
    }
    out = json.loads(RESULTS.read_text()).get("ablation", {}) if RESULTS.exists() else {}
    for name in models:
        model, strength, extra = cases[name]
        maps: dict = {}
        out[name] = {v: _slice(model, v, strength, extra, maps) for v in VARIANTS}
        _merge("ablation", out)
        from neuralslicer.run.report import plot_collision_map

        plot_collision_map(RESULTS.with_name(f"bench_head_collision_{name}.png"), maps)
    print("| model | variant | collisions (first print -> printed) | overhang | SR | steps | time s |")
    print("| --- | --- | --- | --- | --- | --- | --- |")
    for name, rows in out.items():
        for v, r in rows.items():
            sr = "-" if r["sr"] is None else f"{100 * r['sr']:.1f} %"
            print(f"| {name} | {v} | {r['first_print_collisions']:,} -> {r['collisions']:,} | "
                  f"{100 * r['overhang']:.2f} % (planar {100 * r['overhang_planar']:.2f} %) | {sr} | {r['steps']} | "
                  f"{r['wall_s']:.0f} |")
    return out


def main() -> None:
    """Run the chosen parts."""
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("part", nargs="?", default="all", choices=("cost", "ablation", "all"))
    ap.add_argument("--models", default="ring,bracket", help="ablation models (ring, bracket)")
    args = ap.parse_args()
    if args.part in ("cost", "all"):
        cost()
    if args.part in ("ablation", "all"):
        ablation(args.models.split(","))


if __name__ == "__main__":
    main()
