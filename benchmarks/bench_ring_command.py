"""The default ring command, end to end, as a user runs it: fresh (a new output folder and store) and again (fully
cached), wall and CPU time, the load, every task's wall time; optionally against another checkout (the code before a
change) on the same machine, alternating, and its metrics.json compared key by key.

    .venv/bin/python benchmarks/bench_ring_command.py [--runs N] [--cached M] [--cold-server] [--against DIR]
                                                      [--out results/bench_ring_command.json]

The command is ``neuralslicer slice neuralslicer/data/ring.tet --up y --out DIR`` (issue 30's targets: under 60 s
fresh, under 5 s cached, on a quiet machine). Each side runs in its own checkout (``cwd``, and
``benchmarks/checkout_env.py``'s environment: that checkout's ``neuralslicer`` and outer layers alone) with this
interpreter, the user's Prefect home and the cage cache in ~/.cache/neuralslicer (the run is deterministic given
it). ``--cold-server``: the local Prefect API server left up by an earlier command is stopped before each fresh run,
so that the fresh run boots its own (what a first command after the idle time does); without it a fresh run uses the
server the last command left up. CPU time is the command's own process and the processes it waited for (user +
system, ``RUSAGE_CHILDREN``), not the server's. The 1-minute load average is recorded before and after every run:
figures taken beside other jobs say so. metrics.json of the runs are compared without their wall-time keys
(``wall_s.*``, ``timings_s``) and the git commit: the runs must agree on everything else. """ from __future__ import
annotations

import argparse
import json
import os
import platform
import resource
import signal
import subprocess
import sys
import tempfile
import time
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parent))
from checkout_env import checkout_environ  # noqa: E402

ROOT = Path(__file__).resolve().parent.parent
RESULTS = Path(__file__).resolve().parent / "results"


def prefect_home() -> Path:
    """The Prefect home a command of this environment uses."""
    return Path(os.environ.get("PREFECT_HOME") or Path.home() / ".prefect").expanduser()


def stop_left_server() -> bool:
    """Stop the local API server an earlier command left up (its record in the Prefect home), if it is one of ours;
    True when one was stopped."""
    record = prefect_home() / "neuralslicer-api.json"
    try:
        pid = int(json.loads(record.read_text())["pid"])
        cmdline = Path(f"/proc/{pid}/cmdline").read_bytes().decode(errors="replace")
    except (OSError, ValueError, KeyError):
        return False
    if "neuralslicer.flows.api_server" not in cmdline:
        return False
    os.kill(pid, signal.SIGTERM)
    for _ in range(100):
        if not Path(f"/proc/{pid}").exists():
            break
        time.sleep(0.05)
    return True


def run_once(checkout: Path, out: Path) -> dict:
    """One command in ``checkout``: wall, CPU (user + system of it and what it waited for), load, tasks."""
    env = checkout_environ(checkout, {**os.environ, "PREFECT_SERVER_ANALYTICS_ENABLED": "false", "DO_NOT_TRACK": "1"})
    cmd = [sys.executable, "-m", "neuralslicer.cli", "slice", str(ROOT / "neuralslicer" / "data" / "ring.tet"),
           "--up", "y", "--out", str(out)]
    load_before = os.getloadavg()[0]
    before = resource.getrusage(resource.RUSAGE_CHILDREN)
    t = time.perf_counter()
    done = subprocess.run(cmd, cwd=checkout, env=env, capture_output=True, text=True)
    wall = time.perf_counter() - t
    after = resource.getrusage(resource.RUSAGE_CHILDREN)
    if done.returncode != 0:
        raise SystemExit(f"the command failed in {checkout}: {done.stderr[-2000:]}")
    run = json.loads((out / "run.json").read_text())
    return {"wall_s": wall, "cpu_s": (after.ru_utime - before.ru_utime) + (after.ru_stime - before.ru_stime),
            "load_before": load_before, "load_after": os.getloadavg()[0], "flow_s": run["wall_s"],
            "tasks": {r["task"]: round(r["wall_s"], 3) for r in run["tasks"]},
            "cached": sum(r["state"] == "Cached" for r in run["tasks"]), "n_tasks": len(run["tasks"])}


def metrics_of(out: Path) -> dict:
    """metrics.json without the keys that may differ between identical runs (wall times, the git commit)."""
    metrics = json.loads((out / "metrics.json").read_text())
    return {k: v for k, v in metrics.items()
            if not (k.startswith("wall_s.") or "timings_s" in k or k == "provenance.code.git_commit")}


def differences(a: dict, b: dict) -> list[str]:
    """Keys whose values differ (or are missing on one side)."""
    return [k for k in sorted(set(a) | set(b)) if a.get(k, "<missing>") != b.get(k, "<missing>")]


def summary(rows: list[dict]) -> dict:
    """Median and range of wall and CPU over runs."""
    def stat(key: str) -> dict:
        v = sorted(r[key] for r in rows)
        return {"median": v[len(v) // 2], "min": v[0], "max": v[-1]}
    return {"wall_s": stat("wall_s"), "cpu_s": stat("cpu_s"), "load": [min(r["load_before"] for r in rows),
                                                                      max(r["load_after"] for r in rows)]}


def main() -> None:
    """Measure, print and write the JSON."""
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--runs", type=int, default=2, help="fresh runs per side (default 2)")
    parser.add_argument("--cached", type=int, default=3, help="cached reruns after each fresh run (default 3)")
    parser.add_argument("--cold-server", action="store_true", help="stop a left local API server before each fresh run")
    parser.add_argument("--against", type=Path, default=None, help="another checkout (the code before), run alternately")
    parser.add_argument("--out", type=Path, default=RESULTS / "bench_ring_command.json")
    args = parser.parse_args()
    sides = {"this": ROOT} | ({"against": args.against.resolve()} if args.against else {})
    rows: dict[str, dict[str, list[dict]]] = {s: {"fresh": [], "cached": []} for s in sides}
    metrics: dict[str, dict] = {}
    with tempfile.TemporaryDirectory(prefix="bench-ring-") as tmp:
        for i in range(args.runs):
            for side, checkout in sides.items():
                out = Path(tmp) / f"{side}-{i}"
                stopped = stop_left_server() if args.cold_server else False
                fresh = run_once(checkout, out) | {"server_stopped_before": stopped}
                rows[side]["fresh"].append(fresh)
                print(f"{side} fresh: {fresh['wall_s']:.1f} s wall, {fresh['cpu_s']:.1f} s CPU, load "
                      f"{fresh['load_before']:.2f}-{fresh['load_after']:.2f}; tasks {fresh['tasks']}", flush=True)
                for _ in range(args.cached):
                    again = run_once(checkout, out)
                    rows[side]["cached"].append(again)
                    print(f"{side} cached ({again['cached']}/{again['n_tasks']} tasks): {again['wall_s']:.2f} s wall, "
                          f"{again['cpu_s']:.2f} s CPU, load {again['load_before']:.2f}", flush=True)
                got = metrics_of(out)
                if side in metrics and differences(metrics[side], got):
                    print(f"{side}: metrics.json differs between runs: {differences(metrics[side], got)}")
                metrics.setdefault(side, got)
    result = {"command": "neuralslicer slice neuralslicer/data/ring.tet --up y --out DIR",
              "cold_server": args.cold_server, "machine": {"cpus": os.cpu_count(), "python": platform.python_version(),
                                                           "platform": platform.platform()},
              "sides": {s: str(c) for s, c in sides.items()},
              "summary": {s: {k: summary(v) for k, v in r.items() if v} for s, r in rows.items()}, "runs": rows}
    if "against" in metrics:
        diff = differences(metrics["this"], metrics["against"])
        result["metrics_identical"] = not diff
        result["metrics_differences"] = diff
        print("metrics.json: identical apart from wall times" if not diff else f"metrics.json differs: {diff}")
    for side, s in result["summary"].items():
        for kind, v in s.items():
            print(f"{side} {kind}: wall median {v['wall_s']['median']:.2f} s ({v['wall_s']['min']:.2f}-"
                  f"{v['wall_s']['max']:.2f}), CPU median {v['cpu_s']['median']:.2f} s, load {v['load'][0]:.2f}-"
                  f"{v['load'][1]:.2f}")
    args.out.parent.mkdir(parents=True, exist_ok=True)
    args.out.write_text(json.dumps(result, indent=2) + "\n")


if __name__ == "__main__":
    main()
