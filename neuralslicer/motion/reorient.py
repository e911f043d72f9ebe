"""Tilting the tool axis away from stray collisions, within a bound, without touching the layers.

An optimised field can leave a handful of waypoints where the head grazes earlier layers (one in
300,000 on a ring cage in nine). Re-optimising the whole field for them costs minutes and gives away
support-free gain; instead the tool axis is tilted away from the LPD there (the bead is still laid
on the same layer). Colliding waypoints closer than two ramps along one path form a run; the whole
run turns by one rotation, the smallest (up to ``max_tilt_deg``) that clears the head at every one
of them, the directions first tried pointing away from the material hit. The rotation fades out
linearly over ``ramp_mm`` of path on both sides, so the rotary axes move smoothly (at most
``max_tilt_deg / ramp_mm`` degrees per mm on top of the LPD's own turning). The exact collision
check stays the judge: the caller checks the tilted program again.
"""
from __future__ import annotations

from dataclasses import dataclass, replace

import numpy as np

from neuralslicer.motion.collision import CollisionReport, head_hits
from neuralslicer.motion.head import platform_clearance
from neuralslicer.motion.material import PrintedMaterial
from neuralslicer.motion.profile import Nozzle
from neuralslicer.toolpath.types import Toolpaths
from neuralslicer.types import FloatArray, IndexArray


@dataclass
class Reorientation:
    """What the tilt did: colliding waypoints cleared (with their tilts, deg) and not, and every waypoint whose axis changed."""

    fixed: IndexArray
    unfixed: IndexArray
    changed: IndexArray
    tilt_deg: FloatArray


def _rotate(vectors: FloatArray, rotvec: FloatArray) -> FloatArray:
    """Rotate unit vectors (n,3) by rotation vectors (n,3) (axis times angle in radians; Rodrigues)."""
    angle = np.linalg.norm(rotvec, axis=1)
    k = rotvec / np.where(angle > 0, angle, 1.0)[:, None]
    c, sn = np.cos(angle)[:, None], np.sin(angle)[:, None]
    out = vectors * c + np.cross(k, vectors) * sn + k * np.einsum("ij,ij->i", k, vectors)[:, None] * (1 - c)
    return out / np.linalg.norm(out, axis=1, keepdims=True)


def _runs(tp: Toolpaths, idx: IndexArray, arc: FloatArray, gap_mm: float) -> list[IndexArray]:
    """Colliding waypoints grouped into runs: same path, consecutive ones less than ``gap_mm`` of path apart
    (travel waypoints are runs of their own)."""
    runs: list[IndexArray] = []
    idx = np.sort(idx)
    start = 0
    for j in range(1, len(idx) + 1):
        if j < len(idx) and tp.path[idx[j]] >= 0 and tp.path[idx[j]] == tp.path[idx[j - 1]] \
                and arc[idx[j]] - arc[idx[j - 1]] < gap_mm:
            continue
        runs.append(idx[start:j])
        start = j
    return runs


def _trial_rotations(axis: FloatArray, away: FloatArray, tilts_deg: FloatArray, n_azimuth: int
                     ) -> tuple[FloatArray, FloatArray]:
    """Rotation vectors (k,3) tilting ``axis`` by each tilt toward each azimuth, in trial order (smallest
    tilt first, azimuths nearest ``away`` first), and the tilts (k,) in degrees."""
    helper = np.array([0.0, 0.0, 1.0]) if abs(axis[2]) < 0.9 else np.array([1.0, 0.0, 0.0])
    u = np.cross(axis, helper)
    u /= np.linalg.norm(u)
    v = np.cross(axis, u)
    phi0 = np.arctan2(away @ v, away @ u)
    steps = np.arange(n_azimuth)
    phi = phi0 + np.radians(360.0 / n_azimuth) * ((steps + 1) // 2) * np.where(steps % 2, 1, -1)   # 0, +1, -1, ...
    side = np.cos(phi)[:, None] * u + np.sin(phi)[:, None] * v              # (n_azimuth, 3) unit, normal to axis
    turn = np.cross(axis, side)                                              # rotating axis toward side
    th = np.radians(np.repeat(tilts_deg, n_azimuth))
    return np.tile(turn, (len(tilts_deg), 1)) * th[:, None], np.degrees(th)


def _run_rotations(tp: Toolpaths, runs: list[IndexArray], where_hit: dict, material: PrintedMaterial,
                   visible: IndexArray, nozzle: Nozzle, platform_z: float, min_height: float, tilts_deg: FloatArray,
                   n_azimuth: int) -> list[tuple[FloatArray | None, float]]:
    """Per run, the first trial rotation clearing the head at every waypoint of the run and its tilt (None, nan if
    none); the trials of all runs are judged in one exact query."""
    trials, xyz, axis, vis = [], [], [], []
    for run in runs:
        mean_axis = tp.axis[run].sum(axis=0)
        mean_axis /= np.linalg.norm(mean_axis)
        away = (tp.xyz[run] - np.array([where_hit[int(i)] for i in run])).sum(axis=0)
        away -= (away @ mean_axis) * mean_axis
        rot, tilt = _trial_rotations(mean_axis, away, tilts_deg, n_azimuth)
        trials.append((rot, tilt))
        xyz.append(np.tile(tp.xyz[run], (len(rot), 1)))
        axis.append(_rotate(np.tile(tp.axis[run], (len(rot), 1)), np.repeat(rot, len(run), axis=0)))
        vis.append(np.tile(visible[run], len(rot)))
    if not runs:
        return []
    xyz_all, axis_all = np.concatenate(xyz), np.concatenate(axis)
    hit, _ = head_hits(material, xyz_all, axis_all, np.concatenate(vis), nozzle, min_height)
    ok = ~hit & (platform_clearance(xyz_all, axis_all, nozzle, platform_z) >= 0)
    out, at = [], 0
    for run, (rot, tilt) in zip(runs, trials):
        clears = ok[at:at + len(rot) * len(run)].reshape(len(rot), len(run)).all(axis=1)
        at += len(rot) * len(run)
        best = int(np.argmax(clears))
        out.append((rot[best], float(tilt[best])) if clears.any() else (None, float("nan")))
    return out


def _arc_length(tp: Toolpaths) -> FloatArray:
    """Arc length along each path at every waypoint (restarting at each path)."""
    seg = np.linalg.norm(np.diff(tp.xyz, axis=0), axis=1)
    seg[tp.path[1:] != tp.path[:-1]] = 0.0
    return np.concatenate([[0.0], np.cumsum(seg)])


def tilt_away(tp: Toolpaths, report: CollisionReport, nozzle: Nozzle, platform_z: float, min_height: float,
              max_tilt_deg: float = 15.0, ramp_mm: float = 5.0, n_azimuth: int = 12,
              material: PrintedMaterial | None = None) -> tuple[Toolpaths, Reorientation]:
    """A copy of ``tp`` with the tool axis tilted clear at colliding waypoints where a tilt up to
    ``max_tilt_deg`` does it (see module doc), and what was changed. ``material``: the print's
    (``PrintedMaterial.of_toolpaths``), when the caller has it; a tilt moves the nozzle, not the beads."""
    material = PrintedMaterial.of_toolpaths(tp) if material is None else material
    idx = np.asarray(report.indices, np.int64)
    tilts = np.linspace(0.0, max_tilt_deg, int(np.ceil(max_tilt_deg / 2.5)) + 1)[1:]
    arc = _arc_length(tp)
    runs = _runs(tp, idx, arc, 2.0 * ramp_mm)
    found = _run_rotations(tp, runs, dict(zip(idx.tolist(), report.locations)), material, material.visible_at(tp),
                           nozzle, platform_z, min_height, tilts, n_azimuth)
    rotvec = np.zeros((len(tp), 3))
    weight = np.zeros(len(tp))
    on_path = np.flatnonzero(tp.path >= 0)
    path_of = tp.path[on_path]   # once, not per run: a 10M-waypoint print with thousands of runs spent 40 s here
    fixed, unfixed, tilt_deg = [], [], []
    for run, (rot, tilt) in zip(runs, found):
        if rot is None:
            unfixed += run.tolist()
            continue
        fixed += run.tolist()
        tilt_deg += [tilt] * len(run)
        ids, frac = _ramp(tp, on_path, path_of, run, arc, ramp_mm)
        stronger = frac > weight[ids]
        rotvec[ids[stronger]] = rot * frac[stronger, None]
        weight[ids[stronger]] = frac[stronger]
    changed = np.flatnonzero(weight > 0)
    axis = tp.axis.copy()
    axis[changed] = _rotate(tp.axis[changed], rotvec[changed])
    out = replace(tp, axis=axis, attrs=dict(tp.attrs))
    return out, Reorientation(np.asarray(fixed, np.int64), np.asarray(unfixed, np.int64), changed,
                              np.asarray(tilt_deg, np.float64))


def _ramp(tp: Toolpaths, on_path: IndexArray, path_of: IndexArray, run: IndexArray, arc: FloatArray, ramp_mm: float
          ) -> tuple[IndexArray, FloatArray]:
    """The waypoints a run's rotation reaches and its weight there: 1 on the run, fading to 0 over ``ramp_mm``
    (``on_path``: the waypoints on a path, whose path ids never decrease; ``path_of``: their path ids)."""
    if tp.path[run[0]] < 0 or ramp_mm <= 0:
        return run, np.ones(len(run))
    same = on_path[np.searchsorted(path_of, tp.path[run[0]]):np.searchsorted(path_of, tp.path[run[0]], side="right")]
    s = arc[same]
    dist = np.maximum(np.maximum(arc[run[0]] - s, s - arc[run[-1]]), 0.0)
    near = dist < ramp_mm
    return same[near], 1.0 - dist[near] / ramp_mm


def _clamp_polar(tp: Toolpaths, limit_deg: FloatArray | float, max_tilt_deg: float) -> tuple[Toolpaths, dict]:
    """Tool axes tipped further from +z than ``limit_deg`` (scalar or per waypoint) turned back to it, azimuth
    kept, where that takes at most ``max_tilt_deg``; the others are left (counted in ``n_unreachable``)."""
    a = tp.axis
    beta = np.degrees(np.arccos(np.clip(a[:, 2], -1.0, 1.0)))
    excess = beta - limit_deg
    fix = (excess > 1e-9) & (excess <= max_tilt_deg + 1e-9)
    summary = {"n_clamped": int(fix.sum()), "max_clamp_deg": float(excess[fix].max(initial=0.0)),
               "n_unreachable": int((excess > max_tilt_deg + 1e-9).sum())}
    if not fix.any():
        return tp, summary
    phi = np.arctan2(a[fix, 1], a[fix, 0])
    polar = np.radians(np.broadcast_to(np.asarray(limit_deg, np.float64), beta.shape)[fix])
    axis = a.copy()
    axis[fix] = np.column_stack([np.sin(polar) * np.cos(phi), np.sin(polar) * np.sin(phi), np.cos(polar)])
    return replace(tp, axis=axis, attrs=dict(tp.attrs)), summary


def clamp_to_reach(tp: Toolpaths, max_polar_deg: float, max_tilt_deg: float) -> tuple[Toolpaths, dict]:
    """Tool axes tipped further from +z than the machine's B range reaches (``max_polar_deg``) turned back
    to that limit, azimuth kept, where that takes at most ``max_tilt_deg``; the others are left (and
    reported as unreachable). The clamp is continuous in the axis, so paths stay smooth."""
    return _clamp_polar(tp, max_polar_deg, max_tilt_deg)


def platform_polar_limit(z: FloatArray, nozzle: Nozzle, platform_z: float, margin: float = 0.01) -> FloatArray:
    """Largest angle (deg) of the tool axis from +z that keeps the whole head at least ``margin`` above the
    platform, per tip height ``z`` (n,) (exact for the head ``platform_clearance`` measures; negative where
    even a vertical head is too low). Each rim of the head (cone base, holder ends) lies ``a cos t - b sin t``
    above the tip at tilt ``t``, a cosine falling on [0, pi - atan2(b, a)], so each gives one bound."""
    room = np.asarray(z, np.float64) - platform_z - margin
    L, R = nozzle.cone_length, nozzle.holder_radius
    rims = [(L, L * np.tan(np.radians(nozzle.cone_half_angle_deg)))]
    if nozzle.holder_length > 0:
        rims += [(L, R), (L + nozzle.holder_length, R)]
    limit = np.full(room.shape, np.pi)
    for a, b in rims:
        rho = np.hypot(a, b)          # a rim never lower than -rho below the tip: no bound where room >= rho
        bound = np.arccos(np.clip(-room / rho, -1.0, 1.0)) - np.arctan2(b, a)
        limit = np.minimum(limit, np.where(room >= rho, np.pi, bound))
    return np.degrees(np.where(room >= 0, limit, -1.0))


def clamp_to_platform(tp: Toolpaths, nozzle: Nozzle, platform_z: float, max_tilt_deg: float
                      ) -> tuple[Toolpaths, dict]:
    """Tool axes whose head dips below the platform turned up toward +z (azimuth kept) just far enough to clear
    it (``platform_polar_limit``), where that takes at most ``max_tilt_deg``; the others are left for the
    collision check to report. The limit grows with the tip's height, so the turned axes stay continuous
    along a path."""
    return _clamp_polar(tp, platform_polar_limit(tp.xyz[:, 2], nozzle, platform_z), max_tilt_deg)
