"""The motion step (SPEC step 12): toolpaths to the machine program, collision-free, with its metrics; and
:func:`plan_print`, the toolpaths and motion steps in one call."""
from __future__ import annotations

import dataclasses
import time
from pathlib import Path
from typing import TYPE_CHECKING, Callable, Sequence

import numpy as np

from neuralslicer.allocator import release_freed_memory
from neuralslicer.errors import PlanError
from neuralslicer.model.grid import values_above
from neuralslicer.motion.collision import CollisionReport, check_collisions, default_min_height
from neuralslicer.motion.material import PrintedMaterial
from neuralslicer.motion.park import parked
from neuralslicer.motion.planning import MachineProgram, feature_runs, plan_motion, program_metrics
from neuralslicer.motion.profile import MachineProfile
from neuralslicer.motion.reorient import clamp_to_platform, clamp_to_reach, tilt_away
from neuralslicer.motion.travel import raise_travels
from neuralslicer.stress_field import StressLike
from neuralslicer.toolpath.beads import bead_summary
from neuralslicer.toolpath.config import ToolpathConfig
from neuralslicer.toolpath.plan import machine_profile, plan_toolpaths
from neuralslicer.toolpath.types import Toolpaths

#: a printing waypoint farther than this (mm) outside the solid (H above it) counts as outside
OUTSIDE_TOL = 1e-3

if TYPE_CHECKING:  # trimesh (and scipy.spatial, networkx) only where a mesh is made: not on a cached rerun
    import trimesh


def plan_print(layers: Sequence[trimesh.Trimesh], *, platform_z: float,
               solid_H: Callable[[np.ndarray], np.ndarray] | None = None,
               toolpath_cfg: ToolpathConfig | None = None,
               profile: MachineProfile | str | None = None, t_max: float | None = None,
               stress: StressLike | None = None) -> tuple[Toolpaths, MachineProgram, dict, CollisionReport]:
    """Toolpaths, machine program, metrics and the head's collisions for curved layers in print order: the
    toolpaths step (:func:`plan_toolpaths`) then the motion step (:func:`plan_motion_of`), as the pipeline runs them.

    layers : build-frame layer meshes (faces along the LPD, ``vertex_attributes['lpd']``);
    platform_z : platform height; solid_H : optional implicit solid (H < 0 inside, at most 1-Lipschitz as a signed
    distance is) used to count waypoints outside the solid; profile : a MachineProfile, a shipped profile name or a
    YAML path (default ``table_bc_linuxcnc``); t_max : the layers' largest thickness (default ``LayerConfig().t_max``),
    which caps the measured bead thickness; stress : the load case's stress, for stress-following infill (whose
    widths are kept within the nozzle's bead widths). Metrics: estimated_print_time_s, toolpath_length_mm,
    n_waypoints, material_mm3, collisions, rotary statistics, timings.
    """
    profile = machine_profile(profile)
    tp = plan_toolpaths(layers, platform_z=platform_z, toolpath_cfg=toolpath_cfg, profile=profile, t_max=t_max,
                        stress=stress)
    return plan_motion_of(tp, platform_z=platform_z, solid_H=solid_H, toolpath_cfg=toolpath_cfg, profile=profile,
                          consume=True)


def plan_motion_of(tp: Toolpaths, *, platform_z: float, solid_H: Callable[[np.ndarray], np.ndarray] | None = None,
                   toolpath_cfg: ToolpathConfig | None = None, profile: MachineProfile | str | None = None,
                   consume: bool = False, scratch: str | Path | None = None
                   ) -> tuple[Toolpaths, MachineProgram, dict, CollisionReport]:
    """The motion step: the head clear of the platform, the exact collision check, travels lifted, axes tilted and
    turned into reach, then the machine program (IK, extrusion) and the print's metrics (:func:`plan_print`).
    With ``consume`` the arrays of ``tp`` are taken over (``tp`` is left empty), so that the toolpaths as they came
    are freed once the lifts have copied them, not held by the caller beside the program. A large print's toolpaths
    are parked in a temporary folder inside ``scratch`` (None: the system's temporary folder) while the program is
    planned (``motion/park.py``)."""
    profile, cfg = machine_profile(profile), toolpath_cfg or ToolpathConfig()
    tp = _taken(tp) if consume else dataclasses.replace(tp, attrs=dict(tp.attrs))   # attrs: the caller's unchanged
    held, n_merged = tp.attrs.pop("held_beads", None), tp.attrs.pop("n_merged_short_moves", 0)
    toolpaths_s = tp.attrs.pop("toolpaths_s", 0.0)
    t1 = time.perf_counter()
    tp, vertical = _vertical_head(tp, profile)
    # near the platform a tilted head dips below it: turn those axes up first (exact, local), the check judges after
    tp, platform = clamp_to_platform(tp, profile.nozzle, platform_z, cfg.collision_tilt_deg)
    # the beads as planned: one structure for the check, the lifts and the tilts (they move the nozzle, not the beads)
    material = PrintedMaterial.of_toolpaths(tp)
    release_freed_memory()   # the build's sort orders and keys (some 40 bytes a waypoint): not kept through the check
    report = check_collisions(tp, profile.nozzle, platform_z, material=material)
    t2 = time.perf_counter()
    min_height = default_min_height(tp)
    tp, report, lifted = raise_travels(tp, report, profile.nozzle, platform_z, min_height, material=material,
                                       consume=True)
    tp, report, tilt = _tilt_clear(tp, report, profile, platform_z, cfg, material)
    tp, report, reach = _clamp_reach(tp, report, profile, platform_z, cfg, material)
    # a travel into a waypoint that collided itself shows only once the tilt has cleared that waypoint: lift it now
    tp, report, again = raise_travels(tp, report, profile.nozzle, platform_z, min_height, material=material,
                                      consume=True)
    lifted = _merged_lifts(lifted, again)
    del material   # the beads' grid (~100 bytes a waypoint): the program and its timing need the room
    release_freed_memory()
    t3 = time.perf_counter()
    on = tp.path >= 0
    # the count of printing waypoints outside the solid, before the program (its arrays would come on top of them)
    outside = None if solid_H is None else values_above(solid_H, tp.xyz[on & tp.extrude], OUTSIDE_TOL)
    release_freed_memory()
    t_plan = time.perf_counter()
    # a large print's toolpaths wait on disk while the program is planned and timed: the two are not held at once
    with parked(tp, scratch) as waiting:
        del tp
        program = plan_motion(waiting, profile, platform_z=platform_z)
        release_freed_memory()     # the planning's temporaries: the features' and the time estimate's arrays come next
        program.attrs["isovalues"] = waiting.attrs.get("isovalues", [])
        program.attrs["features"] = feature_runs(program, waiting.path, waiting.attrs.get("path_kinds", ""))
        release_freed_memory()
        t4 = time.perf_counter()
        metrics = program_metrics(program)
        release_freed_memory()
        tp = waiting.load()
    if vertical is not None:
        metrics["three_axis"] = vertical
    metrics.update(travel_lift=lifted, axis_tilt=tilt, axis_reach=reach, axis_platform=platform,
                   n_merged_short_moves=n_merged,
                   beads=held if held is not None else bead_summary(tp, profile.nozzle.bead_thickness_mm),
                   n_waypoints=len(tp), n_layers=tp.n_layers, n_paths=int(tp.attrs.get("n_paths", 0)))
    metrics.update(report.summary())
    metrics.update({k: v for k, v in program.attrs.items() if k not in ("platform_z", "isovalues", "features")})
    metrics["thickness_mm"] = {"min": float(tp.thickness[on].min()), "mean": float(tp.thickness[on].mean()),
                               "max": float(tp.thickness[on].max())}
    if outside is not None:
        metrics["n_waypoints_outside_solid"], metrics["max_H_at_waypoints"] = outside
    metrics["timings_s"] = {"toolpaths": toolpaths_s, "collisions": t2 - t1, "tilt": t3 - t2, "motion": t4 - t_plan}
    tp.attrs["collision_waypoints"] = [int(i) for i in report.indices[:1000]]
    release_freed_memory()         # the store's write of the toolpaths and the program comes next
    return tp, program, metrics, report


def _taken(tp: Toolpaths) -> Toolpaths:
    """Toolpaths holding the arrays of ``tp`` (and a copy of its attrs), ``tp`` left with empty arrays."""
    out = dataclasses.replace(tp, attrs=dict(tp.attrs))
    for name in Toolpaths.ARRAYS:
        setattr(tp, name, getattr(tp, name)[:0].copy())
    return out


def _vertical_head(tp: Toolpaths, profile: MachineProfile) -> tuple[Toolpaths, dict | None]:
    """On a three-axis machine the head stays vertical: the tool axes set to +z (the check, the lifts and the
    program see the head as it is), with how far the printing directions (the layers' normals) lean from +z
    against the head's clearance; five-axis toolpaths unchanged (and None)."""
    kin = profile.kinematics
    if kin.rotary:
        return tp, None
    on = tp.extrude
    lean = np.degrees(np.arccos(np.clip(tp.axis[on, 2], -1.0, 1.0)))
    beyond = lean > kin.clearance_deg + 1e-6
    summary = {"clearance_deg": float(kin.clearance_deg), "max_printing_angle_deg": float(lean.max(initial=0.0)),
               "p99_printing_angle_deg": float(np.percentile(lean, 99)) if len(lean) else 0.0,
               "n_printing_beyond_clearance": int(beyond.sum()),
               "frac_printing_beyond_clearance": float(beyond.mean()) if len(lean) else 0.0}
    axis = np.zeros_like(tp.axis)
    axis[:, 2] = 1.0
    return dataclasses.replace(tp, axis=axis, attrs=dict(tp.attrs)), summary


def _merged_lifts(first: dict, second: dict) -> dict:
    """The travel-lift summary of two passes of ``raise_travels`` (the second on what the tilt left)."""
    return {"n_travels_lifted": first["n_travels_lifted"] + second["n_travels_lifted"],
            "n_travels_by_clearance_plane": first["n_travels_by_clearance_plane"] + second["n_travels_by_clearance_plane"],
            "max_lift_mm": max(first["max_lift_mm"], second["max_lift_mm"]),
            "n_travels_unresolved": second["n_travels_unresolved"],
            "n_travels_lifted_after_tilt": second["n_travels_lifted"]}


def _tilt_clear(tp: Toolpaths, report: CollisionReport, profile: MachineProfile, platform_z: float,
                cfg: ToolpathConfig, material: PrintedMaterial | None = None, passes: int = 3
                ) -> tuple[Toolpaths, CollisionReport, dict]:
    """Tilt the tool axis clear at stray colliding waypoints (``cfg.collision_tilt_deg``); every tilted
    waypoint is checked again exactly (the material, earlier waypoints' positions, does not move), and a
    pass that does not lower the count is dropped. Later passes try the collisions the ramps caused."""
    summary = {"n_collisions_before": report.count, "n_collisions_cleared": 0, "n_untiltable_collisions": 0,
               "n_waypoints_tilted": 0, "max_tilt_deg": 0.0}
    if (not report.count or cfg.collision_tilt_deg <= 0 or report.count > cfg.collision_tilt_max_waypoints
            or not profile.kinematics.rotary):
        return tp, report, summary
    min_height = default_min_height(tp)
    material = PrintedMaterial.of_toolpaths(tp) if material is None else material
    untiltable = np.zeros(0, np.int64)
    changed: list[np.ndarray] = []
    max_tilt = 0.0
    for _ in range(passes):
        todo = report.subset(~np.isin(report.indices, untiltable))
        if not todo.count:
            break
        tilted, how = tilt_away(tp, todo, profile.nozzle, platform_z, min_height, max_tilt_deg=cfg.collision_tilt_deg,
                                ramp_mm=cfg.collision_tilt_ramp, material=material)
        untiltable = np.union1d(untiltable, how.unfixed)
        if len(how.fixed) == 0:
            break
        after = report.replaced(how.changed, check_collisions(tilted, profile.nozzle, platform_z, min_height,
                                                              only=how.changed, material=material))
        if after.count >= report.count:
            break
        tp, report = tilted, after
        changed.append(how.changed)
        max_tilt = max(max_tilt, float(how.tilt_deg.max(initial=0.0)))
    if changed:
        all_changed = np.unique(np.concatenate(changed))
        tp.attrs["tilted_waypoints"] = [int(i) for i in all_changed[:1000]]
        summary.update({"n_waypoints_tilted": int(len(all_changed)), "max_tilt_deg": max_tilt,
                        "n_collisions_cleared": summary["n_collisions_before"] - report.count})
    summary["n_untiltable_collisions"] = int(np.isin(report.indices, untiltable).sum())
    return tp, report, summary


def _clamp_reach(tp: Toolpaths, report: CollisionReport, profile: MachineProfile, platform_z: float,
                 cfg: ToolpathConfig, material: PrintedMaterial | None = None
                 ) -> tuple[Toolpaths, CollisionReport, dict]:
    """Tool axes beyond the machine's tilt range turned back to it: up to ``cfg.collision_tilt_deg`` always, any
    angle with ``kinematics.beyond_reach = "turn"`` (else a PlanError naming the layers); the turned
    waypoints checked for collisions again."""
    kin = profile.kinematics
    reach_deg = kin.reach_deg()
    excess = np.degrees(np.arccos(np.clip(tp.axis[:, 2], -1.0, 1.0))) - reach_deg
    far = excess > cfg.collision_tilt_deg + 1e-9
    if far.any() and kin.beyond_reach == "fail":
        layers = np.unique(tp.layer[far])
        raise PlanError(f"{int(far.sum()):,} waypoints need the tool axis more than {cfg.collision_tilt_deg:g} deg beyond "
                        f"the machine's reach ({reach_deg:g} deg from +z, {profile.name}) in layers "
                        f"{', '.join(str(int(k)) for k in layers[:10])}{' ...' if len(layers) > 10 else ''}; "
                        "kinematics.beyond_reach: turn turns them back onto the limit")
    clamped, summary = clamp_to_reach(tp, reach_deg, 180.0)
    summary["n_beyond_tilt_bound"] = int(far.sum())
    if clamped is tp:
        return tp, report, summary
    changed = np.flatnonzero(np.any(clamped.axis != tp.axis, axis=1))
    report = report.replaced(changed, check_collisions(clamped, profile.nozzle, platform_z, only=changed,
                                                       material=material))
    return clamped, report, summary
