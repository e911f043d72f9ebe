"""Robustness to the initial guess (paper Sec. 6.1.5) on the ring: final loss per term for the
height, heat and user starts, the same inputs as `neuralslicer study initial-guess`.

    python benchmarks/bench_neural_initial_guess.py                 # default settings (20k samples, 10k cage)
    python benchmarks/bench_neural_initial_guess.py --reduced       # the study's 4k samples, 6k cage
    python benchmarks/bench_neural_initial_guess.py --old           # the optimiser settings before issue #4
    python benchmarks/bench_neural_initial_guess.py --set optim.max_steps=120 --set init.pretrain_steps=100

Objectives sf, po (the ring's default; the collision term off, as `--objectives sf,po` does).
Prints one line per start and the spread max/min - 1 of the final totals; merges the rows into
benchmarks/results/bench_neural.json under ``initial_guess[_reduced][_old]``.
"""
from __future__ import annotations

import argparse
import json
import sys
import time
from pathlib import Path

import numpy as np
import torch

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from neuralslicer.neural import NeuralConfig, optimise_field  # noqa: E402
from neuralslicer.samples import SurfaceSamples  # noqa: E402

RESULTS = ROOT / "benchmarks" / "results" / "bench_neural.json"
#: the optimiser as it was before issue #4 (the DC3 correction is not emulated: collision is off here)
OLD = {"optim": {"betas": [0.9, 0.999], "plateau_patience": 30, "divergence_factor": 0, "return_best": False,
                 "restart_from_best": False, "max_steps": 800, "convergence_window": 100,
                 "convergence_atol": 1e-5, "target_loss": 0},
       "init": {"pretrain_harmonic": 0}}


def ring_inputs(reduced: bool) -> dict[str, np.ndarray]:
    """Samples B, cage and the study's default user field for the ring (y-up), as the pipeline makes them."""
    from neuralslicer.flows.branch import load_branch_spec, make_user_field
    from neuralslicer.cage import build_cage, interior_points
    from neuralslicer.config import SliceConfig
    from neuralslicer.model.solid import implicit_solid
    from neuralslicer.samples import surface_samples

    ring = ROOT / "neuralslicer" / "data" / "ring.tet"
    solid = implicit_solid(load_branch_spec(str(ring), "y"))
    cfg = SliceConfig()
    if reduced:
        cfg.samples.n_samples, cfg.cage.n_elements = 4000, 6000
    B = surface_samples(solid, cfg.samples.n_samples, k=cfg.samples.k, seed=cfg.samples.seed)
    check = np.concatenate([B.points, interior_points(solid.H, solid.bounds, 20_000, cfg.cage.seed)])
    cage = build_cage(solid.H, solid.bounds, solid.volume(), cfg.cage, check)
    path = Path(make_user_field(solid.bounds, Path("/tmp") / "neuralslicer_ring_user_field.npz"))
    with np.load(path) as uf:
        up, uv = uf["points"], uf["values"]
    return {"V": cage.vertices, "T": cage.tets, "P": B.points, "N": B.normals, "A": B.areas, "K": B.knn,
            "F": B.on_platform, "pz": np.float64(solid.platform_z), "up": up, "uv": uv}


def field_agreement(d: dict[str, np.ndarray], results: dict) -> dict[str, dict[str, float]]:
    """How alike the fields of each pair of starts are: the angle between their LPDs at the samples B
    (area-weighted median and 95th percentile) and the rank correlation of G at B (the print order)."""
    from scipy.stats import spearmanr

    from neuralslicer.tetmesh import TetLocator

    tet, bary = TetLocator(d["V"], d["T"]).locate(d["P"], tol=1e-7)
    ok = tet >= 0
    w = d["A"][ok] / d["A"][ok].sum()
    out = {}
    kinds = list(results)
    for i, a in enumerate(kinds):
        for b in kinds[i + 1:]:
            la, lb = results[a].lpd[tet[ok]], results[b].lpd[tet[ok]]
            ang = np.degrees(np.arccos(np.clip(np.einsum("ij,ij->i", la, lb), -1.0, 1.0)))
            order = np.argsort(ang)
            cw = np.cumsum(w[order])
            ga = np.einsum("ni,ni->n", bary[ok], results[a].G[d["T"][tet[ok]]])
            gb = np.einsum("ni,ni->n", bary[ok], results[b].G[d["T"][tet[ok]]])
            out[f"{a}-{b}"] = {"lpd_angle_deg_median": float(ang[order][np.searchsorted(cw, 0.5)]),
                               "lpd_angle_deg_p95": float(ang[order][min(np.searchsorted(cw, 0.95), len(ang) - 1)]),
                               "spearman_G": float(spearmanr(ga, gb).statistic)}
    return out


def plot_learning_curves(results: dict, path: Path) -> None:
    """Total loss per step of every start, log scale, with the target loss (PNG)."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, ax = plt.subplots(figsize=(6.5, 4))
    for kind, r in results.items():
        ax.semilogy(np.arange(1, len(r.history["total"]) + 1), r.history["total"], label=kind, lw=1)
    target = next(iter(results.values())).attrs["config"]["optim"]["target_loss"]
    if target > 0:
        ax.axhline(target, color="k", ls="--", lw=0.8, label="target loss")
    ax.set_xlabel("step")
    ax.set_ylabel("total loss")
    ax.set_title("ring: learning curves from three initial guesses")
    ax.legend()
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)


def _deep(a: dict, b: dict) -> dict:
    """a updated recursively with b."""
    for k, v in b.items():
        a[k] = _deep(dict(a.get(k, {})), v) if isinstance(v, dict) else v
    return a


def _parse_set(items: list[str]) -> dict:
    """--set a.b=value (value as JSON when it parses) -> nested dict."""
    out: dict = {}
    for item in items:
        key, value = item.split("=", 1)
        try:
            val = json.loads(value)
        except json.JSONDecodeError:
            val = value
        node = out
        *parents, leaf = key.split(".")
        for p in parents:
            node = node.setdefault(p, {})
        node[leaf] = val
    return out


def main(argv: list[str] | None = None) -> None:
    """Command line entry point."""
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--reduced", action="store_true", help="4k samples, 6k cage elements (the study's budget)")
    p.add_argument("--old", action="store_true", help="the optimiser settings before issue #4")
    p.add_argument("--kinds", default="height,heat,user")
    p.add_argument("--set", action="append", default=[], help="config override, e.g. optim.max_steps=120")
    p.add_argument("--results", type=Path, default=RESULTS, help="JSON file the rows are merged into")
    p.add_argument("--threads", type=int, default=1, help="torch CPU threads (1: stable timings on a shared machine)")
    a = p.parse_args(argv)
    torch.set_num_threads(a.threads)
    d = ring_inputs(a.reduced)
    base = {"device": "cpu", "loss": {"w_sr": 0.0, "collision": False}}
    if a.old:
        base = _deep(base, OLD)
    base = _deep(base, _parse_set(a.set))
    rows = []
    results_by_kind = {}
    for kind in a.kinds.split(","):
        cfg = NeuralConfig.model_validate(_deep(json.loads(json.dumps(base)), {"init": {"kind": kind}}))
        t0 = time.perf_counter()
        r = optimise_field(d["V"], d["T"], SurfaceSamples(d["P"], d["N"], d["A"], d["K"], d["F"]), config=cfg,
                           platform_z=float(d["pz"]), user_field=d["uv"] if kind == "user" else None,
                           user_field_points=d["up"] if kind == "user" else None)
        row = {"init": kind, "tets": int(len(d["T"])), "samples": int(len(d["P"])), "steps": r.steps,
               "converged": r.converged, "wall_s": time.perf_counter() - t0, "final": r.final,
               "overhang": r.satisfaction["overhang_area_fraction"], "rollbacks": r.attrs.get("rollbacks"),
               "pretrain_final_mse": float(r.pretrain_history[-1]) if len(r.pretrain_history) else None,
               "history_total_every_10": [float(v) for v in r.history["total"][::10]]}
        rows.append(row)
        results_by_kind[kind] = r
        f = r.final
        print(f"{kind:>6}: {row['tets']} tets, {r.steps} steps ({'converged' if r.converged else 'budget'}), "
              f"{row['wall_s']:.0f} s, total {f['total']:.3e} = sf {f['sf']:.2e} + po {f['po']:.2e} + "
              f"hs {f['hs']:.2e} + hq {f['hq']:.2e}; overhang {100 * row['overhang']:.3f} %", flush=True)
    totals = [r["final"]["total"] for r in rows]
    print(f"spread of the final totals (max/min - 1): {100 * (max(totals) / min(totals) - 1):.1f} %")
    agreement = field_agreement(d, results_by_kind)
    for pair, ag in agreement.items():
        print(f"{pair}: LPD angle at B median {ag['lpd_angle_deg_median']:.2f} deg, 95 % {ag['lpd_angle_deg_p95']:.2f} deg; "
              f"layer order: Spearman {ag['spearman_G']:.4f}")
    key = "initial_guess" + ("_reduced" if a.reduced else "") + ("_old" if a.old else "")
    plot_learning_curves(results_by_kind, a.results.parent / f"bench_neural_{key}.png")
    results = json.loads(a.results.read_text()) if a.results.exists() else {}
    results[key] = {"rows": rows, "agreement": agreement, "overrides": base, "threads": a.threads}
    a.results.write_text(json.dumps(results, indent=2, default=float))


if __name__ == "__main__":
    main()
