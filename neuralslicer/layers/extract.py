"""The paper's layer step: isovalues for the thickness range, isosurfaces of G trimmed by H, in print order."""
from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass, field
from typing import TYPE_CHECKING

import numpy as np
from pydantic import BaseModel, ConfigDict, Field

from neuralslicer.cage import interior_points
from neuralslicer.errors import InputError
from neuralslicer.forked import shared_map
from neuralslicer.layers.marching import marching_batch, tet_edges
from neuralslicer.layers.trim import trim
from neuralslicer.model.solid import Solid
from neuralslicer.scalar_field import ScalarField

if TYPE_CHECKING:  # trimesh (and scipy.spatial, networkx) only where a mesh is made: not on a cached rerun
    import trimesh


class LayerConfig(BaseModel):
    """How layers are chosen and trimmed."""

    model_config = ConfigDict(extra="forbid")

    layer_height: float = Field(0.8, gt=0, description="target layer thickness, mm")
    t_min: float = Field(0.4, gt=0, description="smallest acceptable local thickness, mm")
    t_max: float = Field(1.0, gt=0, description="largest acceptable local thickness, mm")
    min_area: float = Field(0.5, ge=0, description="connected layer pieces smaller than this (mm^2) are dropped")
    trim_iterations: int = Field(30, ge=1, description="bisection steps that put trimmed edges on H = 0")
    trim_tolerance: float = Field(5e-4, gt=0, description="how far (mm) a layer triangle may leave the solid")
    trim_rounds: int = Field(12, ge=0, description="rounds of refinement of the triangles that leave the solid")
    thickness_samples: int = Field(20_000, ge=100, description="interior points used to measure layer thickness")
    max_layers: int = Field(
        5000, ge=1, description="more isovalues than this is an error that names the cause (a field gone flat, "
        "or a unit mistake), not hours of layer extraction")
    low_gradient_fraction: float = Field(
        0.05, ge=0, lt=1,
        description="interior points whose |grad G| is below this multiple of the median are low-gradient: "
        "they do not shrink the layer spacing of the whole slab (one point at |grad G| = 1e-4 would multiply "
        "the layer count); they are reported, and the toolpaths cap their bead thickness locally")


@dataclass
class Layers:
    """Layers in print order: one triangle mesh each (faces oriented along +grad G), with their isovalues."""

    meshes: list[trimesh.Trimesh]
    isovalues: np.ndarray
    report: dict = field(default_factory=dict)

    def to_arrays(self) -> tuple[dict[str, np.ndarray], dict]:
        """Concatenated vertices/faces/lpd with per-layer offsets, for the store."""
        nv = np.cumsum([0] + [len(m.vertices) for m in self.meshes])
        nf = np.cumsum([0] + [len(m.faces) for m in self.meshes])
        empty3 = np.zeros((0, 3))
        arrays = {
            "vertices": np.concatenate([m.vertices for m in self.meshes]) if self.meshes else empty3,
            "faces": np.concatenate([m.faces for m in self.meshes]).astype(np.int64) if self.meshes else empty3.astype(np.int64),
            "lpd": np.concatenate([m.vertex_attributes["lpd"] for m in self.meshes]) if self.meshes else empty3,
            "vertex_offsets": nv.astype(np.int64),
            "face_offsets": nf.astype(np.int64),
            "isovalues": np.asarray(self.isovalues, dtype=np.float64),
        }
        return arrays, {"n_layers": len(self.meshes), "report": self.report}

    @classmethod
    def from_arrays(cls, arrays: dict[str, np.ndarray], attrs: dict) -> Layers:
        """Rebuild from store arrays."""
        import trimesh

        nv, nf = arrays["vertex_offsets"], arrays["face_offsets"]
        meshes = []
        for i, iso in enumerate(arrays["isovalues"]):
            m = trimesh.Trimesh(arrays["vertices"][nv[i] : nv[i + 1]], arrays["faces"][nf[i] : nf[i + 1]], process=False)
            m.vertex_attributes["lpd"] = arrays["lpd"][nv[i] : nv[i + 1]]
            m.metadata["isovalue"] = float(iso)
            meshes.append(m)
        return cls(meshes, arrays["isovalues"], attrs.get("report", {}))


def _step(gn_slab: np.ndarray, height: float, config: LayerConfig) -> float:
    """Isovalue step for a slab: ``height`` at the slab's median |grad G|, kept in [t_min, t_max] where it can be."""
    dg = height * float(np.median(gn_slab))
    dg = max(dg, config.t_min * float(gn_slab.max()))
    return max(min(dg, config.t_max * float(gn_slab.min())), 1e-12)


def choose_isovalues(
    g_points: np.ndarray, grad_norm: np.ndarray, config: LayerConfig
) -> tuple[np.ndarray, dict]:
    """Isovalues so that the local thickness dG/|grad G| at interior points stays in [t_min, t_max] as far as possible.

    Low-gradient points (|grad G| below ``low_gradient_fraction`` x the median) do not limit the step; the
    first slab (from the lowest point to the first isovalue: the first layer's thickness) counts in the
    statistics like any other, and the material above the last isovalue is reported as ``top_gap_max``.
    """
    order = np.argsort(g_points)
    g, gn = g_points[order], grad_norm[order]
    lo, hi = float(g[0]), float(g[-1])
    low = gn < config.low_gradient_fraction * float(np.median(gn))
    g_ok, gn_ok = (g[~low], gn[~low]) if (~low).any() else (g, gn)
    reach = 2 * config.t_max * float(gn_ok.max())

    def slab(c: float) -> np.ndarray:
        i0, i1 = np.searchsorted(g_ok, [c, c + reach])
        return gn_ok[i0:max(i1, i0 + 1)] if i0 < len(g_ok) else gn_ok[-1:]

    isos = [lo + _step(slab(lo), 0.5 * config.layer_height, config)]
    while isos[-1] < hi:
        if len(isos) > config.max_layers:
            raise InputError("layers", f"the field needs more than {config.max_layers:,} layers between G = {lo:.4g} "
                             f"and {hi:.4g} (median |grad G| {float(np.median(gn)):.3g}, smallest {float(gn_ok.min()):.3g}); "
                             "the field is nearly flat somewhere or the model's unit is wrong (raise layers.max_layers "
                             "if it is meant)")
        isos.append(isos[-1] + _step(slab(isos[-1]), config.layer_height, config))
    isos = np.asarray(isos[:-1] if len(isos) > 1 and isos[-1] >= hi else isos)
    # thickness of the slab each interior point lies in
    slab_id = np.searchsorted(isos, g)
    edges = np.concatenate([[lo], isos, [hi]])
    thick_all = (edges[slab_id + 1] - edges[slab_id]) / gn
    printed = slab_id < len(isos)                       # below the last isovalue: printed by some layer
    thick = thick_all[printed & ~low] if (printed & ~low).any() else thick_all
    report = {
        "thickness_min": float(thick.min()),
        "thickness_median": float(np.median(thick)),
        "thickness_max": float(thick.max()),
        "fraction_outside_range": float(np.mean((thick < config.t_min - 1e-9) | (thick > config.t_max + 1e-9))),
        "low_gradient_fraction": float(low.mean()),
        "low_gradient_thickness_max": float(thick_all[low & printed].max(initial=0.0)),
        "top_gap_max": float(thick_all[~printed].max(initial=0.0)),
    }
    return isos, report


def extract_layers(
    cage_vertices: np.ndarray,
    cage_tets: np.ndarray,
    G: np.ndarray,
    lpd: np.ndarray,
    H: Callable[[np.ndarray], np.ndarray],
    isovalues: np.ndarray,
    config: LayerConfig,
    progress: Callable[[int, int], None] | None = None,
    batch: int = 64,
) -> Layers:
    """Isosurfaces of G at the isovalues, trimmed by H <= 0, small pieces dropped, in print order.

    Layers are trimmed in batches (one H evaluation per batch and crossing iteration, not per layer); the batches,
    independent of each other, are shared with a forked helper process (:func:`neuralslicer.forked.shared_map`).
    """
    edges, tet_edge = tet_edges(cage_tets)
    meshes, kept_iso = [], []
    dropped_pieces, dropped_area = 0, 0.0

    def trimmed(isos: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
        """One batch: its isosurfaces trimmed, (points, faces, source tet and layer in the batch per face)."""
        parts = marching_batch(cage_vertices, cage_tets, G, isos, lpd, edges, tet_edge)
        offsets = np.cumsum([0] + [len(p) for p, _, _ in parts])
        pts = np.concatenate([p for p, _, _ in parts])
        faces = np.concatenate([f + o for (_, f, _), o in zip(parts, offsets)]).astype(np.int64)
        src_tet = np.concatenate([t for _, _, t in parts])
        face_layer = np.concatenate([np.full(len(f), i) for i, (_, f, _) in enumerate(parts)])
        if len(faces):
            pts, faces, src = trim(pts, faces, H, config.trim_iterations, config.trim_rounds, config.trim_tolerance)
            src_tet, face_layer = src_tet[src], face_layer[src]
        return pts, faces, src_tet, face_layer

    starts = range(0, len(isovalues), batch)
    batches = [np.asarray(isovalues[start : start + batch]) for start in starts]
    done = shared_map([lambda isos=isos: trimmed(isos) for isos in batches], [float(len(b)) for b in batches])
    for start, isos, (pts, faces, src_tet, face_layer) in zip(starts, batches, done):
        for i, iso in enumerate(isos):
            mesh, n_drop, a_drop = _layer_mesh(pts, faces[face_layer == i], lpd[src_tet[face_layer == i]], config.min_area)
            dropped_pieces += n_drop
            dropped_area += a_drop
            if mesh is not None:
                mesh.metadata["isovalue"] = float(iso)
                meshes.append(mesh)
                kept_iso.append(float(iso))
        if progress is not None:
            progress(min(start + batch, len(isovalues)), len(isovalues))
    report = {"dropped_pieces": int(dropped_pieces), "dropped_area_mm2": float(dropped_area)}
    return Layers(meshes, np.asarray(kept_iso), report)


def _layer_mesh(
    pts: np.ndarray, faces: np.ndarray, face_lpd: np.ndarray, min_area: float
) -> tuple[trimesh.Trimesh | None, int, float]:
    """One layer's mesh with per-vertex LPD (area-weighted), small pieces dropped; None when nothing is left."""
    import trimesh

    if len(faces) == 0:
        return None, 0, 0.0
    used, inv = np.unique(faces, return_inverse=True)
    mesh = trimesh.Trimesh(pts[used], inv.reshape(-1, 3), process=False)
    vlpd = np.zeros((len(used), 3))
    np.add.at(vlpd, mesh.faces.ravel(), np.repeat(face_lpd * mesh.area_faces[:, None], 3, axis=0))
    vlpd /= np.maximum(np.linalg.norm(vlpd, axis=1, keepdims=True), 1e-300)
    mesh.vertex_attributes["lpd"] = vlpd
    mesh, n_drop, a_drop = _drop_small_pieces(mesh, min_area)
    return (mesh if len(mesh.faces) else None), n_drop, a_drop


def _drop_small_pieces(mesh: trimesh.Trimesh, min_area: float) -> tuple[trimesh.Trimesh, int, float]:
    """Remove connected pieces whose area is below min_area."""
    import trimesh

    if min_area <= 0 or len(mesh.faces) == 0:
        return mesh, 0, 0.0
    labels = trimesh.graph.connected_component_labels(mesh.face_adjacency, node_count=len(mesh.faces))
    area = np.bincount(labels, weights=mesh.area_faces)
    small = area < min_area
    if not small.any():
        return mesh, 0, 0.0
    keep = ~small[labels]
    lpd = mesh.vertex_attributes["lpd"]
    faces = mesh.faces[keep]
    used, inv = np.unique(faces, return_inverse=True)
    out = trimesh.Trimesh(mesh.vertices[used], inv.reshape(-1, 3), process=False)
    out.vertex_attributes["lpd"] = lpd[used]
    return out, int(small.sum()), float(area[small].sum())


def slice_layers(solid: Solid, field: ScalarField, config: LayerConfig,
                 progress: Callable[[int, int], None] | None = None) -> Layers:
    """The layer step: isovalues from the local thickness at interior points of the solid, isosurfaces of
    G trimmed by H <= 0 in print order, and the thickness report; ``progress(done, total)`` per batch."""
    inside = interior_points(solid.H, solid.bounds, config.thickness_samples, seed=1)
    g, _, gn = field.sample(inside)
    ok = np.isfinite(g)
    isovalues, thickness = choose_isovalues(g[ok], gn[ok], config)
    layers = extract_layers(field.cage_vertices, field.cage_tets, field.G, field.lpd(), solid.H, isovalues, config,
                            progress=progress)
    layers.report.update(thickness)
    return layers
