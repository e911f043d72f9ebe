"""Robot export: per waypoint position, tool orientation quaternion and extrusion (CSV, JSON)."""
from __future__ import annotations

import json
from pathlib import Path

import numpy as np

from neuralslicer.fileio import atomic_path
from neuralslicer.toolpath.types import Toolpaths
from neuralslicer.types import FloatArray

ROBOT_COLUMNS = ("index", "layer", "path", "x", "y", "z", "qw", "qx", "qy", "qz", "extrude",
                 "volume_mm3", "filament_mm", "thickness", "width")


def tool_frames(axis: FloatArray) -> FloatArray:
    """Tool frames (n, 3, 3), columns x, y, z: z = -LPD (into the material), x = build +x projected."""
    z = -np.asarray(axis, np.float64)
    z = z / np.linalg.norm(z, axis=1, keepdims=True)
    ref = np.where((np.abs(z[:, 0]) > 0.9)[:, None], [0.0, 1.0, 0.0], [1.0, 0.0, 0.0])
    x = ref - np.einsum("ij,ij->i", ref, z)[:, None] * z
    x /= np.linalg.norm(x, axis=1, keepdims=True)
    y = np.cross(z, x)
    return np.stack([x, y, z], axis=2)


def matrix_to_quaternion(r: FloatArray) -> FloatArray:
    """Unit quaternions (n, 4) as (w, x, y, z), w >= 0, from rotation matrices (n, 3, 3)."""
    r = np.asarray(r, np.float64)
    tr = np.trace(r, axis1=1, axis2=2)
    q = np.empty((len(r), 4))
    cand = np.stack([tr, r[:, 0, 0], r[:, 1, 1], r[:, 2, 2]], axis=1)
    k = np.argmax(cand, axis=1)
    for case in range(4):
        m = k == case
        if not m.any():
            continue
        rr = r[m]
        if case == 0:
            s = 2.0 * np.sqrt(1.0 + tr[m])
            q[m] = np.stack([0.25 * s, (rr[:, 2, 1] - rr[:, 1, 2]) / s, (rr[:, 0, 2] - rr[:, 2, 0]) / s,
                             (rr[:, 1, 0] - rr[:, 0, 1]) / s], 1)
        else:
            i = case - 1
            j, l = (i + 1) % 3, (i + 2) % 3
            s = 2.0 * np.sqrt(np.maximum(1.0 + rr[:, i, i] - rr[:, j, j] - rr[:, l, l], 1e-300))
            qq = np.empty((m.sum(), 4))
            qq[:, 0] = (rr[:, l, j] - rr[:, j, l]) / s
            qq[:, 1 + i] = 0.25 * s
            qq[:, 1 + j] = (rr[:, j, i] + rr[:, i, j]) / s
            qq[:, 1 + l] = (rr[:, l, i] + rr[:, i, l]) / s
            q[m] = qq
    q *= np.where(q[:, :1] < 0, -1.0, 1.0)
    return q / np.linalg.norm(q, axis=1, keepdims=True)


def quaternion_to_matrix(q: FloatArray) -> FloatArray:
    """Rotation matrices (n, 3, 3) from unit quaternions (w, x, y, z)."""
    w, x, y, z = np.asarray(q, np.float64).T
    return np.stack([
        np.stack([1 - 2 * (y * y + z * z), 2 * (x * y - w * z), 2 * (x * z + w * y)], -1),
        np.stack([2 * (x * y + w * z), 1 - 2 * (x * x + z * z), 2 * (y * z - w * x)], -1),
        np.stack([2 * (x * z - w * y), 2 * (y * z + w * x), 1 - 2 * (x * x + y * y)], -1)], -2)


def robot_table(tp: Toolpaths, filament_diameter: float = 1.75) -> np.ndarray:
    """(n, 15) table in ``ROBOT_COLUMNS`` order; volume/filament of the move arriving at each point."""
    q = matrix_to_quaternion(tool_frames(tp.axis))
    seg = tp.segment_lengths()
    t = np.concatenate([[0.0], 0.5 * (tp.thickness[1:] + tp.thickness[:-1])])
    w = np.concatenate([[0.0], 0.5 * (tp.width[1:] + tp.width[:-1])])
    vol = np.where(tp.extrude, seg * t * w, 0.0)
    fil = vol / (np.pi * 0.25 * filament_diameter ** 2)
    return np.column_stack([np.arange(len(tp)), tp.layer, tp.path, tp.xyz, q, tp.extrude.astype(float),
                            vol, fil, tp.thickness, tp.width])


def write_robot_csv(path: str | Path, tp: Toolpaths, filament_diameter: float = 1.75) -> Path:
    """Robot waypoints CSV: position (build frame, mm), quaternion wxyz of the tool frame, extrusion."""
    table = robot_table(tp, filament_diameter)
    fmt = ["%d", "%d", "%d", "%.6f", "%.6f", "%.6f", "%.8f", "%.8f", "%.8f", "%.8f", "%d", "%.6f",
           "%.6f", "%.6f", "%.6f"]
    with atomic_path(path) as tmp:
        np.savetxt(tmp, table, fmt=fmt, delimiter=",", header=",".join(ROBOT_COLUMNS), comments="")
    return Path(path)


def write_robot_json(path: str | Path, tp: Toolpaths, filament_diameter: float = 1.75) -> Path:
    """Robot waypoints JSON: ``{"units", "frame", "quaternion", "columns", "rows": [[...], ...]}``."""
    table = robot_table(tp, filament_diameter)
    doc = {"units": "mm", "frame": "build (+z up)",
           "quaternion": "w,x,y,z of the tool frame: z = -LPD (into the material), x = build +x projected",
           "columns": list(ROBOT_COLUMNS), "rows": np.round(table, 8).tolist()}
    with atomic_path(path) as tmp:
        tmp.write_text(json.dumps(doc))
    return Path(path)
