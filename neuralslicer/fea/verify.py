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
from neuralslicer.fea.solver import FEAResult, run_fea, solve_on_grid
from neuralslicer.fea.spec import FEASpec
from neuralslicer.layers import LayerConfig, slice_layers
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


def verify_field(solid: SolidLike, fea_spec: FEASpec, field: ScalarField, reference: FEAResult | None = None,
                 toolpaths: Toolpaths | None = None, planar_toolpaths: Toolpaths | None = None
                 ) -> tuple[dict[str, np.ndarray], dict[str, Any]]:
    """Strain of the part printed with planar layers and with the layers of ``field`` (its LPD; planar
    where a voxel centre lies outside the cage): per-voxel strains and their maxima and 99th percentiles.

    With ``toolpaths`` (the program printed from the field) the curved part's stiff axis is the direction of
    the filament laid nearest each voxel, and with ``planar_toolpaths`` (toolpaths of planar layers on the same
    part) the planar part's; without, the ideal one, tau_max projected onto the layer (a best case).
    ``tangent`` / ``tangent_planar`` in the figures say which."""

    def lpd_at(points: np.ndarray) -> np.ndarray:
        """LPD of the field, +z outside the cage."""
        d = field.sample(points)[1]
        d[~np.all(np.isfinite(d), axis=1)] = [0.0, 0.0, 1.0]
        return d

    planar_tangent_at = printed_tangents(planar_toolpaths) if planar_toolpaths is not None else None
    planar = verify_layers(solid, fea_spec, lambda p: np.tile([0.0, 0.0, 1.0], (len(p), 1)),
                           tangent_at=planar_tangent_at, reference=reference)
    tangent_at = printed_tangents(toolpaths) if toolpaths is not None else None
    curved = verify_layers(solid, fea_spec, lpd_at, tangent_at=tangent_at, reference=reference)
    return {"strain_planar": planar["strain"], "strain": curved["strain"], "centres": curved["centres"]}, {
        "max_strain_planar": planar["max_strain"], "max_strain": curved["max_strain"],
        "max_strain_p99_planar": planar["max_strain_p99"], "max_strain_p99": curved["max_strain_p99"],
        "tangent": "printed toolpaths" if tangent_at is not None else "ideal: tau_max projected onto the layer",
        "tangent_planar": ("printed toolpaths" if planar_tangent_at is not None
                           else "ideal: tau_max projected onto the layer (best case for planar)"),
    }


def verify_print(solid: Solid, fea_spec: FEASpec, field: ScalarField, toolpaths: Toolpaths,
                 layer_config: LayerConfig | None = None, toolpath_config: ToolpathConfig | None = None,
                 reference: FEAResult | None = None) -> tuple[dict[str, np.ndarray], dict[str, Any]]:
    """:func:`verify_field` on what is printed: the computed layers' toolpaths, and toolpaths of planar layers
    of the same part made here with the same layer and toolpath settings (a like-for-like planar baseline)."""
    lc = layer_config or LayerConfig()
    flat = slice_layers(solid, field.blend(1.0), lc)
    planar = make_toolpaths(flat.meshes, platform_z=solid.platform_z, config=toolpath_config, t_max=lc.t_max)
    strains, figures = verify_field(solid, fea_spec, field, reference, toolpaths=toolpaths, planar_toolpaths=planar)
    return strains, {**figures, "n_planar_layers": len(flat.meshes), "n_planar_waypoints": len(planar)}
