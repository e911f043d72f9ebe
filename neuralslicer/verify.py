"""Anisotropic verification of printed layers: strain of the part with a per-voxel printed material.

Each voxel gets the transversely isotropic material of ``FEASpec.anisotropic`` with material axes
``e1`` = toolpath tangent (stiff ``Y1``), ``e2`` = LPD ``d_p`` (layer normal, weak ``Y2``) and
``e3 = e1 x e2`` (weak ``Y3 = Y2``).  When no toolpath tangent is given, the tangent is the
isotropic ``tau_max`` projected onto the layer plane (filaments laid along the largest principal
stress, as far as the layer allows); where that projection is degenerate (``tau_max`` within ~0.06°
of ``d_p``, or no stress) the projection of the x axis is used, and of the y axis if that too is
degenerate.
"""
from __future__ import annotations

from typing import Any, Callable

import numpy as np
from scipy.spatial import cKDTree

from neuralslicer.errors import InputError
from neuralslicer.fea.element import rotate_D, transversely_isotropic_D
from neuralslicer.fea.grid import SolidLike, voxelize
from neuralslicer.fea.samples import stress_field, top_stress_indices
from neuralslicer.fea.solver import FEAResult, PrintedFEA, run_fea, solve_on_grid
from neuralslicer.fea.spec import FEASpec
from neuralslicer.layers import LayerConfig, slice_layers
from neuralslicer.metrics import strength_angles
from neuralslicer.model.solid import Solid
from neuralslicer.scalar_field import ScalarField
from neuralslicer.toolpath.config import ToolpathConfig
from neuralslicer.toolpath.generate import toolpaths as make_toolpaths
from neuralslicer.toolpath.types import Toolpaths

DirectionField = Callable[[np.ndarray], np.ndarray]


def _unit(v: np.ndarray, what: str) -> np.ndarray:
    """Normalise rows of v (n, 3); a zero or non-finite row is an input error."""
    v = np.asarray(v, dtype=np.float64).reshape(-1, 3)
    nrm = np.linalg.norm(v, axis=1)
    if not np.all(np.isfinite(nrm)) or np.any(nrm < 1e-12):
        raise InputError(what, "direction field is zero or not finite at some voxel centres")
    return v / nrm[:, None]


def _project(v: np.ndarray, d: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Projection of v onto the planes normal to d (both (n, 3)), and its norm (n,)."""
    p = v - np.sum(v * d, axis=1, keepdims=True) * d
    return p, np.linalg.norm(p, axis=1)


def material_frames(lpd: np.ndarray, tangent: np.ndarray) -> np.ndarray:
    """Frames R (n, 3, 3), columns (tangent, LPD, tangent x LPD), from LPD and tangent (n, 3).

    The tangent is projected onto the layer plane; where it is (nearly) along the LPD the x axis,
    then the y axis, projected, is used instead.
    """
    d = _unit(lpd, "lpd_at")
    t, nt = _project(np.asarray(tangent, dtype=np.float64).reshape(-1, 3), d)
    for axis in (0, 1):
        bad = nt < 1e-3 * np.maximum(1.0, np.linalg.norm(tangent, axis=1))
        if not bad.any():
            break
        e = np.zeros((int(bad.sum()), 3))
        e[:, axis] = 1.0
        t[bad], nt[bad] = _project(e, d[bad])
    t = t / np.maximum(nt, 1e-300)[:, None]
    return np.stack([t, d, np.cross(t, d)], axis=2)


def verify_layers(solid: SolidLike, fea_spec: FEASpec, lpd_at: DirectionField,
                  tangent_at: DirectionField | None = None,
                  reference: FEAResult | None = None) -> dict[str, Any]:
    """Anisotropic FEA with the material frames of printed layers; returns the strain measures.

    lpd_at : points (n, 3) -> (n, 3) LPD (layer normal, need not be unit).
    tangent_at : points (n, 3) -> (n, 3) toolpath tangent, or None for the projected isotropic
    ``tau_max`` (from ``reference`` if given, else computed).
    Returns ``max_strain`` (largest |principal strain| over voxels), ``max_strain_p99`` (its 99th
    percentile), ``strain`` (n,) per-voxel largest |principal strain|, ``von_mises_strain`` (n,),
    ``max_displacement_mm``, ``centres`` (n, 3) and the anisotropic ``result`` (FEAResult).
    """
    if tangent_at is None and reference is None:
        reference = run_fea(solid, fea_spec)
    grid = reference.grid if reference is not None else voxelize(solid, fea_spec.voxels)
    centres = grid.centres
    lpd = _unit(lpd_at(centres), "lpd_at")
    if tangent_at is not None:
        tangent = np.asarray(tangent_at(centres), dtype=np.float64).reshape(-1, 3)
        tangent_rule = "given"
    else:
        tangent = reference.tau_max
        tangent_rule = "tau_max projected onto the layer plane"
    a = fea_spec.anisotropic
    Dm = transversely_isotropic_D(a.y1_mpa, a.y2_mpa, a.nu12, a.nu23, a.shear_12)
    D = rotate_D(Dm, material_frames(lpd, tangent))
    res = solve_on_grid(grid, fea_spec, float(solid.platform_z), D=D)
    res.info["material"] = a.model_dump()
    res.info["tangent"] = tangent_rule
    e = np.linalg.eigvalsh(res.strain)
    strain = np.abs(e).max(axis=1)
    ed = res.strain - np.trace(res.strain, axis1=1, axis2=2)[:, None, None] * np.eye(3) / 3.0
    vm_strain = np.sqrt(2.0 / 3.0 * np.sum(ed * ed, axis=(1, 2)))
    return {"max_strain": float(strain.max()),
            "max_strain_p99": float(np.percentile(strain, 99)),
            "strain": strain, "von_mises_strain": vm_strain,
            "max_displacement_mm": float(np.linalg.norm(res.displacement, axis=1).max()),
            "centres": res.grid.centres, "tangent": tangent_rule, "result": res}


def printed_tangents(tp: Toolpaths) -> DirectionField:
    """``tangent_at`` for :func:`verify_layers`: the direction of the printed (extruding) move whose midpoint
    is nearest each point, so the stiff material axis is the filament actually laid there."""
    ext = np.flatnonzero(tp.extrude[1:]) + 1
    d = tp.xyz[ext] - tp.xyz[ext - 1]
    keep = np.linalg.norm(d, axis=1) > 1e-9
    ext, d = ext[keep], d[keep]
    if not len(ext):
        raise InputError("toolpaths", "no printed move to take the filament directions from")
    tree = cKDTree(0.5 * (tp.xyz[ext] + tp.xyz[ext - 1]))

    def tangent_at(points: np.ndarray) -> np.ndarray:
        """Direction (n, 3) of the nearest printed move."""
        return d[tree.query(np.asarray(points, np.float64).reshape(-1, 3))[1]]

    return tangent_at


def filament_alignment(tp: Toolpaths, reference: FEAResult, top_fraction: float = 0.10, band_deg: float = 20.0
                       ) -> dict[str, Any]:
    """How the printed filaments lie against the load: for every printing move whose midpoint is in a voxel of the
    top ``top_fraction`` of |max principal stress| (the region of T), the angle between the move and tau_max
    projected onto the layer (the plane normal to the tool axis); 90° where tau_max crosses the layer (its
    projection shorter than 1e-3). Returns ``angles_deg`` (k,), ``lengths`` (k,) mm and ``aligned_fraction``: the
    share of that filament length within ``band_deg`` of the projected tau_max."""
    ext = np.flatnonzero(tp.extrude[1:]) + 1
    move = tp.xyz[ext] - tp.xyz[ext - 1]
    length = np.linalg.norm(move, axis=1)
    ok = length > 1e-9
    ext, move, length = ext[ok], move[ok] / length[ok, None], length[ok]
    mid = 0.5 * (tp.xyz[ext] + tp.xyz[ext - 1])
    top = np.zeros(reference.grid.n_voxels, bool)
    top[top_stress_indices(reference, top_fraction)] = True
    dist, vox = cKDTree(reference.grid.centres).query(mid, distance_upper_bound=reference.grid.spacing)
    inside = np.isfinite(dist)
    inside[inside] = top[vox[inside]]
    normal = tp.axis[ext[inside]] + tp.axis[ext[inside] - 1]
    normal /= np.maximum(np.linalg.norm(normal, axis=1, keepdims=True), 1e-300)
    tau, _ = _project(reference.tau_max[vox[inside]], normal)
    norm = np.linalg.norm(tau, axis=1)
    cos = np.abs(np.einsum("ij,ij->i", move[inside], tau)) / np.maximum(norm, 1e-300)
    angles = np.where(norm > 1e-3, np.degrees(np.arccos(np.clip(cos, 0.0, 1.0))), 90.0)
    w = length[inside]
    share = float(w[angles <= band_deg].sum() / w.sum()) if w.sum() > 0 else 0.0
    return {"angles_deg": angles, "lengths": w, "aligned_fraction": share}


#: the parts --verify prints side by side: planar layers with today's zig-zag infill (what people print now),
#: planar layers with stress-following infill (the best planar can do) and the program printed from the field
PARTS = {"planar_zigzag": "planar layers + zig-zag infill", "planar_stress": "planar layers + stress-following infill",
         "printed": "the printed program"}
#: the figures of every part (``<part>.<figure>`` in verify's attributes, ``fea.<part>.<figure>`` in metrics.json)
PART_FIGURES = ("max_strain", "max_strain_p99", "max_displacement_mm", "aligned_fraction")


def _planar_lpd(points: np.ndarray) -> np.ndarray:
    """+z everywhere (planar layers)."""
    return np.tile([0.0, 0.0, 1.0], (len(points), 1))


def _field_lpd(field: ScalarField) -> DirectionField:
    """The LPD of a field, +z outside its cage."""

    def lpd_at(points: np.ndarray) -> np.ndarray:
        """LPD of the field, +z outside the cage."""
        d = field.sample(points)[1]
        d[~np.all(np.isfinite(d), axis=1)] = [0.0, 0.0, 1.0]
        return d

    return lpd_at


def _part(solid: SolidLike, fea_spec: FEASpec, lpd_at: DirectionField, tp: Toolpaths | None, reference: FEAResult
          ) -> tuple[dict[str, np.ndarray], dict[str, Any]]:
    """One part's strain (filaments along ``tp``, or ideal without) and filament alignment: arrays, figures."""
    out = verify_layers(solid, fea_spec, lpd_at, tangent_at=None if tp is None else printed_tangents(tp),
                        reference=reference)
    figures = {k: out[k] for k in ("max_strain", "max_strain_p99", "max_displacement_mm")}
    arrays = {"strain": out["strain"]}
    if tp is not None:
        align = filament_alignment(tp, reference, fea_spec.top_fraction)
        figures["aligned_fraction"] = align["aligned_fraction"]
        arrays.update(angles=align["angles_deg"], angle_weights=align["lengths"])
    figures["tangent"] = "printed toolpaths" if tp is not None else "ideal: tau_max projected onto the layer"
    return arrays, figures


def _collect(parts: dict[str, tuple[dict[str, np.ndarray], dict[str, Any]]], labels: dict[str, str],
             reference: FEAResult) -> tuple[dict[str, np.ndarray], dict[str, Any]]:
    """The parts' arrays under ``<array>/<part>`` and figures under ``<part>.<figure>``, with the gains."""
    arrays: dict[str, np.ndarray] = {"centres": reference.grid.centres}
    figures: dict[str, Any] = {"parts": list(parts), "voxel_size_mm": float(reference.grid.spacing)}
    for name, (a, f) in parts.items():
        arrays.update({f"{k}/{name}": v for k, v in a.items()})
        figures.update({f"{name}.{k}": v for k, v in f.items()})
        figures[f"{name}.label"] = labels[name]
    figures.update(strain_gains(figures))
    return arrays, figures


def strain_gains(figures: dict[str, Any]) -> dict[str, float]:
    """Relative strain reductions (max and 99th percentile): ``gain.filaments`` (planar + stress infill against
    planar + zig-zag), ``gain.layers`` (the printed part against planar + stress infill) and ``gain.total`` (the
    printed part against planar + zig-zag), where the parts are there."""
    out = {}
    for gain, (part, base) in {"filaments": ("planar_stress", "planar_zigzag"), "layers": ("printed", "planar_stress"),
                               "total": ("printed", "planar_zigzag")}.items():
        for fig in ("max_strain", "max_strain_p99"):
            a, b = figures.get(f"{part}.{fig}"), figures.get(f"{base}.{fig}")
            if a is not None and b:
                out[f"gain.{gain}.{fig}"] = 1.0 - a / b
    return out


def verify_field(solid: SolidLike, fea_spec: FEASpec, field: ScalarField, reference: FEAResult | None = None
                 ) -> tuple[dict[str, np.ndarray], dict[str, Any]]:
    """The best case (``verify_tangents: ideal``): planar layers and the layers of ``field`` (its LPD; planar where a
    voxel centre lies outside the cage), both with filaments along tau_max projected onto the layer."""
    reference = reference if reference is not None else run_fea(solid, fea_spec)
    parts = {"planar": _part(solid, fea_spec, _planar_lpd, None, reference),
             "printed": _part(solid, fea_spec, _field_lpd(field), None, reference)}
    labels = {"planar": "planar layers, ideal filaments", "printed": "the field's layers, ideal filaments"}
    return _collect(parts, labels, reference)


def verify_print(solid: Solid, fea_spec: FEASpec, field: ScalarField, toolpaths: Toolpaths,
                 layer_config: LayerConfig | None = None, toolpath_config: ToolpathConfig | None = None,
                 reference: FEAResult | None = None) -> tuple[dict[str, np.ndarray], dict[str, Any]]:
    """Three printed parts of one model through one anisotropic FEA (:data:`PARTS`): planar layers with zig-zag and with
    stress-following infill, made here with the print's layer and toolpath settings, and the program printed from
    ``field`` (``toolpaths``); filaments along each part's own toolpaths."""
    reference = reference if reference is not None else run_fea(solid, fea_spec)
    lc = layer_config or LayerConfig()
    cfg = toolpath_config or ToolpathConfig()
    flat = slice_layers(solid, field.blend(1.0), lc)
    stress = stress_field(reference, fea_spec.top_fraction)
    planar = {infill: make_toolpaths(flat.meshes, platform_z=solid.platform_z, t_max=lc.t_max,
                                     config=cfg.model_copy(update={"infill": infill}),
                                     stress=stress if infill == "stress" else None) for infill in ("zigzag", "stress")}
    parts = {"planar_zigzag": _part(solid, fea_spec, _planar_lpd, planar["zigzag"], reference),
             "planar_stress": _part(solid, fea_spec, _planar_lpd, planar["stress"], reference),
             "printed": _part(solid, fea_spec, _field_lpd(field), toolpaths, reference)}
    infill = (toolpaths.attrs.get("config") or {}).get("infill", "zigzag")
    labels = {**PARTS, "printed": f"the printed program ({infill} infill)"}
    arrays, figures = _collect(parts, labels, reference)
    return arrays, {**figures, "n_planar_layers": len(flat.meshes),
                    "n_planar_waypoints": {k: len(v) for k, v in planar.items()}}


def printed_fea(solid: SolidLike, fea_spec: FEASpec, field: ScalarField, toolpaths: Toolpaths,
                reference: FEAResult) -> dict[str, Any]:
    """The anisotropic FEA of the part printed with ``toolpaths`` on the layers of ``field`` (``verify_layers`` with
    the printed filaments): its stress is where the load goes in the printed part, the stress a strength round
    re-optimises against, and its strain is the print's."""
    return verify_layers(solid, fea_spec, _field_lpd(field), tangent_at=printed_tangents(toolpaths), reference=reference)


def printed_fea_of(solid: SolidLike, fea_spec: FEASpec, field: ScalarField, toolpaths: Toolpaths,
                   reference: FEAResult) -> PrintedFEA:
    """The FEA of the printed part (:func:`printed_fea`) with how far tau_max turned (:func:`stress_turn`) and the
    print's strain figures: what the store keeps of it, and what a strength round samples its T from."""
    printed = printed_fea(solid, fea_spec, field, toolpaths, reference)
    result = printed["result"]
    turn = stress_turn(reference, result, field, fea_spec.top_fraction)
    figures = {k: float(printed[k]) for k in ("max_strain", "max_strain_p99", "max_displacement_mm")}
    figures.update(tau_turn_median_deg=float(np.median(turn["tau_turn_deg"])),
                   tau_turn_p90_deg=float(np.percentile(turn["tau_turn_deg"], 90)))
    return PrintedFEA.of(result, figures, turn)


def stress_turn(reference: FEAResult, printed: FEAResult, field: ScalarField, top_fraction: float = 0.10
                ) -> dict[str, np.ndarray]:
    """How the printed material turned tau_max, at the voxels of the isotropic FEA's top ``top_fraction`` (its T):
    ``tau_turn_deg`` the angle between the isotropic and the printed part's tau_max, ``layer_tau_iso_deg`` and
    ``layer_tau_printed_deg`` the angle of the field's layers to each (the paper's Fig. 19: 0° is a layer along the
    stress, the SR goal)."""
    idx = top_stress_indices(reference, top_fraction)
    iso, aniso = reference.tau_max[idx], printed.tau_max[idx]
    lpd = _unit(_field_lpd(field)(reference.grid.centres[idx]), "lpd")
    return {"tau_turn_deg": np.degrees(np.arccos(np.clip(np.abs(np.sum(iso * aniso, axis=1)), 0.0, 1.0))),
            "layer_tau_iso_deg": strength_angles(iso, lpd), "layer_tau_printed_deg": strength_angles(aniso, lpd)}
