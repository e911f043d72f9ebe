"""compas_slicer printpoints export: the waypoints as the nested JSON compas_slicer's print organizer writes.

The file is what ``utils.save_to_json(print_organizer.output_nested_printpoints_dict(), ...)`` writes:
``{"layer_i": {"path_j": {"k": printpoint}}}`` with contiguous numbers from 0 and each printpoint as
``PrintPoint.to_data()`` gives it (``point``/``pt``, ``up_vector``, ``mesh_normal``, ``frame``, ``layer_height``,
``extruder_toggle``, ``velocity``, ``wait_time``, ``blend_radius``, ``closest_support_pt``,
``distance_to_support``, ``is_feasible``, ``attributes``), so compas_slicer's loaders (``PrintPoint.from_data``,
the Grasshopper ``load_nested_printpoints``) read it unchanged. Build frame, mm, s, mm/s (docs/outputs.md).
"""
from __future__ import annotations

import json
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import numpy as np

from neuralslicer.fileio import atomic_path
from neuralslicer.gcode.robot import blend_radii, extruder_toggle, move_material, tool_frames, velocities, wait_times
from neuralslicer.motion.profile import MachineProfile
from neuralslicer.toolpath.types import Toolpaths
from neuralslicer.types import FloatArray, IndexArray

#: decimals of positions (mm) and of unit vectors in the file
POINT_DECIMALS = 6
VECTOR_DECIMALS = 9


def printpoint_groups(tp: Toolpaths) -> tuple[IndexArray, IndexArray]:
    """compas_slicer layer and path numbers (n,) of every waypoint, both contiguous from 0 in print order.

    A path is a run of waypoints of one of our paths; the lifted travel waypoints after it (path -1) stay in it,
    as compas_slicer's safety printpoints stay in the path they leave (travels before the first path: in the
    first path). A layer is a run of paths of one of our layers; its paths are numbered from 0.
    """
    n = len(tp)
    if n == 0:
        return np.zeros(0, np.int64), np.zeros(0, np.int64)
    on = tp.path >= 0
    owner = np.maximum.accumulate(np.where(on, np.arange(n), -1))
    owner = np.where(owner >= 0, owner, np.flatnonzero(on)[0] if on.any() else np.arange(n))
    key_layer, key_path = tp.layer[owner], tp.path[owner]
    new_path = np.r_[True, (key_layer[1:] != key_layer[:-1]) | (key_path[1:] != key_path[:-1])]
    new_layer = np.r_[True, key_layer[1:] != key_layer[:-1]]
    layer = np.cumsum(new_layer) - 1
    path_run = np.cumsum(new_path) - 1
    first_run_of_layer = path_run[np.flatnonzero(new_layer)]
    return layer.astype(np.int64), (path_run - first_run_of_layer[layer]).astype(np.int64)


def layer_heights(tp: Toolpaths) -> FloatArray:
    """``layer_height`` (n,) in mm: the local layer thickness; points without one (lifted travels, 0) carry the
    last positive thickness before them (the first one for leading points; the line width if there is none)."""
    t = np.asarray(tp.thickness, np.float64)
    ok = t > 0
    if not ok.any():
        return np.asarray(tp.width, np.float64).copy()
    src = np.maximum.accumulate(np.where(ok, np.arange(len(t)), -1))
    src[src < 0] = np.flatnonzero(ok)[0]
    return t[src]


def _round(a: np.ndarray, decimals: int) -> list:
    """Rounded nested lists of an array (-0.0 written as 0.0)."""
    return (np.round(a, decimals) + 0.0).tolist()


def printpoint_columns(tp: Toolpaths, profile: MachineProfile | None = None) -> dict[str, list]:
    """Every printpoint field as a list over the waypoints (JSON-ready values; ``profile``: speeds, waits,
    filament; default profile otherwise).

    ``closest_support_pt`` is the point of the layer below along the tool axis (``point - thickness * up``) on
    a layer; at points without material below (lifted travels) it is the point itself, since compas_slicer 0.7's
    ``PrintPoint.from_data`` reads it with ``Point.from_data`` unconditionally (null raises a TypeError there);
    their ``distance_to_support`` stays null, which marks them.
    """
    profile = profile or MachineProfile()
    frames = tool_frames(tp.axis, tp.xyz, tp.extrude)
    up = -frames[:, :, 2]                                                 # the unit tool axis (LPD)
    height = layer_heights(tp)
    on_layer = (tp.path >= 0) & (tp.thickness > 0)
    support = tp.xyz - tp.thickness[:, None] * up
    wait = wait_times(tp, profile)
    vol, fil = move_material(tp, profile.extrusion.filament_diameter)
    infeasible = np.zeros(len(tp), bool)
    hits = np.asarray(tp.attrs.get("collision_waypoints", []), np.int64)
    infeasible[hits[(hits >= 0) & (hits < len(tp))]] = True
    point = _round(tp.xyz, POINT_DECIMALS)
    on = on_layer.tolist()
    return {
        "point": point,
        "up_vector": _round(up, VECTOR_DECIMALS),
        "mesh_normal": _round(frames[:, :, 1], VECTOR_DECIMALS),
        "xaxis": _round(frames[:, :, 0], VECTOR_DECIMALS),
        "layer_height": _round(height, POINT_DECIMALS),
        "extruder_toggle": extruder_toggle(tp.extrude).tolist(),
        "velocity": _round(velocities(tp, profile), POINT_DECIMALS),
        "wait_time": _round(wait, POINT_DECIMALS),
        "blend_radius": _round(blend_radii(tp, wait), POINT_DECIMALS),
        "closest_support_pt": _round(np.where(on_layer[:, None], support, tp.xyz), POINT_DECIMALS),
        "distance_to_support": [d if ok else None for d, ok in zip(_round(tp.thickness, POINT_DECIMALS), on)],
        "is_feasible": (~infeasible).tolist(),
        "layer": tp.layer.tolist(), "path": tp.path.tolist(), "extrude": tp.extrude.tolist(),
        "width": _round(tp.width, POINT_DECIMALS), "volume_mm3": _round(vol, POINT_DECIMALS),
        "filament_mm": _round(fil, POINT_DECIMALS),
    }


def printpoint_data(c: dict[str, list], i: int) -> dict[str, Any]:
    """Waypoint ``i`` as compas_slicer's ``PrintPoint.to_data()`` (``point`` as compas_slicer <= 0.6 and its
    Grasshopper loader read it, ``pt`` as 0.7's ``__data__`` does) from ``printpoint_columns``."""
    p = c["point"][i]
    return {
        "point": p, "pt": p,
        "layer_height": c["layer_height"][i],
        "mesh_normal": c["mesh_normal"][i],
        "up_vector": c["up_vector"][i],
        "frame": {"point": p, "xaxis": c["xaxis"][i], "yaxis": c["mesh_normal"][i]},
        "extruder_toggle": c["extruder_toggle"][i],
        "velocity": c["velocity"][i],
        "wait_time": c["wait_time"][i],
        "blend_radius": c["blend_radius"][i],
        "closest_support_pt": c["closest_support_pt"][i],
        "distance_to_support": c["distance_to_support"][i],
        "is_feasible": c["is_feasible"][i],
        "attributes": {"index": i, "layer": c["layer"][i], "path": c["path"][i], "extrude": c["extrude"][i],
                       "width": c["width"][i], "volume_mm3": c["volume_mm3"][i], "filament_mm": c["filament_mm"][i]},
    }


def printpoint_layers(tp: Toolpaths, profile: MachineProfile | None = None) -> Iterator[tuple[str, dict]]:
    """(``layer_i``, ``{"path_j": {"k": printpoint}}``) of each compas_slicer layer in print order."""
    columns = printpoint_columns(tp, profile)
    layer, path = printpoint_groups(tp)
    starts = np.flatnonzero(np.r_[True, layer[1:] != layer[:-1]]) if len(tp) else np.zeros(0, np.int64)
    for a, b in zip(starts.tolist(), np.r_[starts[1:], len(tp)].tolist()):
        doc: dict[str, dict[str, dict]] = {}
        for i in range(a, b):
            points = doc.setdefault(f"path_{int(path[i])}", {})
            points[str(len(points))] = printpoint_data(columns, i)
        yield f"layer_{int(layer[a])}", doc


def write_printpoints_json(path: str | Path, tp: Toolpaths, profile: MachineProfile | None = None) -> Path:
    """compas_slicer's nested printpoints JSON (``printpoint_layers``), written a layer at a time, atomically."""
    with atomic_path(path) as tmp, tmp.open("w") as f:
        f.write("{")
        for n, (key, doc) in enumerate(printpoint_layers(tp, profile)):
            f.write(("," if n else "") + json.dumps(key) + ":" + json.dumps(doc))
        f.write("}")
    return Path(path)
