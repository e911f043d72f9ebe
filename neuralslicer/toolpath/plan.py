"""The toolpaths step (SPEC step 11): paths on every curved layer, with the beads the machine's nozzle lays."""
from __future__ import annotations

import time
from pathlib import Path
from typing import TYPE_CHECKING, Sequence

import numpy as np

from neuralslicer.allocator import release_freed_memory
from neuralslicer.errors import InputError
from neuralslicer.layers import LayerConfig
from neuralslicer.motion.planning import merge_short_moves
from neuralslicer.motion.profile import MachineProfile, load_profile
from neuralslicer.stress_field import StressLike
from neuralslicer.toolpath.beads import hold_beads
from neuralslicer.toolpath.config import ToolpathConfig
from neuralslicer.toolpath.generate import toolpaths
from neuralslicer.toolpath.types import Toolpaths

if TYPE_CHECKING:  # trimesh only where a mesh is made: not on a cached rerun
    import trimesh


def machine_profile(profile: MachineProfile | str | Path | None) -> MachineProfile:
    """A machine profile from a profile, a shipped name or a YAML path (default ``table_bc_linuxcnc``)."""
    return load_profile(profile or "table_bc_linuxcnc") if profile is None or isinstance(profile, (str, Path)) else profile


def plan_toolpaths(layers: Sequence[trimesh.Trimesh], *, platform_z: float, toolpath_cfg: ToolpathConfig | None = None,
                   profile: MachineProfile | str | None = None, t_max: float | None = None,
                   stress: StressLike | None = None) -> Toolpaths:
    """The toolpaths step: paths on every layer (:func:`neuralslicer.motion.plan.plan_print` for the arguments), bead
    widths within the nozzle's, thin beads held, short moves merged; what the motion step reports of them rides in
    ``attrs``."""
    profile, cfg = machine_profile(profile), toolpath_cfg or ToolpathConfig()
    t0 = time.perf_counter()
    w_lo, w_hi = profile.nozzle.bead_width_mm
    if not w_lo <= cfg.line_width <= w_hi:
        raise InputError("toolpath.line_width", f"{cfg.line_width:g} mm is outside the bead widths the nozzle of "
                         f"{profile.name} lays ({w_lo:g}..{w_hi:g} mm, nozzle.bead_width_mm)")
    tp = toolpaths(layers, platform_z=platform_z, config=cfg, t_max=LayerConfig().t_max if t_max is None else t_max,
                   stress=stress)
    np.clip(tp.width, w_lo, w_hi, out=tp.width)
    release_freed_memory()   # the layers' many small arrays, freed: room for the whole print's copies below
    tp, beads = hold_beads(tp, profile.nozzle.bead_thickness_mm) if cfg.thin_beads == "carry" else (tp, None)
    tp, n_merged = merge_short_moves(tp, profile)
    tp.attrs.update(held_beads=beads, n_merged_short_moves=n_merged, toolpaths_s=time.perf_counter() - t0)
    return tp
