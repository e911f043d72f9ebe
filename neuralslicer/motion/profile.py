"""Machine profiles (YAML + pydantic): the kinematic chain, limits, feeds, extrusion, nozzle."""
from __future__ import annotations

from importlib import resources
from pathlib import Path
from typing import Literal

import numpy as np
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
    #: the tilting rotary axis (``kinematics.tilt_axis``): B when it turns about Y, A when about X.
    tilt: str = "B"
    #: the rotary axis about Z (``kinematics.rotate_axis``): C.
    rotate: str = "C"
    #: filament axis: "A" on the LinuxCNC profile (linear-like, mm of filament), "E" on RepRap.
    extruder: str = "A"


#: the layouts a profile can describe: where each of the two rotary axes sits (none on a three-axis printer)
LAYOUTS = ("table-table", "head-head", "table-head", "three-axis")
_LEGACY_KEYS = {"b_min_deg": "tilt_min_deg", "b_max_deg": "tilt_max_deg", "c_min_deg": "rotate_min_deg",
                "c_max_deg": "rotate_max_deg"}


class Kinematics(_Model):
    """The machine as a kinematic chain: a rotary axis that tilts (about machine X or Y at home) and one that
    turns about Z, each moving the table or the head, or none (three-axis). The tool tip is the control point.

    With R_T the tilt (about ``tilt_axis``) and R_R the rotation (about ``rotate_axis``), a part point ``p``
    (build frame) and the tool tip at machine position ``m`` meet where
    - table-table (the rotary table rides on the tilting cradle): ``m = pivot + R_T (c_offset + R_R (p + part_offset))``;
    - head-head (the tilt rides on the rotary head): ``m + R_R (pivot + R_T t) - (pivot + t) = c_offset + p +
      part_offset``;
    - table-head (tilting head, rotary table): ``m + R_T t - t = c_offset + R_R (p + part_offset)``;
    - three-axis: ``m = c_offset + p + part_offset``;
    where ``t = (0, 0, -tool_length)`` runs from the head's tilt pivot to the tool tip (head layouts zero
    machine XYZ on the tool tip with the head at home). See ``neuralslicer.motion.kinematics``.
    """

    layout: Literal["table-table", "head-head", "table-head", "three-axis"] = "table-table"
    #: direction of the tilting axis at home (right-hand rule, the table's or the head's rotation):
    #: "+Y" for a B axis, "+X" for an A axis; a minus sign where the machine turns the other way.
    tilt_axis: Literal["+X", "-X", "+Y", "-Y"] = "+Y"
    #: direction of the rotary axis at home: "+Z", or "-Z" where the machine turns the other way.
    rotate_axis: Literal["+Z", "-Z"] = "+Z"
    #: table-table: machine XYZ of the tool tip when it is at the tilt-axis pivot (includes the tool length).
    #: head-head: the tilt pivot's offset from the rotary axis in the head, at home (usually 0 0 0).
    #: table-head: unused (0 0 0).
    pivot: tuple[float, float, float] = (0.0, 0.0, 0.0)
    #: table-table: vector from the pivot to the point where the rotary axis crosses the table, table frame
    #: at home. table-head: machine XYZ of the point where the rotary axis crosses the table top. head-head and
    #: three-axis: machine XYZ of the bed's centre on its top (where the part is placed by default).
    c_offset: tuple[float, float, float] = (0.0, 0.0, 0.0)
    #: head layouts: distance from the tilt axis to the tool tip along the tool (mm); else 0.
    tool_length: float = Field(0.0, ge=0)
    #: build-frame origin relative to the rotary axis on the table (or the fixed bed's centre, ``c_offset``); null =
    #: centre the part's xy on it, the platform on the table (z = 0).
    part_offset: tuple[float, float, float] | None = None
    #: tilt range (deg); both IK solutions are tried: (T, R) and (-T, R + 180).
    tilt_min_deg: float = -90.0
    tilt_max_deg: float = 90.0
    #: rotary range (deg); null = unlimited (continuous rotary axis, unwrapped). When set (a span of at least
    #: 360 deg), the rotary axis is unwound by whole turns where it would leave the range: between paths where a
    #: path fits, else inside it, each time retracting, lifting to the safe height, turning, coming back down.
    rotate_min_deg: float | None = None
    rotate_max_deg: float | None = None
    #: the controller does tool-centre-point control (LinuxCNC xyzbc-trt-kins / xyzac-trt-kins in TCP mode,
    #: RTCP, TRAORI, M128): false (default) writes machine coordinates that carry the kinematics above (the
    #: controller must run without TCP, or the offsets are applied twice); true writes the tool tip in workpiece
    #: coordinates (the part on the table at home) with the rotary angles, and the controller does the rest.
    tcp: bool = False
    #: three-axis: the largest angle between the printing direction and +z that the vertical head clears (deg):
    #: at most 90 - nozzle.cone_half_angle_deg (the cone's flank), less for the bead's squish and the flat tip.
    clearance_deg: float = Field(30.0, gt=0, lt=90)
    #: tool axes tipped further from +z than the tilt range reaches: "turn" them back onto the limit (azimuth
    #: kept, the turned waypoints checked for collisions again and reported), or "fail" the plan with an
    #: error naming the layers. Turns up to ``toolpath.collision_tilt_deg`` happen either way.
    beyond_reach: Literal["turn", "fail"] = "turn"
    #: largest rotary change per move (deg); longer moves are split.
    max_rotary_step_deg: float = Field(2.0, gt=0)
    #: tool axes within this angle of the rotary axis are singular: tilt 0, the rotary axis keeps its value.
    singular_tol_deg: float = Field(0.05, ge=0)

    @model_validator(mode="before")
    @classmethod
    def _legacy(cls, data: object) -> object:
        """Programs stored before layouts existed: ``kind: table_bc`` and the B/C names of the limits."""
        if isinstance(data, dict) and data.get("kind") == "table_bc":
            data = {_LEGACY_KEYS.get(k, k): v for k, v in data.items() if k != "kind"}
        return data

    @property
    def rotary(self) -> bool:
        """Whether the machine has rotary axes (all layouts but three-axis)."""
        return self.layout != "three-axis"

    def reach_deg(self) -> float:
        """Largest angle between the tool axis and +z (deg) the machine reaches: the tilt range, or the
        three-axis clearance."""
        if not self.rotary:
            return float(self.clearance_deg)
        return min(180.0, max(self.tilt_max_deg, -self.tilt_min_deg))

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


#: what a profile leaves out of its nozzle follows from ``diameter_mm`` by the rules of ordinary slicers (a 0.4 mm
#: nozzle: 0.2 mm layers in 0.1-0.3 mm, 0.45 mm lines), as multiples of the diameter.
NOZZLE_RULES: dict[str, float | tuple[float, float]] = {
    "layer_height_mm": 0.5, "layer_thickness_mm": (0.25, 0.75), "line_width_mm": 1.125,
    "bead_thickness_mm": (0.125, 1.0), "bead_width_mm": (0.75, 2.0)}
#: a nozzle without a diameter is the paper's: 1.0 mm, printing thicker layers and thinner lines than the rules give
PAPER_NOZZLE: dict[str, float | tuple[float, float]] = {
    "diameter_mm": 1.0, "layer_height_mm": 0.8, "layer_thickness_mm": (0.4, 1.0), "line_width_mm": 0.5,
    "bead_thickness_mm": (0.15, 1.2), "bead_width_mm": (0.3, 1.0)}


class Nozzle(_Model):
    """The nozzle: its diameter, the layers and lines it prints, and the head around it for collision checks (a
    cone with its apex at the tool tip, then a holder cylinder). Values left out follow from the diameter
    (``NOZZLE_RULES``); without a diameter it is the paper's nozzle (``PAPER_NOZZLE``)."""

    #: the nozzle's bore (mm); null: the paper's 1.0 mm nozzle with the paper's layers and lines.
    diameter_mm: float | None = Field(None, gt=0, le=5)
    #: target layer thickness (mm): the slice's ``layers.layer_height`` unless the configuration sets it.
    layer_height_mm: float | None = Field(None, gt=0)
    #: smallest and largest local layer thickness the layers aim for (mm): ``layers.t_min`` / ``t_max``.
    layer_thickness_mm: tuple[float, float] | None = None
    #: line width (mm): ``toolpath.line_width`` unless the configuration sets it.
    line_width_mm: float | None = Field(None, gt=0)
    cone_half_angle_deg: float = Field(30.0, gt=0, lt=90)
    cone_length: float = Field(8.0, gt=0)
    holder_radius: float = Field(15.0, gt=0)
    holder_length: float = Field(30.0, ge=0)
    #: bead thickness the nozzle lays with controlled flow (mm): thinner beads are not extruded (their
    #: material goes to the next layer's bead above them), thicker ones get this much at most.
    bead_thickness_mm: tuple[float, float] | None = None
    #: bead width the nozzle lays (mm); the toolpaths' line width must lie in it.
    bead_width_mm: tuple[float, float] | None = None

    @model_validator(mode="after")
    def _check_beads(self) -> "Nozzle":
        d = self.diameter_mm
        for name, rule in NOZZLE_RULES.items():
            if getattr(self, name) is None:
                value = PAPER_NOZZLE[name] if d is None else \
                    tuple(round(r * d, 6) for r in rule) if isinstance(rule, tuple) else round(rule * d, 6)
                object.__setattr__(self, name, value)
        if d is None:
            object.__setattr__(self, "diameter_mm", PAPER_NOZZLE["diameter_mm"])
        for name in ("layer_thickness_mm", "bead_thickness_mm", "bead_width_mm"):
            lo, hi = getattr(self, name)
            if not 0 < lo < hi:
                raise ValueError(f"{name}: need 0 < min < max, got [{lo}, {hi}]")
        t_lo, t_hi = self.layer_thickness_mm
        if not t_lo <= self.layer_height_mm <= t_hi:
            raise ValueError(f"layer_height_mm: {self.layer_height_mm:g} mm is outside layer_thickness_mm "
                             f"[{t_lo:g}, {t_hi:g}]")
        if t_hi > self.bead_thickness_mm[1]:
            raise ValueError(f"layer_thickness_mm: its largest, {t_hi:g} mm, is more than the thickest bead, "
                             f"bead_thickness_mm {self.bead_thickness_mm[1]:g}")
        w_lo, w_hi = self.bead_width_mm
        if not w_lo <= self.line_width_mm <= w_hi:
            raise ValueError(f"line_width_mm: {self.line_width_mm:g} mm is outside bead_width_mm [{w_lo:g}, {w_hi:g}]")
        return self

    def in_words(self) -> str:
        """The nozzle and what it prints, for a listing: ``0.4 mm nozzle, layers 0.2 (0.1-0.3) mm, lines 0.45 mm``."""
        t_lo, t_hi = self.layer_thickness_mm
        return (f"{self.diameter_mm:g} mm nozzle, layers {self.layer_height_mm:g} ({t_lo:g}-{t_hi:g}) mm, "
                f"lines {self.line_width_mm:g} mm")


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
    #: RepRap: part-cooling fan speed in percent, M106 S0-255 from the second layer on (the first layer cools
    #: slowly, on the platform) and M107 at the end; null: no fan commands.
    fan_percent: float | None = Field(None, ge=0, le=100)
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
        k = self.kinematics
        letters = [self.axes.x, self.axes.y, self.axes.z] + ([self.axes.tilt, self.axes.rotate] if k.rotary else []) \
            + [self.axes.extruder]
        if len(set(letters)) != len(letters) or any(len(c) != 1 or not c.isalpha() for c in letters):
            raise ValueError(f"axes: letters must be distinct single letters, got {letters}")
        if self.gcode.dialect == "linuxcnc" and self.axes.extruder.upper() not in "ABCUVW":
            raise ValueError("axes.extruder: LinuxCNC has no E axis; use one of A B C U V W")
        if k.tilt_min_deg >= k.tilt_max_deg:
            raise ValueError("kinematics: tilt_min_deg must be below tilt_max_deg")
        if k.rotate_min_deg is not None and k.rotate_max_deg is not None and k.rotate_max_deg - k.rotate_min_deg < 360.0:
            raise ValueError("kinematics: the rotary range must span at least 360 deg (rotate_max_deg - rotate_min_deg), "
                             "or be unlimited (null)")
        unused = {"table-table": ("tool_length",), "head-head": (),
                  "table-head": ("pivot",), "three-axis": ("pivot", "tool_length")}[k.layout]
        for name in unused:
            if np.any(np.asarray(getattr(k, name), float) != 0.0):
                raise ValueError(f"kinematics.{name}: not used by a {k.layout} machine; leave it 0")
        if k.tcp and not k.rotary:
            raise ValueError("kinematics.tcp: a three-axis machine has no rotary axes to compensate; set it false")
        if not k.rotary and k.clearance_deg > self.head_clearance_deg() + 1e-9:
            raise ValueError(f"kinematics.clearance_deg: {k.clearance_deg:g} deg is more than the vertical head clears "
                             f"on a slope, {self.head_clearance_deg():.1f} deg (the cone's flank, 90 - "
                             "nozzle.cone_half_angle_deg, and the holder's rim, atan(cone_length / holder_radius))")
        return self

    def head_clearance_deg(self) -> float:
        """The steepest plane slope (deg) through the tool tip that a vertical head clears: the cone's flank
        (90 - cone half angle) and the holder's rim (atan(cone_length / holder_radius)), whichever is lower."""
        n = self.nozzle
        return float(min(90.0 - n.cone_half_angle_deg, np.degrees(np.arctan2(n.cone_length, n.holder_radius))))

    def layout_words(self) -> str:
        """The layout in words with its rotary letters: ``table-table A/C``, ``head-head B/C``, ``three-axis``."""
        k = self.kinematics
        return k.layout if not k.rotary else f"{k.layout} {self.axes.tilt}/{self.axes.rotate}"

    def printing_direction_bound_deg(self) -> float | None:
        """The largest angle (deg) between the printing direction and +z the machine prints (three-axis: the
        head's clearance), None where the head tilts (five axes)."""
        return None if self.kinematics.rotary else float(self.kinematics.clearance_deg)


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
