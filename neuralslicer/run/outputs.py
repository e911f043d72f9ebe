"""The output contract of a slice: meshes, field, layers, print files, metrics.json, report.md and figures.

Everything here takes the step results as plain objects (:class:`RunResults`) and writes files
atomically; reading them from a store is the tasks' business.
"""
from __future__ import annotations

import json
import os
import shutil
import uuid
from collections.abc import Callable, Iterable
from dataclasses import dataclass, field
from functools import cached_property
from pathlib import Path
from typing import Any

import numpy as np
import pyvista as pv
import trimesh

from neuralslicer.allocator import release_freed_memory
from neuralslicer.cage import Cage
from neuralslicer.fea.samples import StressSamples
from neuralslicer.fileio import atomic_path, save_vtk_xml, write_json_atomic, write_text_atomic
from neuralslicer.forked import SharedJobs
from neuralslicer.gcode.printpoints import write_printpoints_json
from neuralslicer.gcode.robot import write_robot_csv, write_robot_json
from neuralslicer.gcode.writers import write_gcode
from neuralslicer.layers import Layers
from neuralslicer.metrics import (heldout_surface_samples, layer_lpd_at, overhang_area_fraction, strength_angles,
                                  strength_satisfaction, support_angles)
from neuralslicer.motion.collision import CollisionMap
from neuralslicer.motion.planning import MachineProgram, ProgramMoves
from neuralslicer.preview import PREVIEW_FILE
from neuralslicer.preview.data import PreviewData
from neuralslicer.preview.page import write_preview
from neuralslicer.run.report import (markdown_report, plot_angle_histogram, plot_collision_map, plot_filament_angles,
                                     plot_layer_toolpaths, plot_layers_3d, plot_learning_curves, plot_overhang_map,
                                     plot_strain_histogram, plot_strain_maps, plot_stress_turn, plot_thickness_map)
from neuralslicer.samples import SurfaceSamples, write_samples_ply
from neuralslicer.scalar_field import ScalarField
from neuralslicer.toolpath.io import plot_toolpaths_png, write_toolpaths_vtp, write_waypoints_csv
from neuralslicer.toolpath.types import Toolpaths
from neuralslicer.types import IndexArray
from neuralslicer.verify import PART_FIGURES, strain_gains

#: print metrics copied into metrics.json
PRINT_METRICS = (
    "toolpath_length_mm", "n_waypoints", "estimated_print_time_s", "material_mm3", "n_collisions",
    "n_part_collisions", "n_platform_collisions", "n_travel_collisions", "n_singular", "n_rotary_out_of_range", "c_range_deg",
    "n_waypoints_outside_solid",
)
PLANAR = np.array([0.0, 0.0, 1.0])


@dataclass
class Attempt:
    """One field printed on the way to a collision-free program: its label, field and print metrics."""

    label: str
    field: ScalarField
    print_metrics: dict


#: the arrays of a strength round (``stress_turn``): how far tau_max turned, the layers' angle to each tau_max
TURN_ARRAYS = ("tau_turn_deg", "layer_tau_iso_deg", "layer_tau_printed_deg")


@dataclass
class StrengthRound:
    """One strength round (``sr_rounds``): its label, its print's collisions, the FEA of that print (``max_strain``,
    ``max_strain_p99``, ``max_displacement_mm``, ``tau_turn_median_deg``, ...) and the :data:`TURN_ARRAYS`."""

    label: str
    collisions: int
    figures: dict
    turn: dict[str, np.ndarray]


@dataclass
class RunResults:
    """The results of every step of one slice, as the output contract needs them."""

    model: str
    surface: trimesh.Trimesh
    surface_attrs: dict
    samples: SurfaceSamples
    cage: Cage
    cage_attrs: dict
    field: ScalarField
    field_history: dict[str, np.ndarray]
    layers: Layers
    toolpaths: Toolpaths
    #: the machine program (ProgramMoves where ``gcode`` holds its G-code: what the preview draws); a stored run's is
    #: its profile, part offset and attrs, its moves read by ``read()`` (``tasks/codec.py: StoredProgram``)
    program: ProgramMoves
    print_metrics: dict
    #: where the head hits, by print (the first print and the printed one), as their figure draws it
    collision_maps: dict[str, CollisionMap]
    #: the printed print's colliding waypoints (sorted indices into ``toolpaths``)
    collided: IndexArray
    wall_s: dict[str, float]
    stress_samples: StressSamples | None = None
    verify: tuple[dict[str, np.ndarray], dict[str, float]] | None = None
    attempts: list[Attempt] = field(default_factory=list)
    strength_rounds: list[StrengthRound] = field(default_factory=list)
    #: the program step's G-code (None: written from ``program`` here)
    gcode: bytes | Iterable[bytes] | None = None

    @cached_property
    def lpd_b(self) -> np.ndarray:
        """The field's LPD at the surface samples B (n, 3), computed once for metrics and figures."""
        return self.field.sample(self.samples.points)[1]

    @cached_property
    def lpd_t(self) -> np.ndarray | None:
        """The field's LPD at the stress samples T, or None without them."""
        return None if self.stress_samples is None else self.field.sample(self.stress_samples.points)[1]


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
    grid.cell_data["lpd"] = field.lpd()
    grid.cell_data["grad_norm"] = np.linalg.norm(field.gradients(), axis=1)
    save_vtk_xml(grid, path)


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


def collision_resolution(samples: SurfaceSamples, attempts: list[Attempt], alpha_deg: float) -> list[dict]:
    """Per field printed on the way to the program: its label, nozzle collisions (of them below the platform) and
    overhang area fraction."""
    rows = []
    for a in attempts:
        _, lpd, _ = a.field.sample(samples.points)
        rows.append({"stage": a.label, "collisions": int(a.print_metrics.get("n_collisions", 0)),
                     "platform_collisions": int(a.print_metrics.get("n_platform_collisions", 0)),
                     "overhang_area_fraction": overhang_area_fraction(samples.normals, samples.areas,
                                                                      samples.on_platform, lpd, alpha_deg)})
    return rows


def collision_table(rows: list[dict], alpha_deg: float) -> str:
    """Markdown table of the collision resolution, in the order tried."""
    lines = [f"| stage | nozzle collisions | of them below the platform | overhang area (α = {alpha_deg:g}°) |",
             "| --- | --- | --- | --- |"]
    lines += [f"| {r['stage']} | {r['collisions']:,} | {r['platform_collisions']:,} | "
              f"{100 * r['overhang_area_fraction']:.2f} % |" for r in rows]
    return "\n".join(lines)


def heldout_overhang(run: RunResults, alpha_deg: float) -> dict[str, float]:
    """Overhang area fractions on held-out samples of the model's surface mesh (as many as B, drawn apart from
    it): with the field's LPD, with the exported layers' own normals, and planar (``sf.heldout.*``)."""
    if not run.layers.meshes:
        return {}
    platform_z = float(run.program.attrs.get("platform_z", run.surface.bounds[0, 2]))
    pts, normals, areas, on_platform = heldout_surface_samples(run.surface, len(run.samples.points), platform_z)
    lpd = {"": run.field.sample(pts)[1], "_layers": layer_lpd_at(run.layers.meshes, pts),
           "_planar": np.tile(PLANAR, (len(pts), 1))}
    return {f"sf.heldout.overhang_area_fraction{k}": overhang_area_fraction(normals, areas, on_platform, d, alpha_deg)
            for k, d in lpd.items()}


def run_metrics(run: RunResults, alpha_deg: float, beta_deg: float) -> dict[str, Any]:
    """metrics.json: the model, cage, field, layers, support-free and strength figures, print metrics."""
    B, fa, lpd = run.samples, run.field.info, run.lpd_b
    planar = np.tile(PLANAR, (len(B.points), 1))
    metrics: dict[str, Any] = {
        "model": run.model, "model_genus": run.surface_attrs["genus"],
        "model_volume_mm3": run.surface_attrs["volume_mm3"], "n_samples_B": int(len(B.points)),
        "n_cage_elements": int(len(run.cage.tets)), "n_cage_vertices": int(len(run.cage.vertices)),
        "cage_genus": run.cage_attrs["genus"], "n_layers": len(run.layers.meshes), "sf.alpha_deg": alpha_deg,
        "sf.overhang_area_fraction": overhang_area_fraction(B.normals, B.areas, B.on_platform, lpd, alpha_deg),
        "sf.overhang_area_fraction_planar": overhang_area_fraction(B.normals, B.areas, B.on_platform, planar,
                                                                   alpha_deg),
        "field.kind": fa.get("kind", "neural"), "field.objectives": ",".join(fa.get("objectives", [])),
        "field.steps": fa.get("steps", 0), "field.stop": fa.get("stop", ""),
        "field.blend_planar": fa.get("blend_planar", 0.0),
    }
    if fa.get("energy_by_iteration"):  # S3: its fabrication energy at the start of each outer iteration and at the end
        metrics["field.energy_by_iteration"] = fa["energy_by_iteration"]
    metrics.update(heldout_overhang(run, alpha_deg))
    metrics.update({f"layers.{k}": v for k, v in run.layers.report.items()})
    metrics.update({f"loss.{k}": v for k, v in (fa.get("final") or {}).items()})
    metrics.update({f"wall_s.{k}": v for k, v in run.wall_s.items()})
    if run.stress_samples is not None:
        T, lpd_t = run.stress_samples, run.lpd_t
        metrics["sr.beta_deg"] = beta_deg
        metrics["sr.satisfied_fraction"] = strength_satisfaction(T.tau_max, T.volumes, lpd_t, beta_deg)
        metrics["sr.satisfied_fraction_planar"] = strength_satisfaction(
            T.tau_max, T.volumes, np.tile(PLANAR, (len(T.points), 1)), beta_deg)
    if run.verify is not None:
        metrics.update(verify_metrics(run.verify[1]))
    for i, row in enumerate(strength_round_rows(run.strength_rounds, beta_deg)):
        metrics.update({f"sr_rounds.{i}.{k}": v for k, v in row.items()})
    metrics.update({k: run.print_metrics[k] for k in PRINT_METRICS if k in run.print_metrics})
    if "stress_infill_fraction" in run.toolpaths.attrs:
        metrics["toolpath.stress_infill_fraction"] = run.toolpaths.attrs["stress_infill_fraction"]
    metrics.update({f"tilt.{k}": v for k, v in (run.print_metrics.get("axis_tilt") or {}).items()})
    metrics.update({f"reach.{k}": v for k, v in (run.print_metrics.get("axis_reach") or {}).items()})
    metrics.update({f"platform_turn.{k}": v for k, v in (run.print_metrics.get("axis_platform") or {}).items()})
    metrics.update({f"travel.{k}": v for k, v in (run.print_metrics.get("travel_lift") or {}).items()})
    metrics.update({f"three_axis.{k}": v for k, v in (run.print_metrics.get("three_axis") or {}).items()})
    metrics.update({f"beads.{k}": v for k, v in (run.print_metrics.get("beads") or {}).items() if not k.startswith("hist_")})
    return metrics


#: a piece of the export that depends on nothing else written: it writes its files and returns the report's
#: figures it drew, {caption: path relative to the output folder} (empty for other files)
Job = Callable[[], dict[str, str]]


def figure_jobs(figs: Path, run: RunResults, alpha_deg: float, beta_deg: float) -> list[tuple[float, Job]]:
    """The report's pictures under ``figs`` as independent jobs, in the report's order, each with a rough cost
    (seconds on the ring) by which :class:`ExportJobs` starts the longest first; those that draw the toolpaths are in
    :data:`TOOLPATH_FIGURES`."""
    B, keep, lpd = run.samples, ~run.samples.on_platform, run.lpd_b
    planar = np.tile(PLANAR, (len(B.points), 1))
    tp = run.toolpaths

    def layers() -> dict[str, str]:
        return {f"Layers ({plot_layers_3d(figs / 'layers.png', run.layers.meshes)})": "figures/layers.png"}

    def overhang() -> dict[str, str]:
        plot_overhang_map(figs / "overhang_map.png", B.points, B.normals, {"planar": planar, "computed": lpd},
                          alpha_deg, B.areas, B.on_platform)
        return {"Overhang map (planar vs computed)": "figures/overhang_map.png"}

    def sf_histogram() -> dict[str, str]:
        plot_angle_histogram(
            figs / "sf_histogram.png",
            {"planar": support_angles(B.normals[keep], planar[keep]),
             "computed": support_angles(B.normals[keep], lpd[keep])},
            B.areas[keep], alpha_deg, "overhang angle asin(-n·d) (°)", "support-free: surface samples B",
        )
        return {"Support-free angle histogram": "figures/sf_histogram.png"}

    def sr_histogram() -> dict[str, str]:
        T, lpd_t = run.stress_samples, run.lpd_t
        plot_angle_histogram(
            figs / "sr_histogram.png",
            {"planar": strength_angles(T.tau_max, np.tile(PLANAR, (len(T.points), 1))),
             "computed": strength_angles(T.tau_max, lpd_t)},
            T.volumes, beta_deg, "angle between tau_max and the layer (°)", "strength: stress samples T",
        )
        return {"Strength angle histogram": "figures/sr_histogram.png"}

    def stress_turn() -> dict[str, str]:
        plot_stress_turn(figs / "stress_turn.png", {r.label: r.turn for r in run.strength_rounds}, beta_deg)
        return {"tau_max of the printed part against the isotropic one, per strength round": "figures/stress_turn.png"}

    def learning() -> dict[str, str]:
        plot_learning_curves(figs / "learning_curves.png", {"field": run.field_history})
        return {"Learning curves": "figures/learning_curves.png"}

    def toolpaths() -> dict[str, str]:
        plot_toolpaths_png(figs / "toolpaths.png", tp)
        return {"Toolpaths (colour = print order)": "figures/toolpaths.png"}

    def layer_toolpaths() -> dict[str, str]:
        plot_layer_toolpaths(figs / "layer_toolpaths.png", tp)
        return {"Toolpaths of representative layers": "figures/layer_toolpaths.png"}

    def thickness() -> dict[str, str]:
        plot_thickness_map(figs / "bead_thickness.png", tp.xyz, tp.thickness, tp.extrude,
                           run.program.profile.nozzle.bead_thickness_mm, gaps=run.print_metrics.get("beads"))
        return {"Bead thickness": "figures/bead_thickness.png"}

    def collisions() -> dict[str, str]:
        plot_collision_map(figs / "collisions.png", run.collision_maps)
        return {"Print head collisions (red)": "figures/collisions.png"}

    jobs: list[tuple[float, Job]] = [(0.8, layers), (0.8, overhang), (0.1, sf_histogram)]
    if run.stress_samples is not None:
        jobs.append((0.1, sr_histogram))
    if run.verify is not None:
        jobs.append((2.0, lambda: draw_strength_figures(figs, *run.verify)))
    if run.strength_rounds:
        jobs.append((0.3, stress_turn))
    if run.field_history:
        jobs.append((0.35, learning))
    jobs += [(0.45, toolpaths), (0.5, layer_toolpaths), (0.6, thickness), (0.3, collisions)]
    return jobs


#: the figures (their jobs' names) that draw the toolpaths' waypoints
TOOLPATH_FIGURES = frozenset({"toolpaths", "layer_toolpaths", "thickness"})
#: a print of at least this many waypoints is exported in two rounds (``write_outputs``)
TWO_ROUNDS_WAYPOINTS = 20_000_000


def draw_figures(figs: Path, run: RunResults, alpha_deg: float, beta_deg: float) -> dict[str, str]:
    """The report's pictures under ``figs``: {caption: path relative to the output folder}."""
    figures: dict[str, str] = {}
    for _, job in figure_jobs(figs, run, alpha_deg, beta_deg):
        figures.update(job())
    return figures


def verify_metrics(figures: dict[str, Any]) -> dict[str, Any]:
    """``fea.<part>.<figure>`` of every verified part, the gains, and the printed part's figures as ``fea.<figure>``."""
    out: dict[str, Any] = {}
    for part in figures.get("parts", []):
        for fig in (*PART_FIGURES, "tangent", "label"):
            if f"{part}.{fig}" in figures:
                out[f"fea.{part}.{fig}"] = figures[f"{part}.{fig}"]
    out.update({f"fea.{fig}": figures[f"printed.{fig}"] for fig in PART_FIGURES if f"printed.{fig}" in figures})
    out.update({f"fea.{k}": v for k, v in figures.items() if k.startswith("gain.")})
    return out


def strength_round_rows(rounds: list[StrengthRound], beta_deg: float) -> list[dict[str, Any]]:
    """Per strength round: its label, collisions, the strain of its print, how far the print turned tau_max, and the
    share of T whose layer lies within beta of tau_max, the isotropic one (what the round optimised, in round 1) and
    the printed part's."""
    rows = []
    for r in rounds:
        row: dict[str, Any] = {"stage": r.label, "collisions": r.collisions}
        row.update({k: float(r.figures[k]) for k in ("max_strain", "max_strain_p99", "max_displacement_mm",
                                                      "tau_turn_median_deg", "tau_turn_p90_deg") if k in r.figures})
        for which in ("iso", "printed"):
            a = r.turn.get(f"layer_tau_{which}_deg")
            if a is not None and len(a):
                row[f"sr_satisfied_{which}"] = float(np.mean(a <= beta_deg))
        rows.append(row)
    return rows


def strength_rounds_table(rows: list[dict[str, Any]], beta_deg: float) -> str:
    """Markdown table of the strength rounds."""
    lines = [f"| round | max strain | 99th percentile | tau_max turned by the print (median / 90th pct) | layers within "
             f"{beta_deg:g}° of tau_max: isotropic / printed | collisions |", "| --- | --- | --- | --- | --- | --- |"]
    lines += [f"| {r['stage']} | {r['max_strain']:.4g} | {r['max_strain_p99']:.4g} | {r['tau_turn_median_deg']:.1f}° / "
              f"{r['tau_turn_p90_deg']:.1f}° | {100 * r.get('sr_satisfied_iso', 0):.1f} % / "
              f"{100 * r.get('sr_satisfied_printed', 0):.1f} % | {r['collisions']:,} |" for r in rows]
    return "\n".join(lines)


def draw_strength_figures(figs: Path, arrays: dict[str, np.ndarray], figures: dict[str, Any]) -> dict[str, str]:
    """The verified parts side by side: strain histograms, strain maps on one scale, filament-to-tau_max angles."""
    parts = figures.get("parts", [])
    labels = {p: figures.get(f"{p}.label", p) for p in parts}
    strains = {labels[p]: arrays[f"strain/{p}"] for p in parts}
    out = {}
    plot_strain_histogram(figs / "strain_histogram.png", strains)
    out["Strain of the printed parts (transversely isotropic FEA, filaments along each part's toolpaths)"] = \
        "figures/strain_histogram.png"
    plot_strain_maps(figs / "strain_maps.png", arrays["centres"], strains, float(figures.get("voxel_size_mm", 1.0)))
    out["Strain maps of the printed parts (one colour scale)"] = "figures/strain_maps.png"
    angles = {labels[p]: (arrays[f"angles/{p}"], arrays[f"angle_weights/{p}"]) for p in parts if f"angles/{p}" in arrays}
    if angles:
        plot_filament_angles(figs / "filament_angles.png", angles)
        out["Filaments against tau_max in the most stressed 10 % (red: within 20°)"] = "figures/filament_angles.png"
    return out


def strength_table(figures: dict[str, Any]) -> str:
    """Markdown table of the verified parts and what the filaments and the layers each earn."""
    lines = ["| part | max strain | 99th percentile | max displacement | filament length within 20° of tau_max "
             "(top 10 % stress) |", "| --- | --- | --- | --- | --- |"]
    for p in figures.get("parts", []):
        share = figures.get(f"{p}.aligned_fraction")
        lines.append(f"| {figures.get(f'{p}.label', p)} | {figures[f'{p}.max_strain']:.4g} | "
                     f"{figures[f'{p}.max_strain_p99']:.4g} | {figures[f'{p}.max_displacement_mm']:.4g} mm | "
                     f"{'-' if share is None else f'{100 * share:.1f} %'} |")
    gains = strain_gains(figures)
    if "gain.total.max_strain" in gains:
        def pct(key: str) -> str:
            """A gain as the signed change of strain."""
            return f"{-100 * gains[key]:+.1f} %".replace("-", "−")

        lines += ["", f"Against planar layers with zig-zag infill, the printed part's strain changes by "
                  f"{pct('gain.total.max_strain')} (max) and {pct('gain.total.max_strain_p99')} (99th percentile): "
                  f"the stress-following filaments on planar layers account for {pct('gain.filaments.max_strain')} / "
                  f"{pct('gain.filaments.max_strain_p99')}, the printed layers and their toolpaths against planar "
                  f"layers with the same infill for {pct('gain.layers.max_strain')} / {pct('gain.layers.max_strain_p99')}."]
    return "\n".join(lines)


def released(job: Job) -> Job:
    """The job, then the memory it freed handed back to the kernel (``release_freed_memory``): the export's jobs each
    make their arrays once, so the freed memory the command keeps for reuse would only add to the next job's peak."""

    def run() -> dict[str, str]:
        """Do the job, then release."""
        try:
            return job()
        finally:
            release_freed_memory()

    return run


class ExportJobs:
    """Independent jobs of the export (the report's figures, the toolpaths' CSV and VTP files), shared with a forked
    helper process (:class:`neuralslicer.forked.SharedJobs`, the longest first): it starts on them at once, this
    process joins in once it has written the rest (meshes, G-code, metrics); the figures come back in the jobs'
    order whoever drew them."""

    def __init__(self, jobs: list[tuple[float, Job]]) -> None:
        """Start the helper (where one can run) on ``jobs`` ((cost, job), in the report's order)."""
        self.shared = SharedJobs([released(job) for _, job in jobs], [cost for cost, _ in jobs])

    def finish(self) -> list[dict[str, str]]:
        """Do the jobs left here and wait for the helper's: each job's figures ({caption: path relative to the output
        folder}), in the jobs' order."""
        return list(self.shared.finish())


def export_rounds(d: Path, run: RunResults, alpha_deg: float, beta_deg: float
                  ) -> tuple[dict[int, tuple[float, Job]], dict[int, tuple[float, Job]]]:
    """The export's jobs (figures, CSV, preview, VTP into ``d``) by their place in the report, in two rounds: those
    to share at once and those once the toolpaths are read (none but for a stored print of at least
    :data:`TWO_ROUNDS_WAYPOINTS` waypoints, whose program's moves and toolpaths are never in memory at once: the
    preview, the CSV and the figures without waypoints first, then the VTP and the figures that draw them). In one
    round the program's moves and the toolpaths are read here, before the helper starts: shared with it."""
    jobs = [(cost, job, job.__name__ in TOOLPATH_FIGURES) for cost, job in figure_jobs(d / "figures", run, alpha_deg,
                                                                                       beta_deg)]
    # the CSV reads a stored print a block at a time: it needs no toolpaths in memory
    jobs.append((1.0, lambda: _quiet(write_waypoints_csv(d / "toolpaths" / "waypoints.csv", run.toolpaths)), False))
    preview = lambda: _quiet(write_run_preview(d / PREVIEW_FILE, run))                     # noqa: E731
    vtp = lambda: _quiet(write_toolpaths_vtp(d / "toolpaths.vtp", run.toolpaths))          # noqa: E731
    if not run.toolpaths.loaded and int(run.print_metrics.get("n_waypoints", 0)) >= TWO_ROUNDS_WAYPOINTS:
        jobs += [(1.0, preview, False), (0.7, vtp, True)]
        return ({i: (cost, job) for i, (cost, job, uses) in enumerate(jobs) if not uses},
                {i: (cost, job) for i, (cost, job, uses) in enumerate(jobs) if uses})
    run.program = run.program.read()
    run.toolpaths.load()
    # the preview and the VTP are the jobs that make per-move arrays: one job, so that they never run at once
    jobs.append((1.7, lambda: (preview(), release_freed_memory(), vtp())[-1], False))
    return {i: (cost, job) for i, (cost, job, _) in enumerate(jobs)}, {}


def write_outputs(out_dir: str | Path, run: RunResults, alpha_deg: float, beta_deg: float, robot: bool = False
                  ) -> dict[str, Any]:
    """Write model.ply, samples_B.ply, field.vtu, layers/, the print files, preview.html, figures, metrics.json and
    report.md to ``out_dir``; returns the metrics. The figures, the preview and the toolpaths' CSV and VTP are shared
    with a helper process (:class:`ExportJobs`) while this one writes the rest, a large stored print's in two rounds
    (:func:`export_rounds`)."""
    d = Path(out_dir)
    run.lpd_b, run.lpd_t  # noqa: B018 - the field's LPD at B and T, computed once for the metrics and the figures
    now, later = export_rounds(d, run, alpha_deg, beta_deg)
    release_freed_memory()   # what reading the run dropped (a first print's waypoints): not into the helper's share
    first = ExportJobs(list(now.values()))
    write_ply(d / "model.ply", run.surface)
    write_samples_ply(d / "samples_B.ply", run.samples)
    write_field_vtu(d / "field.vtu", run.field)
    write_layers(d / "layers", run.layers.meshes)
    write_print_outputs(d, run.toolpaths, run.program, run.print_metrics, robot=robot, png=False, gcode=run.gcode,
                        csv=False, vtp=False)
    release_freed_memory()
    metrics = run_metrics(run, alpha_deg, beta_deg)
    drawn = dict(zip(now, first.finish()))
    if later:
        run.toolpaths.load()   # read here, before the helper starts: shared with it, not read twice
        drawn.update(zip(later, ExportJobs(list(later.values())).finish()))
    figures = {caption: path for i in sorted(drawn) for caption, path in drawn[i].items()}
    sections = {}
    if run.verify is not None and run.verify[1].get("parts"):
        sections["Strength of the printed part"] = strength_table(run.verify[1])
    share = run.toolpaths.attrs.get("stress_infill_fraction")
    if share is not None:
        sections["Stress-following infill"] = (
            f"{100 * share:.1f} % of the infill length follows the in-layer principal stress of the load case; the rest, "
            "where it is below toolpath.stress_threshold of the reference stress, is zig-zag." if share > 0 else
            "No layer has a significant in-layer stress (below toolpath.stress_threshold of the reference stress "
            "everywhere, or a load case without stress): the infill is zig-zag throughout.")
    if run.strength_rounds:
        sections["Strength rounds"] = strength_rounds_table(strength_round_rows(run.strength_rounds, beta_deg), beta_deg)
    if run.attempts:
        rows = collision_resolution(run.samples, run.attempts, alpha_deg)
        for i, row in enumerate(rows):
            metrics.update({f"collision_resolution.{i}.{k}": v for k, v in row.items()})
        sections["Collision resolution"] = collision_table(rows, alpha_deg)
    if metrics.get("tilt.n_waypoints_tilted"):
        sections["Tool axis tilted at stray collisions"] = (
            f"{metrics['tilt.n_collisions_before']:,} waypoints of the printed field collided; tilting the tool axis away "
            f"from the LPD by at most {metrics['tilt.max_tilt_deg']:g}° (ramped along the path, "
            f"{metrics['tilt.n_waypoints_tilted']:,} waypoints turned) cleared {metrics['tilt.n_collisions_cleared']:,} "
            f"of them; {metrics['n_collisions']:,} remain. The layers are the field's own.")
    beads = run.print_metrics.get("beads")
    if beads:
        lo, hi = beads["thickness_range_mm"]
        sections["Beads"] = (
            f"{100 * beads['fraction_outside_range']:.2f} % of the {beads['n_extruding']:,} printing waypoints have a gap to "
            f"the layer below outside the nozzle's bead range [{lo:g}, {hi:g}] mm ({100 * beads['fraction_thin']:.2f} % "
            f"thinner, {100 * beads['fraction_thick']:.2f} % thicker). {beads['n_skipped']:,} thin beads were not extruded and "
            f"their gap went to the bead above ({beads['n_carried']:,} beads carry one); {beads['n_capped']:,} thick gaps "
            "were printed at the largest bead.")
    reach = run.print_metrics.get("axis_reach") or {}
    if reach.get("n_clamped"):
        sections["Tool axes turned into the machine's reach"] = (
            f"{reach['n_clamped']:,} waypoints needed a tool axis beyond the machine's B range; it was turned back onto "
            f"the limit (largest turn {reach['max_clamp_deg']:.1f}°, {reach.get('n_beyond_tilt_bound', 0):,} by more than "
            "the collision tilt bound), so the bead there leaves the field's print direction by that angle.")
    turned = run.print_metrics.get("axis_platform") or {}
    if turned.get("n_clamped") or turned.get("n_unreachable"):
        sections["Tool axes turned up at the platform"] = (
            f"{turned['n_clamped']:,} waypoints near the platform had a tool axis tilted so far that the head dipped below "
            f"the platform; it was turned up toward +z just enough to clear it (largest turn {turned['max_clamp_deg']:.1f}°, "
            f"at most the collision tilt bound), so the bead there leaves the field's print direction by that angle. "
            f"{turned['n_unreachable']:,} needed more and are left to the collision check.")
    write_json_atomic(d / "metrics.json", metrics)
    write_text_atomic(d / "report.md", markdown_report(f"Neural Slicer report: {run.model}", metrics, figures, sections))
    return json.loads(json.dumps(metrics, default=float))


def write_run_preview(path: Path, run: RunResults) -> PreviewData:
    """``preview.html`` of the run's program (beside print.gcode): its moves by forward kinematics, bead widths and
    the printed program's collisions; the decimated moves it draws."""
    return write_preview(path, run.program.read(), run.toolpaths.column("width"), run.collided, run.model,
                         run.print_metrics)


def _quiet(_: Any) -> dict[str, str]:
    """No figure: what a job that writes a file returns."""
    return {}


def write_print_outputs(out_dir: str | Path, tp: Toolpaths, program: ProgramMoves, metrics: dict | None = None,
                        *, robot: bool = False, vtp: bool = True, png: bool = True,
                        gcode: bytes | Iterable[bytes] | None = None,
                        csv: bool = True) -> dict[str, Path]:
    """Write ``toolpaths/waypoints.csv`` (if ``csv``), ``print.gcode``, ``toolpaths.vtp``, ``toolpaths.png``,
    ``robot_waypoints.csv``/``.json`` and compas_slicer's ``printpoints.json`` (if ``robot``) and
    ``print_metrics.json`` under ``out_dir``."""
    out = Path(out_dir)
    files = {"waypoints_csv": write_waypoints_csv(out / "toolpaths" / "waypoints.csv", tp)} if csv else {}
    if gcode is None and not isinstance(program, MachineProgram):
        raise TypeError("write_print_outputs: the G-code or the whole MachineProgram is needed to write print.gcode")
    files["gcode"] = write_gcode(out / "print.gcode", program if gcode is None else gcode)
    if vtp:
        files["vtp"] = write_toolpaths_vtp(out / "toolpaths.vtp", tp)
    if png:
        files["png"] = plot_toolpaths_png(out / "toolpaths.png", tp)
    if robot:
        d = program.profile.extrusion.filament_diameter
        files["robot_csv"] = write_robot_csv(out / "robot_waypoints.csv", tp, d, profile=program.profile)
        files["robot_json"] = write_robot_json(out / "robot_waypoints.json", tp, d, profile=program.profile)
        files["printpoints"] = write_printpoints_json(out / "printpoints.json", tp, program.profile)
    if metrics is not None:
        p = out / "print_metrics.json"
        write_text_atomic(p, json.dumps(metrics, indent=2, default=float))
        files["metrics"] = p
    return files
