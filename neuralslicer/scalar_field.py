"""The printing field G on the cage: values at cage vertices, piecewise linear, LPD constant per tet."""
from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from neuralslicer.tetmesh import TetLocator, barycentric_gradients


@dataclass
class ScalarField:
    """G at the cage vertices (n,), with the cage it lives on; LPD = grad G / |grad G| per tet."""

    cage_vertices: np.ndarray
    cage_tets: np.ndarray
    G: np.ndarray
    info: dict = field(default_factory=dict)

    @classmethod
    def height(cls, cage_vertices: np.ndarray, cage_tets: np.ndarray) -> ScalarField:
        """The identity mapping: planar layers, G = z."""
        return cls(cage_vertices, cage_tets, cage_vertices[:, 2].copy(), {"kind": "height"})

    def blend(self, t: float) -> ScalarField:
        """The field blended toward planar layers, (1 - t) G + t z (t = 1: planar), the last resort
        against head collisions."""
        G = (1.0 - t) * self.G + t * self.cage_vertices[:, 2]
        return ScalarField(self.cage_vertices, self.cage_tets, G, {**self.info, "blend_planar": float(t)})

    def gradients(self) -> np.ndarray:
        """grad G per cage tet (m,3)."""
        return np.einsum("mi,mij->mj", self.G[self.cage_tets], barycentric_gradients(self.cage_vertices, self.cage_tets))

    def lpd(self) -> np.ndarray:
        """Unit local printing direction per cage tet (m,3)."""
        g = self.gradients()
        return g / np.maximum(np.linalg.norm(g, axis=1, keepdims=True), 1e-300)

    def sample(self, points: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """G, unit LPD and |grad G| at points (points outside the cage get NaN)."""
        tet, bary = TetLocator(self.cage_vertices, self.cage_tets).locate(points, tol=1e-7)
        grad = self.gradients()
        ok = tet >= 0
        g = np.full(len(points), np.nan)
        g[ok] = np.einsum("ni,ni->n", bary[ok], self.G[self.cage_tets[tet[ok]]])
        d = np.full((len(points), 3), np.nan)
        norm = np.full(len(points), np.nan)
        norm[ok] = np.linalg.norm(grad[tet[ok]], axis=1)
        d[ok] = grad[tet[ok]] / np.maximum(norm[ok], 1e-300)[:, None]
        return g, d, norm

    def to_arrays(self) -> tuple[dict[str, np.ndarray], dict]:
        """Arrays for the store: G per cage vertex and LPD per cage tet."""
        return {"G": self.G, "lpd": self.lpd()}, dict(self.info)

    @classmethod
    def from_arrays(cls, cage_vertices: np.ndarray, cage_tets: np.ndarray, arrays: dict, attrs: dict) -> ScalarField:
        """Rebuild on its cage from store arrays."""
        return cls(cage_vertices, cage_tets, np.asarray(arrays["G"], dtype=np.float64), dict(attrs))
