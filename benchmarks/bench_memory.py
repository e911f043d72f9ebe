"""Peak memory of the whole slicing command, step by step: the ring, the coin, the bunny, the bunny at 400 mm
and at 0.2 mm layers.

    .venv/bin/python benchmarks/bench_memory.py [NAME ...]      # default: every case in CASES

Each case runs `neuralslicer slice` in a fresh store and Prefect home. Every second the command's processes (the
command, its local API server, the export's forked helper) are sampled: the sum of their resident sets (RSS: a page
two processes share counts twice) and of their proportional sets (PSS: a shared page counts once, split between its
processes; what the machine really gives them). The peaks are attributed to the step that was running (the
command's ``STEP: started`` lines). A case that would take the machine's last ``--reserve-gb`` (default 2) of
memory is stopped and recorded as not fitting, with the step it was in. Results are merged by name into
benchmarks/results/bench_memory.json and printed as a table.
"""
from __future__ import annotations

import argparse
import contextlib
import json
import os
import re
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
RESULTS = ROOT / "results" / "bench_memory.json"
GB = 2**30
STEP_LINE = re.compile(r"^(\w+): started")

#: name -> (model file, scale factor, extra CLI arguments)
CASES: dict[str, tuple[Path, float, list[str]]] = {
    "ring": (DATA / "ring.tet", 1.0, ["--up", "y"]),
    "coin": (DATA / "overhang_coin_closed_low_res.stl", 1.0, []),
    "bunny-planar": (DATA / "bunny_closed_low_res.stl", 1.0, ["--objectives", "none"]),
    "bunny": (DATA / "bunny_closed_low_res.stl", 1.0, []),
    "bunny-400mm": (DATA / "bunny_closed_low_res.stl", 2.0, []),
    # a 0.4 mm nozzle's 0.2 mm layers (issue 43), planar: one print of 37M waypoints
    "bunny-0.2mm-reprap-planar": (DATA / "bunny_closed_low_res.stl", 1.0,
                                  ["--machine", "reprap_5axis", "--layer-height", "0.2", "--objectives", "none"]),
}


def scaled_model(model: Path, factor: float, folder: Path) -> Path:
    """The model file itself, or a copy of a mesh with its coordinates multiplied by ``factor``."""
    if factor == 1.0:
        return model
    import trimesh

    mesh = trimesh.load(model, force="mesh")
    mesh.apply_scale(factor)
    path = folder / f"{model.stem}_x{factor:g}{model.suffix}"
    mesh.export(path)
    return path


def tree_memory(root: psutil.Process) -> tuple[int, int, dict[str, float]]:
    """(RSS sum, PSS sum) in bytes of a process and its descendants, and the PSS (GB) of each by role."""
    rss = pss = 0
    parts: dict[str, float] = {}
    for proc in [root, *root.children(recursive=True)]:
        try:
            info = proc.memory_full_info()
            role = "command" if proc.pid == root.pid else _role(proc, root)
        except (psutil.Error, OSError):
            continue
        rss, pss = rss + info.rss, pss + getattr(info, "pss", info.rss)
        parts[role] = parts.get(role, 0.0) + getattr(info, "pss", info.rss) / GB
    return rss, pss, parts


def _role(proc: psutil.Process, root: psutil.Process) -> str:
    """What a child of the command is: its local API server, a step's own process (a spawned one), a helper forked
    by either (its parent's command line: the export's, the layers'), or another process (a cage's fTetWild
    worker)."""
    cmdline = proc.cmdline()
    if "api_server" in " ".join(cmdline) or "uvicorn" in " ".join(cmdline):
        return "api_server"
    if "multiprocessing.spawn" in " ".join(cmdline):
        return "step_process"        # a large print's motion, program or export step (tasks/isolate.py)
    parent = proc.parent()
    return "helper" if parent is not None and cmdline == parent.cmdline() else "other"


class Watch:
    """Samples a command's memory every second; keeps the peaks per step and stops it near the machine's limit."""

    def __init__(self, proc: subprocess.Popen, reserve_gb: float) -> None:
        """Watch ``proc`` until it exits."""
        self.proc, self.reserve = psutil.Process(proc.pid), reserve_gb * GB
        self.step = "start"
        self.peaks: dict[str, dict] = {}
        self.stopped_in: str | None = None
        self.thread = threading.Thread(target=self._run, daemon=True)
        self.thread.start()

    def _run(self) -> None:
        """The sampling loop."""
        while self.proc.is_running() and self.proc.status() != psutil.STATUS_ZOMBIE:
            rss, pss, parts = tree_memory(self.proc)
            # at_start_pss_gb: what the step found held when it started (the command, what earlier steps left)
            peak = self.peaks.setdefault(self.step, {"rss_gb": 0.0, "pss_gb": 0.0, "at_start_pss_gb": pss / GB})
            if pss / GB >= peak["pss_gb"]:
                peak["by_process_pss_gb"] = {k: round(v, 2) for k, v in sorted(parts.items())}
            peak["rss_gb"], peak["pss_gb"] = max(peak["rss_gb"], rss / GB), max(peak["pss_gb"], pss / GB)
            if psutil.virtual_memory().available < self.reserve and self.stopped_in is None:
                self.stopped_in = self.step
                for child in [self.proc, *self.proc.children(recursive=True)]:
                    child.kill()
            time.sleep(1.0)


def run_case(name: str, reserve_gb: float, keep: Path | None = None) -> dict:
    """One case in a fresh store: the peaks of the whole command and of each step, wall time, waypoints (``keep``: a
    new folder to run it in and leave, with its store and outputs, for profiling the steps alone)."""
    model, factor, extra = CASES[name]
    if keep is not None:
        keep.mkdir(parents=True)
    with (contextlib.nullcontext(str(keep)) if keep is not None
          else tempfile.TemporaryDirectory(prefix=f"bench-memory-{name}-")) as tmp:
        folder = Path(tmp)
        path = scaled_model(model, factor, folder)
        env = {**os.environ, "PREFECT_HOME": str(folder / "prefect"), "NEURALSLICER_CACHE_DIR": "off",
               "NEURALSLICER_API_IDLE_S": "0"}
        cmd = [sys.executable, "-m", "neuralslicer.cli", "slice", str(path), "--out", str(folder / "out"), *extra]
        load = os.getloadavg()[0]
        start = time.perf_counter()
        proc = subprocess.Popen(cmd, env=env, stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True, cwd=REPO)
        watch = Watch(proc, reserve_gb)
        tail: list[str] = []
        for line in proc.stdout:
            match = STEP_LINE.match(line.strip())
            if match:
                watch.step = match.group(1)
            tail = (tail + [line.rstrip()])[-5:]
        proc.wait()
        watch.thread.join(timeout=5)
        wall = time.perf_counter() - start
        metrics = folder / "out" / "metrics.json"
        m = json.loads(metrics.read_text()) if metrics.is_file() and proc.returncode == 0 else {}
    peaks = watch.peaks
    return {"model": model.name, "scale": factor, "args": extra, "exit": proc.returncode,
            "fits": watch.stopped_in is None, "stopped_in_step": watch.stopped_in, "wall_s": round(wall, 1),
            "load_at_start": round(load, 2), "n_waypoints": m.get("n_waypoints"), "n_layers": m.get("n_layers"),
            "peak_rss_gb": round(max((p["rss_gb"] for p in peaks.values()), default=0.0), 2),
            "peak_pss_gb": round(max((p["pss_gb"] for p in peaks.values()), default=0.0), 2),
            "steps": {k: {kk: round(v, 2) if isinstance(v, float) else v for kk, v in p.items()}
                      for k, p in peaks.items()},
            "machine_memory_gb": round(psutil.virtual_memory().total / GB, 1), "tail": tail if proc.returncode else []}


def main() -> None:
    """Run the cases asked for, merge them into the results file, print a table."""
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("names", nargs="*", default=list(CASES), choices=list(CASES), metavar="NAME")
    parser.add_argument("--reserve-gb", type=float, default=2.0, help="stop a case that leaves less memory than this")
    parser.add_argument("--keep", type=Path, default=None,
                        help="run in this new folder and keep it (one case; its store and outputs, to profile steps)")
    args = parser.parse_args()
    if args.keep is not None and len(args.names) != 1:
        parser.error("--keep takes one case")
    results = json.loads(RESULTS.read_text()) if RESULTS.is_file() else {}
    for name in args.names:
        results[name] = run_case(name, args.reserve_gb, args.keep)
        RESULTS.parent.mkdir(exist_ok=True)
        RESULTS.write_text(json.dumps(results, indent=1) + "\n")
        r = results[name]
        worst = max(r["steps"].items(), key=lambda kv: kv[1]["pss_gb"], default=("-", {}))[0]
        print(f"{name:13s} exit {r['exit']}  {r['wall_s']:7.1f} s  waypoints {r['n_waypoints'] or '-':>10}  peak PSS "
              f"{r['peak_pss_gb']:5.2f} GB (RSS sum {r['peak_rss_gb']:5.2f}) in {worst}"
              + ("" if r["fits"] else f"  STOPPED in {r['stopped_in_step']}: would not fit"), flush=True)


if __name__ == "__main__":
    main()
