"""Toolpaths on curved layers: shells, infill, ordering, thickness, CSV/VTP output (SPEC step 11)."""
from __future__ import annotations

from neuralslicer.toolpath.config import ToolpathConfig, load_toolpath_config, toolpath_config_from_dict
from neuralslicer.toolpath.generate import toolpaths
from neuralslicer.toolpath.io import (plot_toolpaths_png, read_waypoints_csv, write_toolpaths_vtp,
                                      write_waypoints_csv)
from neuralslicer.toolpath.types import Toolpaths

__all__ = [
    "ToolpathConfig", "Toolpaths", "load_toolpath_config", "plot_toolpaths_png", "read_waypoints_csv",
    "toolpath_config_from_dict", "toolpaths", "write_toolpaths_vtp", "write_waypoints_csv",
]
