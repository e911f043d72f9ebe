"""The paper's network (10 x 512 SIREN, ``--network paper``) against the default network on the Ring, run to
convergence on this machine's CPU: the whole chain with default settings (objectives sf, po, gc, ca), each network
in a process of its own, one after the other.

    .venv/bin/python benchmarks/bench_paper_network.py [--networks default paper] [--max-steps 3000]
                                                       [--out benchmarks/results/bench_paper_network.json]

For each network: the optimisation's stop (``constraints``: the overhang target met with no head collision;
``converged``: the loss stalled; ``budget``: ``--max-steps`` reached), steps, the field step's wall time, the best
total loss and its terms, the overhang on held-out samples of the surface (the field's and the exported layers'), the
layer count, the collisions of the printed program, peak RSS; and its learning curve, the best total loss against
wall time from the start of the optimisation. "At equal wall time" compares the curves at the default network's stop
and at fixed times. The Ring has no load case (the paper's Ring experiment is support-free only), so there is no
strain to compare here. Writes the JSON and a PNG of the curves beside it (``_curves.png``).
"""
from __future__ import annotations

import argparse
import json
import os
import platform
import resource
import subprocess
import sys
import tempfile
import time
from pathlib import Path

from neuralslicer.allocator import keep_freed_memory
from neuralslicer.neural.device import limit_threads

limit_threads()  # as the command: a short OpenMP spin (GOMP_SPINCOUNT), set before torch is imported
keep_freed_memory()  # as the command: large arrays from the heap, freed memory kept (neuralslicer/allocator.py)

import numpy as np  # noqa: E402

ROOT = Path(__file__).resolve().parent.parent
RESULTS = Path(__file__).resolve().parent / "results"
RING = ROOT / "neuralslicer" / "data" / "ring.tet"
#: wall times (s from the optimisation's start) at which the curves are compared, besides the default's stop
COMPARE_AT_S = (10.0, 30.0, 60.0, 300.0, 900.0, 1800.0, 3600.0)
#: metrics of the run kept in the JSON
KEPT = ("field.steps", "field.stop", "n_layers", "n_waypoints", "n_collisions", "loss.total", "loss.sf", "loss.po",
        "loss.gc", "loss.ca", "loss.hs", "loss.hq", "sf.overhang_area_fraction", "sf.heldout.overhang_area_fraction",
        "sf.heldout.overhang_area_fraction_layers", "sf.heldout.overhang_area_fraction_planar", "n_cage_elements",
        "n_samples_B", "wall_s.field")


def one(network: str, max_steps: int, out: Path) -> dict:
    """Slice the Ring with one network in this process: its metrics, learning curve and peak RSS."""
    from neuralslicer.config import SliceConfig
    from neuralslicer.model.spec import spec_for_file
    from neuralslicer.run.in_process import slice_model

    config = SliceConfig.model_validate({"neural": {"network": network, "optim": {"max_steps": max_steps}}})
    curve: list[tuple[int, float, float]] = []

    def progress(step: int, info: dict) -> None:
        """Record (step, s since the optimisation started, best total loss so far) after each optimisation step."""
        if info.get("phase") == "optimise":
            curve.append((step, float(info["elapsed_s"]), float(info["best"])))

    t = time.perf_counter()
    with tempfile.TemporaryDirectory(prefix="bench-paper-network-") as tmp:
        _, metrics = slice_model(spec_for_file(RING, "y"), config, Path(tmp) / "run", progress=progress)
    wall = time.perf_counter() - t
    row = {"network": network, "max_steps": max_steps, "wall_s": wall,
           "peak_rss_gb": resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 2**20,
           **{k: metrics[k] for k in KEPT if k in metrics},
           "curve": {"step": [c[0] for c in curve], "elapsed_s": [round(c[1], 3) for c in curve],
                     "best_total": [c[2] for c in curve]}}
    out.write_text(json.dumps(row))
    return row


def run_network(network: str, max_steps: int) -> dict:
    """One network in a fresh process (its own peak memory, nothing held from the other)."""
    with tempfile.TemporaryDirectory(prefix="bench-paper-network-") as tmp:
        out = Path(tmp) / "row.json"
        load = os.getloadavg()[0]
        done = subprocess.run([sys.executable, __file__, "--one", network, "--max-steps", str(max_steps),
                               "--row", str(out)], cwd=ROOT)
        if done.returncode != 0:
            raise SystemExit(f"the {network} network's run failed (exit {done.returncode})")
        return {**json.loads(out.read_text()), "load_at_start": load, "load_at_end": os.getloadavg()[0]}


def best_at(row: dict, t: float) -> float | None:
    """The best total loss a run had reached t seconds into its optimisation (its last value once it stopped;
    None before its first step ended)."""
    times = np.asarray(row["curve"]["elapsed_s"])
    i = int(np.searchsorted(times, t, side="right")) - 1
    return None if i < 0 else row["curve"]["best_total"][i]


def at_equal_time(rows: list[dict]) -> list[dict]:
    """Each network's best total loss at the default network's stop and at COMPARE_AT_S."""
    default = next((r for r in rows if r["network"] == "default"), None)
    stop = [default["curve"]["elapsed_s"][-1]] if default and default["curve"]["elapsed_s"] else []
    times = sorted(stop + list(COMPARE_AT_S))
    longest = max(r["curve"]["elapsed_s"][-1] for r in rows if r["curve"]["elapsed_s"])
    return [{"t_s": round(t, 1), **{r["network"]: best_at(r, t) for r in rows}} for t in times if t <= longest]


def plot(rows: list[dict], path: Path) -> None:
    """The learning curves, best total loss against wall time, log-log."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, ax = plt.subplots(figsize=(7, 4.5))
    for r in rows:
        c = r["curve"]
        ax.loglog(np.maximum(c["elapsed_s"], 1e-2), c["best_total"],
                  label=f"{r['network']}: {r.get('field.steps')} steps, {r.get('field.stop')}")
    ax.set_xlabel("wall time of the optimisation (s, 2 CPU cores)")
    ax.set_ylabel("best total loss")
    ax.set_title("Ring, default objectives: default vs paper network")
    ax.grid(True, which="both", alpha=0.3)
    ax.legend()
    fig.tight_layout()
    fig.savefig(path, dpi=120)
    plt.close(fig)


def main(argv: list[str] | None = None) -> None:
    """Run the networks one after the other, then write the JSON, the PNG and a table."""
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--networks", nargs="+", default=["default", "paper"])
    p.add_argument("--max-steps", type=int, default=3000, help="step budget of each run (the product's default)")
    p.add_argument("--out", type=Path, default=RESULTS / "bench_paper_network.json")
    p.add_argument("--one", help=argparse.SUPPRESS)
    p.add_argument("--row", type=Path, help=argparse.SUPPRESS)
    a = p.parse_args(argv)
    if a.one:
        one(a.one, a.max_steps, a.row)
        return
    rows = []
    for network in a.networks:
        rows.append(run_network(network, a.max_steps))
        r = rows[-1]
        print(f"{network:>8}: {r['field.steps']} steps ({r['field.stop']}), field {r['wall_s.field']:.0f} s, "
              f"best loss {r['curve']['best_total'][-1] if r['curve']['best_total'] else float('nan'):.3g}, "
              f"held-out overhang {100 * r['sf.heldout.overhang_area_fraction']:.2f} % (layers "
              f"{100 * r['sf.heldout.overhang_area_fraction_layers']:.2f} %, planar "
              f"{100 * r['sf.heldout.overhang_area_fraction_planar']:.2f} %), {r['n_layers']} layers, "
              f"{r['n_collisions']} collisions, {r['peak_rss_gb']:.2f} GB", flush=True)
    result = {"model": "ring.tet", "machine": {"platform": platform.platform(), "cpu_count": os.cpu_count()},
              "rows": rows, "at_equal_time": at_equal_time(rows)}
    a.out.parent.mkdir(parents=True, exist_ok=True)
    tmp = a.out.with_suffix(".json.tmp")
    tmp.write_text(json.dumps(result, indent=1))
    tmp.replace(a.out)
    plot(rows, a.out.with_name(a.out.stem + "_curves.png"))
    for row in result["at_equal_time"]:
        print("  at {t_s:>7.1f} s: ".format(**row) + ", ".join(
            f"{n} {'-' if row[n] is None else format(row[n], '.3g')}" for n in a.networks))


if __name__ == "__main__":
    main()
