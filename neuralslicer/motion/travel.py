"""Travels that would drag the head through the part are lifted higher.

A travel is printed 1 mm above the layer (``travel_lift``) along a straight chord; between two
patches of a curved layer the chord can pass through earlier layers (measured on the ring: 4-63
travels of one print). Each such move is replaced by three: up along the tool axis at its start by
``h``, across, and down along the tool axis at its end, with the smallest ``h`` of a doubling
series that clears the head at poses every ``spacing`` mm of all three (exact test, the same
material as the check). Where no lift along the axes clears it (tool axes leaning over earlier
material, whose lifted chord still cuts it), the move goes by the clearance plane, as a machinist's
retract does: up along the start's axis by ``h``, straight up to a plane above all earlier material
with the tool axis turning to vertical on the way, across that plane, down to ``h`` above the end along
its axis and onto it; up there the head is clear whatever the part, and every pose of the route is
checked exactly like the others. The layers and the printing moves do not change.
"""
from __future__ import annotations

import numpy as np

from neuralslicer.motion.collision import (TRAVEL_PATH, CollisionReport, _head_hits, _TreeSet, earlier_material,
                                           platform_clearance)
from neuralslicer.motion.profile import Nozzle
from neuralslicer.toolpath.types import Toolpaths
from neuralslicer.types import FloatArray


def _poses(points: list[FloatArray], axes: list[FloatArray], spacing: float) -> tuple[FloatArray, FloatArray]:
    """Tool poses every ``spacing`` mm along the polyline ``points`` (axes interpolated), ends included."""
    xyz, ax = [], []
    for (p, q), (a, b) in zip(zip(points[:-1], points[1:]), zip(axes[:-1], axes[1:])):
        n = max(1, int(np.ceil(np.linalg.norm(q - p) / spacing)))
        t = (np.arange(n + 1) / n)[:, None]
        xyz.append((1 - t) * p + t * q)
        v = (1 - t) * a + t * b
        ax.append(v / np.linalg.norm(v, axis=1, keepdims=True))
    return np.concatenate(xyz), np.concatenate(ax)


def _lift_route(p: FloatArray, q: FloatArray, a: FloatArray, b: FloatArray, h: float
                ) -> tuple[list[FloatArray], list[FloatArray]]:
    """Up along a by h, across, down along b: the detour's corner points and axes, ends included."""
    return [p, p + h * a, q + h * b, q], [a, a, b, b]


def _plane_route(p: FloatArray, q: FloatArray, a: FloatArray, b: FloatArray, h: float, z_plane: float
                 ) -> tuple[list[FloatArray], list[FloatArray]]:
    """Up along a by h, up to the plane z = z_plane (axis turning to +z), across it, down to h along b, onto q."""
    up = np.array([0.0, 0.0, 1.0])
    p1, q1 = p + h * a, q + h * b
    p2, q2 = np.r_[p1[:2], max(z_plane, p1[2])], np.r_[q1[:2], max(z_plane, q1[2])]
    return [p, p1, p2, q2, q1, q], [a, a, up, up, b, b]


def _clear_route(material: _TreeSet, p: FloatArray, q: FloatArray, a: FloatArray, b: FloatArray, nozzle: Nozzle,
                 platform_z: float, min_height: float, lifts: FloatArray, spacing: float
                 ) -> tuple[FloatArray, FloatArray, float] | None:
    """The first clear detour from p to q: lifts along the axes (smallest first), then routes by the clearance
    plane (``min_height`` above the highest earlier material, where the tip of a vertical head is clear of it);
    its inner points and axes and its largest lift (mm above the higher end), or None."""
    z_plane = material.top + 2.0 * min_height + 1.0
    routes = [_lift_route(p, q, a, b, h) for h in lifts]
    routes += [_plane_route(p, q, a, b, h, z_plane) for h in lifts[:3]]
    for points, axes in routes:
        xyz, ax = _poses(points, axes, spacing)
        hit, _ = _head_hits(material, xyz, ax, nozzle, min_height)
        if not hit.any() and (platform_clearance(xyz, ax, nozzle, platform_z) >= 0).all():
            inner = np.stack(points[1:-1])
            return inner, np.stack(axes[1:-1]), float(inner[:, 2].max() - max(p[2], q[2]))
    return None


def raise_travels(tp: Toolpaths, report: CollisionReport, nozzle: Nozzle, platform_z: float, min_height: float,
                  spacing: float = 2.0, lifts: tuple[float, ...] = (2.0, 4.0, 8.0, 16.0, 32.0, 64.0)
                  ) -> tuple[Toolpaths, CollisionReport, dict]:
    """Toolpaths with every travel collision (kind TRAVEL_PATH) replaced by a lifted detour where one of
    ``lifts`` clears it, or else a route by the clearance plane that does, the report with those collisions
    removed and the others' indices shifted, and a summary (detours, how many by the clearance plane, their
    largest rise above the travel's higher end, travels left colliding)."""
    travel = np.flatnonzero(report.kind == TRAVEL_PATH)
    summary = {"n_travels_lifted": 0, "n_travels_by_clearance_plane": 0, "max_lift_mm": 0.0,
               "n_travels_unresolved": int(len(travel))}
    if not len(travel):
        return tp, report, summary
    detours: dict[int, tuple[FloatArray, FloatArray]] = {}
    for layer in np.unique(tp.layer[report.indices[travel]]):
        material = earlier_material(tp, int(layer))
        for j in report.indices[travel][tp.layer[report.indices[travel]] == layer]:
            i = int(j) - 1
            p, q, a, b = tp.xyz[i], tp.xyz[j], tp.axis[i], tp.axis[j]
            route = _clear_route(material, p, q, a, b, nozzle, platform_z, min_height, np.asarray(lifts), spacing)
            if route is not None:
                detours[int(j)] = route[:2]
                summary["max_lift_mm"] = max(summary["max_lift_mm"], route[2])
                summary["n_travels_by_clearance_plane"] += int(len(route[0]) > 2)
    if not detours:
        return tp, report, summary
    at = np.array(sorted(detours), np.int64)                       # insert each detour's points before these
    counts = np.array([len(detours[int(j)][0]) for j in at], np.int64)
    ins_xyz = np.concatenate([detours[int(j)][0] for j in at])
    ins_axis = np.concatenate([detours[int(j)][1] for j in at])
    where = np.repeat(at, counts)
    ins = lambda arr, val: np.insert(arr, where, val, axis=0)  # noqa: E731
    out = Toolpaths(layer=ins(tp.layer, tp.layer[where]), path=ins(tp.path, -1), xyz=ins(tp.xyz, ins_xyz),
                    axis=ins(tp.axis, ins_axis), thickness=ins(tp.thickness, 0.0), width=ins(tp.width, 0.0),
                    extrude=ins(tp.extrude, False), attrs=dict(tp.attrs))
    keep = ~np.isin(report.indices, at) | (report.kind != TRAVEL_PATH)
    added = np.r_[0, np.cumsum(counts)]
    shift = added[np.searchsorted(at, report.indices[keep], side="right")]
    if "tilted_waypoints" in out.attrs:  # indices recorded by an earlier tilt move with their waypoints
        tilted = np.asarray(out.attrs["tilted_waypoints"], np.int64)
        out.attrs["tilted_waypoints"] = [int(i) for i in tilted + added[np.searchsorted(at, tilted, side="right")]]
    # a waypoint that also collided itself (part/platform) keeps that collision, its detour's points further on
    moved = CollisionReport(report.indices[keep] + shift, report.locations[keep], report.kind[keep])
    summary.update(n_travels_lifted=len(detours), n_travels_unresolved=int(len(travel) - len(detours)))
    return out, moved, summary
