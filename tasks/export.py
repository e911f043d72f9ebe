"""The export task: the output contract in DIR (meshes, field, metrics, report), written atomically."""
from __future__ import annotations

import json
import os
import shutil
import uuid
from pathlib import Path
from typing import Any

import numpy as np
import pyvista as pv
import trimesh

from neuralslicer.metrics import overhang_area_fraction, strength_angles, strength_satisfaction, support_angles
from neuralslicer.report import (
    markdown_report,
    plot_angle_histogram,
    plot_collision_map,
    plot_layers,
    plot_learning_curves,
    plot_strain_histogram,
)
from neuralslicer.cage import Cage
from neuralslicer.samples import SurfaceSamples, write_samples_ply
from neuralslicer.scalar_field import ScalarField
from storage import ArtifactRef, ArtifactStore, atomic_path, write_json_atomic, write_text_atomic
from tasks.common import pipeline_task
from neuralslicer.outputs import write_print_outputs
from neuralslicer.toolpath.io import plot_toolpaths_png
from tasks.steps import read_cage, read_collision_map, read_field, read_layers, read_print, read_samples

STAMP = ".neuralslicer-export"
PRINT_METRICS = (
    "toolpath_length_mm",
    "n_waypoints",
    "estimated_print_time_s",
    "material_mm3",
    "n_collisions",
    "n_part_collisions",
    "n_platform_collisions",
    "n_singular",
    "n_rotary_out_of_range",
    "c_range_deg",
    "n_waypoints_outside_solid",
)


def _export_current(out: ArtifactRef, params: dict[str, Any]) -> bool:
    """The export is current when DIR still holds the files of this very export."""
    stamp = Path(params["out_dir"], STAMP)
    return stamp.is_file() and stamp.read_text().strip() == out.digest and Path(params["out_dir"], "metrics.json").is_file()


def write_ply(path: Path, mesh: trimesh.Trimesh, normals: np.ndarray | None = None) -> None:
    """Binary PLY of a triangle mesh (with per-vertex normals when given), atomically."""
    m = trimesh.Trimesh(mesh.vertices, mesh.faces, process=False)
    if normals is not None:
        m.vertex_normals = normals
    data = trimesh.exchange.ply.export_ply(m, encoding="binary", vertex_normal=normals is not None)
    with atomic_path(path) as tmp:
        tmp.write_bytes(data)


def write_field_vtu(path: Path, field: ScalarField) -> None:
    """The cage as a VTK unstructured grid: G as point data, the unit LPD and |grad G| as cell data."""
    cells = np.hstack([np.full((len(field.cage_tets), 1), 4), field.cage_tets]).ravel()
    grid = pv.UnstructuredGrid(cells, np.full(len(field.cage_tets), pv.CellType.TETRA, dtype=np.uint8), field.cage_vertices)
    grid.point_data["G"] = field.G
    grad = field.gradients()
    grid.cell_data["lpd"] = field.lpd()
    grid.cell_data["grad_norm"] = np.linalg.norm(grad, axis=1)
    with atomic_path(path) as tmp:
        grid.save(tmp)


def write_layers(layers_dir: Path, meshes: list[trimesh.Trimesh]) -> None:
    """All layers as layers/layer_00000.ply..., replacing the previous folder in one rename."""
    staging = layers_dir.with_name(f".{layers_dir.name}.{uuid.uuid4().hex}.tmp")
    staging.mkdir(parents=True)
    try:
        for i, m in enumerate(meshes):
            write_ply(staging / f"layer_{i:05d}.ply", m, m.vertex_attributes["lpd"])
        if layers_dir.exists():
            trash = layers_dir.with_name(f".{layers_dir.name}.{uuid.uuid4().hex}.old")
            os.replace(layers_dir, trash)
            os.replace(staging, layers_dir)
            shutil.rmtree(trash, ignore_errors=True)
        else:
            os.replace(staging, layers_dir)
    finally:
        shutil.rmtree(staging, ignore_errors=True)


def collision_resolution(
    cage: Cage, B: SurfaceSamples, attempts: list[tuple[str, ArtifactRef, ArtifactRef]], alpha_deg: float
) -> list[dict]:
    """Per field printed on the way to the program: its label, nozzle collisions and overhang area fraction."""
    rows = []
    for label, field_ref, printing in attempts:
        _, lpd, _ = read_field(cage, field_ref).sample(B.points)
        pm = ArtifactStore(printing.store).attrs(printing.path)["metrics"]
        rows.append({"stage": label, "collisions": int(pm.get("n_collisions", 0)),
                          "overhang_area_fraction": overhang_area_fraction(B.normals, B.areas, B.on_platform, lpd,
                                                                           alpha_deg)})
    return rows


def collision_table(rows: list[dict], alpha_deg: float) -> str:
    """Markdown table of the collision resolution, in the order tried."""
    lines = [f"| stage | nozzle collisions | overhang area (α = {alpha_deg:g}°) |", "| --- | --- | --- |"]
    lines += [f"| {r['stage']} | {r['collisions']:,} | {100 * r['overhang_area_fraction']:.2f} % |" for r in rows]
    return "\n".join(lines)


@pipeline_task("export", exclude=(), valid=_export_current)
def export_outputs(
    out: ArtifactRef,
    store: str,
    out_dir: str,
    model: ArtifactRef,
    solid: ArtifactRef,
    samples: ArtifactRef,
    cage: ArtifactRef,
    field: ArtifactRef,
    layers: ArtifactRef,
    printing: ArtifactRef,
    stress: ArtifactRef | None,
    verify: ArtifactRef | None,
    robot: bool,
    alpha_deg: float,
    beta_deg: float,
    attempts: list[tuple[str, ArtifactRef, ArtifactRef]] | None = None,
) -> tuple[dict, dict]:
    """Write model.ply, layers/, field.vtu, samples_B.ply, metrics.json, report.md and figures to out_dir."""
    st = ArtifactStore(store)
    d = Path(out_dir)
    figs = d / "figures"
    surf_arrays, surf_attrs = st.read(solid.path)
    surface = trimesh.Trimesh(surf_arrays["vertices"], surf_arrays["faces"], process=False)
    write_ply(d / "model.ply", surface)
    B = read_samples(samples)
    write_samples_ply(d / "samples_B.ply", B)
    c = read_cage(cage)
    f = read_field(c, field)
    write_field_vtu(d / "field.vtu", f)
    lay = read_layers(layers)
    write_layers(d / "layers", lay.meshes)

    _, lpd, _ = f.sample(B.points)
    planar = np.tile([0.0, 0.0, 1.0], (len(B.points), 1))
    attrs = {k: st.attrs(r.path) for k, r in
             {"model": model, "solid": solid, "samples": samples, "cage": cage, "field": field, "layers": layers,
              "toolpaths": printing, "stress_samples": stress, "verify": verify}.items() if r is not None}
    field_attrs = attrs["field"]
    metrics: dict[str, Any] = {
        "model": model.model,
        "model_genus": surf_attrs["genus"],
        "model_volume_mm3": surf_attrs["volume_mm3"],
        "n_samples_B": int(len(B.points)),
        "n_cage_elements": int(len(c.tets)),
        "n_cage_vertices": int(len(c.vertices)),
        "cage_genus": attrs["cage"]["genus"],
        "n_layers": len(lay.meshes),
        "sf.alpha_deg": alpha_deg,
        "sf.overhang_area_fraction": overhang_area_fraction(B.normals, B.areas, B.on_platform, lpd, alpha_deg),
        "sf.overhang_area_fraction_planar": overhang_area_fraction(B.normals, B.areas, B.on_platform, planar, alpha_deg),
        "field.kind": field_attrs.get("kind", "neural"),
        "field.objectives": ",".join(field_attrs.get("objectives", [])),
        "field.steps": field_attrs.get("steps", 0),
        "field.blend_planar": field_attrs.get("blend_planar", 0.0),
    }
    metrics.update({f"layers.{k}": v for k, v in attrs["layers"]["report"].items()})
    metrics.update({f"loss.{k}": v for k, v in (field_attrs.get("final") or {}).items()})
    metrics.update({f"wall_s.{k}": a["wall_s"] for k, a in attrs.items()})
    keep = ~B.on_platform
    figures = {}
    plot_layers(figs / "layers.png", lay.meshes)
    figures["Layers"] = "figures/layers.png"
    plot_angle_histogram(
        figs / "sf_histogram.png",
        {"planar": support_angles(B.normals[keep], planar[keep]), "computed": support_angles(B.normals[keep], lpd[keep])},
        B.areas[keep], alpha_deg, "overhang angle asin(-n·d) (°)", "support-free: surface samples B",
    )
    figures["Support-free angle histogram"] = "figures/sf_histogram.png"
    if stress is not None:
        T, _ = st.read(stress.path)
        _, lpd_t, _ = f.sample(T["points"])
        planar_t = np.tile([0.0, 0.0, 1.0], (len(T["points"]), 1))
        metrics["sr.beta_deg"] = beta_deg
        metrics["sr.satisfied_fraction"] = strength_satisfaction(T["tau_max"], T["volumes"], lpd_t, beta_deg)
        metrics["sr.satisfied_fraction_planar"] = strength_satisfaction(T["tau_max"], T["volumes"], planar_t, beta_deg)
        plot_angle_histogram(
            figs / "sr_histogram.png",
            {"planar": strength_angles(T["tau_max"], planar_t), "computed": strength_angles(T["tau_max"], lpd_t)},
            T["volumes"], beta_deg, "angle between tau_max and the layer (°)", "strength: stress samples T",
        )
        figures["Strength angle histogram"] = "figures/sr_histogram.png"
    if verify is not None:
        v_arrays, v_attrs = st.read(verify.path)
        metrics.update({f"fea.{k}": v for k, v in v_attrs.items() if k.startswith("max_strain")})
        plot_strain_histogram(figs / "strain_histogram.png", {"planar": v_arrays["strain_planar"], "computed": v_arrays["strain"]})
        figures["Strain of the printed part (transversely isotropic FEA)"] = "figures/strain_histogram.png"
    field_arrays, _ = st.read(field.path)
    history = {k.split("/", 1)[1]: v for k, v in field_arrays.items() if k.startswith("history/")}
    if history:
        plot_learning_curves(figs / "learning_curves.png", {"field": history})
        figures["Learning curves"] = "figures/learning_curves.png"
    tp, program, print_metrics = read_print(printing)
    write_print_outputs(d, tp, program, print_metrics, robot=robot, png=False)
    metrics.update({k: print_metrics[k] for k in PRINT_METRICS if k in print_metrics})
    metrics["collisions"] = int(print_metrics.get("n_collisions", 0))
    plot_toolpaths_png(figs / "toolpaths.png", tp)
    figures["Toolpaths (colour = print order)"] = "figures/toolpaths.png"
    maps = {"printed": read_collision_map(printing)}
    if attempts and attempts[0][2] != printing:
        maps = {f"first print ({attempts[0][0]})": read_collision_map(attempts[0][2]), **maps}
    plot_collision_map(figs / "collisions.png", maps)
    figures["Print head collisions (red)"] = "figures/collisions.png"
    sections = {}
    if attempts:
        rows = collision_resolution(c, B, attempts, alpha_deg)
        for i, row in enumerate(rows):
            metrics.update({f"collision_resolution.{i}.{k}": v for k, v in row.items()})
        sections["Collision resolution"] = collision_table(rows, alpha_deg)
    write_json_atomic(d / "metrics.json", metrics)
    write_text_atomic(d / "report.md",
                      markdown_report(f"Neural Slicer report: {model.model}", metrics, figures, sections))
    write_text_atomic(d / STAMP, out.digest)
    return {}, {"out_dir": str(d), "metrics": json.loads(json.dumps(metrics, default=float))}
