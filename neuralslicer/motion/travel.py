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

from neuralslicer.motion.collision import TRAVEL_PATH, CollisionReport, head_hits
from neuralslicer.motion.head import platform_clearance
from neuralslicer.motion.material import PrintedMaterial
from neuralslicer.motion.profile import Nozzle
from neuralslicer.toolpath.types import Toolpaths
from neuralslicer.types import FloatArray, IndexArray


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


def _routes(p: FloatArray, q: FloatArray, a: FloatArray, b: FloatArray, lifts: FloatArray, z_plane: float
            ) -> list[tuple[list[FloatArray], list[FloatArray]]]:
    """The detours from p to q in the order they are tried: lifts along the axes (smallest first), then routes by
    the clearance plane with the three smallest lifts."""
    return [_lift_route(p, q, a, b, h) for h in lifts] + [_plane_route(p, q, a, b, h, z_plane) for h in lifts[:3]]


def _clear_routes(material: PrintedMaterial, tp: Toolpaths, ends: IndexArray, visible: IndexArray, nozzle: Nozzle,
                  platform_z: float, min_height: float, lifts: FloatArray, spacing: float
                  ) -> dict[int, tuple[FloatArray, FloatArray, float]]:
    """Per travel arriving at a waypoint of ``ends``, the first clear detour (its inner points and axes and its
    largest lift above the higher end), if any. The clearance plane lies ``2 min_height + 1`` mm above the highest
    material laid before the travel (where the tip of a vertical head is clear of it). Every travel's candidate of
    one kind is judged in one exact query, the next kind only for the travels left."""
    found: dict[int, tuple[FloatArray, FloatArray, float]] = {}
    candidates = {int(j): _routes(tp.xyz[j - 1], tp.xyz[j], tp.axis[j - 1], tp.axis[j], lifts,
                                  float(material.top_before(visible[j:j + 1])[0]) + 2.0 * min_height + 1.0)
                  for j in ends}
    for kind in range(len(lifts) + min(3, len(lifts))):
        left = [j for j in candidates if j not in found]
        if not left:
            break
        poses = [_poses(*candidates[j][kind], spacing) for j in left]
        xyz, ax = np.concatenate([x for x, _ in poses]), np.concatenate([a for _, a in poses])
        owner = np.repeat(np.arange(len(left)), [len(x) for x, _ in poses])
        hit, _ = head_hits(material, xyz, ax, visible[np.asarray(left)][owner], nozzle, min_height)
        bad = hit | (platform_clearance(xyz, ax, nozzle, platform_z) < 0)
        blocked = np.bincount(owner[bad], minlength=len(left)) > 0
        for j in np.asarray(left)[~blocked]:
            points, axes = candidates[int(j)][kind]
            inner = np.stack(points[1:-1])
            found[int(j)] = (inner, np.stack(axes[1:-1]), float(inner[:, 2].max() - max(points[0][2], points[-1][2])))
    return found


def raise_travels(tp: Toolpaths, report: CollisionReport, nozzle: Nozzle, platform_z: float, min_height: float,
                  spacing: float = 2.0, lifts: tuple[float, ...] = (2.0, 4.0, 8.0, 16.0, 32.0, 64.0),
                  material: PrintedMaterial | None = None, consume: bool = False
                  ) -> tuple[Toolpaths, CollisionReport, dict]:
    """Toolpaths with every travel collision (kind TRAVEL_PATH) replaced by a lifted detour where one of
    ``lifts`` clears it, or else a route by the clearance plane that does, the report with those collisions
    removed and the others' indices shifted, and a summary (detours, how many by the clearance plane, their
    largest rise above the travel's higher end, travels left colliding). ``material``: the print's
    (``PrintedMaterial.of_toolpaths``), when the caller has it; detours lay no material. With ``consume`` the
    arrays of ``tp`` are dropped from it one by one as their copies with the detours are made (``tp`` is left
    empty where detours were inserted), so that the print is not held twice."""
    travel = np.flatnonzero(report.kind == TRAVEL_PATH)
    summary = {"n_travels_lifted": 0, "n_travels_by_clearance_plane": 0, "max_lift_mm": 0.0,
               "n_travels_unresolved": int(len(travel))}
    if not len(travel):
        return tp, report, summary
    material = PrintedMaterial.of_toolpaths(tp) if material is None else material
    routes = _clear_routes(material, tp, report.indices[travel], material.visible_at(tp), nozzle, platform_z,
                           min_height, np.asarray(lifts, np.float64), spacing)
    detours = {j: route[:2] for j, route in routes.items()}
    for route in routes.values():
        summary["max_lift_mm"] = max(summary["max_lift_mm"], route[2])
        summary["n_travels_by_clearance_plane"] += int(len(route[0]) > 2)
    if not detours:
        return tp, report, summary
    at = np.array(sorted(detours), np.int64)                       # insert each detour's points before these
    counts = np.array([len(detours[int(j)][0]) for j in at], np.int64)
    ins_xyz = np.concatenate([detours[int(j)][0] for j in at])
    ins_axis = np.concatenate([detours[int(j)][1] for j in at])
    where = np.repeat(at, counts)
    values = {"layer": tp.layer[where], "path": -1, "xyz": ins_xyz, "axis": ins_axis, "thickness": 0.0, "width": 0.0,
              "extrude": False}
    columns = {}
    for name in Toolpaths.ARRAYS:
        columns[name] = np.insert(getattr(tp, name), where, values.pop(name), axis=0)
        if consume:
            setattr(tp, name, getattr(tp, name)[:0].copy())
    out = Toolpaths(**columns, attrs=dict(tp.attrs))
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
