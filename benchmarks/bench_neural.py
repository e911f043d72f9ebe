"""Benchmark of the neural optimisation: ARAP solve (sparse factor vs dense Cholesky), time per
optimisation step and peak memory for the default and `paper` networks, and the Ring experiment.

    python benchmarks/bench_neural.py solve            # sparse vs dense solve at 5k/20k/50k tets
    python benchmarks/bench_neural.py steps            # time/step + peak memory per size and network
    python benchmarks/bench_neural.py ring             # Ring, SF only: overhang vs planar, 3 initial guesses
    python benchmarks/bench_neural.py bridge           # the paper's Bridge size: a real part's cage at 47k tets,
                                                       # default objectives, per step and to convergence
    python benchmarks/bench_neural.py loaded           # time/step alone and two optimisations at once, per OpenMP
                                                       # spin setting (what a busy shared node does to a run)
    python benchmarks/bench_neural.py all

Prints a table per part and merges the figures into benchmarks/results/bench_neural.json. The process is set up as
the command sets itself up (a short OpenMP spin, ``GOMP_SPINCOUNT``; the allocator), except where ``loaded`` sets
the OpenMP wait itself.
"""
from __future__ import annotations

import argparse
import json
import math
import os
import platform
import resource
import subprocess
import sys
import time
from pathlib import Path

from neuralslicer.allocator import keep_freed_memory
from neuralslicer.neural.device import limit_threads

limit_threads()  # as the command: a short OpenMP spin (GOMP_SPINCOUNT), set before torch is imported
keep_freed_memory()  # as the command: large arrays from the heap, freed memory kept (neuralslicer/allocator.py)

import numpy as np  # noqa: E402
import scipy.linalg as sla  # noqa: E402
import torch  # noqa: E402

from neuralslicer.neural import NeuralConfig, optimise_field
from neuralslicer.neural.config import DeformationConfig
from neuralslicer.neural.deformation import ArapDeformation
from neuralslicer.neural.problem import FieldProblem
from neuralslicer.samples import SurfaceSamples
from neuralslicer.tetmesh import box_tet_grid

RESULTS = Path(__file__).parent / "results" / "bench_neural.json"
#: grid shapes giving about 5k, 20k and 50k tets (6 per cell)
SIZES = {"5k": (10, 10, 9), "20k": (16, 16, 13), "50k": (22, 22, 18)}


def _merge(key: str, value) -> None:
    """Merge one part's figures into the JSON results file."""
    data = json.loads(RESULTS.read_text()) if RESULTS.exists() else {}
    data[key] = value
    data["machine"] = {"platform": platform.platform(), "cpu_count": os.cpu_count(),
                       "torch_threads": torch.get_num_threads(), "torch": torch.__version__,
                       "cuda": torch.cuda.get_device_name() if torch.cuda.is_available() else None}
    RESULTS.parent.mkdir(parents=True, exist_ok=True)
    RESULTS.write_text(json.dumps(data, indent=2))


def _sphere_samples(lo: np.ndarray, hi: np.ndarray, n: int = 4000, k: int = 10):
    """Fibonacci samples on a sphere inside the box (synthetic B)."""
    from scipy.spatial import cKDTree

    c, r = 0.5 * (lo + hi), 0.4 * float(np.min(hi - lo))
    i = np.arange(n) + 0.5
    phi, th = np.arccos(1 - 2 * i / n), math.pi * (1 + 5**0.5) * i
    nrm = np.stack([np.cos(th) * np.sin(phi), np.sin(th) * np.sin(phi), np.cos(phi)], axis=1)
    pts = c + r * nrm
    dist, knn = cKDTree(pts).query(pts, k=k + 1)
    return pts, nrm, (dist[:, 1:] ** 2).mean(axis=1), knn[:, 1:], nrm[:, 2] < -0.99


def _cage(size: str):
    """Structured cage of the named size in a 100 mm box."""
    shape = SIZES[size]
    return box_tet_grid(shape, np.zeros(3), 100.0 * np.asarray(shape) / max(shape))


def bench_solve(sizes: list[str], repeats: int = 20) -> list[dict]:
    """Per-solve time and memory: our sparse factor vs a dense Cholesky of the same K."""
    rows = []
    backends = ["splu"]
    try:
        import cholespy  # noqa: F401

        backends.append("cholespy")
    except ImportError:
        pass
    for size, backend in [(s, b) for s in sizes for b in backends]:
        V, T = _cage(size)
        t = time.perf_counter()
        arap = ArapDeformation(V, T, DeformationConfig(solver=backend))
        t_factor = time.perf_counter() - t
        rhs = np.random.default_rng(0).standard_normal((len(V), 3))
        arap._solve_xyz(rhs)
        t = time.perf_counter()
        for _ in range(repeats):
            x = arap._solve_xyz(rhs)
        t_solve = (time.perf_counter() - t) / repeats
        lu = getattr(arap._solve_xyz, "__self__", None)
        nnz_factor = int(lu.L.nnz + lu.U.nnz) if lu is not None else -1
        row = {"size": size, "tets": len(T), "vertices": len(V), "backend": arap.backend,
               "nnz_K": int(arap.K.nnz), "nnz_factor": nnz_factor,
               "sparse_factor_s": t_factor, "sparse_solve_s": t_solve,
               "sparse_factor_MB": nnz_factor * 12 / 2**20 if nnz_factor > 0 else None}
        n = len(V)
        if n <= 12_000 and backend == "splu":
            K = arap.K.toarray()
            t = time.perf_counter()
            c = sla.cho_factor(K, lower=True)
            row["dense_factor_s"] = time.perf_counter() - t
            sla.cho_solve(c, rhs)
            t = time.perf_counter()
            for _ in range(max(3, repeats // 4)):
                xd = sla.cho_solve(c, rhs)
            row["dense_solve_s"] = (time.perf_counter() - t) / max(3, repeats // 4)
            row["dense_matrix_MB"] = n * n * 8 / 2**20
            row["max_abs_diff"] = float(np.abs(xd - x).max())
            row["speedup_per_solve"] = row["dense_solve_s"] / t_solve
            dense = {k: row[k] for k in ("dense_factor_s", "dense_solve_s", "dense_matrix_MB")}
            del K, c
        elif "dense" in locals() and backend != "splu":
            row.update(dense)
            row["speedup_per_solve"] = row["dense_solve_s"] / t_solve
        rows.append(row)
    print(f"\n{'size':>5} {'backend':>8} {'tets':>7} {'verts':>6} {'nnz(K)':>8} {'nnz(LU)':>9} {'fact s':>8} "
          f"{'solve ms':>9} {'dense fact s':>12} {'dense ms':>9} {'speedup':>8} {'dense MB':>9} {'LU MB':>7}")
    for r in rows:
        print(f"{r['size']:>5} {r['backend']:>8} {r['tets']:>7} {r['vertices']:>6} {r['nnz_K']:>8} {r['nnz_factor']:>9} "
              f"{r['sparse_factor_s']:>8.3f} {1e3 * r['sparse_solve_s']:>9.3f} "
              f"{r.get('dense_factor_s', float('nan')):>12.3f} {1e3 * r.get('dense_solve_s', float('nan')):>9.2f} "
              f"{r.get('speedup_per_solve', float('nan')):>8.1f} {r.get('dense_matrix_MB', float('nan')):>9.1f} "
              f"{r['sparse_factor_MB'] or float('nan'):>7.2f}")
    return rows


def _step_case(size: str, network: str, steps: int, device: str) -> dict:
    """Time per optimisation step (forward, backward, Adam) and peak memory, in this process."""
    V, T = _cage(size)
    lo, hi = V.min(0), V.max(0)
    pts, nrm, area, knn, pf = _sphere_samples(lo, hi)
    cfg = NeuralConfig.model_validate({"network": network, "device": device})
    t = time.perf_counter()
    prob = FieldProblem(V, T, SurfaceSamples(pts, nrm, area, knn, pf), None, cfg, 0.0)
    setup = time.perf_counter() - t
    torch.manual_seed(0)
    fields = prob.new_fields()
    opt = torch.optim.Adam(fields.parameters(), lr=1e-3)
    if prob.device.type == "cuda":
        torch.cuda.reset_peak_memory_stats()
    times = []
    for i in range(steps + 1):
        if prob.device.type == "cuda":
            torch.cuda.synchronize()
        t = time.perf_counter()
        total, _ = prob.evaluate(fields)
        opt.zero_grad()
        total.backward()
        opt.step()
        if prob.device.type == "cuda":
            torch.cuda.synchronize()
        if i:  # the first step warms up
            times.append(time.perf_counter() - t)
    out = {"size": size, "tets": len(T), "network": network, "device": str(prob.device),
           "setup_s": setup, "step_s": float(np.median(times)), "steps_timed": steps,
           "peak_rss_MB": resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024}
    if prob.device.type == "cuda":
        out["peak_cuda_MB"] = torch.cuda.max_memory_allocated() / 2**20
    return out


def _step_proc(size: str, steps: int, network: str = "default", device: str = "cpu",
               env: dict[str, str] | None = None) -> subprocess.Popen:
    """A `_step` measurement in a subprocess (its own peak memory), with the given environment additions (an OpenMP
    wait setting among them replaces the command's, which this process passes on otherwise)."""
    base = dict(os.environ)
    if env and {"GOMP_SPINCOUNT", "OMP_WAIT_POLICY"} & env.keys():
        base.pop("GOMP_SPINCOUNT", None)
        base.pop("OMP_WAIT_POLICY", None)
    return subprocess.Popen([sys.executable, __file__, "_step", size, network, str(steps), device],
                            stdout=subprocess.PIPE, text=True, env={**base, **(env or {})})


def _step_result(proc: subprocess.Popen) -> dict:
    """The figures a `_step` subprocess printed on its last line."""
    out, _ = proc.communicate()
    if proc.returncode:
        raise RuntimeError(f"_step failed with exit status {proc.returncode}")
    return json.loads(out.strip().splitlines()[-1])


def bench_steps(sizes: list[str], networks: list[str], steps: int, device: str) -> list[dict]:
    """Each (size, network) in a fresh subprocess so that peak memory is its own."""
    rows = []
    for network in networks:
        for size in sizes:
            n = steps if network != "paper" or device != "cpu" else max(1, steps // 5)
            rows.append(_step_result(_step_proc(size, n, network=network, device=device)))
            r = rows[-1]
            print(f"{r['network']:>8} {r['size']:>4} {r['tets']:>7} tets {r['device']:>5}: "
                  f"{1e3 * r['step_s']:9.1f} ms/step, peak RSS {r['peak_rss_MB']:8.0f} MB"
                  + (f", peak CUDA {r['peak_cuda_MB']:.0f} MB" if "peak_cuda_MB" in r else ""), flush=True)
    return rows


def _step_ms(proc: subprocess.Popen) -> float:
    """Median ms per step a `_step` subprocess reported."""
    return 1e3 * _step_result(proc)["step_s"]


def bench_loaded(size: str, steps: int) -> list[dict]:
    """ms/step of one optimisation alone and of two at once (a shared node), per OpenMP wait setting."""
    from neuralslicer.neural.device import GOMP_SPINCOUNT

    settings = {"libgomp default (300000 spins)": {"GOMP_SPINCOUNT": "300000"},
                f"GOMP_SPINCOUNT={GOMP_SPINCOUNT} (ours)": {"GOMP_SPINCOUNT": str(GOMP_SPINCOUNT)},
                "OMP_WAIT_POLICY=PASSIVE": {"OMP_WAIT_POLICY": "PASSIVE"}}
    rows = []
    for name, env in settings.items():
        alone = _step_ms(_step_proc(size, steps, env=env))
        pair = [_step_proc(size, steps, env=env) for _ in range(2)]
        both = [_step_ms(p) for p in pair]
        rows.append({"setting": name, "size": size, "alone_ms": alone, "two_at_once_ms": float(np.mean(both)),
                     "slowdown": float(np.mean(both)) / alone})
    base = rows[0]["alone_ms"]
    print(f"\n{'OpenMP setting':>34} {'alone ms':>9} {'two at once ms':>15} {'x own alone':>12} {'x default alone':>16}")
    for r in rows:
        print(f"{r['setting']:>34} {r['alone_ms']:>9.1f} {r['two_at_once_ms']:>15.1f} {r['slowdown']:>12.1f} "
              f"{r['two_at_once_ms'] / base:>16.1f}")
    return rows


def ring_inputs(n_elements: int = 5000, n_samples: int = 8000) -> dict[str, np.ndarray]:
    """Ring (y-up) -> solid -> samples B -> cage, with the project's own modules."""
    from neuralslicer.cage import CageConfig, build_cage, interior_points
    from neuralslicer.model.solid import implicit_solid
    from neuralslicer.model.spec import spec_for_file
    from neuralslicer.samples import surface_samples

    ring = Path(__file__).resolve().parents[1] / "neuralslicer" / "data" / "ring.tet"
    solid = implicit_solid(spec_for_file(ring, up="y"))
    B = surface_samples(solid, n_samples)
    check = np.concatenate([interior_points(solid.H, solid.bounds, 2000), B.points])
    cage = build_cage(solid.H, solid.bounds, solid.volume(), CageConfig(n_elements=n_elements), check)
    return {"CV": cage.vertices, "CT": cage.tets, "P": B.points, "N": B.normals, "A": B.areas,
            "K": B.knn, "F": B.on_platform, "pz": np.float64(solid.platform_z)}


def cached_ring_inputs(cache: Path | None) -> dict[str, np.ndarray]:
    """ring_inputs(), kept in (and read back from) an .npz when a cache path is given."""
    if cache is not None and cache.exists():
        return dict(np.load(cache))
    d = ring_inputs()
    if cache is not None:
        cache.parent.mkdir(parents=True, exist_ok=True)
        np.savez(cache, **d)
    return d


def bench_ring(kinds: list[str], cache: Path | None) -> list[dict]:
    """Ring, SF only, default settings: overhang fraction vs planar, time, per initial guess."""
    d = cached_ring_inputs(cache)
    rows = []
    for kind in kinds:
        cfg = NeuralConfig.model_validate({"init": {"kind": kind}})
        user = None
        if kind == "user":  # a user field: distance from the ring's centre axis, flipped (a 'dome')
            c = np.array([0.0, 0.0, 55.0])
            user = -np.linalg.norm((d["CV"] - c)[:, [0, 2]], axis=1)
        r = optimise_field(d["CV"], d["CT"], SurfaceSamples(d["P"], d["N"], d["A"], d["K"], d["F"]), config=cfg,
                           platform_z=float(d["pz"]), user_field=user)
        s = r.satisfaction
        row = {"init": kind, "tets": int(len(d["CT"])), "samples": int(len(d["P"])),
               "steps": r.steps, "converged": r.converged, "wall_s": r.wall_time_s,
               "overhang": s["overhang_area_fraction"], "planar_overhang": s["planar_overhang_area_fraction"],
               "ratio_to_planar": s["overhang_area_fraction"] / s["planar_overhang_area_fraction"],
               "final": r.final, "pretrain_final_mse": float(r.pretrain_history[-1]) if len(r.pretrain_history) else None}
        rows.append(row)
        print(f"ring init={kind:>6}: {row['tets']} tets, {r.steps} steps ({'converged' if r.converged else 'budget'}),"
              f" {r.wall_time_s:6.1f} s, overhang {100 * row['overhang']:.2f}% vs planar"
              f" {100 * row['planar_overhang']:.2f}% ({100 * row['ratio_to_planar']:.1f}%), final loss {r.final['total']:.5f}",
              flush=True)
    return rows


def step_scaling(rows: list[dict]) -> dict:
    """Least-squares fit step_s = a + b * tets over the default network's rows: how linear the step is."""
    pts = [(r["tets"], r["step_s"]) for r in rows if r["network"] == "default"]
    if len(pts) < 2:
        return {}
    n, t = (np.array(v, dtype=float) for v in zip(*pts))
    b, a = np.polyfit(n, t, 1)
    pred = a + b * n
    r2 = 1.0 - float(np.sum((t - pred) ** 2) / max(np.sum((t - t.mean()) ** 2), 1e-300))
    return {"intercept_s": float(a), "s_per_tet": float(b), "r2": r2,
            "us_per_tet": [float(1e6 * ti / ni) for ni, ti in zip(n, t)]}


def bench_bridge(model: Path, up: str, n_elements: int) -> dict:
    """A real part's cage at about ``n_elements`` tets (the paper's Bridge has 47k), the slice command's default
    settings and objectives for it, optimised to convergence: steps, wall time, time per step, overhang."""
    from neuralslicer.cage import make_cage
    from neuralslicer.config import SliceConfig
    from neuralslicer.model.solid import implicit_solid
    from neuralslicer.model.spec import spec_for_file
    from neuralslicer.neural.optimise import optimise_for_solid
    from neuralslicer.samples import surface_samples

    spec = spec_for_file(model, up=up)
    defaults = SliceConfig()
    config = defaults.model_copy(update={"cage": defaults.cage.model_copy(update={"n_elements": n_elements})})
    solid = implicit_solid(spec)
    samples = surface_samples(solid, config.samples.n_samples, k=config.samples.k, seed=config.samples.seed)
    t = time.perf_counter()
    cage = make_cage(solid, samples.points, config.cage)
    cage_s = time.perf_counter() - t
    objectives = config.objectives_for(spec)
    load = os.getloadavg()[0]
    r = optimise_for_solid(solid, cage.vertices, cage.tets, samples, None, objectives, config.neural)
    s = r.satisfaction
    row = {"model": model.name, "tets": int(len(cage.tets)), "vertices": int(len(cage.vertices)),
           "objectives": ",".join(objectives), "cage_s": cage_s, "steps": r.steps, "converged": r.converged,
           "wall_s": r.wall_time_s, "s_per_step": r.wall_time_s / max(r.steps, 1),
           "overhang": s["overhang_area_fraction"], "planar_overhang": s["planar_overhang_area_fraction"],
           "load_at_start": load, "load_at_end": os.getloadavg()[0],
           "peak_rss_MB": resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024}
    print(f"bridge size ({model.name}): {row['tets']} tets, {r.steps} steps "
          f"({'converged' if r.converged else 'budget'}), {r.wall_time_s:.1f} s, {1e3 * row['s_per_step']:.0f} ms/step, "
          f"overhang {100 * row['overhang']:.2f} % (planar {100 * row['planar_overhang']:.2f} %), load {load:.1f}",
          flush=True)
    return row


def main(argv: list[str] | None = None) -> None:
    """Command line entry point."""
    argv = sys.argv[1:] if argv is None else argv
    if argv and argv[0] == "_step":
        size, network, steps, device = argv[1], argv[2], int(argv[3]), argv[4]
        print(json.dumps(_step_case(size, network, steps, device)))
        return
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("part", choices=["solve", "steps", "loaded", "ring", "bridge", "all"])
    p.add_argument("--bridge-model", default=str(Path(os.environ.get("NEURALSLICER_DATA", Path(__file__).resolve().parents[1] / "neuralslicer" / "data"))
                                                   / "topopt_new4.tet"))
    p.add_argument("--bridge-up", default="y")
    p.add_argument("--bridge-elements", type=int, default=47_000)
    p.add_argument("--sizes", default="5k,20k,50k")
    p.add_argument("--networks", default="default,paper")
    p.add_argument("--steps", type=int, default=10)
    p.add_argument("--device", default="cpu")
    p.add_argument("--inits", default="height,heat,user")
    p.add_argument("--ring-cache", default="", help="npz to cache the Ring inputs in (optional)")
    p.add_argument("--no-save", action="store_true", help="print the figures only (a dry run leaves the results alone)")
    a = p.parse_args(argv)
    sizes = a.sizes.split(",")
    if a.part in ("solve", "all"):
        _merge("solve", bench_solve(sizes))
    if a.part in ("steps", "all"):
        rows = bench_steps(sizes, a.networks.split(","), a.steps, a.device)
        fit = step_scaling(rows)
        if fit:
            print(f"default network: step = {1e3 * fit['intercept_s']:.1f} ms + {1e6 * fit['s_per_tet']:.2f} us/tet "
                  f"(R^2 {fit['r2']:.4f})")
        if not a.no_save:
            _merge(f"steps_{rows[0]['device'] if rows else a.device}", rows)
            _merge(f"steps_scaling_{rows[0]['device'] if rows else a.device}", fit)
    if a.part in ("loaded", "all"):
        rows = bench_loaded(sizes[min(1, len(sizes) - 1)], max(a.steps, 40))
        if not a.no_save:
            _merge("loaded_cpu", rows)
    if a.part in ("ring", "all"):
        _merge("ring", bench_ring(a.inits.split(","), Path(a.ring_cache) if a.ring_cache else None))
    if a.part in ("bridge", "all"):
        row = bench_bridge(Path(a.bridge_model), a.bridge_up, a.bridge_elements)
        if not a.no_save:
            _merge("bridge", row)


if __name__ == "__main__":
    main()
