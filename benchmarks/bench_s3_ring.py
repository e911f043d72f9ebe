"""S3-Slicer against the Neural Slicer on the ring (the paper's Fig. 2 and Ring comparison): overhang
area fraction of B realised by each field, time and steps.

    python benchmarks/bench_s3_ring.py                       # S3 and NS (sf, po; default configs)
    python benchmarks/bench_s3_ring.py --skip-ns             # S3 only
    python benchmarks/bench_s3_ring.py --cache runs/ring.npz  # reuse the ring's samples and cage
    python benchmarks/bench_s3_ring.py --threads 1           # one torch thread for both (a busy machine)

Rows: planar layers (G = z), S3, NS with its default config (which stops once the overhang is at most
0.1 %) and NS run to its loss target (``optim.target_overhang = 0``). The inputs are those of
``bench_neural.py ring`` (ring.tet, up = y; 8k samples; a 5k-element cage
request). Both fields are judged by one function: the LPD grad G / |grad G| of the cage tet holding each
sample of B, overhang iff -n.d > sin 45 deg, platform samples excluded. For S3 the overhang its rotations
intend (the rotated normals in the deformed space) is reported too. Prints a table and writes
benchmarks/results/bench_s3_ring.json.
"""
from __future__ import annotations

import argparse
import json
import os
import platform
import sys
from pathlib import Path

import numpy as np
import torch

sys.path.insert(0, str(Path(__file__).resolve().parent))

from bench_neural import cached_ring_inputs  # noqa: E402

from neuralslicer.baselines.s3 import S3Config, optimise_s3  # noqa: E402
from neuralslicer.metrics import overhang_area_fraction  # noqa: E402
from neuralslicer.neural import NeuralConfig, optimise_field  # noqa: E402
from neuralslicer.neural.field import CageGeometry  # noqa: E402
from neuralslicer.samples import SurfaceSamples  # noqa: E402

RESULTS = Path(__file__).parent / "results" / "bench_s3_ring.json"
OBJECTIVES = ["sf", "po"]


def realised_overhang(d: dict[str, np.ndarray], G: np.ndarray) -> float:
    """Overhang area fraction of B for the field G (n,) at the cage vertices (LPD of each sample's tet)."""
    geo = CageGeometry.build(d["CV"], d["CT"])
    grad = np.einsum("ei,eij->ej", G[geo.tets], geo.bary_grads)
    lpd = grad / np.maximum(np.linalg.norm(grad, axis=1, keepdims=True), 1e-300)
    return overhang_area_fraction(d["N"], d["A"], d["F"].astype(bool), lpd[geo.locate(d["P"])], 45.0)


def main(argv: list[str] | None = None) -> None:
    """Command line entry point."""
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--cache", default="", help="npz to cache the ring inputs in (optional)")
    p.add_argument("--skip-ns", action="store_true", help="run the S3 baseline only")
    p.add_argument("--device", default="auto", help="torch device of both methods")
    p.add_argument("--threads", type=int, default=0, help="torch CPU threads of both methods (0: torch's default)")
    a = p.parse_args(argv)
    if a.threads > 0:
        torch.set_num_threads(a.threads)
    cache = Path(a.cache) if a.cache else None
    d = cached_ring_inputs(cache)
    B = SurfaceSamples(d["P"], d["N"], d["A"], d["K"], d["F"].astype(bool))
    pz = float(d["pz"])
    rows = [{"method": "planar", "overhang": realised_overhang(d, d["CV"][:, 2].copy()), "wall_s": 0.0, "steps": 0}]
    s3 = optimise_s3(d["CV"], d["CT"], B, None, OBJECTIVES, S3Config(device=a.device), pz)
    rows.append({"method": "s3", "overhang": realised_overhang(d, s3.G), "wall_s": s3.wall_time_s, "steps": s3.steps,
                 "converged": s3.converged,
                 "deformed_space_overhang": s3.satisfaction["deformed_space_overhang_area_fraction"],
                 "summary": s3.summary()})
    # NS with the default config stops once the overhang is at most optim.target_overhang (0.1 %);
    # 'neural_full' turns that stop off and runs to the loss target or the stall test
    ns_runs = {"neural": {}, "neural_full": {"optim": {"target_overhang": 0.0}}}
    for name, update in ([] if a.skip_ns else ns_runs.items()):
        cfg = NeuralConfig.model_validate({"device": a.device, **update}).for_objectives(OBJECTIVES)
        ns = optimise_field(d["CV"], d["CT"], B, config=cfg, platform_z=pz)
        rows.append({"method": name, "overhang": realised_overhang(d, ns.G), "wall_s": ns.wall_time_s,
                     "steps": ns.steps, "converged": ns.converged, "final": ns.final})
    planar = rows[0]["overhang"]
    print(f"\nring: {len(d['CT'])} cage tets, {len(d['P'])} samples, objectives {','.join(OBJECTIVES)}")
    print(f"{'method':>11} {'overhang %':>11} {'vs planar':>10} {'time s':>8} {'steps':>6} {'converged':>10}")
    for r in rows:
        rel = f"{100 * r['overhang'] / planar:9.1f}%" if planar > 0 else f"{'-':>10}"
        print(f"{r['method']:>11} {100 * r['overhang']:10.3f}% {rel} {r['wall_s']:8.1f} {r['steps']:>6}"
              f" {str(r.get('converged', '-')):>10}")
    if "deformed_space_overhang" in rows[1]:
        own = 100 * rows[1]["deformed_space_overhang"]
        print(f"(S3's own view, rotated normals in the deformed space: {own:.3f}%)")
    out = {"tets": int(len(d["CT"])), "vertices": int(len(d["CV"])), "samples": int(len(d["P"])),
           "objectives": OBJECTIVES, "rows": rows,
           "machine": {"platform": platform.platform(), "cpu_count": os.cpu_count(),
                       "torch_threads": torch.get_num_threads(), "torch": torch.__version__,
                       "cuda": torch.cuda.get_device_name() if torch.cuda.is_available() else None}}
    RESULTS.parent.mkdir(parents=True, exist_ok=True)
    RESULTS.write_text(json.dumps(out, indent=2))
    print(f"wrote {RESULTS}")


if __name__ == "__main__":
    main()
