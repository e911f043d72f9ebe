"""Print time under the machine's axis limits: every move a trapezoid (accelerate, cruise, decelerate).

The model, per move ``i`` (from pose ``i-1`` to pose ``i``; move 0 has zero length):

- All axes move linearly together (coordinated motion); the move's progress ``s`` runs from 0 to 1.
- **Cruise rate** (1/s): the programmed one, ``1 / max(planned_s, min_move_s)``, lowered until no axis
  exceeds its velocity limit (X, Y, Z: ``max_axis_mm_s``; B, C: ``rotary_deg_s``).
- **Acceleration** (1/s^2): the largest one no axis exceeds (X, Y, Z: ``accel_mm_s2``; B, C:
  ``rotary_accel_deg_s2``): the slowest axis governs.
- **Junction speeds.** Speeds are measured in the axis space scaled by the velocity limits (each axis
  delta divided by its limit; for moves without rotation this is the machine XYZ direction and a speed
  proportional to mm/s). At the junction of two moves the speed is at most the smaller of their cruise
  speeds times ``(1 + cos theta) / 2``, theta the angle between their scaled directions: full speed when
  collinear, half at a right angle, zero at a reversal. Moves without axis motion (extruder only) start
  and end at rest. The junction speeds are then lowered to what the moves' accelerations can reach over
  their lengths (backward and forward pass, as a controller with unlimited look-ahead), so every move's
  trapezoid from its entry to its exit speed is feasible; both passes are cumulative minima (vectorised).
- The extruder is not limited (its acceleration is typically several times the axes'): moves that turn
  no axis take their planned time, at least ``min_move_s``.

Approximations: velocity jumps at junctions are allowed as the cosine rule says (no jerk or junction
deviation model, no S-curves, no corner blending), and the look-ahead is unlimited.
"""
from __future__ import annotations

from typing import Protocol

import numpy as np

from neuralslicer.motion.profile import Feeds, MachineProfile
from neuralslicer.types import FloatArray

#: scaled move lengths (s at the axis velocity limits) at or below this count as no axis motion.
_STILL = 1e-12


class TimedProgram(Protocol):
    """What ``program_time`` reads of a program: ``planning.MachineProgram`` fits (not imported here, so
    that planning can call this module)."""

    machine: FloatArray
    time_s: FloatArray
    profile: MachineProfile


def axis_limits(feeds: Feeds) -> tuple[FloatArray, FloatArray]:
    """Velocity and acceleration limits (5,) of X, Y, Z (mm/s, mm/s^2) and B, C (deg/s, deg/s^2)."""
    v = np.array([feeds.max_axis_mm_s] * 3 + [feeds.rotary_deg_s] * 2, np.float64)
    a = np.array([feeds.accel_mm_s2] * 3 + [feeds.rotary_accel_deg_s2] * 2, np.float64)
    return v, a


def junction_speeds(scaled: FloatArray, cruise: FloatArray, accel: FloatArray) -> FloatArray:
    """Speed (n,) at the end of each move, in the scaled axis space (the module docstring's rule).

    scaled : (n, 5) axis deltas of the moves divided by the axis velocity limits; cruise : (n,) cruise
    speeds in that space (cruise rate x scaled length); accel : (n,) accelerations of the moves' progress
    (1/s^2). The last move ends at rest; so does every move next to one without axis motion.
    """
    length, cos = _lengths_and_turns(scaled)
    return _junctions(length, cos, cruise, accel)[0]


#: rows per block of the per-move terms (bounds the (rows, 5) temporaries)
_ROWS = 1 << 19


def _lengths_and_turns(scaled: FloatArray, length: FloatArray | None = None) -> tuple[FloatArray, FloatArray]:
    """Lengths (n,) of the scaled moves and the cosine (n - 1,) of the angle between each and the next
    (0-length moves count as direction 0), in blocks of rows (``length``: the lengths, when known already)."""
    n = len(scaled)
    known = length is not None
    length, cos = (length if known else np.empty(n)), np.empty(max(n - 1, 0))
    prev = None
    for a in range(0, n, _ROWS):
        block = scaled[a:a + _ROWS]
        if known:
            ln = length[a:a + len(block)]
        else:
            ln = np.linalg.norm(block, axis=1)
            length[a:a + len(block)] = ln
        unit = block / np.where(ln > _STILL, ln, 1.0)[:, None]
        pair = unit if prev is None else np.concatenate([prev, unit])
        cos[max(a - 1, 0):a + len(block) - 1] = np.clip(np.einsum("ij,ij->i", pair[:-1], pair[1:]), -1.0, 1.0)
        prev = unit[-1:]
    return length, cos


def _junctions(length: FloatArray, cos: FloatArray, cruise: FloatArray, accel: FloatArray, p0: float | None = None
               ) -> tuple[FloatArray, float]:
    """``junction_speeds`` from the moves' scaled lengths (n,) and turn cosines (n - 1,), and the running sum of
    the moves' reach at the last move. ``p0``: that sum at the move before, for a stretch of a program that
    follows a move ending at rest (``schedule``'s blocks); the same numbers as the whole program's."""
    n = len(length)
    moving = length > _STILL
    cap = np.zeros(n)
    if n > 1:
        both = moving[:-1] & moving[1:]
        cap[:-1] = np.where(both, np.minimum(cruise[:-1], cruise[1:]) * 0.5 * (1.0 + cos), 0.0)
    reach = np.where(moving, 2.0 * accel * length ** 2, 0.0)      # v_end^2 - v_start^2 a move can make
    p = np.cumsum(reach) if p0 is None else np.cumsum(np.r_[p0, reach])[1:]   # one running sum, as a whole's
    del reach, moving
    # in place, a print of millions of moves holds three arrays here, not eight
    np.square(cap, out=cap)
    cap += p
    sq = np.minimum.accumulate(cap[::-1])[::-1]                     # backward: J_k^2 <= J_{k+1}^2 + reach_{k+1}
    del cap
    sq -= p
    sq -= p
    if p0 is not None and n:
        sq[0] = min(sq[0], -p0)                                     # the move before ends at rest
    np.minimum.accumulate(sq, out=sq)                               # forward: J_k^2 <= J_{k-1}^2 + reach_k
    np.minimum(sq, 0.0, out=sq)
    sq += p
    np.maximum(sq, 0.0, out=sq)
    return np.sqrt(sq, out=sq), float(p[-1]) if n else (p0 or 0.0)


def trapezoid_times(rate: FloatArray, accel: FloatArray, start: FloatArray, end: FloatArray) -> FloatArray:
    """Time (n,) to cover a unit length from speed ``start`` to ``end`` with speed <= ``rate`` and
    |acceleration| <= ``accel`` (all (n,), 1/s and 1/s^2; start, end <= rate and reachable)."""
    peak_sq = accel + 0.5 * (start ** 2 + end ** 2)                 # top speed without a cruise phase
    cruises = peak_sq > rate ** 2
    peak = np.sqrt(np.minimum(peak_sq, rate ** 2))
    ramps = (2.0 * peak - start - end) / accel
    ramp_len = (2.0 * peak ** 2 - start ** 2 - end ** 2) / (2.0 * accel)
    return ramps + np.where(cruises, np.maximum(1.0 - ramp_len, 0.0) / rate, 0.0)


def schedule(machine: FloatArray, planned_s: FloatArray, feeds: Feeds) -> tuple[FloatArray, FloatArray]:
    """Trapezoidal times (n,) and cruise-only times (n,) of the moves (the module docstring's model): what
    ``move_times`` and ``program_time`` compute, for callers that need both.

    Computed in blocks of about ``_ROWS`` moves, each ending at a move that ends at rest (next to a move without
    axis motion, as every retraction is): no speed limit crosses such a move, so each block's passes give the
    whole program's numbers, and a long print holds its moves' lengths and the two results, not a dozen arrays."""
    machine = np.asarray(machine, np.float64).reshape(-1, 5)
    planned = np.asarray(planned_s, np.float64).reshape(-1)
    n = len(machine)
    v_lim, a_lim = axis_limits(feeds)
    length = np.empty(n)
    for a in range(0, n, _ROWS):
        z = min(a + _ROWS, n)
        length[a:z] = np.linalg.norm(_deltas(machine, a, z) / v_lim, axis=1)
    moving = length > _STILL
    times, cruise_t = np.empty(n), np.empty(n)
    p_end: float | None = None
    for a, z in _blocks_at_rest(moving, _ROWS):
        delta = _deltas(machine, a, z)
        scaled = delta / v_lim
        top = np.abs(scaled).max(axis=1)                 # the largest scaled axis delta
        with np.errstate(divide="ignore"):
            accel = np.min(a_lim / np.abs(delta), axis=1)   # the acceleration the slowest axis allows
        del delta
        ln, m, plan = length[a:z], moving[a:z], planned[a:z]
        cos = _lengths_and_turns(scaled, ln)[1]
        del scaled
        nominal = np.where(m | (plan > 0), np.maximum(plan, feeds.min_move_s), 0.0)
        rate = np.where(m, 1.0 / np.where(m, np.maximum(nominal, top), 1.0), 0.0)
        accel = np.where(m, accel, 0.0)
        junction, p_end = _junctions(ln, cos, rate * ln, accel, p_end)
        cruise_t[a:z] = np.where(m, 1.0 / np.where(m, rate, 1.0), nominal)
        # the moves' trapezoids from their entry to exit speeds (the block's first move starts at rest)
        w = np.where(m, ln, 1.0)
        start = np.r_[0.0, junction[:-1]] / w
        end = junction / w
        r = rate[m]
        nominal[m] = trapezoid_times(r, accel[m], np.minimum(start[m], r), np.minimum(end[m], r))
        times[a:z] = nominal
    return times, cruise_t


def _deltas(machine: FloatArray, a: int, z: int) -> FloatArray:
    """Axis deltas (z - a, 5) of the moves a..z-1 (move 0 has none)."""
    delta = np.empty((z - a, 5))
    if a == 0:
        delta[:1] = 0.0
        np.subtract(machine[1:z], machine[:z - 1], out=delta[1:])
    else:
        np.subtract(machine[a:z], machine[a - 1:z - 1], out=delta)
    return delta


def _blocks_at_rest(moving: np.ndarray, rows: int) -> list[tuple[int, int]]:
    """Blocks [a, z) of about ``rows`` moves covering all, each ending at a move that ends at rest (it or the next
    one without axis motion) or at the program's end."""
    n, blocks, a = len(moving), [], 0
    while a < n:
        s, w = min(a + rows, n) - 1, 4096
        while s < n - 1:
            hi = min(s + w, n - 1)
            both = moving[s:hi] & moving[s + 1:hi + 1]
            if not both.all():
                s += int(np.argmin(both))
                break
            s, w = hi, 2 * w
        blocks.append((a, s + 1))
        a = s + 1
    return blocks


def move_times(machine: FloatArray, planned_s: FloatArray, feeds: Feeds) -> FloatArray:
    """Duration (n,) of each move under the axis limits of ``feeds`` (the module docstring's model).

    machine : (n, 5) X, Y, Z (mm), B, C (deg) at the end of each move; planned_s : (n,) nominal durations
    (length / programmed speed, at least rotary change / rotary speed). Every move that turns an axis or
    has a planned duration takes at least ``feeds.min_move_s``.
    """
    return schedule(machine, planned_s, feeds)[0]


def program_time(program: TimedProgram, times: tuple[FloatArray, FloatArray] | None = None) -> dict[str, float | int]:
    """Print time of a program under its profile's axis limits.

    Returns ``estimated_print_time_s`` (trapezoidal moves, ``move_times``), ``nominal_print_time_s`` (sum
    of the planned durations), ``n_moves_below_min_s`` (planned moves shorter than ``feeds.min_move_s``)
    and ``accel_limited_fraction``: the share of the estimated time that acceleration adds to the moves
    run at their (velocity- and min_move_s-limited) cruise rate throughout. ``times``: the program's
    ``schedule`` when already computed.
    """
    feeds = program.profile.feeds
    planned = np.asarray(program.time_s, np.float64)
    times, cruise_t = schedule(program.machine, planned, feeds) if times is None else times
    total = float(times.sum())
    return {
        "estimated_print_time_s": total,
        "nominal_print_time_s": float(planned.sum()),
        "n_moves_below_min_s": int(np.count_nonzero((planned > 0) & (planned < feeds.min_move_s))),
        "accel_limited_fraction": float(max(total - cruise_t.sum(), 0.0) / total) if total > 0 else 0.0,
    }
