"""Toolpaths on curved layers: shells, infill, ordering, thickness, CSV/VTP output (SPEC step 11).

The names below are imported on first use (PEP 562): ``from neuralslicer.toolpath.config import ToolpathConfig``
(every configuration does it) then costs the configuration alone, not the planner and its scipy.
"""
from __future__ import annotations

import importlib
from typing import TYPE_CHECKING, Any

if TYPE_CHECKING:
    from neuralslicer.toolpath.config import ToolpathConfig, load_toolpath_config, toolpath_config_from_dict
    from neuralslicer.toolpath.generate import toolpaths
    from neuralslicer.toolpath.io import (plot_toolpaths_png, read_waypoints_csv, write_toolpaths_vtp,
                                          write_waypoints_csv)
    from neuralslicer.toolpath.plan import plan_toolpaths
    from neuralslicer.toolpath.types import Toolpaths

#: where each exported name lives
_WHERE = {
    "ToolpathConfig": "config", "load_toolpath_config": "config", "toolpath_config_from_dict": "config",
    "toolpaths": "generate", "plot_toolpaths_png": "io", "read_waypoints_csv": "io", "write_toolpaths_vtp": "io",
    "write_waypoints_csv": "io", "plan_toolpaths": "plan", "Toolpaths": "types",
}

__all__ = sorted(_WHERE)


def __getattr__(name: str) -> Any:
    """An exported name, imported from its module on first use."""
    if name in _WHERE:
        value = getattr(importlib.import_module(f"{__name__}.{_WHERE[name]}"), name)
        globals()[name] = value
        return value
    raise AttributeError(f"module {__name__!r} has no attribute {name!r}")
