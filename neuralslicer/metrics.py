"""Quality figures of a field: support-free and strength satisfaction on the sample sets."""
from __future__ import annotations

import numpy as np


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
