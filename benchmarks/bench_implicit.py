"""Benchmark of the implicit solid H: evaluation of H and ∇H, surface extraction, sampling B.

    .venv/bin/python benchmarks/bench_implicit.py [--points 1000000] [--samples 50000]

Models: the shipped hybrid example (mesh + shell + struts + tubes) and ring.tet (y up).
Prints a table and writes benchmarks/results/bench_implicit.json.
"""
from __future__ import annotations

import argparse
import json
import os
import platform
import time
from pathlib import Path
from typing import Any, Callable

import numpy as np

import neuralslicer
from neuralslicer.model import Solid, implicit_solid, load_spec, spec_for_file
from neuralslicer.samples import surface_samples

ROOT = Path(__file__).resolve().parent
RING = Path(__file__).resolve().parents[1] / "neuralslicer" / "data" / "ring.tet"


def timed(fn: Callable[..., Any], *args: Any, **kwargs: Any) -> tuple[Any, float]:
    """(result, seconds) of one call."""
    t = time.perf_counter()
    out = fn(*args, **kwargs)
    return out, time.perf_counter() - t


def bench_model(name: str, solid: Solid, n_points: int, n_samples: int) -> dict:
    """Time every operation on one model."""
    row: dict = {"model": name, "components": [c.attrs()["type"] for c in solid.components]}
    surf, row["surface_s"] = timed(solid.surface)
    row["surface_faces"] = int(len(surf.faces))
    lo, hi = solid.bounds
    pad = 0.1 * (hi - lo)
    x = np.random.default_rng(0).uniform(lo - pad, hi + pad, size=(n_points, 3))
    _, row["H_s"] = timed(solid.H, x)
    _, row["H_grad_s"] = timed(solid.value_and_grad, x)
    row["points"] = n_points
    row["H_points_per_s"] = n_points / row["H_s"]
    B, row["samples_s"] = timed(surface_samples, solid, n_samples)
    row["samples"] = n_samples
    row["samples_residual_mm"] = B.residual
    row["samples_on_platform"] = int(B.on_platform.sum())
    return row


def main() -> None:
    """Run the benchmark, print the table, write the JSON."""
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--points", type=int, default=1_000_000)
    ap.add_argument("--samples", type=int, default=50_000)
    args = ap.parse_args()
    examples = Path(neuralslicer.__file__).parent / "examples"
    rows = []
    for name, make in [("hybrid", lambda: implicit_solid(load_spec(examples / "hybrid" / "model.yaml"))),
                       ("ring.tet", lambda: implicit_solid(spec_for_file(RING, up="y")))]:
        solid, load_s = timed(make)
        row = bench_model(name, solid, args.points, args.samples)
        row["load_s"] = load_s
        rows.append(row)
    header = f"{'model':10} {'load s':>7} {'surface s':>9} {'faces':>8} {'H 1M s':>7} {'H+∇H s':>7} {'B 50k s':>8} {'B resid mm':>10}"
    print(header)
    print("-" * len(header))
    for r in rows:
        print(f"{r['model']:10} {r['load_s']:7.2f} {r['surface_s']:9.2f} {r['surface_faces']:8d} "
              f"{r['H_s']:7.2f} {r['H_grad_s']:7.2f} {r['samples_s']:8.2f} {r['samples_residual_mm']:10.1e}")
    out = {"machine": {"cpu_count": os.cpu_count(), "platform": platform.platform(),
                       "note": "CPU shared with other jobs while measuring"},
           "points": args.points, "samples": args.samples, "results": rows}
    (ROOT / "results").mkdir(exist_ok=True)
    (ROOT / "results" / "bench_implicit.json").write_text(json.dumps(out, indent=2))


if __name__ == "__main__":
    main()
