"""Machine profiles, kinematics (table-table B/C), motion planning, collisions (SPEC step 12).

The names below are imported on first use, so that reading a machine profile (the configuration does, before
anything runs) does not import the planner and the toolpaths with it.
"""
from __future__ import annotations

from importlib import import_module
from typing import Any

_WHERE = {
    "CollisionReport": "collision", "check_collisions": "collision", "platform_clearance": "head",
    "forward_kinematics": "kinematics", "inverse_kinematics": "kinematics", "machine_position": "kinematics",
    "plan_print": "plan", "PRINT": "planning", "RETRACT": "planning", "TRAVEL": "planning",
    "MachineProgram": "planning", "auto_part_offset": "planning", "plan_motion": "planning",
    "program_metrics": "planning", "MachineProfile": "profile", "load_profile": "profile",
    "profile_names": "profile", "move_times": "timing", "program_time": "timing",
}

__all__ = sorted(_WHERE)


def __getattr__(name: str) -> Any:
    """A name of the motion package, from the module that defines it."""
    if name in _WHERE:
        return getattr(import_module(f"neuralslicer.motion.{_WHERE[name]}"), name)
    raise AttributeError(f"module 'neuralslicer.motion' has no attribute {name!r}")
