"""Robot export: per waypoint position, tool frame (quaternion and x axis), process data (CSV, JSON).

The fields follow compas_slicer's ``PrintPoint`` (``pt``, ``frame``, ``layer_height``, ``velocity``,
``wait_time``, ``blend_radius``, ``extruder_toggle``), so robot pipelines built for it read ours.
"""
from __future__ import annotations

import json
from pathlib import Path

import numpy as np

from neuralslicer.fileio import atomic_path
from neuralslicer.motion.planning import move_speeds
from neuralslicer.motion.profile import MachineProfile
from neuralslicer.toolpath.types import Toolpaths
from neuralslicer.types import BoolArray, FloatArray

ROBOT_COLUMNS = ("index", "layer", "path", "x", "y", "z", "qw", "qx", "qy", "qz", "extrude",
                 "volume_mm3", "filament_mm", "thickness", "width", "xx", "xy", "xz", "layer_height",
                 "velocity", "wait_time", "blend_radius", "extruder_toggle")
_CSV_FORMAT = ["%d", "%d", "%d", "%.6f", "%.6f", "%.6f", "%.8f", "%.8f", "%.8f", "%.8f", "%d", "%.6f",
               "%.6f", "%.6f", "%.6f", "%.8f", "%.8f", "%.8f", "%.6f", "%.6f", "%.6f", "%.6f", "%d"]
#: what each column means (the JSON export carries it).
COLUMN_NOTES = {
    "x,y,z": "tool tip, build frame (mm)",
    "qw,qx,qy,qz": "tool frame as a unit quaternion (w >= 0): z = -LPD (into the material), x = the path "
                   "direction projected orthogonal to z (continuous), y = z cross x",
    "xx,xy,xz": "x axis of the tool frame (build frame)",
    "extrude": "1: the move arriving at this point deposits",
    "volume_mm3,filament_mm": "material and filament of the move arriving at this point",
    "thickness,layer_height": "local layer thickness (mm)",
    "velocity": "tool-tip speed of the move arriving at this point (mm/s): print, first-layer or travel speed",
    "wait_time": "dwell at this point before moving on (s): the prime time where printing starts after a "
                 "retracting travel (and at the first path), else 0",
    "blend_radius": "zone / blend radius (mm): 0 at path starts and ends, waits, corners and travels; along "
                    "smooth printed paths a fraction of the line width, at most 0.3 of either segment",
    "extruder_toggle": "1: the extruder is on for the move leaving this point (compas_slicer's convention)",
}
#: blend radius along smooth printed paths, as a fraction of the line width ...
BLEND_WIDTH_FRACTION = 0.5
#: ... and at most this fraction of the segments before and after the point (compas_slicer's buffer).
BLEND_SEGMENT_FRACTION = 0.3
#: a turn of the path sharper than this (deg) is a corner: blend radius 0 there.
CORNER_DEG = 30.0
#: moves within this angle (deg) of the tool axis give no path direction for the frame's x axis.
_AXIAL_DEG = 1.0


def _unit(v: FloatArray) -> tuple[FloatArray, FloatArray]:
    """Unit vectors (n, 3) and norms (n,) of v (n, 3); zero rows stay zero."""
    norm = np.linalg.norm(v, axis=1)
    return v / np.where(norm > 0, norm, 1.0)[:, None], norm


def _reference_x(z: FloatArray) -> FloatArray:
    """Build +x projected orthogonal to z (n, 3), build +y where z is nearly along x."""
    ref = np.where((np.abs(z[:, 0]) > 0.9)[:, None], [0.0, 1.0, 0.0], [1.0, 0.0, 0.0])
    return _unit(ref - np.einsum("ij,ij->i", ref, z)[:, None] * z)[0]


def _project(v: FloatArray, z: FloatArray) -> FloatArray:
    """v (n, 3) minus its component along the unit vectors z (n, 3)."""
    return v - np.einsum("ij,ij->i", v, z)[:, None] * z


def path_x_axes(xyz: FloatArray, z: FloatArray, extrude: BoolArray | None = None) -> FloatArray:
    """Continuous x axes (n, 3) orthogonal to the unit tool axes z (n, 3), following the path xyz (n, 3).

    At each point x is the mean of the unit directions of the moves arriving and leaving, each projected
    orthogonal to z (a move within 1 deg of the tool axis gives no direction); where a printed run starts
    or ends (``extrude`` (n,): the move arriving deposits) only its printing move counts. Where no move
    gives a direction (lifts along the tool axis, reversals, repeated points) the last x is carried over,
    projected, so consecutive frames turn by no more than the path does. Leading points take the first x;
    without any path direction, build +x projected.
    """
    n = len(xyz)
    if n == 0:
        return np.zeros((0, 3))
    d = np.diff(xyz, axis=0)
    ext = np.zeros(n, bool) if extrude is None else np.asarray(extrude, bool)
    same = ext[1:-1] == ext[2:]                                         # points 1..n-2: both moves alike
    use_in = np.r_[same | ext[1:-1], True]                              # arriving at points 1..n-1
    use_out = np.r_[True, same | ext[2:]]                               # leaving points 0..n-2
    tangent = np.zeros((n, 3))
    sin_min = np.sin(np.radians(_AXIAL_DEG))
    u, length = _unit(d)
    for at, use in ((slice(1, None), use_in), (slice(None, -1), use_out)):
        p, size = _unit(_project(u, z[at]))
        tangent[at] += np.where((use & (length > 1e-12) & (size > sin_min))[:, None], p, 0.0)
    x, size = _unit(tangent)
    valid = size > 1e-3
    if not valid.any():
        return _reference_x(z)
    src = np.maximum.accumulate(np.where(valid, np.arange(n), -1))
    src[src < 0] = np.flatnonzero(valid)[0]
    carried, size = _unit(_project(x[src], z))
    return np.where((size > 1e-6)[:, None], carried, _reference_x(z))


def tool_frames(axis: FloatArray, xyz: FloatArray | None = None, extrude: BoolArray | None = None) -> FloatArray:
    """Tool frames (n, 3, 3), columns x, y, z: z = -LPD (into the material); x along the path xyz (n, 3)
    projected orthogonal to z (``path_x_axes``, printed runs by their own moves when ``extrude`` (n,) is
    given), or build +x projected when no path is given."""
    z = _unit(-np.asarray(axis, np.float64))[0]
    x = _reference_x(z) if xyz is None else path_x_axes(np.asarray(xyz, np.float64), z, extrude)
    y = np.cross(z, x)
    return np.stack([x, y, z], axis=2)


def matrix_to_quaternion(r: FloatArray) -> FloatArray:
    """Unit quaternions (n, 4) as (w, x, y, z), w >= 0, from rotation matrices (n, 3, 3)."""
    r = np.asarray(r, np.float64)
    tr = np.trace(r, axis1=1, axis2=2)
    q = np.empty((len(r), 4))
    cand = np.stack([tr, r[:, 0, 0], r[:, 1, 1], r[:, 2, 2]], axis=1)
    k = np.argmax(cand, axis=1)
    for case in range(4):
        m = k == case
        if not m.any():
            continue
        rr = r[m]
        if case == 0:
            s = 2.0 * np.sqrt(1.0 + tr[m])
            q[m] = np.stack([0.25 * s, (rr[:, 2, 1] - rr[:, 1, 2]) / s, (rr[:, 0, 2] - rr[:, 2, 0]) / s,
                             (rr[:, 1, 0] - rr[:, 0, 1]) / s], 1)
        else:
            i = case - 1
            j, l = (i + 1) % 3, (i + 2) % 3
            s = 2.0 * np.sqrt(np.maximum(1.0 + rr[:, i, i] - rr[:, j, j] - rr[:, l, l], 1e-300))
            qq = np.empty((m.sum(), 4))
            qq[:, 0] = (rr[:, l, j] - rr[:, j, l]) / s
            qq[:, 1 + i] = 0.25 * s
            qq[:, 1 + j] = (rr[:, j, i] + rr[:, i, j]) / s
            qq[:, 1 + l] = (rr[:, l, i] + rr[:, i, l]) / s
            q[m] = qq
    q *= np.where(q[:, :1] < 0, -1.0, 1.0)
    return q / np.linalg.norm(q, axis=1, keepdims=True)


def quaternion_to_matrix(q: FloatArray) -> FloatArray:
    """Rotation matrices (n, 3, 3) from unit quaternions (w, x, y, z)."""
    w, x, y, z = np.asarray(q, np.float64).T
    return np.stack([
        np.stack([1 - 2 * (y * y + z * z), 2 * (x * y - w * z), 2 * (x * z + w * y)], -1),
        np.stack([2 * (x * y + w * z), 1 - 2 * (x * x + z * z), 2 * (y * z - w * x)], -1),
        np.stack([2 * (x * z - w * y), 2 * (y * z + w * x), 1 - 2 * (x * x + y * y)], -1)], -2)


def extruder_toggle(extrude: BoolArray) -> BoolArray:
    """(n,) True where the move leaving the point deposits (the last point: False)."""
    return np.r_[np.asarray(extrude, bool)[1:], False]


def velocities(tp: Toolpaths, profile: MachineProfile) -> FloatArray:
    """Speed (n,) of the move arriving at each waypoint (mm/s): first-layer speed on the first layer, else
    print speed, where it deposits; travel speed elsewhere (the speeds ``plan_motion`` programs)."""
    return move_speeds(tp.layer, tp.extrude, profile.feeds)


def wait_times(tp: Toolpaths, profile: MachineProfile) -> FloatArray:
    """Dwell (n,) before printing starts (s): the prime time ``extrusion.prime_mm / feeds.retract_mm_s``
    where the extruder turns on after a travel longer than ``extrusion.retract_min_travel`` (where the
    G-code program retracts and primes) and at the first printing start; 0 elsewhere."""
    ex = profile.extrusion
    n = len(tp)
    on = extruder_toggle(tp.extrude) & ~np.r_[False, extruder_toggle(tp.extrude)[:-1]]
    travel = np.cumsum(np.where(tp.extrude, 0.0, tp.segment_lengths()))
    last_print = np.maximum.accumulate(np.where(tp.extrude, np.arange(n), -1))
    run = travel - np.where(last_print >= 0, travel[np.maximum(last_print, 0)], 0.0)
    primes = on & ((run > ex.retract_min_travel) | (last_print < 0))
    return np.where(primes, ex.prime_mm / profile.feeds.retract_mm_s, 0.0)


def blend_radii(tp: Toolpaths, wait: FloatArray, width_fraction: float = BLEND_WIDTH_FRACTION,
                corner_deg: float = CORNER_DEG) -> FloatArray:
    """Blend radius (n,) in mm: ``width_fraction`` x line width, at most ``BLEND_SEGMENT_FRACTION`` of the
    segments before and after, at points inside a printed run (both moves deposit) that turn by at most
    ``corner_deg`` and do not wait; 0 at path starts and ends, corners, waits and on travels."""
    n = len(tp)
    r = np.zeros(n)
    if n < 3:
        return r
    d = np.diff(tp.xyz, axis=0)
    u, length = _unit(d)
    cos = np.einsum("ij,ij->i", u[:-1], u[1:])
    inner = (tp.extrude[1:-1] & tp.extrude[2:] & (length[:-1] > 0) & (length[1:] > 0)
             & (cos >= np.cos(np.radians(corner_deg))) & (wait[1:-1] == 0))
    size = np.minimum(width_fraction * tp.width[1:-1], BLEND_SEGMENT_FRACTION * np.minimum(length[:-1], length[1:]))
    r[1:-1] = np.where(inner, size, 0.0)
    return r


def move_material(tp: Toolpaths, filament_diameter: float) -> tuple[FloatArray, FloatArray]:
    """Volume (n,) in mm^3 and filament (n,) in mm of the move arriving at each waypoint (0 where it does not
    deposit): length x mean thickness x mean width of its ends."""
    seg = tp.segment_lengths()
    t = np.concatenate([[0.0], 0.5 * (tp.thickness[1:] + tp.thickness[:-1])])
    w = np.concatenate([[0.0], 0.5 * (tp.width[1:] + tp.width[:-1])])
    vol = np.where(tp.extrude, seg * t * w, 0.0)
    return vol, vol / (np.pi * 0.25 * filament_diameter ** 2)


def robot_table(tp: Toolpaths, filament_diameter: float | None = None, *,
                profile: MachineProfile | None = None) -> np.ndarray:
    """(n, 23) table in ``ROBOT_COLUMNS`` order (``COLUMN_NOTES``); speeds and waits from ``profile``
    (default: the default profile), the filament diameter from it unless given."""
    profile = profile or MachineProfile()
    d = profile.extrusion.filament_diameter if filament_diameter is None else filament_diameter
    frames = tool_frames(tp.axis, tp.xyz, tp.extrude)
    q = matrix_to_quaternion(frames)
    vol, fil = move_material(tp, d)
    wait = wait_times(tp, profile)
    return np.column_stack([np.arange(len(tp)), tp.layer, tp.path, tp.xyz, q, tp.extrude.astype(float),
                            vol, fil, tp.thickness, tp.width, frames[:, :, 0], tp.thickness,
                            velocities(tp, profile), wait, blend_radii(tp, wait),
                            extruder_toggle(tp.extrude).astype(float)])


def write_robot_csv(path: str | Path, tp: Toolpaths, filament_diameter: float | None = None, *,
                    profile: MachineProfile | None = None) -> Path:
    """Robot waypoints CSV, one row per waypoint in ``ROBOT_COLUMNS`` (``robot_table``)."""
    table = robot_table(tp, filament_diameter, profile=profile)
    with atomic_path(path) as tmp:
        np.savetxt(tmp, table, fmt=_CSV_FORMAT, delimiter=",", header=",".join(ROBOT_COLUMNS), comments="")
    return Path(path)


def write_robot_json(path: str | Path, tp: Toolpaths, filament_diameter: float | None = None, *,
                     profile: MachineProfile | None = None) -> Path:
    """Robot waypoints JSON: ``{"units", "frame", "quaternion", "columns", "notes", "rows": [[...], ...]}``."""
    table = robot_table(tp, filament_diameter, profile=profile)
    doc = {"units": "mm, s, mm/s", "frame": "build (+z up)", "quaternion": COLUMN_NOTES["qw,qx,qy,qz"],
           "columns": list(ROBOT_COLUMNS), "notes": COLUMN_NOTES, "rows": np.round(table, 8).tolist()}
    with atomic_path(path) as tmp:
        tmp.write_text(json.dumps(doc))
    return Path(path)
