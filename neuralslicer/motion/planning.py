"""Motion planning (SPEC step 12): machine coordinates, rotary splitting, feeds, extrusion, retraction."""
from __future__ import annotations

from dataclasses import dataclass, field, replace
from collections.abc import Iterable
from typing import ClassVar, Self

import numpy as np

from neuralslicer.allocator import release_freed_memory
from neuralslicer.errors import PlanError
from neuralslicer.motion.kinematics import (ROWS_PER_BLOCK, forward_kinematics, inverse_kinematics, machine_position,
                                            workpiece_position)
from neuralslicer.motion.profile import Feeds, MachineProfile
from neuralslicer.motion.timing import program_time
from neuralslicer.toolpath.types import Toolpaths, segment_lengths
from neuralslicer.types import FloatArray, IndexArray

PROGRAM_SCHEMA_VERSION = 2   # 2: no stored tool tips and axes (part_xyz, part_axis): the forward kinematics of machine
#: move kinds
TRAVEL, PRINT, RETRACT = 0, 1, 2


def program_header(attrs: dict) -> tuple[MachineProfile, FloatArray, dict]:
    """The profile, part offset and other attributes of a stored program's attributes (``MachineProgram.to_arrays``)."""
    attrs = dict(attrs)
    profile = MachineProfile.model_validate(attrs.pop("profile"))
    offset = np.asarray(attrs.pop("part_offset"), np.float64)
    for k in ("schema_version", "units", "axes"):
        attrs.pop(k, None)
    return profile, offset, attrs


@dataclass
class ProgramMoves:
    """The moves of a machine program as a preview draws them (in 65 of a :class:`MachineProgram`'s 73 bytes a
    move): its ``machine``, ``time_s``, ``kind``, ``source`` and ``layer`` arrays, part offset, profile and attributes.
    The export reads a stored program back as these."""

    #: the arrays of its kind (in the store: the program group's arrays of these names)
    ARRAYS: ClassVar[tuple[str, ...]] = ("machine", "time_s", "kind", "source", "layer")

    machine: FloatArray
    time_s: FloatArray
    kind: np.ndarray
    source: IndexArray
    layer: IndexArray
    part_offset: FloatArray
    profile: MachineProfile
    attrs: dict = field(default_factory=dict)

    def __len__(self) -> int:
        """Number of moves."""
        return int(len(self.machine))

    @classmethod
    def from_arrays(cls, arrays: dict[str, np.ndarray], attrs: dict) -> Self:
        """Inverse of ``MachineProgram.to_arrays`` (``arrays``: at least those of ``ARRAYS``)."""
        profile, offset, attrs = program_header(attrs)
        kw = {k: np.asarray(arrays[k]) for k in cls.ARRAYS}
        return cls(**kw, part_offset=offset, profile=profile, attrs=attrs)

    def read(self) -> Self:
        """The moves: this program itself (a stored one, ``tasks/codec.py: StoredProgram``, reads them only here)."""
        return self

    @property
    def axis_letters(self) -> tuple[str, ...]:
        """G-code letters of X, Y, Z, the tilt, the rotary axis and the extruder."""
        a = self.profile.axes
        return (a.x, a.y, a.z, a.tilt, a.rotate, a.extruder)

    def forward(self, rows: slice | IndexArray = slice(None)) -> tuple[FloatArray, FloatArray]:
        """Forward kinematics of the moves ``rows`` (default: all): tool tip and tool axis (each (k, 3)) in the build
        frame, where each move is meant to reach (the program stores machine coordinates only)."""
        m = self.machine[rows]
        return forward_kinematics(m[:, :3], m[:, 3], m[:, 4], self.profile.kinematics, self.part_offset)

    def tip_segment_lengths(self) -> FloatArray:
        """Length (n,) of each move's tool-tip path in the build frame, the chord from the move before (0 for the
        first), in blocks of rows: a block's tips, not the whole program's."""
        n = len(self)
        d = np.zeros(n)
        for a in range(1, n, ROWS_PER_BLOCK):
            z = min(a + ROWS_PER_BLOCK, n)
            d[a:z] = segment_lengths(self.forward(slice(a - 1, z))[0])[1:]
        return d


@dataclass(kw_only=True)
class MachineProgram(ProgramMoves):
    """Moves of a printer, in execution order.

    machine : (n, 5) float64 X, Y, Z (mm), T, R (deg: the tilt and the rotary axis of the profile's layout, R
    unwrapped; both 0 on a three-axis printer) at the end of each move;
    extruder : (n,) absolute filament position (mm) at the end of each move;
    time_s : (n,) planned duration of each move; kind : (n,) int8 TRAVEL/PRINT/RETRACT (RETRACT:
    extruder-only moves, retraction < 0 or prime > 0); source : (n,) int64 toolpath waypoint index
    reached by the move, -1 for inserted moves (rotary splitting, retract/prime, approach);
    layer : (n,) int64. The tool tip and tool axis in the build frame that each move reaches are the forward
    kinematics of ``machine`` (:meth:`forward`), computed where needed rather than stored.
    """

    ARRAYS: ClassVar[tuple[str, ...]] = ("machine", "extruder", "time_s", "kind", "source", "layer")

    extruder: FloatArray

    def to_arrays(self) -> tuple[dict[str, np.ndarray], dict]:
        """Store-able form: (arrays, JSON attrs incl. the profile) for one zarr group."""
        arrays = {k: np.ascontiguousarray(getattr(self, k)) for k in self.ARRAYS}
        attrs = {"schema_version": PROGRAM_SCHEMA_VERSION, "units": "mm, deg, s",
                 "axes": list(self.axis_letters), "part_offset": [float(v) for v in self.part_offset],
                 "profile": self.profile.model_dump(mode="json"), **self.attrs}
        return arrays, attrs

    def program_xyz(self, start: int = 0, stop: int | None = None) -> FloatArray:
        """The XYZ the G-code carries for moves start..stop-1: machine coordinates, or with ``kinematics.tcp`` the
        tool tip in workpiece coordinates (the part at home), which the controller's TCP turns into machine ones."""
        m = self.machine[start:stop]
        if not self.profile.kinematics.tcp:
            return m[:, :3]
        p, _ = forward_kinematics(m[:, :3], m[:, 3], m[:, 4], self.profile.kinematics, self.part_offset)
        return workpiece_position(p, self.profile.kinematics, self.part_offset)


def auto_part_offset(tp: Toolpaths, platform_z: float) -> FloatArray:
    """Default placement: the part's xy centre on the C axis and the platform on the table (z = 0)."""
    if len(tp) == 0:
        return np.array([0.0, 0.0, -platform_z])
    lo, hi = tp.xyz.min(axis=0), tp.xyz.max(axis=0)
    c = 0.5 * (lo + hi)
    return np.array([-c[0], -c[1], -platform_z])


def filament_area(profile: MachineProfile) -> float:
    """Filament cross-section (mm^2)."""
    return float(np.pi * 0.25 * profile.extrusion.filament_diameter ** 2)


def move_speeds(layer: IndexArray, extrude: np.ndarray, feeds: Feeds) -> FloatArray:
    """Programmed tool-tip speed (n,) of the move arriving at each waypoint (mm/s): the first-layer speed on the
    first printed layer, the print speed elsewhere where it extrudes, the travel speed where it does not."""
    first = layer == layer.min() if len(layer) else np.zeros(0, bool)
    return np.where(extrude, np.where(first, feeds.first_layer_mm_s, feeds.print_mm_s), feeds.travel_mm_s)


def _travel_times(poses: FloatArray, feeds: Feeds) -> FloatArray:
    """Duration (k,) of travels through machine poses (k, 5): length over the travel speed, at least the rotary
    change over the rotary speed (the first pose's own move has length 0)."""
    seg = np.linalg.norm(np.diff(poses[:, :3], axis=0, prepend=poses[:1, :3]), axis=1)
    rot = np.abs(np.diff(poses[:, 3:5], axis=0, prepend=poses[:1, 3:5])).max(axis=1)
    return np.maximum(seg / feeds.travel_mm_s, rot / feeds.rotary_deg_s)


def _moves(tp: Toolpaths, profile: MachineProfile) -> dict[str, np.ndarray]:
    """One move per waypoint (plus the approach from above the first one along its tool axis): part
    position, B/C by IK with its singular flags, filament and duration of the move arriving there."""
    kin, f = profile.kinematics, profile.feeds
    lift = float(tp.attrs.get("config", {}).get("travel_lift", 1.0)) or 1.0
    m = len(tp) + 1

    def first(a: np.ndarray, v: np.ndarray) -> np.ndarray:     # v, then a (one copy, no temporaries)
        out = np.empty((m,) + a.shape[1:], np.result_type(a, np.asarray(v)))
        out[0], out[1:] = v, a
        return out

    # the IK first: its temporaries are freed before the moves' arrays are made
    b, c, singular, _ = inverse_kinematics(first(tp.axis, tp.axis[0]), kin)   # the limits: check_limits
    xyz = first(tp.xyz, tp.xyz[0] + lift * tp.axis[0])
    layer, extrude = first(tp.layer, tp.layer[0]), first(tp.extrude, False)
    seg, drot = segment_lengths(xyz), np.zeros(m)

    def mean_over_move(v: np.ndarray) -> np.ndarray:        # (m,) mean of the values at a move's two ends
        out = np.zeros(m)
        out[1] = 0.5 * (v[0] + v[0])
        np.add(v[1:], v[:-1], out=out[2:])
        out[2:] *= 0.5
        return out

    de = profile.extrusion.flow * mean_over_move(tp.thickness)   # flow x thickness x width x length / area
    de *= mean_over_move(tp.width)
    de *= seg
    de /= filament_area(profile)
    de[~extrude] = 0.0
    speed = move_speeds(layer, extrude, f)
    drot[1:] = np.maximum(np.abs(np.diff(b)), np.abs(np.diff(c)))
    np.divide(seg, speed, out=seg)
    dt = np.maximum(seg, drot / f.rotary_deg_s)
    source = np.arange(-1, m - 1, dtype=np.int64)
    return {"xyz": xyz, "b": b, "c": c, "de": de, "dt": dt, "drot": drot, "extrude": extrude, "layer": layer,
            "source": source, "singular": singular}


def _split_rotary(mv: dict[str, np.ndarray], max_step_deg: float) -> dict[str, np.ndarray]:
    """Moves whose rotary change exceeds the maximal step split into equal parts (linear in part xyz
    and in B, C; filament and time shared); the source waypoint is kept on the last part, which ends
    exactly on the move's own pose. Without a move to split, the arrays are ``mv``'s (no copies). Empties ``mv``
    (each of its arrays is freed once its split copy is made)."""
    m = len(mv["xyz"])
    nsub = np.maximum(1, np.ceil(mv.pop("drot") / max_step_deg - 1e-9)).astype(np.int64)
    nsub[0] = 1
    kind = np.where(mv.pop("extrude"), PRINT, TRAVEL).astype(np.int8)
    mv.pop("singular", None)
    if not (nsub > 1).any():
        return {**{k: mv.pop(k) for k in ("xyz", "b", "c", "de", "dt", "source", "layer")}, "kind": kind}
    rep = np.repeat(np.arange(m), nsub)
    parts = nsub[rep]                                     # parts of the move each part belongs to
    k = np.arange(len(rep)) - np.repeat(np.cumsum(nsub) - nsub, nsub) + 1
    del nsub
    inner = np.flatnonzero(k < parts)                     # parts before the last one of a split move
    last = k == parts
    frac = k[inner] / parts[inner]
    del k
    prev = np.maximum(rep[inner] - 1, 0)

    def lerp(a: np.ndarray) -> np.ndarray:
        out = a[rep]
        out[inner] = a[prev] + (a[rep[inner]] - a[prev]) * (frac if a.ndim == 1 else frac[:, None])
        return out

    out = {name: lerp(mv.pop(name)) for name in ("xyz", "b", "c")}
    out["de"] = np.divide(mv.pop("de")[rep], parts)
    out["dt"] = np.divide(mv.pop("dt")[rep], parts)
    out["kind"] = kind[rep]
    del kind
    out["source"] = np.where(last, mv.pop("source")[rep], -1)
    out["layer"] = mv.pop("layer")[rep]
    return out


def _retract_and_prime(e: dict[str, np.ndarray], profile: MachineProfile) -> tuple[dict[str, np.ndarray], int]:
    """Retract before and prime after travel runs longer than retract_min_travel (moves in place, at
    the pose of the move before / the travel's end); the moves and the number of retractions. Empties
    ``e`` (its arrays are freed as their copies are made)."""
    ex, f = profile.extrusion, profile.feeds
    e_len = segment_lengths(e["xyz"])
    m = len(e_len)
    trav = e["kind"] == TRAVEL
    starts = np.flatnonzero(trav & ~np.concatenate([[False], trav[:-1]]))
    ends = np.flatnonzero(trav & ~np.concatenate([trav[1:], [False]]))
    cum = np.zeros(m + 1)
    e_len[~trav] = 0.0
    np.cumsum(e_len, out=cum[1:])
    run_len = cum[ends + 1] - cum[starts]
    do = (run_len > ex.retract_min_travel) & (starts > 0) & (ex.retract_mm > 0 or ex.prime_mm > 0)
    r_at, p_at = starts[do], ends[do]
    ins_idx = np.concatenate([r_at, p_at + 1])            # insert before these indices
    ins_from = np.concatenate([r_at - 1, p_at])           # copy pose of this move
    ins_de = np.concatenate([np.full(len(r_at), -ex.retract_mm), np.full(len(p_at), ex.prime_mm)])
    ins_dt = np.concatenate([np.full(len(r_at), ex.retract_mm), np.full(len(p_at), ex.prime_mm)]) / f.retract_mm_s
    order = np.argsort(ins_idx, kind="stable")
    ins_idx, ins_from, ins_de, ins_dt = ins_idx[order], ins_from[order], ins_de[order], ins_dt[order]
    ins = lambda a, v: np.insert(a, ins_idx, v, axis=0)  # noqa: E731
    del e_len, trav, cum
    out = {}
    for k in ("xyz", "b", "c", "layer"):             # popped: each input array is freed once copied
        a = e.pop(k)
        out[k] = ins(a, a[ins_from])
    out.update(de=ins(e.pop("de"), ins_de), dt=ins(e.pop("dt"), np.maximum(ins_dt, 1e-3)),
               kind=ins(e.pop("kind"), RETRACT), source=ins(e.pop("source"), -1))
    out["dt"][0] = 0.0
    return out, int(len(r_at))


def _rotary_steps(frm: FloatArray, targets: list[FloatArray], max_step_deg: float) -> FloatArray:
    """Machine poses (k, 5) from ``frm`` through each target, linear in all axes, rotary steps split
    (a target where the machine already is adds no move)."""
    out, cur = [], np.asarray(frm, np.float64)
    for t in targets:
        t = np.asarray(t, np.float64)
        if np.allclose(t, cur, rtol=0.0, atol=1e-9):
            continue
        n = max(1, int(np.ceil(np.abs(t[3:5] - cur[3:5]).max() / max_step_deg - 1e-9)))
        out.append(cur + (t - cur) * (np.arange(1, n + 1) / n)[:, None])
        cur = t
    return np.concatenate(out) if out else np.zeros((0, 5))


def safe_height(program: MachineProgram) -> float:
    """Machine Z at which the tool tip clears the part at any rotary angles: above the sphere around the pivot
    holding it (table-table), else above the part's top (a head's tilt lifts the tip, a table's rotation keeps z)."""
    tips = (program.forward(slice(a, a + ROWS_PER_BLOCK))[0] for a in range(0, len(program), ROWS_PER_BLOCK))
    return _safe_height(tips, program.part_offset, program.profile)


def _safe_height(tips: Iterable[FloatArray], part_offset: FloatArray, profile: MachineProfile) -> float:
    """``safe_height`` of moves reaching the tool tips ``tips`` (blocks of (k, 3) rows)."""
    kin = profile.kinematics
    if kin.layout != "table-table":
        top = max((float(p[:, 2].max(initial=0.0)) for p in tips), default=0.0) + float(part_offset[2])
        lift = float(kin.c_offset[2])                 # the bed's (or rotary table's) top in machine Z
        return top + lift + profile.gcode.safe_clearance_mm
    reach = max((float(np.linalg.norm(p + part_offset, axis=1).max()) for p in tips if len(p)), default=0.0)
    return float(kin.pivot[2] + np.linalg.norm(kin.c_offset) + reach + profile.gcode.safe_clearance_mm)


def _home_c(c: float, lo: float | None, hi: float | None) -> float:
    """The whole turn nearest ``c`` inside [lo, hi] (C home at the end of a program)."""
    k = np.round(c / 360.0)
    if lo is not None:
        k = max(k, np.ceil(lo / 360.0 - 1e-12))
    if hi is not None:
        k = min(k, np.floor(hi / 360.0 + 1e-12))
    return float(360.0 * k)


def _with_safe_start_end(program: MachineProgram, z_safe: float | None = None, consume: bool = False) -> MachineProgram:
    """The program between a safe start (safe height over the approach point with B = C = 0, rotary axes to the
    first pose up there, the approach down the tool axis, prime) and a safe end (retract, lift to the safe
    height, B to 0 and C to its nearest full turn, park): all inserted moves, source -1. With ``consume`` the
    input's arrays are released (set empty) as soon as they are copied, so the two programs are not held at once."""
    prof = program.profile
    kin, f, ex, g = prof.kinematics, prof.feeds, prof.extrusion, prof.gcode
    z_safe = safe_height(program) if z_safe is None else z_safe
    m0, mn = program.machine[0].copy(), program.machine[-1].copy()
    above0 = np.array([m0[0], m0[1], z_safe, 0.0, _home_c(m0[4], kin.rotate_min_deg, kin.rotate_max_deg)])
    start = np.vstack([above0[None], _rotary_steps(above0, [np.r_[m0[:2], z_safe, m0[3:5]]], kin.max_rotary_step_deg)])
    home = np.r_[mn[:2], z_safe, 0.0, _home_c(mn[4], kin.rotate_min_deg, kin.rotate_max_deg)]
    park = np.r_[g.park_xy if g.park_xy is not None else mn[:2], z_safe, home[3:5]]
    end = _rotary_steps(mn, [np.r_[mn[:2], z_safe, mn[3:5]], home, park], kin.max_rotary_step_deg)
    # moves: start..., approach (program move 0), prime, program moves 1.., retract, end...
    pm = program.machine
    machine = np.concatenate([start, pm[:1], pm[:1], pm[1:], pm[-1:], end])
    del pm
    n_s, n_e = len(start), len(end)

    def done(*names: str) -> None:
        for name in names if consume else ():
            setattr(program, name, getattr(program, name)[:0].copy())

    done("machine")
    # travel times of the inserted travels (each from the pose before; the program's own moves keep theirs)
    t_start = _travel_times(machine[:n_s + 1], f)
    t_end = _travel_times(machine[len(machine) - n_e - 1:], f)[1:]
    retract = np.array([RETRACT], np.int8)
    kind = np.concatenate([np.full(n_s, TRAVEL, np.int8), program.kind[:1].astype(np.int8), retract,
                           program.kind[1:].astype(np.int8), retract, np.full(n_e, TRAVEL, np.int8)])
    done("kind")
    de = np.concatenate([np.zeros(n_s), program.extruder[:1], [ex.prime_mm], np.diff(program.extruder),
                         [-ex.retract_mm], np.zeros(n_e)])
    done("extruder")
    time_s = np.concatenate([t_start[:n_s], program.time_s[:1], [ex.prime_mm / f.retract_mm_s], program.time_s[1:],
                             [ex.retract_mm / f.retract_mm_s], t_end])
    time_s[n_s] = t_start[n_s]                     # the approach now comes from the safe height
    time_s[0] = 0.0
    done("time_s")
    layer = np.concatenate([np.full(n_s + 2, program.layer[0], np.int64), program.layer[1:],
                            np.full(n_e + 1, program.layer[-1], np.int64)]).astype(np.int64, copy=False)
    done("layer")
    source = np.concatenate([np.full(n_s, -1, np.int64), program.source[:1], [-1], program.source[1:], [-1],
                             np.full(n_e, -1, np.int64)]).astype(np.int64, copy=False)
    done("source")
    return MachineProgram(machine=machine, extruder=np.cumsum(de, out=de), time_s=time_s, kind=kind, source=source,
                          layer=layer, part_offset=program.part_offset, profile=prof,
                          attrs={**program.attrs, "safe_z": z_safe})


def merge_short_moves(tp: Toolpaths, profile: MachineProfile) -> tuple[Toolpaths, int]:
    """Printing waypoints reached by a move shorter than ``feeds.min_move_s`` dropped, so the move goes on to
    the next waypoint of the path (path ends, travels and the first layer's speed respected); greedy along each
    path, so a run of tiny moves becomes one. Returns the toolpaths and the number of waypoints dropped."""
    f = profile.feeds
    n = len(tp)
    if f.min_move_s <= 0 or n < 3:
        return tp, 0
    speed = move_speeds(tp.layer, np.ones(n, bool), f)                 # the inner moves considered all extrude
    turn = np.zeros(n)
    turn[1:] = np.degrees(np.arccos(np.clip(np.einsum("ij,ij->i", tp.axis[1:], tp.axis[:-1]), -1.0, 1.0)))
    seg = tp.segment_lengths()
    same = np.zeros(n, bool)
    same[1:-1] = (tp.path[1:-1] >= 0) & (tp.path[1:-1] == tp.path[:-2]) & (tp.path[1:-1] == tp.path[2:])
    inner = same & tp.extrude & np.r_[tp.extrude[1:], False]
    short = np.maximum(seg / speed, turn / f.rotary_deg_s) < f.min_move_s
    cand = np.flatnonzero(inner & short)
    if not len(cand):
        return tp, 0
    keep = np.ones(n, bool)
    prev_of = {}
    for i in cand:                                  # few: the moves under a few milliseconds
        j = prev_of.get(i - 1, i - 1) if not keep[i - 1] else i - 1
        d = float(np.linalg.norm(tp.xyz[i] - tp.xyz[j]))
        a = float(np.degrees(np.arccos(np.clip(tp.axis[i] @ tp.axis[j], -1.0, 1.0))))
        if max(d / speed[i], a / f.rotary_deg_s) < f.min_move_s:
            keep[i] = False
            prev_of[i] = j
    if keep.all():
        return tp, 0
    del speed, turn, seg, same, inner, short, cand, prev_of   # the copy below is the step's peak: room for it
    sub = {k: getattr(tp, k)[keep] for k in ("layer", "path", "xyz", "axis", "thickness", "width", "extrude")}
    return replace(tp, **sub, attrs=dict(tp.attrs)), int((~keep).sum())


def _segment_starts(kind: np.ndarray) -> IndexArray:
    """Moves where a travel run begins (and move 0): the places to unwind C between paths."""
    trav = kind == TRAVEL
    starts = np.flatnonzero(trav[1:] & ~trav[:-1]) + 1
    return np.concatenate([[0], starts]).astype(np.int64)


def _turns_fitting(c_lo: float, c_hi: float, lo: float, hi: float) -> tuple[float, float]:
    """Range of whole turns k with [c_lo, c_hi] + 360 k inside [lo, hi] (empty when first > second)."""
    return np.ceil((lo - c_lo) / 360.0 - 1e-12), np.floor((hi - c_hi) / 360.0 + 1e-12)


def c_turns(c: FloatArray, kind: np.ndarray, lo: float, hi: float) -> np.ndarray:
    """Whole turns (n,) to add to each move's C so that all lie in [lo, hi]: one number for the program when
    that fits; else kept per path (a travel run and the moves up to the next) while a path fits, changed at
    its start when it must, and inside a path only when the path alone spans more than the range (there to
    the far end of the range, the fewest unwinds). Where the count changes, the move before (the pose the
    axis is turned at) fits the new count too. The first turn count is the one nearest zero. With one side of
    the range open a single count always fits."""
    n = len(c)
    k_lo, k_hi = _turns_fitting(float(c.min(initial=0.0)), float(c.max(initial=0.0)), lo, hi)
    if n == 0 or k_lo <= k_hi:
        return np.full(n, 0.0 if n == 0 else float(np.clip(0.0, k_lo, k_hi)))
    starts = _segment_starts(kind)
    seg_lo, seg_hi = np.minimum.reduceat(c, starts), np.maximum.reduceat(c, starts)
    # a count that changes at a path's start turns the axis at the pose before it: that pose must fit the new count
    before = c[np.maximum(starts - 1, 0)]
    seg_lo, seg_hi = np.minimum(seg_lo, before), np.maximum(seg_hi, before)
    ends = np.r_[starts[1:], n]
    turns = np.empty(n)
    k = None
    for s, (a, b) in enumerate(zip(starts, ends)):
        f_lo, f_hi = _turns_fitting(float(seg_lo[s]), float(seg_hi[s]), lo, hi)
        if f_lo <= f_hi:
            k = float(np.clip(0.0 if k is None else k, f_lo, f_hi))
            turns[a:b] = k
            continue
        rising = c[b - 1] >= c[a]
        for i in range(a, b):                      # the path spans more than the range: unwind inside it,
            if k is None or not lo <= c[i] + 360.0 * k <= hi:   # to the end of the range it moves away from
                up = c[i] + 360.0 * k > hi if k is not None else rising
                pair = c[max(i - 1, 0):i + 1]      # the pose turned at (the move before) and the move itself
                k = float(np.ceil((lo - pair.min()) / 360.0 - 1e-12) if up
                          else np.floor((hi - pair.max()) / 360.0 + 1e-12))
            turns[i] = k
    return turns


def unwind_c(program: MachineProgram, z_safe: float) -> tuple[MachineProgram, int]:
    """Keep C inside the profile's range by whole turns (``c_turns``); where the turn count changes, the
    program retracts, lifts straight up (along the tool) to ``z_safe``, turns C there, comes back down to the
    same pose and primes. Returns the program and the number of unwinds."""
    prof = program.profile
    kin, f, ex = prof.kinematics, prof.feeds, prof.extrusion
    lo = -np.inf if kin.rotate_min_deg is None else float(kin.rotate_min_deg)
    hi = np.inf if kin.rotate_max_deg is None else float(kin.rotate_max_deg)
    if not len(program) or (np.isinf(lo) and np.isinf(hi)):
        return program, 0
    turns = c_turns(program.machine[:, 4], program.kind, lo, hi)
    machine = program.machine.copy()
    machine[:, 4] += 360.0 * turns
    at = np.flatnonzero(np.diff(turns) != 0) + 1
    if not len(at):
        return replace(program, machine=machine), 0
    cols = {"machine": machine, "de": np.diff(program.extruder, prepend=0.0), "time_s": program.time_s,
            "kind": program.kind, "source": program.source, "layer": program.layer}
    pieces: dict[str, list] = {k: [] for k in cols}
    prev = 0
    for j in at:
        for key, arr in cols.items():
            pieces[key].append(arr[prev:j])
        p = machine[j - 1]
        up = np.r_[p[:2], max(z_safe, p[2]), p[3:5]]
        turned = np.r_[up[:4], p[4] + 360.0 * (turns[j] - turns[j - 1])]
        spin = _rotary_steps(up, [turned], kin.max_rotary_step_deg)
        down = np.r_[p[:4], turned[4]]
        block = np.vstack([p, up, spin, down, down])
        m = len(block)
        t = _travel_times(block, f)
        t[0], t[-1] = ex.retract_mm / f.retract_mm_s, ex.prime_mm / f.retract_mm_s
        pieces["machine"].append(block)
        pieces["de"].append(np.r_[-ex.retract_mm, np.zeros(m - 2), ex.prime_mm])
        pieces["time_s"].append(np.maximum(t, 1e-3))
        pieces["kind"].append(np.r_[RETRACT, np.full(m - 2, TRAVEL), RETRACT].astype(np.int8))
        pieces["source"].append(np.full(m, -1, np.int64))
        pieces["layer"].append(np.full(m, program.layer[j - 1], np.int64))
        prev = j
    for key, arr in cols.items():
        pieces[key].append(arr[prev:])
    cat = {k: np.concatenate(v) for k, v in pieces.items()}
    out = replace(program, machine=cat["machine"], extruder=np.cumsum(cat["de"]), time_s=cat["time_s"],
                  kind=cat["kind"].astype(np.int8), source=cat["source"], layer=cat["layer"],
                  attrs=dict(program.attrs))
    return out, int(len(at))


def check_limits(program: MachineProgram) -> None:
    """Raise PlanError when any pose lies outside the profile's tilt or rotary range (naming layers and counts)."""
    kin = program.profile.kinematics
    if not kin.rotary:
        return
    b, c = program.machine[:, 3], program.machine[:, 4]
    tol = 1e-6
    bad_b = (b < kin.tilt_min_deg - tol) | (b > kin.tilt_max_deg + tol)
    bad_c = np.zeros(len(c), bool)
    if kin.rotate_min_deg is not None:
        bad_c |= c < kin.rotate_min_deg - tol
    if kin.rotate_max_deg is not None:
        bad_c |= c > kin.rotate_max_deg + tol
    _, _, _, lt, lr, _ = program.axis_letters
    for bad, axis, lo, hi in ((bad_b, lt, kin.tilt_min_deg, kin.tilt_max_deg),
                              (bad_c, lr, kin.rotate_min_deg, kin.rotate_max_deg)):
        if bad.any():
            layers, counts = np.unique(program.layer[bad], return_counts=True)
            where = ", ".join(f"layer {int(k)} ({int(n)})" for k, n in list(zip(layers, counts))[:8])
            more = f" and {len(layers) - 8} more layers" if len(layers) > 8 else ""
            raise PlanError(f"{int(bad.sum()):,} moves put {axis} outside the machine's range [{lo}, {hi}] deg "
                            f"({program.profile.name}): {where}{more}. Turn the tool axes into reach "
                            "(plan_print does; kinematics.beyond_reach: turn) or widen the range in the profile")


def plan_motion(tp: Toolpaths, profile: MachineProfile, platform_z: float | None = None) -> MachineProgram:
    """Machine program for toolpaths: IK with continuous rotary axes, rotary splitting, feeds, extrusion.

    Extrusion per print move = flow * mean thickness * mean width * length / filament area (mm of
    filament); travels longer than ``extrusion.retract_min_travel`` retract before and prime after.
    Move durations: length / speed (print, first-layer or travel speed), at least the rotary change
    divided by ``feeds.rotary_deg_s``.
    """
    kin = profile.kinematics
    pz = float(platform_z if platform_z is not None else tp.attrs.get("platform_z", 0.0))
    offset = (np.asarray(kin.part_offset, np.float64) if kin.part_offset is not None
              else auto_part_offset(tp, pz))
    mv = _moves(tp, profile)
    n_singular, n_moves = int(mv["singular"].sum()), len(mv["xyz"])
    e = _split_rotary(mv, kin.max_rotary_step_deg)
    n_inserted_rotary = len(e["xyz"]) - n_moves
    del mv                                         # e may share its arrays: freed as _retract_and_prime copies
    e, n_retractions = _retract_and_prime(e, profile)
    release_freed_memory()     # the IK's and the splits' temporaries: the program's arrays are the next to come
    n = len(e["xyz"])
    machine = np.empty((n, 5))
    machine_position(e["xyz"], e["b"], e["c"], kin, offset, out=machine[:, :3])
    machine[:, 3], machine[:, 4] = e.pop("b"), e.pop("c")
    xyz = e.pop("xyz")
    z_safe = _safe_height((xyz[a:a + ROWS_PER_BLOCK] for a in range(0, n, ROWS_PER_BLOCK)), offset, profile)
    del xyz
    program = MachineProgram(machine=machine, extruder=np.cumsum(e.pop("de")), time_s=e.pop("dt"), kind=e.pop("kind"),
                             source=e.pop("source").astype(np.int64, copy=False),
                             layer=e.pop("layer").astype(np.int64, copy=False), part_offset=offset, profile=profile)
    del machine
    program, n_unwinds = unwind_c(program, z_safe)
    if profile.gcode.safe_start_end and n:
        program = _with_safe_start_end(program, z_safe, consume=True)
    check_limits(program)
    machine = program.machine
    b_all = machine[:, 3]
    program.attrs = {
        **program.attrs,
        "platform_z": pz,
        "n_singular": n_singular,
        "n_rotary_out_of_range": 0,
        "n_c_unwinds": n_unwinds,
        "n_inserted_rotary": int(n_inserted_rotary),
        "n_retractions": n_retractions,
        "max_rotary_step_deg": max((float(np.max(np.abs(np.diff(machine[a:a + ROWS_PER_BLOCK + 1, 3:5], axis=0)),
                                                 initial=0.0)) for a in range(0, len(machine), ROWS_PER_BLOCK)),
                                   default=0.0),
        "b_range_deg": [float(b_all.min()), float(b_all.max())],
        "c_range_deg": [float(machine[:, 4].min()), float(machine[:, 4].max())],
    }
    return program


#: what print hosts call the toolpath kinds (``toolpath/generate.py``: SHELL, INFILL, STRESS), PrusaSlicer's names
FEATURE_NAMES = {"0": "Perimeter", "1": "Internal infill", "2": "Internal infill"}


def feature_runs(program: MachineProgram, path: IndexArray, path_kinds: str) -> dict[str, object]:
    """Where the printed feature changes: ``{"moves": [i, ...], "kinds": "01..."}``, each the first printing move of a
    run of one feature (its rotary-split parts included) and one digit of its toolpath kind (``path``: the toolpaths'
    path id per waypoint, ``path_kinds``: one digit per path id); a run ends where :data:`FEATURE_NAMES` changes."""
    n = len(program)
    src = program.source
    ahead = np.where(src >= 0, np.arange(n), n)
    ahead = np.minimum.accumulate(ahead[::-1])[::-1]             # the next move that reaches a waypoint
    printing = np.flatnonzero((program.kind == PRINT) & (ahead < n))
    pid = path[src[ahead[printing]]]
    printing, pid = printing[pid >= 0], pid[pid >= 0]
    if not len(printing) or int(pid.max()) >= len(path_kinds):
        return {"moves": [], "kinds": ""}
    codes = np.frombuffer(path_kinds.encode(), np.uint8)[pid]
    named = np.array([ord(FEATURE_NAMES.get(chr(c), "Perimeter")[0]) for c in range(256)], np.uint8)[codes]
    start = np.r_[True, named[1:] != named[:-1]]
    return {"moves": [int(i) for i in printing[start]], "kinds": codes[start].tobytes().decode()}


def program_metrics(program: MachineProgram, times: tuple[FloatArray, FloatArray] | None = None) -> dict:
    """Totals of a program: time, path length, waypoints, material, filament (``times``: its
    ``timing.schedule`` when already computed)."""
    timed = program_time(program, times)     # first: its schedule's arrays are the largest the metrics need
    seg = program.tip_segment_lengths()[1:]
    kind = program.kind[1:]
    de = np.diff(program.extruder)
    area = filament_area(program.profile)
    material = float(de[kind == PRINT].sum() * area / program.profile.extrusion.flow)
    return {
        **timed,
        "toolpath_length_mm": float(seg[kind == PRINT].sum()),
        "travel_length_mm": float(seg[kind == TRAVEL].sum()),
        "n_moves": len(program),
        "n_waypoints": int((program.source >= 0).sum()),
        "material_mm3": material,
        "filament_mm": float(de[kind == PRINT].sum()),
    }
