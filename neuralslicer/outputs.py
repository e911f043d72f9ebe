"""The files a print is delivered as: waypoints, G-code, toolpath previews, robot targets, print metrics."""
from __future__ import annotations

import json
from pathlib import Path

from neuralslicer.fileio import write_text_atomic
from neuralslicer.gcode.robot import write_robot_csv, write_robot_json
from neuralslicer.gcode.writers import write_gcode
from neuralslicer.motion.planning import MachineProgram
from neuralslicer.toolpath.io import plot_toolpaths_png, write_toolpaths_vtp, write_waypoints_csv
from neuralslicer.toolpath.types import Toolpaths


def write_print_outputs(out_dir: str | Path, tp: Toolpaths, program: MachineProgram, metrics: dict | None = None,
                        *, robot: bool = False, vtp: bool = True, png: bool = True) -> dict[str, Path]:
    """Write ``toolpaths/waypoints.csv``, ``print.gcode``, ``toolpaths.vtp``, ``toolpaths.png``,
    ``robot_waypoints.csv``/``.json`` (if ``robot``) and ``print_metrics.json`` under ``out_dir``."""
    out = Path(out_dir)
    files = {"waypoints_csv": write_waypoints_csv(out / "toolpaths" / "waypoints.csv", tp),
             "gcode": write_gcode(out / "print.gcode", program)}
    if vtp:
        files["vtp"] = write_toolpaths_vtp(out / "toolpaths.vtp", tp)
    if png:
        files["png"] = plot_toolpaths_png(out / "toolpaths.png", tp)
    if robot:
        d = program.profile.extrusion.filament_diameter
        files["robot_csv"] = write_robot_csv(out / "robot_waypoints.csv", tp, d)
        files["robot_json"] = write_robot_json(out / "robot_waypoints.json", tp, d)
    if metrics is not None:
        p = out / "print_metrics.json"
        write_text_atomic(p, json.dumps(metrics, indent=2, default=float))
        files["metrics"] = p
    return files
