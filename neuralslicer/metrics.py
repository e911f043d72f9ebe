"""Quality figures of a field: support-free and strength satisfaction on the sample sets."""
from __future__ import annotations

from typing import TYPE_CHECKING

import numpy as np
from scipy.spatial import cKDTree

if TYPE_CHECKING:
    import trimesh

    from neuralslicer.scalar_field import ScalarField


def support_angles(normals: np.ndarray, lpd: np.ndarray) -> np.ndarray:
    """Overhang angle in degrees, asin(-n·d): a point is an overhang where it exceeds alpha."""
    return np.degrees(np.arcsin(np.clip(-np.einsum("ij,ij->i", normals, lpd), -1.0, 1.0)))


def overhang_area_fraction(
    normals: np.ndarray, areas: np.ndarray, on_platform: np.ndarray, lpd: np.ndarray, alpha_deg: float = 45.0
) -> float:
    """Area fraction of the (non-platform) surface that overhangs: -n·d > sin(alpha)."""
    keep = ~on_platform & np.all(np.isfinite(lpd), axis=1)
    over = -np.einsum("ij,ij->i", normals[keep], lpd[keep]) > np.sin(np.radians(alpha_deg))
    total = areas[keep].sum()
    return float(areas[keep][over].sum() / total) if total > 0 else 0.0


def strength_angles(tau: np.ndarray, lpd: np.ndarray) -> np.ndarray:
    """Angle in degrees between the max principal stress direction and the layer, asin(|d·tau|)."""
    return np.degrees(np.arcsin(np.clip(np.abs(np.einsum("ij,ij->i", tau, lpd)), 0.0, 1.0)))


def strength_satisfaction(tau: np.ndarray, volumes: np.ndarray, lpd: np.ndarray, beta_deg: float = 10.0) -> float:
    """Volume fraction of the stress samples T whose max stress direction lies in the layer: |d·tau| <= sin(beta)."""
    ok = np.all(np.isfinite(lpd), axis=1)
    sat = np.abs(np.einsum("ij,ij->i", tau[ok], lpd[ok])) <= np.sin(np.radians(beta_deg))
    total = volumes[ok].sum()
    return float(volumes[ok][sat].sum() / total) if total > 0 else 0.0


def heldout_surface_samples(surface: trimesh.Trimesh, n: int, platform_z: float, seed: int = 1_000_003
                            ) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """A sample set the optimiser never saw: ``n`` area-uniform points on the model's surface mesh (not on the
    implicit solid B was drawn from), with their face normals, equal area weights and platform flags (on the
    platform plane within 1e-3 of the bounding-box diagonal, normal pointing down): (points, normals, areas,
    on_platform)."""
    import trimesh

    points, faces = trimesh.sample.sample_surface(surface, n, seed=seed)
    normals = np.asarray(surface.face_normals[faces], np.float64)
    tol = 1e-3 * float(np.linalg.norm(surface.extents))
    on_platform = (np.abs(points[:, 2] - platform_z) <= tol) & (normals[:, 2] < -0.9)
    return np.asarray(points, np.float64), normals, np.full(len(points), surface.area / max(n, 1)), on_platform


def layer_lpd_at(layers: list[trimesh.Trimesh], points: np.ndarray) -> np.ndarray:
    """The print direction the exported layers give at points (n, 3): the LPD (vertex normal) of the nearest
    layer vertex, unit."""
    verts = np.concatenate([np.asarray(m.vertices, np.float64) for m in layers])
    lpd = np.concatenate([np.asarray(m.vertex_attributes["lpd"], np.float64) for m in layers])
    d = lpd[cKDTree(verts).query(np.asarray(points, np.float64))[1]]
    return d / np.maximum(np.linalg.norm(d, axis=1, keepdims=True), 1e-300)


def field_agreement(fields: dict[str, ScalarField], points: np.ndarray) -> list[dict[str, float | str]]:
    """How alike fields are where it matters: for each pair, the angle between their print directions (LPD)
    at the points (median, 90th percentile, mean, degrees) and the Spearman rank correlation of their values
    (1: the same print order, -1: reversed); points outside either cage are left out."""
    from scipy.stats import spearmanr

    sampled = {name: f.sample(np.asarray(points, np.float64))[:2] for name, f in fields.items()}
    names = list(sampled)
    rows: list[dict[str, float | str]] = []
    for i, a in enumerate(names):
        for b in names[i + 1:]:
            (ga, da), (gb, db) = sampled[a], sampled[b]
            ok = np.isfinite(ga) & np.isfinite(gb) & np.all(np.isfinite(da), axis=1) & np.all(np.isfinite(db), axis=1)
            if ok.sum() < 3:
                continue
            ang = np.degrees(np.arccos(np.clip(np.einsum("ij,ij->i", da[ok], db[ok]), -1.0, 1.0)))
            rows.append({"a": a, "b": b, "n_points": int(ok.sum()), "lpd_angle_median_deg": float(np.median(ang)),
                         "lpd_angle_p90_deg": float(np.percentile(ang, 90)), "lpd_angle_mean_deg": float(ang.mean()),
                         "print_order_spearman": float(spearmanr(ga[ok], gb[ok]).statistic)})
    return rows
