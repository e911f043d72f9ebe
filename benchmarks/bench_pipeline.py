"""Benchmark of the foundation steps on the ring: signed distance, cage generation, layer extraction, whole slice.

    .venv/bin/python benchmarks/bench_pipeline.py

Prints a table and writes benchmarks/results/bench_pipeline.json. The whole slice runs the CLI
(`neuralslicer slice ring.tet --up y --objectives none`) in a subprocess, Prefect start-up included.
"""
from __future__ import annotations

import json
import os
import platform
import resource
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

from neuralslicer.cage import CageConfig, build_cage, interior_points
from neuralslicer.layers import LayerConfig, choose_isovalues, extract_layers
from neuralslicer.model import implicit_solid, spec_for_file
from neuralslicer.scalar_field import ScalarField

ROOT = Path(__file__).resolve().parent
RING = ROOT.parent / "neuralslicer" / "data" / "ring.tet"


def timed(fn, *args, **kwargs):  # noqa: ANN001, ANN002, ANN003, ANN201
    """(result, seconds) of one call."""
    t = time.perf_counter()
    out = fn(*args, **kwargs)
    return out, time.perf_counter() - t


def main() -> None:
    """Run every measurement and write the JSON."""
    solid = implicit_solid(spec_for_file(RING, "y"))
    rng = np.random.default_rng(0)
    lo, hi = solid.bounds
    q = rng.uniform(lo - 5, hi + 5, size=(1_000_000, 3))
    solid.H(q[:1000])
    _, t_sdf = timed(solid.H, q)
    rows: dict = {"signed_distance_1M_s": t_sdf}
    check = interior_points(solid.H, solid.bounds, 10_000)
    cages = {}
    for n in (5_000, 10_000, 20_000, 50_000):
        cage, t = timed(build_cage, solid.H, solid.bounds, solid.volume(), CageConfig(n_elements=n), check)
        cages[n] = cage
        rows[f"cage_{n}"] = {"seconds": t, "elements": int(len(cage.tets))}
    cage = cages[10_000]
    field = ScalarField.height(cage.vertices, cage.tets)
    cfg = LayerConfig()
    inside = interior_points(solid.H, solid.bounds, cfg.thickness_samples, seed=1)
    g, _, gn = field.sample(inside)
    isos, _ = choose_isovalues(g, gn, cfg)
    layers, t_layers = timed(extract_layers, cage.vertices, cage.tets, field.G, field.lpd(), solid.H, isos, cfg)
    rows["layers"] = {"seconds": t_layers, "n_layers": len(layers.meshes),
                      "triangles": int(sum(len(m.faces) for m in layers.meshes))}
    with tempfile.TemporaryDirectory() as tmp:
        env = {**os.environ, "PREFECT_HOME": str(Path(tmp) / "prefect")}
        cmd = [sys.executable, "-m", "neuralslicer.cli", "slice", str(RING), "--up", "y", "--out", str(Path(tmp) / "ring"),
               "--objectives", "none"]
        t = time.perf_counter()
        subprocess.run(cmd, check=True, env=env, capture_output=True)
        first = time.perf_counter() - t
        t = time.perf_counter()
        subprocess.run(cmd, check=True, env=env, capture_output=True)
        second = time.perf_counter() - t
        steps = {k: v for k, v in json.loads((Path(tmp) / "ring" / "metrics.json").read_text()).items() if k.startswith("wall_s.")}
    rows["ring_slice_identity"] = {"first_run_s": first, "cached_rerun_s": second, "steps_s": steps}
    rows["peak_rss_mb"] = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024
    rows["machine"] = {"cpus": os.cpu_count(), "python": platform.python_version(), "platform": platform.platform()}
    print(f"signed distance, 1M points (ring): {t_sdf:.2f} s")
    for n in cages:
        print(f"cage {n:>6}: {rows[f'cage_{n}']['elements']:>6} tets in {rows[f'cage_{n}']['seconds']:.1f} s")
    print(f"layers: {rows['layers']['n_layers']} layers, {rows['layers']['triangles']} triangles in {t_layers:.2f} s")
    print(f"ring slice (identity field, CLI): {first:.1f} s; cached rerun {second:.1f} s")
    out = ROOT / "results" / "bench_pipeline.json"
    out.parent.mkdir(exist_ok=True)
    out.write_text(json.dumps(rows, indent=2))


if __name__ == "__main__":
    main()
