"""Travels that would drag the head through the part are lifted higher.

A travel is printed 1 mm above the layer (``travel_lift``) along a straight chord; between two
patches of a curved layer the chord can pass through earlier layers (measured on the ring: 4-63
travels of one print). Each such move is replaced by three: up along the tool axis at its start by
``h``, across, and down along the tool axis at its end, with the smallest ``h`` of a doubling
series that clears the head at poses every ``spacing`` mm of all three (exact test, the same
material as the check). The layers and the printing moves do not change.
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


def _clear_lift(material: _TreeSet, p: FloatArray, q: FloatArray, a: FloatArray, b: FloatArray, nozzle: Nozzle,
                platform_z: float, min_height: float, lifts: FloatArray, spacing: float) -> float | None:
    """The smallest lift ``h`` for which up-across-down from p to q is clear, or None."""
    for h in lifts:
        xyz, ax = _poses([p, p + h * a, q + h * b, q], [a, a, b, b], spacing)
        hit, _ = _head_hits(material, xyz, ax, nozzle, min_height)
        if not hit.any() and (platform_clearance(xyz, ax, nozzle, platform_z) >= 0).all():
            return float(h)
    return None


def raise_travels(tp: Toolpaths, report: CollisionReport, nozzle: Nozzle, platform_z: float, min_height: float,
                  spacing: float = 2.0, lifts: tuple[float, ...] = (2.0, 4.0, 8.0, 16.0, 32.0, 64.0)
                  ) -> tuple[Toolpaths, CollisionReport, dict]:
    """Toolpaths with every travel collision (kind TRAVEL_PATH) replaced by a lifted detour where one of
    ``lifts`` clears it, the report with those collisions removed and the others' indices shifted, and a
    summary (detours, their largest lift, travels left colliding)."""
    travel = np.flatnonzero(report.kind == TRAVEL_PATH)
    summary = {"n_travels_lifted": 0, "max_lift_mm": 0.0, "n_travels_unresolved": int(len(travel))}
    if not len(travel):
        return tp, report, summary
    detours: dict[int, tuple[FloatArray, FloatArray]] = {}
    for layer in np.unique(tp.layer[report.indices[travel]]):
        material = earlier_material(tp, int(layer))
        for j in report.indices[travel][tp.layer[report.indices[travel]] == layer]:
            i = int(j) - 1
            p, q, a, b = tp.xyz[i], tp.xyz[j], tp.axis[i], tp.axis[j]
            h = _clear_lift(material, p, q, a, b, nozzle, platform_z, min_height, np.asarray(lifts), spacing)
            if h is not None:
                detours[int(j)] = (np.stack([p + h * a, q + h * b]), np.stack([a, b]))
                summary["max_lift_mm"] = max(summary["max_lift_mm"], h)
    if not detours:
        return tp, report, summary
    at = np.array(sorted(detours), np.int64)                       # insert two waypoints before each of these
    ins_xyz = np.concatenate([detours[int(j)][0] for j in at])
    ins_axis = np.concatenate([detours[int(j)][1] for j in at])
    where = np.repeat(at, 2)
    ins = lambda arr, val: np.insert(arr, where, val, axis=0)  # noqa: E731
    out = Toolpaths(layer=ins(tp.layer, tp.layer[where]), path=ins(tp.path, -1), xyz=ins(tp.xyz, ins_xyz),
                    axis=ins(tp.axis, ins_axis), thickness=ins(tp.thickness, 0.0), width=ins(tp.width, 0.0),
                    extrude=ins(tp.extrude, False), attrs=dict(tp.attrs))
    keep = ~np.isin(report.indices, at) | (report.kind != TRAVEL_PATH)
    shift = 2 * np.searchsorted(at, report.indices[keep], side="right")
    # a waypoint that also collided itself (part/platform) keeps that collision, two places further on
    moved = CollisionReport(report.indices[keep] + shift, report.locations[keep], report.kind[keep])
    summary.update(n_travels_lifted=len(detours), n_travels_unresolved=int(len(travel) - len(detours)))
    return out, moved, summary
