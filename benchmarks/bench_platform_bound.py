"""How much of planar layers' overhang can any field remove on a part, given only that the print head stays above
the platform? An optimistic bound that tells a target the head cannot reach from one the optimiser misses.

    .venv/bin/python benchmarks/bench_platform_bound.py [NAME.stl ...]   # default: the 200 mm bunny and coin

For every held-out surface sample of the overhang metric (`metrics.heldout_surface_samples`, platform contact left
out as the metric does), every tool axis of a 2° x 10° grid (tilt x azimuth) is tried at that point; an axis is
allowed when the head (the machine profile's nozzle: cone and holder, `HeadShape.lowest`, the same geometry as
L_GC's platform term and the exact check) stays above the platform with its tip there, either as it is or, as the
planner does (`motion.reorient.clamp_to_platform`), after turning it up toward +z by at most
`toolpath.collision_tilt_deg` (15°; the overhang metrics judge the layers, not the turned axis, so both figures are
given). The point stays overhanging when no allowed axis brings its overhang angle to α = 45° or below. Everything
else a print must respect is left out: material printed earlier (the holder sweeping over the part), the field being
one smooth function (neighbouring points share their axis), layer thickness limits, the machine's axis range. A real
field can only do worse than this bound.
Results: benchmarks/results/bench_platform_bound.json.
"""
from __future__ import annotations

import json
import sys
from pathlib import Path

import numpy as np
import torch
import trimesh

from neuralslicer.data import sample
from neuralslicer.metrics import heldout_surface_samples, overhang_area_fraction
from neuralslicer.motion.profile import Nozzle
from neuralslicer.neural.head_collision import HeadShape
from neuralslicer.toolpath.config import ToolpathConfig

RESULTS = Path(__file__).resolve().parent / "results" / "bench_platform_bound.json"
ALPHA_DEG = 45.0


def axes_grid(tilt_step_deg: float = 2.0, azimuth_step_deg: float = 10.0) -> np.ndarray:
    """Unit tool axes (k,3) on a tilt x azimuth grid, tilt 0..90°."""
    tilt = np.radians(np.arange(0.0, 90.0 + 1e-9, tilt_step_deg))
    azimuth = np.radians(np.arange(0.0, 360.0, azimuth_step_deg))
    t, a = (g.ravel() for g in np.meshgrid(tilt, azimuth))
    return np.stack([np.sin(t) * np.cos(a), np.sin(t) * np.sin(a), np.cos(t)], axis=1)


def platform_bound(mesh: trimesh.Trimesh, head: HeadShape, turn_deg: float = 0.0, n_points: int = 40_000) -> dict:
    """Planar overhang area fraction and the least any head-above-platform field could leave, on the held-out
    surface samples of the overhang metric (its platform flags included)."""
    platform_z = float(mesh.bounds[0, 2])
    points, normals, areas, on_platform = heldout_surface_samples(mesh, n_points, platform_z)
    planar = overhang_area_fraction(normals, areas, on_platform, np.tile([0.0, 0.0, 1.0], (len(points), 1)), ALPHA_DEG)
    keep = ~on_platform
    normals, height = normals[keep], points[keep, 2] - platform_z
    axes = axes_grid()
    lowest = head.lowest(torch.as_tensor(axes), np.radians(turn_deg)).numpy()  # turned toward +z as the planner does
    best = np.empty(len(height))
    for i in range(0, len(height), 2000):
        allowed = height[i:i + 2000, None] + lowest[None, :] >= 0.0
        angle = np.degrees(np.arcsin(np.clip(-(normals[i:i + 2000] @ axes.T), -1.0, 1.0)))
        best[i:i + 2000] = np.where(allowed, angle, np.inf).min(axis=1)
    left = best > ALPHA_DEG  # equal areas: the share of samples is the area fraction
    return {"samples": int(len(height)), "overhang_planar": planar, "overhang_bound": float(left.mean()),
            "reduction_bound": float(1.0 - left.mean() / planar) if planar > 0 else None,
            "bound_left_below_mm": {str(z): float((left & (height < z)).mean()) for z in (2, 5, 10, 20)}}


def main(names: list[str]) -> None:
    """Bound every model named (shipped z-up STLs), print and write the JSON."""
    nozzle = Nozzle()
    head = HeadShape.from_nozzle(nozzle, 0.5)
    turn = ToolpathConfig().collision_tilt_deg
    results = {"nozzle": nozzle.model_dump(mode="json"), "alpha_deg": ALPHA_DEG, "turn_deg": turn, "models": {}}
    for name in names or ["bunny_closed_low_res.stl", "overhang_coin_closed_low_res.stl"]:
        mesh = trimesh.load(sample(name), force="mesh")
        for label, deg in (("axis_is_lpd", 0.0), ("planner_turn", turn)):
            row = platform_bound(mesh, head, deg)
            results["models"].setdefault(name, {})[label] = row
            print(f"{name}, {label}: planar {100 * row['overhang_planar']:.1f} %, at best "
                  f"{100 * row['overhang_bound']:.2f} % ({100 * row['reduction_bound']:.0f} % removed at most); left "
                  f"within 5 mm of the platform: {100 * row['bound_left_below_mm']['5']:.2f} %", flush=True)
    tmp = RESULTS.with_suffix(".json.tmp")
    tmp.write_text(json.dumps(results, indent=2))
    tmp.replace(RESULTS)


if __name__ == "__main__":
    main(sys.argv[1:])
