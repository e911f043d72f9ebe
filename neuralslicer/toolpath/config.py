"""Toolpath settings (SPEC step 11), loaded from YAML; every default is documented here."""
from __future__ import annotations

from pathlib import Path
from typing import Literal

import yaml
from pydantic import BaseModel, ConfigDict, Field, ValidationError

from neuralslicer.errors import InputError, validation_error_line


class ToolpathConfig(BaseModel):
    """How curved layers are filled with extrusion paths (all lengths in mm)."""

    model_config = ConfigDict(extra="forbid")

    #: nozzle line width; shells are isolines of the geodesic boundary distance at (k+1/2)*width.
    line_width: float = Field(0.5, gt=0)
    #: number of contour-parallel shells (perimeters) per layer patch.
    n_shells: int = Field(2, ge=0)
    #: infill pattern inside the shells: zig-zag lines, more contour-parallel rings, lines along the in-layer principal
    #: stress of the load case (``stress``: the regular zig-zag where the stress is negligible), or none. ``auto``:
    #: ``stress`` when the slice has a load case with the ``sr`` objective, else ``zigzag``.
    infill: Literal["auto", "zigzag", "contour", "stress", "none"] = "auto"
    #: infill density in (0, 1]; line spacing = line_width / density.
    infill_density: float = Field(1.0, gt=0, le=1)
    #: zig-zag direction of the first layer (degrees about +z in the build frame) ...
    infill_angle_deg: float = 45.0
    #: ... rotated by this much on every following layer.
    infill_angle_step_deg: float = 90.0
    #: ``infill: stress``: the in-layer stress counts as significant (lines follow it) where the difference of its two
    #: in-layer principal stresses reaches this fraction of the load case's reference stress (the smallest |max
    #: principal stress| of the strength samples T); below, zig-zag. 0.2 keeps the strength of 0.05 within 2 % on the
    #: bracket, bridge and ring with about half the paths.
    stress_threshold: float = Field(0.2, ge=0)
    #: ``infill: stress``: how many times the line spacing may be halved or doubled where the stress lines diverge or
    #: converge (lines start or end so that the local spacing stays within line_width / sqrt 2 .. line_width sqrt 2).
    stress_levels: int = Field(3, ge=0, le=6)
    #: ``infill: stress``: the scalar whose isolines are the stress lines is solved on the layer's triangles split to
    #: this edge length (mm); its isolines are straight within each of them.
    stress_resolution: float = Field(2.0, gt=0)
    #: ``infill: stress``: each stress line's width follows its local spacing (within 1/sqrt 2 .. sqrt 2 of
    #: line_width, and the nozzle's bead widths), so the layer is filled evenly; false: line_width everywhere.
    stress_adapt_width: bool = True
    #: target waypoint spacing along paths (arc-length resampling; corners are kept).
    spacing: float = Field(0.5, gt=0)
    #: original polyline vertices turning by more than this angle are kept as waypoints.
    corner_angle_deg: float = Field(30.0, gt=0, le=180)
    #: layer triangles within the boundary-distance band of a patch (all of it for contour infill) are
    #: split until every edge is at most this (0: line_width).
    max_edge: float = Field(0.0, ge=0)
    #: lift along the tool axis before/after a travel (retract height).
    travel_lift: float = Field(1.0, ge=0)
    #: travels shorter than this inside one patch are not lifted.
    lift_min_travel: float = Field(2.0, ge=0)
    #: consecutive infill lines whose ends are closer than this factor * infill spacing are joined
    #: by an extruding connector (this makes the zig-zag).
    join_factor: float = Field(2.5, ge=0)
    #: closed loops alternate direction (a table C axis then unwinds instead of turning once more
    #: per loop around it).
    alternate_loops: bool = True
    #: the measured bead thickness is capped at this multiple of the layers' ``t_max`` (also the value
    #: where the ray along -LPD misses everything below); the first layer's distance to the platform
    #: is capped at ``t_max`` itself. The thickness limits live in one place, ``LayerConfig``.
    thickness_cap_factor: float = Field(1.5, ge=1)
    #: waypoints where the head still hits earlier layers get their tool axis tilted away from the LPD
    #: by the smallest angle up to this (degrees; 0: never) that clears the head, the tilt fading out
    #: along the path over ``collision_tilt_ramp`` mm; the layers are unchanged.
    collision_tilt_deg: float = Field(15.0, ge=0, le=45)
    collision_tilt_ramp: float = Field(5.0, ge=0)
    #: more colliding waypoints than this are not tilted (the field itself needs to change).
    collision_tilt_max_waypoints: int = Field(20000, ge=0)
    #: beads against the nozzle's range (machine profile ``nozzle.bead_thickness_mm``): "carry" stops
    #: extruding where the gap to the layer below is thinner than the nozzle lays and carries that gap to the
    #: bead above it in the next layer, and caps thicker gaps at the largest bead; "print" prints every gap.
    thin_beads: Literal["carry", "print"] = "carry"
    #: patches whose area is below this (mm^2) are skipped (marching-tet slivers).
    min_patch_area: float = Field(0.05, ge=0)

    def resolved(self, has_stress: bool) -> ToolpathConfig:
        """This config with ``infill: auto`` decided: ``stress`` when a stress field is there to follow
        (``has_stress``), else ``zigzag``."""
        if self.infill != "auto":
            return self
        return self.model_copy(update={"infill": "stress" if has_stress else "zigzag"})


def load_toolpath_config(path: str | Path) -> ToolpathConfig:
    """Read a ToolpathConfig from a YAML file (top-level mapping, or under a ``toolpath:`` key)."""
    path = Path(path)
    try:
        data = yaml.safe_load(path.read_text()) or {}
    except (OSError, yaml.YAMLError) as err:
        raise InputError(path, f"cannot read toolpath settings: {err}") from None
    if isinstance(data, dict) and "toolpath" in data:
        data = data["toolpath"]
    return toolpath_config_from_dict(data, where=path)


def toolpath_config_from_dict(data: dict | None, where: str | Path = "toolpath") -> ToolpathConfig:
    """Validate a mapping into a ToolpathConfig, raising InputError naming the bad key."""
    try:
        return ToolpathConfig.model_validate(data or {})
    except ValidationError as err:
        key, msg = validation_error_line(ToolpathConfig, err.errors())
        raise InputError(where, f"{key}: {msg}") from None
