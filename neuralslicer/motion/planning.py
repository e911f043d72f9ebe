"""Motion planning (SPEC step 12): machine coordinates, rotary splitting, feeds, extrusion, retraction."""
from __future__ import annotations

from dataclasses import dataclass, field, replace

import numpy as np

from neuralslicer.errors import PlanError
from neuralslicer.motion.kinematics import forward_kinematics, inverse_kinematics, machine_position
from neuralslicer.motion.profile import Feeds, MachineProfile
from neuralslicer.motion.timing import program_time
from neuralslicer.toolpath.types import Toolpaths
from neuralslicer.types import FloatArray, IndexArray

PROGRAM_SCHEMA_VERSION = 1
#: move kinds
TRAVEL, PRINT, RETRACT = 0, 1, 2
_ARRAYS = ("machine", "extruder", "time_s", "kind", "source", "layer", "part_xyz", "part_axis")


@dataclass
class MachineProgram:
    """Moves of a table-table B/C printer, in execution order.

    machine : (n, 5) float64 X, Y, Z (mm), B, C (deg, C unwrapped) at the end of each move;
    extruder : (n,) absolute filament position (mm) at the end of each move;
    time_s : (n,) planned duration of each move; kind : (n,) int8 TRAVEL/PRINT/RETRACT (RETRACT:
    extruder-only moves, retraction < 0 or prime > 0); source : (n,) int64 toolpath waypoint index
    reached by the move, -1 for inserted moves (rotary splitting, retract/prime, approach);
    layer : (n,) int64; part_xyz / part_axis : (n, 3) the tool tip and tool axis in the build frame
    the move is meant to reach (forward kinematics of ``machine`` reproduces them).
    """

    machine: FloatArray
    extruder: FloatArray
    time_s: FloatArray
    kind: np.ndarray
    source: IndexArray
    layer: IndexArray
    part_xyz: FloatArray
    part_axis: FloatArray
    part_offset: FloatArray
    profile: MachineProfile
    attrs: dict = field(default_factory=dict)

    def __len__(self) -> int:
        """Number of moves."""
        return int(len(self.machine))

    def to_arrays(self) -> tuple[dict[str, np.ndarray], dict]:
        """Store-able form: (arrays, JSON attrs incl. the profile) for one zarr group."""
        arrays = {k: np.ascontiguousarray(getattr(self, k)) for k in _ARRAYS}
        attrs = {"schema_version": PROGRAM_SCHEMA_VERSION, "units": "mm, deg, s",
                 "axes": list(self.axis_letters), "part_offset": [float(v) for v in self.part_offset],
                 "profile": self.profile.model_dump(mode="json"), **self.attrs}
        return arrays, attrs

    @classmethod
    def from_arrays(cls, arrays: dict[str, np.ndarray], attrs: dict) -> "MachineProgram":
        """Inverse of ``to_arrays``."""
        attrs = dict(attrs)
        profile = MachineProfile.model_validate(attrs.pop("profile"))
        offset = np.asarray(attrs.pop("part_offset"), np.float64)
        for k in ("schema_version", "units", "axes"):
            attrs.pop(k, None)
        kw = {k: np.asarray(arrays[k]) for k in _ARRAYS}
        return cls(**kw, part_offset=offset, profile=profile, attrs=attrs)

    @property
    def axis_letters(self) -> tuple[str, ...]:
        """G-code letters of X, Y, Z, B, C and the extruder."""
        a = self.profile.axes
        return (a.x, a.y, a.z, a.tilt, a.rotate, a.extruder)

    def forward(self) -> tuple[FloatArray, FloatArray]:
        """Forward kinematics of all moves: tool tip and tool axis in the build frame."""
        return forward_kinematics(self.machine[:, :3], self.machine[:, 3], self.machine[:, 4],
                                  self.profile.kinematics, self.part_offset)


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
    first = lambda a, v: np.concatenate([v, a])  # noqa: E731
    xyz = first(tp.xyz, tp.xyz[:1] + lift * tp.axis[:1])
    layer, extrude = first(tp.layer, tp.layer[:1]), first(tp.extrude, [False])
    thick, width = first(tp.thickness, tp.thickness[:1]), first(tp.width, tp.width[:1])
    b, c, singular, _ = inverse_kinematics(first(tp.axis, tp.axis[:1]), kin)   # the limits: check_limits
    m = len(xyz)
    seg, t_mean, w_mean, drot = np.zeros(m), np.zeros(m), np.zeros(m), np.zeros(m)
    seg[1:] = np.linalg.norm(np.diff(xyz, axis=0), axis=1)
    t_mean[1:] = 0.5 * (thick[1:] + thick[:-1])
    w_mean[1:] = 0.5 * (width[1:] + width[:-1])
    de = np.where(extrude, profile.extrusion.flow * t_mean * w_mean * seg / filament_area(profile), 0.0)
    speed = move_speeds(layer, extrude, f)
    drot[1:] = np.maximum(np.abs(np.diff(b)), np.abs(np.diff(c)))
    return {"xyz": xyz, "b": b, "c": c, "de": de, "dt": np.maximum(seg / speed, drot / f.rotary_deg_s),
            "drot": drot, "extrude": extrude, "layer": layer, "source": first(np.arange(len(tp)), [-1]),
            "singular": singular}


def _split_rotary(mv: dict[str, np.ndarray], max_step_deg: float) -> dict[str, np.ndarray]:
    """Moves whose rotary change exceeds the maximal step split into equal parts (linear in part xyz
    and in B, C; filament and time shared); the source waypoint is kept on the last part."""
    m = len(mv["xyz"])
    nsub = np.maximum(1, np.ceil(mv["drot"] / max_step_deg - 1e-9)).astype(np.int64)
    nsub[0] = 1
    rep = np.repeat(np.arange(m), nsub)
    k = np.arange(len(rep)) - np.repeat(np.cumsum(nsub) - nsub, nsub) + 1
    frac = k / nsub[rep]
    prev = np.maximum(rep - 1, 0)
    lerp = lambda a: a[prev] + (a[rep] - a[prev]) * (frac if a.ndim == 1 else frac[:, None])  # noqa: E731
    return {"xyz": lerp(mv["xyz"]), "b": lerp(mv["b"]), "c": lerp(mv["c"]), "de": mv["de"][rep] / nsub[rep],
            "dt": mv["dt"][rep] / nsub[rep], "kind": np.where(mv["extrude"][rep], PRINT, TRAVEL).astype(np.int8),
            "source": np.where(k == nsub[rep], mv["source"][rep], -1), "layer": mv["layer"][rep]}


def _retract_and_prime(e: dict[str, np.ndarray], profile: MachineProfile) -> tuple[dict[str, np.ndarray], int]:
    """Retract before and prime after travel runs longer than retract_min_travel (moves in place, at
    the pose of the move before / the travel's end); the moves and the number of retractions."""
    ex, f = profile.extrusion, profile.feeds
    e_len = np.linalg.norm(np.diff(e["xyz"], axis=0, prepend=e["xyz"][:1]), axis=1)
    trav = e["kind"] == TRAVEL
    starts = np.flatnonzero(trav & ~np.concatenate([[False], trav[:-1]]))
    ends = np.flatnonzero(trav & ~np.concatenate([trav[1:], [False]]))
    cum = np.concatenate([[0.0], np.cumsum(np.where(trav, e_len, 0.0))])
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
    out = {k: ins(e[k], e[k][ins_from]) for k in ("xyz", "b", "c", "layer")}
    out.update(de=ins(e["de"], ins_de), dt=ins(e["dt"], np.maximum(ins_dt, 1e-3)), kind=ins(e["kind"], RETRACT),
               source=ins(e["source"], -1))
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
    """Machine Z at which the tool tip clears the part at any B/C: above the sphere around the pivot holding it."""
    kin = program.profile.kinematics
    reach = float(np.linalg.norm(program.part_xyz + program.part_offset, axis=1).max(initial=0.0))
    return float(kin.pivot[2] + np.linalg.norm(kin.c_offset) + reach + program.profile.gcode.safe_clearance_mm)


def _home_c(c: float, lo: float | None, hi: float | None) -> float:
    """The whole turn nearest ``c`` inside [lo, hi] (C home at the end of a program)."""
    k = np.round(c / 360.0)
    if lo is not None:
        k = max(k, np.ceil(lo / 360.0 - 1e-12))
    if hi is not None:
        k = min(k, np.floor(hi / 360.0 + 1e-12))
    return float(360.0 * k)


def _with_safe_start_end(program: MachineProgram, z_safe: float | None = None) -> MachineProgram:
    """The program between a safe start (safe height over the approach point with B = C = 0, rotary axes to the
    first pose up there, the approach down the tool axis, prime) and a safe end (retract, lift to the safe
    height, B to 0 and C to its nearest full turn, park): all inserted moves, source -1."""
    prof = program.profile
    kin, f, ex, g = prof.kinematics, prof.feeds, prof.extrusion, prof.gcode
    z_safe = safe_height(program) if z_safe is None else z_safe
    m0, mn = program.machine[0], program.machine[-1]
    above0 = np.array([m0[0], m0[1], z_safe, 0.0, _home_c(m0[4], kin.c_min_deg, kin.c_max_deg)])
    start = np.vstack([above0[None], _rotary_steps(above0, [np.r_[m0[:2], z_safe, m0[3:5]]], kin.max_rotary_step_deg)])
    home = np.r_[mn[:2], z_safe, 0.0, _home_c(mn[4], kin.c_min_deg, kin.c_max_deg)]
    park = np.r_[g.park_xy if g.park_xy is not None else mn[:2], z_safe, home[3:5]]
    end = _rotary_steps(mn, [np.r_[mn[:2], z_safe, mn[3:5]], home, park], kin.max_rotary_step_deg)
    # moves: start..., approach (program move 0), prime, program moves 1.., retract, end...
    machine = np.vstack([start, program.machine[:1], program.machine[:1], program.machine[1:], program.machine[-1:], end])
    n_s, n_e = len(start), len(end)
    kind = np.r_[np.full(n_s, TRAVEL), program.kind[:1], RETRACT, program.kind[1:], RETRACT, np.full(n_e, TRAVEL)]
    de_prog = np.diff(program.extruder, prepend=0.0)
    de = np.r_[np.zeros(n_s), de_prog[:1], ex.prime_mm, de_prog[1:], -ex.retract_mm, np.zeros(n_e)]
    travel_t = _travel_times(machine, f)
    t_prog = program.time_s.copy()
    t_prog[0] = travel_t[n_s]                      # the approach now comes from the safe height
    time_s = np.r_[travel_t[:n_s], t_prog[:1], ex.prime_mm / f.retract_mm_s, t_prog[1:], ex.retract_mm / f.retract_mm_s,
                   travel_t[len(travel_t) - n_e:]]
    time_s[0] = 0.0
    layer = np.r_[np.full(n_s + 2, program.layer[0]), program.layer[1:], np.full(n_e + 1, program.layer[-1])]
    source = np.r_[np.full(n_s, -1), program.source[:1], -1, program.source[1:], -1, np.full(n_e, -1)]
    p, a = forward_kinematics(machine[:, :3], machine[:, 3], machine[:, 4], kin, program.part_offset)
    return MachineProgram(machine=machine, extruder=np.cumsum(de), time_s=time_s, kind=kind.astype(np.int8),
                          source=source.astype(np.int64), layer=layer.astype(np.int64), part_xyz=p, part_axis=a,
                          part_offset=program.part_offset, profile=prof, attrs={**program.attrs, "safe_z": z_safe})


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
    the far end of the range, the fewest unwinds). The first turn count is the one nearest zero. With one
    side of the range open a single count always fits."""
    n = len(c)
    k_lo, k_hi = _turns_fitting(float(c.min(initial=0.0)), float(c.max(initial=0.0)), lo, hi)
    if n == 0 or k_lo <= k_hi:
        return np.full(n, 0.0 if n == 0 else float(np.clip(0.0, k_lo, k_hi)))
    starts = _segment_starts(kind)
    seg_lo, seg_hi = np.minimum.reduceat(c, starts), np.maximum.reduceat(c, starts)
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
                k = float(np.ceil((lo - c[i]) / 360.0 - 1e-12) if up else np.floor((hi - c[i]) / 360.0 + 1e-12))
            turns[i] = k
    return turns


def unwind_c(program: MachineProgram, z_safe: float) -> tuple[MachineProgram, int]:
    """Keep C inside the profile's range by whole turns (``c_turns``); where the turn count changes, the
    program retracts, lifts straight up (along the tool) to ``z_safe``, turns C there, comes back down to the
    same pose and primes. Returns the program and the number of unwinds."""
    prof = program.profile
    kin, f, ex = prof.kinematics, prof.feeds, prof.extrusion
    lo = -np.inf if kin.c_min_deg is None else float(kin.c_min_deg)
    hi = np.inf if kin.c_max_deg is None else float(kin.c_max_deg)
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
    mach = cat["machine"]
    xyz, axis = forward_kinematics(mach[:, :3], mach[:, 3], mach[:, 4], kin, program.part_offset)
    out = replace(program, machine=mach, extruder=np.cumsum(cat["de"]), time_s=cat["time_s"],
                  kind=cat["kind"].astype(np.int8), source=cat["source"], layer=cat["layer"],
                  part_xyz=xyz, part_axis=axis, attrs=dict(program.attrs))
    return out, int(len(at))


def check_limits(program: MachineProgram) -> None:
    """Raise PlanError when any pose lies outside the profile's B or C range (naming layers and counts)."""
    kin = program.profile.kinematics
    b, c = program.machine[:, 3], program.machine[:, 4]
    tol = 1e-6
    bad_b = (b < kin.b_min_deg - tol) | (b > kin.b_max_deg + tol)
    bad_c = np.zeros(len(c), bool)
    if kin.c_min_deg is not None:
        bad_c |= c < kin.c_min_deg - tol
    if kin.c_max_deg is not None:
        bad_c |= c > kin.c_max_deg + tol
    for bad, axis, lo, hi in ((bad_b, "B", kin.b_min_deg, kin.b_max_deg), (bad_c, "C", kin.c_min_deg, kin.c_max_deg)):
        if bad.any():
            layers, counts = np.unique(program.layer[bad], return_counts=True)
            where = ", ".join(f"layer {int(k)} ({int(n)})" for k, n in list(zip(layers, counts))[:8])
            more = f" and {len(layers) - 8} more layers" if len(layers) > 8 else ""
            raise PlanError(f"{int(bad.sum()):,} moves put {axis} outside the machine's range [{lo}, {hi}] deg "
                            f"({program.profile.name}): {where}{more}. Turn the tool axes into reach "
                            "(plan_print does; kinematics.beyond_reach: turn) or widen the range in the profile")


def plan_motion(tp: Toolpaths, profile: MachineProfile, platform_z: float | None = None) -> MachineProgram:
    """Machine program for toolpaths: IK with continuous B/C, rotary splitting, feeds, extrusion.

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
    split = _split_rotary(mv, kin.max_rotary_step_deg)
    e, n_retractions = _retract_and_prime(split, profile)
    mxyz = machine_position(e["xyz"], e["b"], e["c"], kin, offset)
    machine = np.column_stack([mxyz, e["b"], e["c"]])
    br, cr = np.radians(e["b"]), np.radians(e["c"])
    a_fk = np.stack([-np.cos(cr) * np.sin(br), np.sin(cr) * np.sin(br), np.cos(br)], axis=1)  # FK tool axis
    program = MachineProgram(machine=machine, extruder=np.cumsum(e["de"]), time_s=e["dt"], kind=e["kind"],
                             source=e["source"].astype(np.int64), layer=e["layer"].astype(np.int64),
                             part_xyz=e["xyz"], part_axis=a_fk, part_offset=offset, profile=profile)
    z_safe = safe_height(program)
    program, n_unwinds = unwind_c(program, z_safe)
    if profile.gcode.safe_start_end and len(program):
        program = _with_safe_start_end(program, z_safe)
    check_limits(program)
    machine = program.machine
    b_all = machine[:, 3]
    program.attrs = {
        **program.attrs,
        "platform_z": pz,
        "n_singular": int(mv["singular"].sum()),
        "n_rotary_out_of_range": 0,
        "n_c_unwinds": n_unwinds,
        "n_inserted_rotary": int(len(split["xyz"]) - len(mv["xyz"])),
        "n_retractions": n_retractions,
        "max_rotary_step_deg": float(np.max(np.abs(np.diff(machine[:, 3:5], axis=0)), initial=0.0)),
        "b_range_deg": [float(b_all.min()), float(b_all.max())],
        "c_range_deg": [float(machine[:, 4].min()), float(machine[:, 4].max())],
    }
    return program


def program_metrics(program: MachineProgram) -> dict:
    """Totals of a program: time, path length, waypoints, material, filament."""
    xyz = program.part_xyz
    seg = np.linalg.norm(np.diff(xyz, axis=0), axis=1)
    kind = program.kind[1:]
    de = np.diff(program.extruder)
    area = filament_area(program.profile)
    material = float(de[kind == PRINT].sum() * area / program.profile.extrusion.flow)
    return {
        **program_time(program),
        "toolpath_length_mm": float(seg[kind == PRINT].sum()),
        "travel_length_mm": float(seg[kind == TRAVEL].sum()),
        "n_moves": len(program),
        "n_waypoints": int((program.source >= 0).sum()),
        "material_mm3": material,
        "filament_mm": float(de[kind == PRINT].sum()),
    }
