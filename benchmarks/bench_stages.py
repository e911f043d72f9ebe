"""Stage budget: wall time and peak memory of every stage of a slice, each next to a limit where one is known.

    .venv/bin/python benchmarks/bench_stages.py [ring|bracket ...]   (default: ring bracket)

Part 1 runs the core pipeline in-process (``neuralslicer.run.pipeline.run_chain`` on in-process steps: no Prefect, no
store), step by step, sampling the process's resident memory every 20 ms: model (implicit solid), solid, samples,
cage, FEA and stress samples (with an fea block), optimisation (with its step count and time per step; every field
the collision policy asks for), layers, toolpaths, motion (collision check, travel lift and tilt, motion planning),
G-code, report figures. Part 2 runs the default CLI command in a fresh store and again on the
same store (the cached rerun): whole wall time, every task run's wall time (Prefect's round trips included, from
run.json) and the time outside them (imports, Prefect start-up, the report artifact). Limits are lower bounds measured here: G-code at the disk's write speed for its bytes, the collision
check at one nearest-neighbour query per waypoint, an optimisation step at one forward and backward pass of the
deformation networks. Writes benchmarks/results/bench_stages.json and bench_stages.png.
"""
from __future__ import annotations

import json
import os
import platform
import subprocess
import sys
import tempfile
import threading
import time
from pathlib import Path

import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt  # noqa: E402
import numpy as np  # noqa: E402
import psutil  # noqa: E402

ROOT = Path(__file__).resolve().parent
DATA = ROOT.parent / "neuralslicer" / "data"
RESULTS = ROOT / "results"
MODELS = {
    "ring": (["slice", str(DATA / "ring.tet"), "--up", "y"], {}),
    "bracket": (["slice", str(ROOT.parent / "neuralslicer" / "examples" / "bracket" / "model.yaml"), "--max-steps", "200"],
                {"max_steps": 200}),
}


class Stage:
    """Context manager: wall time and peak resident memory (sampled every 20 ms) of one stage."""

    def __init__(self, rows: list[dict], name: str, limit_s: float | None = None) -> None:
        self.rows, self.name, self.limit_s = rows, name, limit_s
        self.proc = psutil.Process()
        self.info: dict = {}

    def __enter__(self) -> "Stage":
        self.base = self.proc.memory_info().rss
        self.peak = self.base
        self.stop = threading.Event()
        self.thread = threading.Thread(target=self._sample, daemon=True)
        self.thread.start()
        self.t0 = time.perf_counter()
        return self

    def _sample(self) -> None:
        while not self.stop.wait(0.02):
            self.peak = max(self.peak, self.proc.memory_info().rss)

    def __exit__(self, *exc: object) -> None:
        wall = time.perf_counter() - self.t0
        self.stop.set()
        self.thread.join()
        self.peak = max(self.peak, self.proc.memory_info().rss)
        self.rows.append({"stage": self.name, "wall_s": wall, "peak_rss_mb": self.peak / 2**20,
                          "added_rss_mb": (self.peak - self.base) / 2**20, "limit_s": self.limit_s, **self.info})


def disk_write_mb_s(folder: Path, mb: int = 256) -> float:
    """Sequential write speed of the disk holding ``folder`` (MB/s, fsync'd)."""
    buf = os.urandom(2**20)
    path = folder / "disk-speed.bin"
    t = time.perf_counter()
    with open(path, "wb") as fh:
        for _ in range(mb):
            fh.write(buf)
        fh.flush()
        os.fsync(fh.fileno())
    s = time.perf_counter() - t
    path.unlink()
    return mb / s


LABELS = {"model": "model (implicit solid)", "samples": "samples B", "cage": "cage (fTetWild)", "fea": "FEA",
          "stress_samples": "stress samples T", "field": "optimisation", "layers": "layers",
          "toolpaths": "toolpaths (shells, infill, order, thickness)", "motion": "motion (check, lifts, tilts, IK)",
          "program": "G-code"}


def core_stages(name: str, tmp: Path) -> tuple[list[dict], dict]:
    """Every stage of one slice in-process (the core pipeline, ``run_chain`` on in-process steps, each step in a
    Stage); the rows and a few counts."""
    from scipy.spatial import cKDTree

    from neuralslicer.config import SliceConfig
    from neuralslicer.model.spec import load_spec, spec_for_file
    from neuralslicer.run.in_process import InProcessSteps
    from neuralslicer.run.pipeline import run_chain
    from neuralslicer.run.report import plot_layers_3d, plot_thickness_map

    args, over = MODELS[name]
    spec = spec_for_file(args[1], "y") if name == "ring" else load_spec(args[1])
    cfg = SliceConfig.model_validate({"neural": {"optim": {"max_steps": over["max_steps"]}}} if over else {})
    rows: list[dict] = []

    class StagedSteps(InProcessSteps):
        """In-process steps, each call measured as one Stage row."""

        def _timed(self, step, make):  # noqa: ANN001, ANN202
            with Stage(rows, LABELS.get(step, step)):
                return super()._timed(step, make)

    steps = StagedSteps()
    chain = run_chain(steps, spec, cfg)
    cage, motion = chain.cage, chain.printed.motion
    tp, metrics = motion.toolpaths, motion.metrics
    opt = next(r for r in rows if r["stage"] == "optimisation")
    n_steps = int(chain.printed.field[1].get("steps", 0))
    opt.update(steps=n_steps, per_step_s=opt["wall_s"] / max(n_steps, 1),
               limit_s=n_steps * network_pass_s(cage, cfg.neural.with_head(motion.program.profile.nozzle,
                                                                          cfg.toolpath.line_width)))
    material = cKDTree(tp.xyz)
    t = time.perf_counter()
    material.query(tp.xyz + 1.0, k=1)
    nn_s = time.perf_counter() - t
    whole = next(r for r in rows if r["stage"] == LABELS["motion"])
    for key, label, limit in (("collisions", "  of which: collision check", nn_s),
                              ("tilt", "  of which: travel lift + tilt + reach", None),
                              ("motion", "  of which: motion planning (IK, feeds, time estimate)", None)):
        rows.append({"stage": label, "wall_s": float(metrics["timings_s"][key]), "peak_rss_mb": whole["peak_rss_mb"],
                     "added_rss_mb": whole["added_rss_mb"], "limit_s": limit})
    speed = disk_write_mb_s(tmp)
    gcode = next(r for r in rows if r["stage"] == LABELS["program"])
    size = len(bytes(chain.program))
    gcode.update(bytes=size, limit_s=size / 2**20 / speed)
    with Stage(rows, "figures (layer preview, bead thickness)"):
        plot_layers_3d(tmp / "layers.png", chain.printed.layers.meshes)
        plot_thickness_map(tmp / "beads.png", tp.xyz, tp.thickness, tp.extrude, motion.program.profile.nozzle.bead_thickness_mm)
    counts = {"cage_tets": int(len(cage.tets)), "steps": n_steps, "layers": len(chain.printed.layers.meshes),
              "waypoints": len(tp), "disk_write_mb_s": speed, "collisions": int(metrics["n_collisions"]),
              "attempts": max(len(chain.attempts), 1)}
    return rows, counts


def network_pass_s(cage, neural) -> float:  # noqa: ANN001
    """One forward and backward pass of the deformation networks at the cage's tet centroids (the floor of an
    optimisation step, which adds the ARAP solves and the losses)."""
    import torch

    from neuralslicer.neural.networks import DeformationFields

    dtype = torch.float32 if neural.dtype == "float32" else torch.float64
    bounds = np.stack([cage.vertices.min(0), cage.vertices.max(0)])
    fields = DeformationFields(neural.network_config(), bounds).to(torch.device("cpu"), dtype)
    x = torch.as_tensor(cage.vertices[cage.tets].mean(axis=1), dtype=dtype)
    best = np.inf
    for _ in range(5):
        t = time.perf_counter()
        q, s = fields(x)
        (q.sum() + s.sum()).backward()
        best = min(best, time.perf_counter() - t)
    return float(best)


def cli_runs(name: str, tmp: Path) -> dict:
    """The default command in a fresh store, then again (cached): wall, tasks' own time, the rest."""
    args, _ = MODELS[name]
    out = tmp / "out"
    env = {**os.environ, "PREFECT_HOME": str(tmp / "prefect"), "PREFECT_SERVER_ANALYTICS_ENABLED": "false",
           "DO_NOT_TRACK": "1"}
    res = {}
    for run in ("fresh", "cached"):
        t = time.perf_counter()
        done = subprocess.run([sys.executable, "-m", "neuralslicer.cli", *args, "--out", str(out)], env=env, cwd=ROOT.parent,
                              capture_output=True, text=True)
        wall = time.perf_counter() - t
        if done.returncode != 0:
            raise SystemExit(f"{name}: the slice failed: {done.stderr[-2000:]}")
        run_json = json.loads((out / "run.json").read_text())
        tasks = {r["task"]: r.get("wall_s", 0.0) for r in run_json["tasks"]}
        tasks_s = float(sum(tasks.values()))             # every task run, Prefect's round trips included
        res[run] = {"wall_s": wall, "tasks_s": tasks_s, "outside_tasks_s": wall - tasks_s, "task_wall_s": tasks,
                    "states": {r["task"]: r["state"] for r in run_json["tasks"]}}
    return res


def plot(path: Path, results: dict) -> None:
    """Bar chart of the stage times per model, limits as black ticks."""
    fig, axes = plt.subplots(1, len(results), figsize=(7 * len(results), 5), squeeze=False)
    for ax, (name, r) in zip(axes[0], results.items()):
        rows = r["stages"]
        y = np.arange(len(rows))
        ax.barh(y, [row["wall_s"] for row in rows], color="tab:blue")
        for i, row in enumerate(rows):
            if row.get("limit_s"):
                ax.plot([row["limit_s"]] * 2, [i - 0.4, i + 0.4], color="black", linewidth=2)
        ax.set_yticks(y, [row["stage"] for row in rows], fontsize=8)
        ax.invert_yaxis()
        ax.set_xscale("log")
        ax.set_xlabel("wall time (s, log); black: the stage's lower bound")
        cli = r.get("cli", {})
        title = name
        if cli:
            title += f": CLI {cli['fresh']['wall_s']:.0f} s fresh, {cli['cached']['wall_s']:.1f} s cached"
        ax.set_title(title)
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)


def main(names: list[str]) -> None:
    """Measure every model named and write the JSON and the chart (models measured before are kept)."""
    path = RESULTS / "bench_stages.json"
    results = json.loads(path.read_text())["models"] if path.exists() else {}
    for name in names:
        with tempfile.TemporaryDirectory() as tmp:
            load = os.getloadavg()[0]
            rows, counts = core_stages(name, Path(tmp))
            cli = cli_runs(name, Path(tmp))
        results[name] = {"stages": rows, "counts": counts, "cli": cli, "load_avg_1min_at_start": load}
        print(f"\n{name} (load {load:.1f}): {counts}")
        print(f"{'stage':48s} {'wall s':>8s} {'limit s':>8s} {'peak MB':>8s}")
        for row in rows:
            lim = f"{row['limit_s']:.2f}" if row.get("limit_s") else "-"
            print(f"{row['stage']:48s} {row['wall_s']:8.2f} {lim:>8s} {row['peak_rss_mb']:8.0f}")
        print(f"CLI: fresh {cli['fresh']['wall_s']:.1f} s (task runs {cli['fresh']['tasks_s']:.1f} s: "
              f"{ {k: round(v, 1) for k, v in cli['fresh']['task_wall_s'].items()} }; outside them (imports, Prefect "
              f"start-up, report artifact) {cli['fresh']['outside_tasks_s']:.1f} s); cached rerun {cli['cached']['wall_s']:.1f} s")
    RESULTS.mkdir(exist_ok=True)
    (RESULTS / "bench_stages.json").write_text(json.dumps(
        {"models": results, "machine": {"cpus": os.cpu_count(), "python": platform.python_version(),
                                        "platform": platform.platform()}}, indent=2, default=float))
    plot(RESULTS / "bench_stages.png", results)


if __name__ == "__main__":
    main(sys.argv[1:] or ["ring", "bracket"])
