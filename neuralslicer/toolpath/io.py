"""Toolpath files: waypoints CSV, VTP polylines (pyvista), PNG preview; all written atomically."""
from __future__ import annotations

from pathlib import Path

import numpy as np

from neuralslicer.errors import InputError
from neuralslicer.toolpath.types import Toolpaths
from neuralslicer.fileio import atomic_path, save_vtk_xml

CSV_COLUMNS = ("layer", "path", "x", "y", "z", "nx", "ny", "nz", "thickness", "width", "extrude")
#: waypoints formatted at a time when writing the CSV (bounded memory for a print of any size)
CSV_CHUNK_ROWS = 100_000


def write_waypoints_csv(path: str | Path, tp: Toolpaths) -> Path:
    """Write ``layer,path,x,y,z,nx,ny,nz,thickness,width,extrude`` (one row per waypoint)."""
    fmt = ["%d", "%d", "%.6f", "%.6f", "%.6f", "%.7f", "%.7f", "%.7f", "%.6f", "%.6f", "%d"]
    with atomic_path(path) as tmp, open(tmp, "w") as fh:
        fh.write(",".join(CSV_COLUMNS) + "\n")
        for block in tp.blocks(CSV_CHUNK_ROWS):   # a stored print's read a block at a time
            table = np.column_stack([block.layer, block.path, block.xyz, block.axis, block.thickness, block.width,
                                     block.extrude.astype(np.int64)])
            np.savetxt(fh, table, fmt=fmt, delimiter=",")
    return Path(path)


def read_waypoints_csv(path: str | Path) -> Toolpaths:
    """Read a waypoints CSV written by ``write_waypoints_csv``."""
    path = Path(path)
    with open(path) as fh:
        header = fh.readline().strip().split(",")
    if tuple(header) != CSV_COLUMNS:
        raise InputError(path, f"line 1: expected columns {','.join(CSV_COLUMNS)}")
    data = np.loadtxt(path, delimiter=",", skiprows=1, ndmin=2)
    return Toolpaths(layer=data[:, 0].astype(np.int64), path=data[:, 1].astype(np.int64),
                     xyz=data[:, 2:5], axis=data[:, 5:8], thickness=data[:, 8], width=data[:, 9],
                     extrude=data[:, 10] != 0)


def _polylines(tp: Toolpaths) -> tuple[np.ndarray, np.ndarray]:
    """Connectivity of the extrusion polylines: (lines array for VTK, first index of each)."""
    idx = np.arange(len(tp))
    # a new polyline starts at every non-extruding waypoint
    start = ~tp.extrude
    run = np.cumsum(start) - 1
    mask = np.zeros(len(tp), bool)
    mask[:-1] |= tp.extrude[1:]
    mask |= tp.extrude
    keep = idx[mask]
    if len(keep) == 0:
        return np.zeros(0, np.int64), np.zeros(0, np.int64)
    first = np.r_[0, np.flatnonzero(np.diff(run[keep])) + 1]       # where each polyline starts in keep
    sizes = np.diff(np.r_[first, len(keep)])
    at = first + np.arange(len(first))                                # where its size goes in the lines array
    lines = np.empty(len(keep) + len(first), np.int64)
    lines[at] = sizes
    points = np.ones(len(lines), bool)
    points[at] = False
    lines[points] = keep
    return lines, keep[first].astype(np.int64)


def write_toolpaths_vtp(path: str | Path, tp: Toolpaths) -> Path:
    """Write the extrusion polylines as VTK PolyData with per-point scalars (pyvista)."""
    import pyvista as pv

    lines, _ = _polylines(tp)
    poly = pv.PolyData(np.asarray(tp.xyz, np.float64))
    if len(lines):
        poly.lines = lines
    poly.point_data["layer"] = tp.layer
    poly.point_data["path"] = tp.path
    poly.point_data["order"] = np.arange(len(tp), dtype=np.int64)
    poly.point_data["thickness"] = tp.thickness
    poly.point_data["width"] = tp.width
    poly.point_data["extrude"] = tp.extrude.astype(np.uint8)
    poly.point_data["axis"] = tp.axis
    save_vtk_xml(poly, path)
    return Path(path)


def plot_toolpaths_png(path: str | Path, tp: Toolpaths, max_segments: int = 60_000,
                       title: str | None = None) -> Path:
    """PNG preview (matplotlib 3D, Agg): extrusion segments coloured by print order."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    from mpl_toolkits.mplot3d.art3d import Line3DCollection

    seg_idx = np.flatnonzero(tp.extrude[1:]) + 1
    if len(seg_idx) > max_segments:
        seg_idx = seg_idx[:: int(np.ceil(len(seg_idx) / max_segments))]
    segs = np.stack([tp.xyz[seg_idx - 1], tp.xyz[seg_idx]], axis=1)
    fig = plt.figure(figsize=(7, 6), dpi=110)
    ax = fig.add_subplot(projection="3d")
    if len(segs):
        order = seg_idx / max(len(tp) - 1, 1)
        coll = Line3DCollection(segs, cmap="viridis", linewidths=0.6)
        coll.set_array(order)
        ax.add_collection3d(coll)
        lo, hi = tp.xyz.min(axis=0), tp.xyz.max(axis=0)
        c, r = 0.5 * (lo + hi), 0.5 * float(np.max(hi - lo)) + 1e-9
        ax.set_xlim(c[0] - r, c[0] + r)
        ax.set_ylim(c[1] - r, c[1] + r)
        ax.set_zlim(c[2] - r, c[2] + r)
        fig.colorbar(coll, ax=ax, shrink=0.6, label="print order (fraction of waypoints)")
    ax.set_xlabel("x (mm)")
    ax.set_ylabel("y (mm)")
    ax.set_zlabel("z (mm)")
    ax.set_title(title or f"toolpaths: {tp.n_layers} layers, {len(tp)} waypoints")
    with atomic_path(path) as tmp:
        fig.savefig(tmp, format="png")
    plt.close(fig)
    return Path(path)
