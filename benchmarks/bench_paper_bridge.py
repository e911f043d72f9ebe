"""The paper's Bridge comparison: the Neural Slicer, the faithful S3-Slicer and planar layers, summarised from runs.

The runs (``neuralslicer/examples/paper_bridge/README.md``), one store for all, SR only as the paper, each field
printed as computed (no collision re-optimisation: the paper's Bridges were printed with PVA supports)::

    M=neuralslicer/examples/paper_bridge; S="--config $M/config.yaml --store S --verify \\
      --collision-refinements 0 --collision-retries 0 --collision-fallback none"
    neuralslicer slice $M/model.yaml $S --out neural
    neuralslicer slice $M/model.yaml $S --out s3 --method s3
    neuralslicer slice $M/model.yaml $S --out neural_zz --infill zigzag
    neuralslicer slice $M/model.yaml $S --out s3_zz --method s3 --infill zigzag
    neuralslicer slice $M/model.yaml --config $M/config_head.yaml --store S --verify --out neural_head_terms

``--verify`` gives planar layers with zig-zag and with stress infill beside each. Besides each run's metrics this
reads the per-voxel strain of its verification from the store and adds the maximum strain away from the load and
support patches (voxels farther than ``--margin`` mm from their boxes): the maximum itself sits under the nodal load
for every part.

Usage: python benchmarks/bench_paper_bridge.py --store S NAME=DIR ...
Writes benchmarks/results/bench_paper_bridge.json.
"""
from __future__ import annotations

import argparse
import json
import re
from pathlib import Path

import numpy as np

HERE = Path(__file__).resolve().parent
EXAMPLE = HERE.parent / "neuralslicer" / "examples" / "paper_bridge" / "model.yaml"
#: the paper's figures (Table CptStatistics, Table FabricationStatistic, Fig. result-bridge (g, h))
PAPER = {"neural": {"layers": 350, "max_strain": 4.6e-2, "cage_elements": 47520, "slicer_s": 229.1,
                    "optimisation_s": 174.3, "gpu": "RTX 4080"},
         "s3": {"layers": 600, "max_strain": 7.9e-2}, "max_strain_gain_vs_s3": -0.405}
KEYS = ("n_layers", "sr.satisfied_fraction", "sr.satisfied_fraction_planar", "n_collisions", "field.steps",
        "wall_s.cage", "wall_s.fea", "wall_s.field", "wall_s.layers", "wall_s.toolpaths", "wall_s.verify",
        "estimated_print_time_s", "material_mm3", "sf.heldout.overhang_area_fraction")


def away_mask(centres: np.ndarray, margin: float) -> np.ndarray:
    """Voxels farther than ``margin`` from every load and support box of the example."""
    from neuralslicer.model.spec import load_model

    fea = load_model(EXAMPLE).fea
    keep = np.ones(len(centres), bool)
    for region in [*fea.supports, *fea.loads]:
        lo, hi = np.asarray(region.box[0], float), np.asarray(region.box[1], float)
        gap = np.maximum(np.maximum(lo - centres, centres - hi), 0.0)
        keep &= np.linalg.norm(gap, axis=1) > margin
    return keep


def wall_clock(path: Path) -> dict:
    """Elapsed seconds and peak resident MB of a ``/usr/bin/time -v`` file."""
    if not path.is_file():
        return {}
    text = path.read_text()
    out = {}
    m = re.search(r"Elapsed \(wall clock\) time \(h:mm:ss or m:ss\): (\S+)", text)
    if m:
        parts = [float(p) for p in m.group(1).split(":")]
        out["elapsed_s"] = sum(p * 60 ** i for i, p in enumerate(reversed(parts)))
    m = re.search(r"Maximum resident set size \(kbytes\): (\d+)", text)
    if m:
        out["peak_rss_mb"] = int(m.group(1)) / 1024
    return out


def summarise(out_dir: Path, store: str, margin: float) -> dict:
    """One run's figures."""
    import zarr

    metrics = json.loads((out_dir / "metrics.json").read_text())
    run = json.loads((out_dir / "run.json").read_text())
    row = {k: metrics.get(k) for k in KEYS}
    row["fea"] = {k[4:]: v for k, v in metrics.items() if k.startswith("fea.") and k.count(".") == 2
                  and k.split(".")[1] in ("printed", "planar_stress", "planar_zigzag")
                  and isinstance(v, (int, float))}
    group = zarr.open_group(f"{store}/{run['groups']['verify']}", mode="r")
    keep = away_mask(np.asarray(group["centres"]), margin)
    row["max_strain_away"] = {part: float(np.asarray(group["strain"][part])[keep].max())
                              for part in group["strain"].array_keys()}
    cage = zarr.open_group(f"{store}/{run['groups']['cage']}", mode="r")
    row["cage_elements"] = int(cage.attrs["n_elements"])
    row["time"] = wall_clock(out_dir.parent / f"{out_dir.name}.time")
    return row


def main() -> None:
    """Summarise the runs, print a line each, write the JSON."""
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--store", required=True)
    ap.add_argument("--margin", type=float, default=5.0, help="mm from the load and support boxes (default 5)")
    ap.add_argument("runs", nargs="+", help="NAME=DIR")
    args = ap.parse_args()
    out = {"paper": PAPER, "margin_mm": args.margin, "runs": {}}
    for item in args.runs:
        name, folder = item.split("=", 1)
        row = summarise(Path(folder), args.store, args.margin)
        out["runs"][name] = row
        f = row["fea"]
        print(f"{name}: {row['n_layers']} layers, printed {f['printed.max_strain']:.4g} / p99 "
              f"{f['printed.max_strain_p99']:.4g} (away {row['max_strain_away']['printed']:.4g}), planar stress "
              f"{f['planar_stress.max_strain']:.4g} / {f['planar_stress.max_strain_p99']:.4g} (away "
              f"{row['max_strain_away']['planar_stress']:.4g}), zig-zag {f['planar_zigzag.max_strain']:.4g} / "
              f"{f['planar_zigzag.max_strain_p99']:.4g} (away {row['max_strain_away']['planar_zigzag']:.4g}), SR "
              f"{row['sr.satisfied_fraction']:.3f}, field {row['wall_s.field']:.0f} s")
    (HERE / "results" / "bench_paper_bridge.json").write_text(json.dumps(out, indent=1))


if __name__ == "__main__":
    main()
