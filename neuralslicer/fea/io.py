"""Files for people: the voxel result as ``.vtu``, a PNG of the stress field, ``metrics.json``."""
from __future__ import annotations

import json
from pathlib import Path
from typing import Any

import numpy as np

from neuralslicer.fea.solver import FEAResult
from neuralslicer.fileio import atomic_path, write_text_atomic


def to_vtk(result: FEAResult, cell_data: dict[str, np.ndarray] | None = None) -> Any:
    """pyvista.UnstructuredGrid of the voxels (VTK_HEXAHEDRON) with the result as cell/point data."""
    import pyvista as pv

    g = result.grid
    n = g.n_voxels
    cells = np.hstack([np.full((n, 1), 8, dtype=np.int64), g.elements]).ravel()
    celltypes = np.full(n, pv.CellType.HEXAHEDRON, dtype=np.uint8)
    mesh = pv.UnstructuredGrid(cells, celltypes, g.nodes)
    mesh.point_data["displacement"] = result.displacement
    cd = mesh.cell_data
    cd["von_mises"] = result.von_mises
    cd["max_principal"] = result.max_principal
    cd["tau_max"] = result.tau_max
    cd["principal_stress"] = result.principal_stress
    cd["stress"] = result.stress.reshape(n, 9)
    cd["strain"] = result.strain.reshape(n, 9)
    for k, v in (cell_data or {}).items():
        cd[k] = np.asarray(v)
    return mesh


def plot_field(result: FEAResult, values: np.ndarray, path: str | Path,
               label: str = "von Mises stress [MPa]") -> Path:
    """PNG of three orthogonal mid-slices (through the median voxel) of a per-voxel field."""
    import matplotlib
    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    g = result.grid
    nx, ny, nz = (int(s) for s in g.shape)
    vol = np.full((nx, ny, nz), np.nan)
    vol[g.ijk[:, 0], g.ijk[:, 1], g.ijk[:, 2]] = values
    mid = np.median(g.ijk, axis=0).astype(int)
    lo = g.origin
    hi = g.origin + g.shape * g.spacing
    vmin, vmax = float(np.nanmin(values)), float(np.nanmax(values))
    views = [("z", vol[:, :, mid[2]].T, (lo[0], hi[0], lo[1], hi[1]), "x [mm]", "y [mm]"),
             ("y", vol[:, mid[1], :].T, (lo[0], hi[0], lo[2], hi[2]), "x [mm]", "z [mm]"),
             ("x", vol[mid[0], :, :].T, (lo[1], hi[1], lo[2], hi[2]), "y [mm]", "z [mm]")]
    fig, axes = plt.subplots(1, 3, figsize=(15, 4.5), constrained_layout=True)
    im = None
    for ax, (axis, img, ext, xl, yl) in zip(axes, views):
        c = {"x": 0, "y": 1, "z": 2}[axis]
        pos = lo[c] + (mid[c] + 0.5) * g.spacing
        im = ax.imshow(img, origin="lower", extent=ext, vmin=vmin, vmax=vmax, cmap="viridis",
                       interpolation="nearest")
        ax.set(title=f"slice {axis} = {pos:.2f} mm", xlabel=xl, ylabel=yl)
    fig.colorbar(im, ax=list(axes), label=label, shrink=0.9)
    fig.suptitle(f"{label}: max {vmax:.4g}   ({g.n_voxels} voxels of {g.spacing:.3g} mm)")
    path = Path(path)
    with atomic_path(path) as tmp:
        fig.savefig(tmp, dpi=110)
    plt.close(fig)
    return path


def fea_metrics(result: FEAResult) -> dict[str, Any]:
    """Scalar summary: max displacement and von Mises, |T| sizes, solver figures."""
    info = result.info
    return {
        "fea.max_displacement_mm": float(np.linalg.norm(result.displacement, axis=1).max()),
        "fea.max_von_mises_mpa": float(result.von_mises.max()),
        "fea.max_abs_principal_mpa": float(np.abs(result.max_principal).max()),
        "fea.n_voxels": int(result.grid.n_voxels),
        "fea.voxel_size_mm": float(result.grid.spacing),
        "fea.dropped_voxels": int(info.get("dropped_voxels", 0)),
        "fea.solver": info.get("solver"),
        "fea.iterations": info.get("iterations"),
        "fea.assembly_s": info.get("assembly_s"),
        "fea.solve_s": info.get("solve_s"),
    }


def write_fea_outputs(result: FEAResult, out_dir: str | Path) -> dict[str, Any]:
    """Write ``fea.vtu``, ``fea_von_mises.png`` and ``metrics.json`` atomically; return metrics."""
    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    vtu = out / "fea.vtu"
    with atomic_path(vtu) as tmp:
        to_vtk(result).save(str(tmp))
    plot_field(result, result.von_mises, out / "fea_von_mises.png")
    metrics = fea_metrics(result)
    mpath = out / "metrics.json"
    write_text_atomic(mpath, json.dumps(metrics, indent=2, sort_keys=True) + "\n")
    return metrics
