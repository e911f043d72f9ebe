"""Time of one optimisation step on a paper-scale cage (issue 42): topopt_new4.tet (up y) in a cage of about
47k target tets (52k built), the slice command's default objectives and head, two torch threads.

    python benchmarks/bench_step.py                       # median step, per-part breakdown, threads 2 then 1
    python benchmarks/bench_step.py --threads 2 --steps 20 --warmup 5
    python benchmarks/bench_step.py --cage-cache CAGE.npz     # reuse (or write) the cage there
    (eval "$(python benchmarks/checkout_env.py /old/tree)"; python /old/tree/benchmarks/bench_step.py --label before)
                                                          # another tree's step, same JSON

The process is set up as the command sets itself up (``GOMP_SPINCOUNT``, the allocator). The cage is built
once by the cage step (fTetWild) and kept in ``--cage-cache``; the problem is built as the field step builds it
(``optimise_for_solid``: the pool of L_GC, the solid tets, the pipeline's head). Each step is the loop's own
``iterate`` (L_GC's pair search every ``optim.check_every`` steps, the DC3 corrections of L_CA, the Adam step),
timed from the loop's checkpoint after ``--start-step`` steps (300: L_GC's pairs active; made once and kept beside
the cage). The breakdown times the parts by wrapping them (one more pass; the wrappers cost a little), and lists
the operations with the most CPU time (torch.profiler). Writes benchmarks/results/bench_step.json.
"""
from __future__ import annotations

import argparse
import contextlib
import functools
import json
import os
import platform
import statistics
import tempfile
import time
from collections import defaultdict
from pathlib import Path
from typing import Callable, Iterator

from neuralslicer.allocator import keep_freed_memory
from neuralslicer.neural.device import limit_threads

limit_threads()  # as the command: a short OpenMP spin (GOMP_SPINCOUNT), set before torch is imported
keep_freed_memory()  # as the command: large arrays from the heap, freed memory kept (neuralslicer/allocator.py)

import numpy as np  # noqa: E402
import torch  # noqa: E402

from neuralslicer.neural import losses as L  # noqa: E402
from neuralslicer.neural import optimise as O  # noqa: E402
from neuralslicer.neural import problem as P  # noqa: E402
from neuralslicer.neural.optimise import LoopState, deterministic_algorithms, iterate  # noqa: E402
from neuralslicer.neural.problem import FieldProblem  # noqa: E402

RESULTS = Path(__file__).parent / "results" / "bench_step.json"
DATA = Path(__file__).resolve().parents[1] / "neuralslicer" / "data"


def build_problem(model: Path, up: str, n_elements: int, cache: Path) -> tuple[FieldProblem, dict]:
    """The field step's problem for the model with the slice command's defaults; the cage from ``cache`` if there."""
    from neuralslicer.cage import make_cage
    from neuralslicer.config import SliceConfig
    from neuralslicer.model.solid import implicit_solid
    from neuralslicer.model.spec import spec_for_file
    from neuralslicer.motion.profile import load_profile
    from neuralslicer.neural.head_collision import collision_pool
    from neuralslicer.neural.optimise import solid_tets
    from neuralslicer.samples import surface_samples

    spec = spec_for_file(model, up=up)
    defaults = SliceConfig()
    config = defaults.model_copy(update={"cage": defaults.cage.model_copy(update={"n_elements": n_elements})})
    solid = implicit_solid(spec)
    samples = surface_samples(solid, config.samples.n_samples, k=config.samples.k, seed=config.samples.seed)
    if cache.exists():
        with np.load(cache) as z:
            V, T = z["vertices"], z["tets"]
    else:
        cage = make_cage(solid, samples.points, config.cage)
        V, T = cage.vertices, cage.tets
        np.savez(cache, vertices=V, tets=T)
    objectives = config.objectives_for(spec)
    machine, toolpath = load_profile(config.machine), config.toolpath_for(spec)
    neural = config.neural.with_head(machine.nozzle, config.toolpath.line_width, toolpath.collision_tilt_deg
                                     ).with_tilt_bound(machine.printing_direction_bound_deg())
    cfg = neural.for_objectives(objectives).model_copy(update={"device": "cpu"})
    pool = None
    if cfg.loss.w_gc > 0:
        pool = collision_pool(solid.H, solid.bounds, solid.volume(), samples.points, cfg.loss.gc_points,
                              cfg.loss.gc_spacing, seed=cfg.optim.seed)
    solid_t = solid_tets(solid, V, T) if pool is not None or cfg.loss.tilt_bound_deg is not None else None
    t = time.perf_counter()
    problem = FieldProblem(V, T, samples, None, cfg, solid.platform_z, pool, solid_t)
    info = {"model": model.name, "up": up, "n_elements_target": n_elements, "tets": int(len(T)),
            "vertices": int(len(V)), "objectives": objectives, "samples_B": int(len(problem.b_tet)),
            "pool_points": 0 if pool is None else int(len(pool.points)),
            "pairs_in_reach": 0 if problem.head is None else int(len(problem.head.near)),
            "adjacent_pairs": int(len(problem.geometry.pairs)), "problem_setup_s": time.perf_counter() - t,
            "solver_backend": problem.arap.backend}
    return problem, info


def mid_run(problem: FieldProblem, steps: int, cache: Path) -> bytes:
    """The loop's checkpoint after ``steps`` steps from the seeded start (L_GC's pairs active, LPDs tilted: a step
    of the run's middle, not of its planar start), kept in ``cache`` (a file beside the cage's)."""
    if cache.exists():
        return cache.read_bytes()
    with deterministic_algorithms():
        st = LoopState.start(problem)
        while st.step < steps and not st.converged:
            iterate(problem, st, st.step == 0)
    blob = st.to_bytes(problem.config)
    cache.write_bytes(blob)
    return blob


def resumed(problem: FieldProblem, start: bytes | None) -> LoopState:
    """A loop state at the checkpoint ``start`` (None: the seeded start)."""
    st = LoopState.start(problem)
    if start is not None and not st.restore(start, problem.device):
        raise RuntimeError("the cached mid-run checkpoint is of an older format: delete it")
    return st


def step_times(problem: FieldProblem, start: bytes | None, warmup: int, steps: int
               ) -> tuple[list[float], list[float], LoopState]:
    """Wall and process CPU time (s) of each of ``steps`` loop steps after ``warmup`` steps from ``start``."""
    with deterministic_algorithms():
        st = resumed(problem, start)
        times, cpu = [], []
        for i in range(warmup + steps):
            t, c = time.perf_counter(), time.process_time()
            iterate(problem, st, i == 0)
            if i >= warmup:
                times.append(time.perf_counter() - t)
                cpu.append(time.process_time() - c)
    return times, cpu, st


class PartTimer:
    """Accumulated wall time (s) and calls per named part."""

    def __init__(self) -> None:
        self.total: dict[str, float] = defaultdict(float)
        self.calls: dict[str, int] = defaultdict(int)

    def wrap(self, name: str, fn: Callable) -> Callable:
        """fn timed under name."""
        @functools.wraps(fn)
        def timed(*args, **kwargs):
            t = time.perf_counter()
            try:
                return fn(*args, **kwargs)
            finally:
                self.total[name] += time.perf_counter() - t
                self.calls[name] += 1
        return timed


@contextlib.contextmanager
def patched(targets: list[tuple[object, str, str]], timer: PartTimer) -> Iterator[None]:
    """Replace each (owner, attribute) by its timed wrapper named name, restoring them after."""
    saved = [(owner, attr, getattr(owner, attr)) for owner, attr, _ in targets]
    try:
        for owner, attr, name in targets:
            setattr(owner, attr, timer.wrap(name, getattr(owner, attr)))
        yield
    finally:
        for owner, attr, fn in saved:
            setattr(owner, attr, fn)


def breakdown(problem: FieldProblem, start: bytes | None, warmup: int, steps: int) -> dict:
    """Mean wall time per step (ms) of each part, the parts timed by wrappers around them."""
    timer = PartTimer()
    head = problem.head
    targets = [(problem.arap, "deformed_height", "arap_rhs_and_solve_fwd"), (P, "field_gradient", "field_gradient"),
               (L, "support_free_loss", "loss_sf"), (L, "point_overhang_loss", "loss_po"),
               (L, "strength_loss", "loss_sr"), (L, "harmonic_scale_loss", "loss_hs"),
               (L, "harmonic_quaternion_loss", "loss_hq"), (L, "collision_excess", "loss_ca_excess"),
               (torch.Tensor, "backward", "backward"), (torch.autograd, "grad", "dc3_correction_grad"),
               (O, "_clone_state", "best_state_copy"), (O, "loss_of", "best_loss_on_new_pairs"),
               (problem, "constraints_met", "constraint_check"), (problem, "refresh_collisions", "gc_refresh_total")]
    if head is not None:
        targets += [(head, "loss", "loss_gc"), (head, "refresh", "gc_pair_search")]
    with deterministic_algorithms():
        st = resumed(problem, start)
        for i in range(warmup):
            iterate(problem, st, i == 0)
        targets += [(st.fields, "forward", "network_fwd"), (st.optimizer, "step", "adam_step")]
        with patched(targets, timer):
            t = time.perf_counter()
            for _ in range(steps):
                iterate(problem, st, False)
            wall = time.perf_counter() - t
    parts = {k: {"ms_per_step": 1e3 * v / steps, "calls_per_step": timer.calls[k] / steps}
             for k, v in sorted(timer.total.items(), key=lambda kv: -kv[1])}
    return {"wall_ms_per_step": 1e3 * wall / steps, "parts": parts}


def top_ops(problem: FieldProblem, start: bytes | None, warmup: int, steps: int, top: int = 15) -> list[dict]:
    """The ops with the most self CPU time over ``steps`` steps (torch.profiler), ms per step."""
    from torch.profiler import ProfilerActivity, profile

    with deterministic_algorithms():
        st = resumed(problem, start)
        for i in range(warmup):
            iterate(problem, st, i == 0)
        with profile(activities=[ProfilerActivity.CPU]) as prof:
            for _ in range(steps):
                iterate(problem, st, False)
    rows = sorted(prof.key_averages(), key=lambda e: -e.self_cpu_time_total)[:top]
    return [{"op": e.key, "self_ms_per_step": e.self_cpu_time_total / 1e3 / steps, "calls_per_step": e.count / steps}
            for e in rows]


def run(problem: FieldProblem, start: bytes | None, threads: int, warmup: int, steps: int) -> dict:
    """Median step (and its spread, and the process's CPU time per step), the load before and after, at ``threads``
    torch threads."""
    torch.set_num_threads(threads)
    load0 = os.getloadavg()
    times, cpu, st = step_times(problem, start, warmup, steps)
    row = {"torch_threads": torch.get_num_threads(), "steps": steps, "warmup": warmup, "from_step": st.step - steps
           - warmup, "median_s": statistics.median(times), "mean_s": statistics.fmean(times),
           "min_s": min(times), "max_s": max(times), "times_s": times, "cpu_median_s": statistics.median(cpu),
           "cpu_mean_s": statistics.fmean(cpu),
           "corrections": st.history["corrections"][warmup:], "active_pairs": int(len(problem.head.pairs))
           if problem.head is not None else 0,
           "loadavg_before": load0, "loadavg_after": os.getloadavg()}
    print(f"threads {threads}: median {1e3 * row['median_s']:.0f} ms/step (mean {1e3 * row['mean_s']:.0f}, min "
          f"{1e3 * row['min_s']:.0f}, max {1e3 * row['max_s']:.0f}; CPU median {1e3 * row['cpu_median_s']:.0f} ms), "
          f"load {load0[0]:.1f} -> {row['loadavg_after'][0]:.1f}", flush=True)
    return row


def main(argv: list[str] | None = None) -> None:
    """Command line entry point."""
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--model", default=str(DATA / "topopt_new4.tet"))
    p.add_argument("--up", default="y")
    p.add_argument("--elements", type=int, default=47_000)
    p.add_argument("--cage-cache", default=str(Path(tempfile.gettempdir()) / "bench_step_cage_topopt_new4_47000.npz"))
    p.add_argument("--threads", type=int, nargs="+", default=[2, 1])
    p.add_argument("--steps", type=int, default=20)
    p.add_argument("--warmup", type=int, default=5)
    p.add_argument("--start-step", type=int, default=300, help="time the steps after this many (0: the start)")
    p.add_argument("--no-breakdown", action="store_true")
    p.add_argument("--out", default=str(RESULTS))
    p.add_argument("--label", default="current", help="the key of these figures in the JSON (others are kept)")
    a = p.parse_args(argv)
    torch.set_num_threads(a.threads[0])
    problem, info = build_problem(Path(a.model), a.up, a.elements, Path(a.cage_cache))
    print(json.dumps(info), flush=True)
    start = None
    if a.start_step > 0:
        t = time.perf_counter()
        start = mid_run(problem, a.start_step, Path(a.cage_cache).with_suffix(f".step{a.start_step}.pt"))
        info["start_step"], info["start_s"] = a.start_step, time.perf_counter() - t
    out = {"problem": info, "runs": [run(problem, start, n, a.warmup, a.steps) for n in a.threads]}
    if not a.no_breakdown:
        torch.set_num_threads(a.threads[0])
        out["breakdown"] = breakdown(problem, start, a.warmup, a.steps)
        out["breakdown"]["torch_threads"] = torch.get_num_threads()
        out["profile_top_ops"] = top_ops(problem, start, a.warmup, min(a.steps, 10))
        for k, v in out["breakdown"]["parts"].items():
            print(f"  {k:>28}: {v['ms_per_step']:8.1f} ms/step ({v['calls_per_step']:.2f} calls)")
        for r in out["profile_top_ops"]:
            print(f"  {r['op'][:40]:>40}: {r['self_ms_per_step']:8.1f} ms/step")
    out["machine"] = {"platform": platform.platform(), "cpu_count": os.cpu_count(), "torch": torch.__version__,
                      "GOMP_SPINCOUNT": os.environ.get("GOMP_SPINCOUNT"), "loadavg_end": os.getloadavg()}
    path = Path(a.out)
    data = json.loads(path.read_text()) if path.exists() else {}
    data[a.label] = out
    path.parent.mkdir(parents=True, exist_ok=True)
    path.write_text(json.dumps(data, indent=2))


if __name__ == "__main__":
    main()
