"""Analytic solids (boxes, cylinders) for tests, benchmarks and examples of the FEA."""
from __future__ import annotations

import numpy as np


class BoxSolid:
    """Axis-aligned box ``lo <= x <= hi``; H = max of the signed slab distances (< 0 inside)."""

    def __init__(self, lo: tuple[float, float, float], hi: tuple[float, float, float],
                 platform_z: float | None = None) -> None:
        """Box between corners ``lo`` and ``hi`` (mm); platform at ``lo[2]`` unless given."""
        self.lo = np.asarray(lo, dtype=np.float64)
        self.hi = np.asarray(hi, dtype=np.float64)
        self.bounds = np.stack([self.lo, self.hi])
        self.platform_z = float(self.lo[2] if platform_z is None else platform_z)

    def H(self, x: np.ndarray) -> np.ndarray:
        """Signed value (n,) at points (n, 3)."""
        x = np.asarray(x, dtype=np.float64).reshape(-1, 3)
        return np.max(np.maximum(self.lo - x, x - self.hi), axis=1)


class CylinderSolid:
    """Cylinder of ``radius`` around the z axis through ``centre`` (x, y), ``z0 <= z <= z1``."""

    def __init__(self, radius: float, z0: float, z1: float,
                 centre: tuple[float, float] = (0.0, 0.0)) -> None:
        """Vertical cylinder (mm); platform at ``z0``."""
        self.radius, self.z0, self.z1 = float(radius), float(z0), float(z1)
        self.centre = np.asarray(centre, dtype=np.float64)
        c, r = self.centre, self.radius
        self.bounds = np.array([[c[0] - r, c[1] - r, z0], [c[0] + r, c[1] + r, z1]])
        self.platform_z = float(z0)

    def H(self, x: np.ndarray) -> np.ndarray:
        """Signed value (n,) at points (n, 3)."""
        x = np.asarray(x, dtype=np.float64).reshape(-1, 3)
        radial = np.linalg.norm(x[:, :2] - self.centre, axis=1) - self.radius
        return np.maximum(radial, np.maximum(self.z0 - x[:, 2], x[:, 2] - self.z1))


class UnionSolid:
    """Union (min of H) of solids, bounds the union of their bounds."""

    def __init__(self, *solids: object) -> None:
        """Union of the given solids; platform at the lowest platform."""
        self.solids = solids
        b = np.stack([np.asarray(s.bounds) for s in solids])   # type: ignore[attr-defined]
        self.bounds = np.stack([b[:, 0].min(axis=0), b[:, 1].max(axis=0)])
        self.platform_z = float(min(s.platform_z for s in solids))  # type: ignore[attr-defined]

    def H(self, x: np.ndarray) -> np.ndarray:
        """Signed value (n,) at points (n, 3)."""
        return np.min(np.stack([s.H(x) for s in self.solids]), axis=0)  # type: ignore[attr-defined]
