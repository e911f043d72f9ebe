"""Machine profiles (YAML + pydantic): kinematic geometry, limits, feeds, extrusion, nozzle."""
from __future__ import annotations

from importlib import resources
from pathlib import Path
from typing import Literal

import yaml
from pydantic import BaseModel, ConfigDict, Field, ValidationError, model_validator

from neuralslicer.errors import InputError


class _Model(BaseModel):
    model_config = ConfigDict(extra="forbid")


class AxisLetters(_Model):
    """G-code letters of the machine axes."""

    x: str = "X"
    y: str = "Y"
    z: str = "Z"
    #: table tilt (rotation about machine +Y through the pivot).
    tilt: str = "B"
    #: table rotation (about the table's own +Z axis).
    rotate: str = "C"
    #: filament axis: "A" on the LinuxCNC profile (linear-like, mm of filament), "E" on RepRap.
    extruder: str = "A"


class Kinematics(_Model):
    """Table-table B/C geometry; the tool is fixed along machine +Z, the tool tip is the control point.

    A part point ``p`` (build frame) is at machine position
    ``pivot + R_y(B) (c_offset + R_z(C) (p + part_offset))``.
    """

    kind: Literal["table_bc"] = "table_bc"
    #: machine XYZ of the tool tip when it is at the tilt-axis pivot (includes the tool length).
    pivot: tuple[float, float, float] = (0.0, 0.0, 0.0)
    #: vector from the pivot to the point where the C axis crosses the table, table frame at B=0.
    c_offset: tuple[float, float, float] = (0.0, 0.0, 0.0)
    #: build-frame origin in the C-axis frame; null = centre the part's xy on C, platform on the table.
    part_offset: tuple[float, float, float] | None = None
    #: B range (deg); both IK solutions (B, C) and (-B, C+180) are tried.
    b_min_deg: float = -90.0
    b_max_deg: float = 90.0
    #: C range (deg); null = unlimited (continuous rotary axis, unwrapped). When set (a span of at least
    #: 360 deg), C is unwound by whole turns where it would leave the range: between paths where a path
    #: fits, else inside it, each time retracting, lifting to the safe height, turning, coming back down.
    c_min_deg: float | None = None
    c_max_deg: float | None = None
    #: tool axes tipped further from +z than the B range reaches: "turn" them back onto the limit (azimuth
    #: kept, the turned waypoints checked for collisions again and reported), or "fail" the plan with an
    #: error naming the layers. Turns up to ``toolpath.collision_tilt_deg`` happen either way.
    beyond_reach: Literal["turn", "fail"] = "turn"
    #: largest rotary change per move (deg); longer moves are split.
    max_rotary_step_deg: float = Field(2.0, gt=0)
    #: tool axes within this angle of the C axis are singular: B = 0 and C keeps its previous value.
    singular_tol_deg: float = Field(0.05, ge=0)


class Feeds(_Model):
    """Speeds (mm/s of the tool tip relative to the part, deg/s for pure rotations) and the machine's axis
    limits, which the print-time estimate (``neuralslicer.motion.timing``) respects."""

    print_mm_s: float = Field(20.0, gt=0)
    first_layer_mm_s: float = Field(10.0, gt=0)
    travel_mm_s: float = Field(60.0, gt=0)
    #: programmed rotary speed, also the B and C axes' velocity limit in the time estimate.
    rotary_deg_s: float = Field(90.0, gt=0)
    retract_mm_s: float = Field(30.0, gt=0)
    #: acceleration limit of each linear axis X, Y, Z (mm/s^2); 1000 suits a LinuxCNC table machine,
    #: RepRap-class machines run 1000-3000.
    accel_mm_s2: float = Field(1000.0, gt=0)
    #: acceleration limit of each rotary axis B, C (deg/s^2): 720 reaches the rotary speed in 1/8 s.
    rotary_accel_deg_s2: float = Field(720.0, gt=0)
    #: velocity limit of each linear axis X, Y, Z (mm/s), whatever the programmed feed.
    max_axis_mm_s: float = Field(150.0, gt=0)
    #: shortest move the controller executes at full rate (s): no move is faster (a controller's block
    #: rate; LinuxCNC needs a few servo periods per segment, Marlin slows segments below min_segment_time).
    min_move_s: float = Field(0.005, ge=0)


class Extrusion(_Model):
    """Filament and retraction."""

    filament_diameter: float = Field(1.75, gt=0)
    #: filament density for the mass print hosts show (PLA 1.24, PETG 1.27, ABS 1.04 g/cm3).
    filament_density_g_cm3: float = Field(1.24, gt=0)
    #: multiplier on the volumetric extrusion (flow).
    flow: float = Field(1.0, gt=0)
    retract_mm: float = Field(1.0, ge=0)
    #: filament pushed back after a travel (usually = retract_mm).
    prime_mm: float = Field(1.0, ge=0)
    #: only travels longer than this retract.
    retract_min_travel: float = Field(2.0, ge=0)


class Nozzle(_Model):
    """Print head for collision checks: a cone with its apex at the tool tip, then a holder cylinder."""

    cone_half_angle_deg: float = Field(30.0, gt=0, lt=90)
    cone_length: float = Field(8.0, gt=0)
    holder_radius: float = Field(15.0, gt=0)
    holder_length: float = Field(30.0, ge=0)
    #: bead thickness the nozzle lays with controlled flow (mm): thinner beads are not extruded (their
    #: material goes to the next layer's bead above them), thicker ones get this much at most.
    bead_thickness_mm: tuple[float, float] = (0.15, 1.2)
    #: bead width the nozzle lays (mm); the toolpaths' line width must lie in it.
    bead_width_mm: tuple[float, float] = (0.3, 1.0)

    @model_validator(mode="after")
    def _check_beads(self) -> "Nozzle":
        for name in ("bead_thickness_mm", "bead_width_mm"):
            lo, hi = getattr(self, name)
            if not 0 < lo < hi:
                raise ValueError(f"{name}: need 0 < min < max, got [{lo}, {hi}]")
        return self


class GcodeOptions(_Model):
    """Dialect-specific output."""

    dialect: Literal["linuxcnc", "reprap"] = "linuxcnc"
    #: LinuxCNC: G93 inverse-time feeds (exact tool-tip speed with rotary moves); else G94 mm/min.
    inverse_time: bool = True
    #: RepRap: the distance F (mm/min) is measured over, as the firmware does (NIST RS274 rule A), from the
    #: coordinates as written. "xyz": the XYZ distance when X, Y or Z moves, else the B/C vector in deg, else
    #: the filament (RepRapFirmware 3 with B/C rotational, its default for axes A-D; Marlin 2.1 with rotary
    #: axes). "all_axes": sqrt(dX^2 + dY^2 + dZ^2 + dB^2 + dC^2), B/C counted as linear (RepRapFirmware with
    #: ``M584 ... S0``). The filament counts only in filament-only moves. F is set so that every move takes its
    #: planned time under that rule; with "xyz" a rotation with little XYZ motion gets a very low F, which
    #: RepRapFirmware raises to its minimum speed (M203 I), running it faster than planned.
    feed_basis: Literal["xyz", "all_axes"] = "xyz"
    decimals_linear: int = Field(4, ge=1, le=8)
    decimals_rotary: int = Field(5, ge=1, le=8)
    decimals_extruder: int = Field(5, ge=1, le=8)
    nozzle_temp_c: float | None = 210.0
    bed_temp_c: float | None = 60.0
    header: list[str] = Field(default_factory=list)
    footer: list[str] = Field(default_factory=list)
    #: start at a safe height (rotary axes turned there, then down along the tool axis, prime) and end
    #: with retract, lift, rotary axes home (C to the nearest full turn), park; false: straight in and out.
    safe_start_end: bool = True
    #: the safe height is the tool tip clear of the sphere around the tilt pivot that holds the part at any
    #: B/C (pivot z + |c_offset| + the part's largest distance from the C-axis origin) by this much (mm).
    safe_clearance_mm: float = Field(10.0, ge=0)
    #: machine X, Y to park at after the print (at the safe height); null: stay above the last point.
    park_xy: tuple[float, float] | None = None


class MachineProfile(_Model):
    """A multi-axis printer: kinematics, limits, feeds, extrusion, nozzle geometry, G-code options."""

    name: str = "table_bc_linuxcnc"
    description: str = ""
    axes: AxisLetters = AxisLetters()
    kinematics: Kinematics = Kinematics()
    feeds: Feeds = Feeds()
    extrusion: Extrusion = Extrusion()
    nozzle: Nozzle = Nozzle()
    gcode: GcodeOptions = GcodeOptions()

    @model_validator(mode="after")
    def _check(self) -> "MachineProfile":
        letters = [self.axes.x, self.axes.y, self.axes.z, self.axes.tilt, self.axes.rotate,
                   self.axes.extruder]
        if len(set(letters)) != len(letters) or any(len(c) != 1 or not c.isalpha() for c in letters):
            raise ValueError(f"axes: letters must be distinct single letters, got {letters}")
        if self.gcode.dialect == "linuxcnc" and self.axes.extruder.upper() not in "ABCUVW":
            raise ValueError("axes.extruder: LinuxCNC has no E axis; use one of A B C U V W")
        k = self.kinematics
        if k.b_min_deg >= k.b_max_deg:
            raise ValueError("kinematics: b_min_deg must be below b_max_deg")
        if k.c_min_deg is not None and k.c_max_deg is not None and k.c_max_deg - k.c_min_deg < 360.0:
            raise ValueError("kinematics: the C range must span at least 360 deg (c_max_deg - c_min_deg), "
                             "or be unlimited (null)")
        return self


def _validate(data: dict | None, where: str | Path) -> MachineProfile:
    try:
        return MachineProfile.model_validate(data or {})
    except ValidationError as err:
        first = err.errors()[0]
        key = ".".join(str(p) for p in first["loc"])
        raise InputError(where, f"{key}: {first['msg']}".strip(": ")) from None


def profile_names() -> list[str]:
    """Names of the profiles shipped in ``neuralslicer/machines/``."""
    root = resources.files("neuralslicer") / "machines"
    return sorted(p.name[:-5] for p in root.iterdir() if p.name.endswith(".yaml"))


def load_profile(name_or_path: str | Path = "table_bc_linuxcnc") -> MachineProfile:
    """Load a machine profile: a shipped name (``table_bc_linuxcnc``, ``reprap_5axis``) or a YAML path."""
    text = None
    where: str | Path = name_or_path
    path = Path(name_or_path)
    if path.suffix in (".yaml", ".yml") and path.exists():
        text = path.read_text()
    else:
        res = resources.files("neuralslicer") / "machines" / f"{name_or_path}.yaml"
        if res.is_file():
            text = res.read_text()
            where = f"machines/{name_or_path}.yaml"
    if text is None:
        raise InputError(name_or_path, f"no such machine profile; shipped: {', '.join(profile_names())}")
    try:
        data = yaml.safe_load(text)
    except yaml.YAMLError as err:
        raise InputError(where, f"invalid YAML: {err}") from None
    return _validate(data, where)
