"""Kinematic chains of multi-axis printers: inverse kinematics with continuous rotary axes, forward kinematics.

A profile's ``Kinematics`` (``neuralslicer.motion.profile``) names a layout; the two rotary axes are T, a tilt
about ``tilt_axis`` (machine +Y for B, +X for A, or their negatives) and R, a rotation about ``rotate_axis``
(+Z or -Z), each turning the table or the head by the right-hand rule. Angles are degrees in the public API.

- table-table: the rotary table rides on the tilting cradle. The tool is fixed along machine +Z; a part point
  ``p`` sits at machine position ``pivot + R_T(T) (c_offset + R_R(R) (p + part_offset))`` and a part direction
  ``a`` is seen by the machine as ``R_T R_R a``; IK makes the tool axis (the LPD) map to +Z.
- head-head: the tilt rides on the rotary head, the table is fixed. The tool axis is ``R_R R_T +Z``; the tool tip
  at ``m + R_R (pivot + R_T t) - (pivot + t)`` with ``t = (0, 0, -tool_length)`` meets the part point at
  ``c_offset + p + part_offset``.
- table-head: the head tilts, the table turns. The machine sees ``R_R a`` and the tool along ``R_T +Z``; the tip
  is at ``m + R_T t - t``, the part point at ``c_offset + R_R (p + part_offset)``.
- three-axis: no rotary axes; the tool is vertical and ``m = c_offset + p + part_offset``.

IK: with beta = acos(a_z) and phi = atan2(a_y, a_x) of a unit tool axis, each rotary layout has the two
solutions (T, R') = (beta, psi - s phi) and (-beta, psi + 180 - s phi) (mod 360), R = sigma R' with sigma = +1
for +Z and -1 for -Z, where psi is the azimuth of the tilted tool and s = +1 when R turns the table, -1 when it
turns the head (for table-table B/C: (B, C) = (beta, 180 - phi) and (-beta, -phi)).
- Singular rule: when beta < ``singular_tol_deg`` (tool axis on the rotary axis), T = 0 and R keeps its
  previous value (the first value of the program: the first non-singular R, else 0).
- Continuity: per waypoint the solution stays on the previous branch unless the branch leaves the tilt range or
  switching branch is cheaper in |dT| + |dR| (which is the case when the tool axis passes through the vertical);
  R is unwrapped (no +-180 deg flips), so it may exceed 360.
"""
from __future__ import annotations

import numpy as np

from neuralslicer.motion.profile import Kinematics
from neuralslicer.types import BoolArray, FloatArray

Components = tuple[FloatArray, FloatArray, FloatArray]


def _wrap(x: FloatArray) -> FloatArray:
    """Wrap angles (rad) to (-pi, pi]: pi - ((pi - x) mod 2 pi), the modulo taken only where it changes the
    value (most angles are in range already; np.mod of a value in [0, 2 pi) is that value)."""
    y = np.pi - np.asarray(x, np.float64)
    out = np.array(y, np.float64, ndmin=1)
    far = np.flatnonzero((out < 0.0) | (out >= 2 * np.pi))
    out[far] = np.mod(out[far], 2 * np.pi)
    return np.pi - out.reshape(y.shape)


#: rows per block of the element-wise kinematics (bounds their temporaries to a few tens of MB)
ROWS_PER_BLOCK = 1 << 19


def _blocks(n: int) -> range:
    return range(0, n, ROWS_PER_BLOCK)


def _tilt(v: Components, cos: FloatArray, sin: FloatArray, axis: str) -> Components:
    """Vectors ``v`` turned by the angle (cos, sin) about the tilt axis ``axis`` ("+Y", "-X", ...)."""
    x, y, z = v
    s = sin if axis[0] == "+" else -sin
    if axis[1] == "Y":
        return cos * x + s * z, y, -s * x + cos * z
    return x, cos * y - s * z, s * y + cos * z


def _turn(v: Components, cos: FloatArray, sin: FloatArray) -> Components:
    """Vectors ``v`` turned by the angle (cos, sin) about +Z."""
    x, y, z = v
    return cos * x - sin * y, sin * x + cos * y, z


def _angles(t_deg: FloatArray, r_deg: FloatArray, kin: Kinematics) -> tuple[FloatArray, ...]:
    """cos T, sin T, cos R', sin R' with R' = sigma R, the rotation about +Z."""
    t, r = np.radians(np.asarray(t_deg, np.float64)), np.radians(np.asarray(r_deg, np.float64))
    sr = np.sin(r) if kin.rotate_axis == "+Z" else -np.sin(r)
    return np.cos(t), np.sin(t), np.cos(r), sr


def _add(v: Components, w: FloatArray | tuple[float, ...], sign: float = 1.0) -> Components:
    """v + sign w for a constant vector w."""
    w = np.asarray(w, np.float64)
    return v[0] + sign * w[0], v[1] + sign * w[1], v[2] + sign * w[2]


def _tool_vector(kin: Kinematics, n: int) -> Components:
    """t = (0, 0, -tool_length): the tilt pivot to the tool tip at home, (n,) components."""
    return np.zeros(n), np.zeros(n), np.full(n, -float(kin.tool_length))


def _head_tip_offset(ct: FloatArray, st: FloatArray, cr: FloatArray, sr: FloatArray, kin: Kinematics
                     ) -> Components:
    """Where the tool tip is relative to machine XYZ (zeroed on the tip at home): head-head
    R_R (pivot + R_T t) - (pivot + t), table-head R_T t - t, else 0."""
    n = len(ct)
    t = _tool_vector(kin, n)
    if kin.layout == "head-head":
        arm = _turn(_add(_tilt(t, ct, st, kin.tilt_axis), kin.pivot), cr, sr)
        return _add(_add(arm, kin.pivot, -1.0), (0.0, 0.0, -float(kin.tool_length)), -1.0)
    if kin.layout == "table-head":
        return _add(_tilt(t, ct, st, kin.tilt_axis), (0.0, 0.0, -float(kin.tool_length)), -1.0)
    z = np.zeros(n)
    return z, z, z


def machine_position(part_xyz: FloatArray, t_deg: FloatArray, r_deg: FloatArray, kin: Kinematics,
                     part_offset: FloatArray, out: FloatArray | None = None) -> FloatArray:
    """Machine XYZ (n, 3) that puts the tool tip on ``part_xyz`` (n, 3) at rotary angles T, R (deg).

    out : optional (n, 3) array (or view) to write into; computed in blocks of rows, so the temporaries
    stay small for millions of moves.
    """
    part_xyz = np.asarray(part_xyz, np.float64).reshape(-1, 3)
    n = len(part_xyz)
    t_deg, r_deg = (np.broadcast_to(np.asarray(v, np.float64), (n,)) for v in (t_deg, r_deg))
    out = np.empty((n, 3)) if out is None else out
    for a in _blocks(n):
        s = slice(a, a + ROWS_PER_BLOCK)
        out[s, 0], out[s, 1], out[s, 2] = _machine_position(part_xyz[s], t_deg[s], r_deg[s], kin, part_offset)
    return out


def _machine_position(part_xyz: FloatArray, t_deg: FloatArray, r_deg: FloatArray, kin: Kinematics,
                      part_offset: FloatArray) -> Components:
    r = np.asarray(part_xyz, np.float64) + np.asarray(part_offset, np.float64)
    p = (r[:, 0], r[:, 1], r[:, 2])
    if kin.layout == "three-axis":
        return _add(p, kin.c_offset)
    ct, st, cr, sr = _angles(t_deg, r_deg, kin)
    if kin.layout == "table-table":
        on_table = _add(_turn(p, cr, sr), kin.c_offset)
        return _add(_tilt(on_table, ct, st, kin.tilt_axis), kin.pivot)
    p = _add(_turn(p, cr, sr) if kin.layout == "table-head" else p, kin.c_offset)
    tip = _head_tip_offset(ct, st, cr, sr, kin)
    return p[0] - tip[0], p[1] - tip[1], p[2] - tip[2]


def _axis_components(ct: FloatArray, st: FloatArray, cr: FloatArray, sr: FloatArray, kin: Kinematics) -> Components:
    """The tool axis in the build frame: table-table R_R^-1 R_T^-1 +Z, head-head R_R R_T +Z, table-head
    R_R^-1 R_T +Z, three-axis +Z."""
    n = len(ct)
    z = (np.zeros(n), np.zeros(n), np.ones(n))
    if kin.layout == "three-axis":
        return z
    if kin.layout == "table-table":
        return _turn(_tilt(z, ct, -st, kin.tilt_axis), cr, -sr)
    tool = _tilt(z, ct, st, kin.tilt_axis)
    return _turn(tool, cr, sr) if kin.layout == "head-head" else _turn(tool, cr, -sr)


def tool_axis(t_deg: FloatArray, r_deg: FloatArray, kin: Kinematics, out: FloatArray | None = None) -> FloatArray:
    """Tool axis (n, 3) in the build frame at rotary angles T, R (deg) (blocks of rows, written into ``out`` when
    given)."""
    t_deg, r_deg = np.asarray(t_deg, np.float64), np.asarray(r_deg, np.float64)
    n = len(t_deg)
    out = np.empty((n, 3)) if out is None else out
    for a in _blocks(n):
        s = slice(a, a + ROWS_PER_BLOCK)
        out[s, 0], out[s, 1], out[s, 2] = _axis_components(*_angles(t_deg[s], r_deg[s], kin), kin)
    return out


def forward_kinematics(machine_xyz: FloatArray, t_deg: FloatArray, r_deg: FloatArray, kin: Kinematics,
                       part_offset: FloatArray) -> tuple[FloatArray, FloatArray]:
    """Tool tip and tool axis in the build frame for machine XYZ (n, 3) and T, R (deg): (n,3), (n,3).

    table-table: p = R_R^-1 (R_T^-1 (m - pivot) - c_offset) - part_offset; see the module's docstring for the
    others. Computed in blocks of rows.
    """
    machine_xyz = np.asarray(machine_xyz, np.float64).reshape(-1, 3)
    n = len(machine_xyz)
    t_deg, r_deg = (np.broadcast_to(np.asarray(v, np.float64), (n,)) for v in (t_deg, r_deg))
    p, axis = np.empty((n, 3)), np.empty((n, 3))
    for a in _blocks(n):
        s = slice(a, a + ROWS_PER_BLOCK)
        (p[s, 0], p[s, 1], p[s, 2]), (axis[s, 0], axis[s, 1], axis[s, 2]) = _forward_kinematics(
            machine_xyz[s], t_deg[s], r_deg[s], kin, part_offset)
    return p, axis


def _forward_kinematics(machine_xyz: FloatArray, t_deg: FloatArray, r_deg: FloatArray, kin: Kinematics,
                        part_offset: FloatArray) -> tuple[Components, Components]:
    ct, st, cr, sr = _angles(t_deg, r_deg, kin)
    m = np.asarray(machine_xyz, np.float64)
    m = (m[:, 0], m[:, 1], m[:, 2])
    if kin.layout == "table-table":
        on_table = _add(_tilt(_add(m, kin.pivot, -1.0), ct, -st, kin.tilt_axis), kin.c_offset, -1.0)
        p = _turn(on_table, cr, -sr)
    elif kin.layout == "three-axis":
        p = _add(m, kin.c_offset, -1.0)
    else:
        tip = _head_tip_offset(ct, st, cr, sr, kin)
        p = _add((m[0] + tip[0], m[1] + tip[1], m[2] + tip[2]), kin.c_offset, -1.0)
        if kin.layout == "table-head":
            p = _turn(p, cr, -sr)
    return _add(p, part_offset, -1.0), _axis_components(ct, st, cr, sr, kin)


def workpiece_position(part_xyz: FloatArray, kin: Kinematics, part_offset: FloatArray,
                       out: FloatArray | None = None) -> FloatArray:
    """Tool tip in workpiece coordinates (n, 3): the machine XYZ of the part point with the rotary axes at home,
    what a controller with tool-centre-point control (LinuxCNC's trt kinematics in TCP mode) is programmed in."""
    n = len(np.asarray(part_xyz).reshape(-1, 3))
    return machine_position(part_xyz, np.zeros(n), np.zeros(n), kin, part_offset, out=out)


def ik_candidates(axis: FloatArray) -> tuple[FloatArray, FloatArray]:
    """Polar angle beta = acos(a_z) and azimuth phi = atan2(a_y, a_x) (rad) of unit tool axes (n, 3)."""
    a = np.asarray(axis, np.float64)
    a = a / np.linalg.norm(a, axis=1, keepdims=True)
    beta = np.arccos(np.clip(a[:, 2], -1.0, 1.0))
    phi = np.arctan2(a[:, 1], a[:, 0])
    return beta, phi


def _branch_azimuth(kin: Kinematics) -> tuple[float, float]:
    """(psi, s) of the layout: R' = psi - s phi on the branch T = beta (rad); psi is the azimuth of the tool tilted
    by a positive T (table: seen from the table), s = +1 when R turns the table, -1 when it turns the head."""
    ct, st = np.ones(1), np.ones(1)                      # 45 deg: only the direction of the tilt matters
    z = (np.zeros(1), np.zeros(1), np.ones(1))
    if kin.layout == "table-table":
        d = _tilt(z, ct, -st, kin.tilt_axis)          # R_R a = R_T^-1 z
    else:
        d = _tilt(z, ct, st, kin.tilt_axis)           # the head's tilted tool
    psi = float(np.arctan2(d[1][0], d[0][0]))
    return (-psi, -1.0) if kin.layout == "head-head" else (psi, 1.0)


def inverse_kinematics(axis: FloatArray, kin: Kinematics, c_start_deg: float = 0.0
                       ) -> tuple[FloatArray, FloatArray, BoolArray, BoolArray]:
    """Continuous T, R (deg, R unwrapped) for a sequence of tool axes (n, 3).

    Returns (T, R, singular, out_of_range): ``singular`` marks waypoints handled by the singular rule,
    ``out_of_range`` those where neither branch satisfies the tilt (and rotary) limits; on a three-axis machine
    T = R = 0 and ``out_of_range`` marks tool axes beyond the clearance cone.
    """
    n = len(axis)
    if n == 0:
        z = np.zeros(0)
        return z, z, np.zeros(0, bool), np.zeros(0, bool)
    beta, phi = ik_candidates(axis)
    if not kin.rotary:
        z = np.zeros(n)
        return z, z.copy(), np.zeros(n, bool), beta > np.radians(kin.clearance_deg) + 1e-9
    psi, sgn = _branch_azimuth(kin)
    sigma = 1.0 if kin.rotate_axis == "+Z" else -1.0
    singular = beta < np.radians(kin.singular_tol_deg)
    beta = np.where(singular, 0.0, beta)
    c_home = sigma * np.radians(c_start_deg)
    # singular rule: keep the previous azimuth (forward fill), leading ones take the first regular one
    idx = np.where(~singular, np.arange(n), -1)
    idx = np.maximum.accumulate(idx)
    if (~singular).any():
        first = int(np.argmax(~singular))
        idx = np.where(idx < 0, first, idx)
        phi = phi[idx]
    else:
        phi = np.full(n, sgn * (psi - c_home))
    b_lo, b_hi = np.radians(kin.tilt_min_deg) - 1e-12, np.radians(kin.tilt_max_deg) + 1e-12
    valid = np.stack([(beta >= b_lo) & (beta <= b_hi), (-beta >= b_lo) & (-beta <= b_hi)], axis=1)
    same = np.zeros(n)
    cross = np.full(n, np.inf)
    if n > 1:
        same[1:] = np.abs(np.diff(beta)) + np.abs(_wrap(phi[:-1] - phi[1:]))
        cross[1:] = np.abs(beta[1:] + beta[:-1]) + np.abs(_wrap(phi[:-1] - phi[1:] + np.pi))
    better = cross < same - 1e-12
    sphi = phi if sgn > 0 else -phi
    cw = np.stack([_wrap(psi - sphi - c_home), _wrap(psi - np.pi - sphi - c_home)], axis=1)
    # start branch: a valid one with the smaller |R - r_start| (T >= 0 on ties)
    if valid[0, 0] == valid[0, 1]:
        s = 0 if abs(cw[0, 0]) <= abs(cw[0, 1]) + 1e-12 else 1
    else:
        s = 0 if valid[0, 0] else 1
    events = [np.flatnonzero(valid[:, 1 - st] & (~valid[:, st] | better)) for st in (0, 1)]
    state = np.empty(n, np.int8)
    state[0] = s
    pos = 1
    while pos < n:
        ev = events[s]
        k = np.searchsorted(ev, pos)
        j = int(ev[k]) if k < len(ev) else n
        state[pos:j] = s
        if j >= n:
            break
        s = 1 - s
        state[j] = s
        pos = j + 1
    b = np.where(state == 0, beta, -beta)
    c_wrapped = np.where(state == 0, cw[:, 0], cw[:, 1])
    c = np.empty(n)
    c[0] = c_wrapped[0]
    if n > 1:
        c[1:] = c_wrapped[0] + np.cumsum(_wrap(np.diff(c_wrapped)))
    c = c + c_home
    out = ~valid[np.arange(n), state]
    b_deg, c_deg = np.degrees(b), np.degrees(c) if sigma > 0 else -np.degrees(c)
    if kin.rotate_min_deg is not None:
        out |= c_deg < kin.rotate_min_deg - 1e-9
    if kin.rotate_max_deg is not None:
        out |= c_deg > kin.rotate_max_deg + 1e-9
    return b_deg, c_deg, singular, out
