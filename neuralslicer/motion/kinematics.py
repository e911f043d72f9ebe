"""Table-table B/C kinematics: inverse kinematics with continuous rotary axes, forward kinematics.

Conventions (all angles in degrees in the public API):
- the tool is fixed along machine +Z and the tool tip is the controlled point;
- C rotates the table about its own +Z axis, B tilts the table about machine +Y through
  ``pivot`` (right-hand rule for both, rotations of the *table*);
- a part point ``p`` (build frame) sits at machine position
  ``pivot + R_y(B) (c_offset + R_z(C) (p + part_offset))``, and a part direction ``a`` is seen
  by the machine as ``R_y(B) R_z(C) a``; inverse kinematics makes the tool axis (LPD) map to +Z.
- For a unit tool axis with polar angle beta = acos(a_z) and azimuth phi = atan2(a_y, a_x) the
  two solutions are (B, C) = (beta, 180 - phi) and (-beta, -phi) (mod 360).
- Singular rule: when beta < ``singular_tol_deg`` (tool axis on the C axis), B = 0 and C keeps
  its previous value (the first value of the program: the first non-singular C, else 0).
- Continuity: per waypoint the solution stays on the previous branch unless the branch leaves the
  B range or switching branch is cheaper in |dB| + |dC| (which is the case when the tool axis
  passes through the vertical); C is unwrapped (no +-180 deg flips), so it may exceed 360.
"""
from __future__ import annotations

import numpy as np

from neuralslicer.motion.profile import Kinematics
from neuralslicer.types import BoolArray, FloatArray


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


def machine_position(part_xyz: FloatArray, b_deg: FloatArray, c_deg: FloatArray, kin: Kinematics,
                     part_offset: FloatArray, out: FloatArray | None = None) -> FloatArray:
    """Machine XYZ (n, 3) that puts the tool tip on ``part_xyz`` (n, 3) at table angles B, C (deg).

    out : optional (n, 3) array (or view) to write into; computed in blocks of rows, so the temporaries
    stay small for millions of moves.
    """
    part_xyz = np.asarray(part_xyz, np.float64).reshape(-1, 3)
    n = len(part_xyz)
    b_deg, c_deg = (np.broadcast_to(np.asarray(v, np.float64), (n,)) for v in (b_deg, c_deg))
    out = np.empty((n, 3)) if out is None else out
    for a in _blocks(n):
        s = slice(a, a + ROWS_PER_BLOCK)
        out[s, 0], out[s, 1], out[s, 2] = _machine_position(part_xyz[s], b_deg[s], c_deg[s], kin, part_offset)
    return out


def _machine_position(part_xyz: FloatArray, b_deg: FloatArray, c_deg: FloatArray, kin: Kinematics,
                      part_offset: FloatArray) -> tuple[FloatArray, FloatArray, FloatArray]:
    b, c = np.radians(b_deg), np.radians(c_deg)
    r = np.asarray(part_xyz, np.float64) + np.asarray(part_offset, np.float64)
    cz, sz = np.cos(c), np.sin(c)
    rx, ry, rz = cz * r[:, 0] - sz * r[:, 1], sz * r[:, 0] + cz * r[:, 1], r[:, 2]
    off = np.asarray(kin.c_offset, np.float64)
    rx, ry, rz = rx + off[0], ry + off[1], rz + off[2]
    cb, sb = np.cos(b), np.sin(b)
    piv = np.asarray(kin.pivot, np.float64)
    return cb * rx + sb * rz + piv[0], ry + piv[1], -sb * rx + cb * rz + piv[2]


def tool_axis(b_deg: FloatArray, c_deg: FloatArray, out: FloatArray | None = None) -> FloatArray:
    """Tool axis (n, 3) in the build frame at table angles B, C (deg): R_z(-C) R_y(-B) +Z (blocks of rows,
    written into ``out`` when given)."""
    b_deg, c_deg = np.asarray(b_deg, np.float64), np.asarray(c_deg, np.float64)
    n = len(b_deg)
    out = np.empty((n, 3)) if out is None else out
    for a in _blocks(n):
        s = slice(a, a + ROWS_PER_BLOCK)
        b, c = np.radians(np.asarray(b_deg[s], np.float64)), np.radians(np.asarray(c_deg[s], np.float64))
        sb = np.sin(b)
        out[s] = np.stack([-np.cos(c) * sb, np.sin(c) * sb, np.cos(b)], axis=1)
    return out


def forward_kinematics(machine_xyz: FloatArray, b_deg: FloatArray, c_deg: FloatArray, kin: Kinematics,
                       part_offset: FloatArray) -> tuple[FloatArray, FloatArray]:
    """Tool tip and tool axis in the build frame for machine XYZ (n, 3) and B, C (deg): (n,3), (n,3).

    p = R_z(-C) (R_y(-B) (m - pivot) - c_offset) - part_offset; axis = R_z(-C) R_y(-B) +Z. Computed in
    blocks of rows.
    """
    machine_xyz = np.asarray(machine_xyz, np.float64).reshape(-1, 3)
    n = len(machine_xyz)
    b_deg, c_deg = (np.broadcast_to(np.asarray(v, np.float64), (n,)) for v in (b_deg, c_deg))
    p, axis = np.empty((n, 3)), np.empty((n, 3))
    for a in _blocks(n):
        s = slice(a, a + ROWS_PER_BLOCK)
        (p[s, 0], p[s, 1], p[s, 2]), (axis[s, 0], axis[s, 1], axis[s, 2]) = _forward_kinematics(
            machine_xyz[s], b_deg[s], c_deg[s], kin, part_offset)
    return p, axis


def _forward_kinematics(machine_xyz: FloatArray, b_deg: FloatArray, c_deg: FloatArray, kin: Kinematics,
                        part_offset: FloatArray) -> tuple[FloatArray, FloatArray]:
    b, c = np.radians(np.asarray(b_deg, np.float64)), np.radians(np.asarray(c_deg, np.float64))
    cb, sb, cc, sc = np.cos(b), np.sin(b), np.cos(c), np.sin(c)
    m = np.asarray(machine_xyz, np.float64) - np.asarray(kin.pivot, np.float64)
    off = np.asarray(kin.c_offset, np.float64)
    rx = cb * m[:, 0] - sb * m[:, 2] - off[0]
    ry = m[:, 1] - off[1]
    rz = sb * m[:, 0] + cb * m[:, 2] - off[2]
    po = np.asarray(part_offset, np.float64)
    return (cc * rx + sc * ry - po[0], -sc * rx + cc * ry - po[1], rz - po[2]), (-cc * sb, sc * sb, cb)


def ik_candidates(axis: FloatArray) -> tuple[FloatArray, FloatArray]:
    """Polar angle beta = acos(a_z) and azimuth phi = atan2(a_y, a_x) (rad) of unit tool axes (n, 3)."""
    a = np.asarray(axis, np.float64)
    a = a / np.linalg.norm(a, axis=1, keepdims=True)
    beta = np.arccos(np.clip(a[:, 2], -1.0, 1.0))
    phi = np.arctan2(a[:, 1], a[:, 0])
    return beta, phi


def inverse_kinematics(axis: FloatArray, kin: Kinematics, c_start_deg: float = 0.0
                       ) -> tuple[FloatArray, FloatArray, BoolArray, BoolArray]:
    """Continuous B, C (deg, C unwrapped) for a sequence of tool axes (n, 3).

    Returns (B, C, singular, out_of_range): ``singular`` marks waypoints handled by the singular
    rule, ``out_of_range`` those where neither branch satisfies the B (and C) limits.
    """
    n = len(axis)
    if n == 0:
        z = np.zeros(0)
        return z, z, np.zeros(0, bool), np.zeros(0, bool)
    beta, phi = ik_candidates(axis)
    singular = beta < np.radians(kin.singular_tol_deg)
    beta = np.where(singular, 0.0, beta)
    # singular rule: keep the previous azimuth (forward fill), leading ones take the first regular one
    idx = np.where(~singular, np.arange(n), -1)
    idx = np.maximum.accumulate(idx)
    if (~singular).any():
        first = int(np.argmax(~singular))
        idx = np.where(idx < 0, first, idx)
        phi = phi[idx]
    else:
        phi = np.full(n, np.pi - np.radians(c_start_deg))
    b_lo, b_hi = np.radians(kin.b_min_deg) - 1e-12, np.radians(kin.b_max_deg) + 1e-12
    valid = np.stack([(beta >= b_lo) & (beta <= b_hi), (-beta >= b_lo) & (-beta <= b_hi)], axis=1)
    same = np.zeros(n)
    cross = np.full(n, np.inf)
    if n > 1:
        same[1:] = np.abs(np.diff(beta)) + np.abs(_wrap(phi[:-1] - phi[1:]))
        cross[1:] = np.abs(beta[1:] + beta[:-1]) + np.abs(_wrap(phi[:-1] - phi[1:] + np.pi))
    better = cross < same - 1e-12
    c_home = np.radians(c_start_deg)
    cw = np.stack([_wrap(np.pi - phi - c_home), _wrap(-phi - c_home)], axis=1)
    # start branch: a valid one with the smaller |C - c_start| (B >= 0 on ties)
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
    b_deg, c_deg = np.degrees(b), np.degrees(c)
    if kin.c_min_deg is not None:
        out |= c_deg < kin.c_min_deg - 1e-9
    if kin.c_max_deg is not None:
        out |= c_deg > kin.c_max_deg + 1e-9
    return b_deg, c_deg, singular, out
