"""G-code (LinuxCNC RS274/NGC, RepRap/Marlin), robot waypoint and compas_slicer printpoints export, plus a reader
for tests."""
from __future__ import annotations

from neuralslicer.gcode.parser import ParsedMoves, parse_gcode
from neuralslicer.gcode.printpoints import printpoint_layers, write_printpoints_json
from neuralslicer.gcode.robot import (ROBOT_COLUMNS, matrix_to_quaternion, quaternion_to_matrix,
                                      robot_table, tool_frames, write_robot_csv, write_robot_json)
from neuralslicer.gcode.writers import gcode_lines, linuxcnc_lines, reprap_lines, write_gcode

__all__ = [
    "ParsedMoves", "ROBOT_COLUMNS", "gcode_lines", "linuxcnc_lines", "matrix_to_quaternion", "parse_gcode",
    "quaternion_to_matrix", "reprap_lines", "robot_table", "tool_frames", "write_gcode", "write_robot_csv",
    "write_robot_json", "printpoint_layers", "write_printpoints_json",
]
