"""Machine profiles, kinematics (table-table B/C), motion planning, collisions (SPEC step 12)."""
from __future__ import annotations

from neuralslicer.motion.collision import CollisionReport, check_collisions, platform_clearance
from neuralslicer.motion.kinematics import forward_kinematics, inverse_kinematics, machine_position
from neuralslicer.motion.pipeline import plan_print
from neuralslicer.motion.planning import (PRINT, RETRACT, TRAVEL, MachineProgram, auto_part_offset, plan_motion,
                                          program_metrics)
from neuralslicer.motion.profile import MachineProfile, load_profile, profile_names
from neuralslicer.motion.timing import move_times, program_time

__all__ = [
    "CollisionReport", "MachineProfile", "MachineProgram", "PRINT", "RETRACT", "TRAVEL", "auto_part_offset",
    "check_collisions", "forward_kinematics", "inverse_kinematics", "load_profile", "machine_position",
    "move_times", "plan_motion", "plan_print", "platform_clearance", "profile_names", "program_metrics",
    "program_time",
]
