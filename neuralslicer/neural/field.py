"""The scalar field G on the cage and its local printing directions (SPEC step 7)."""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import torch
from scipy.spatial import cKDTree

from neuralslicer.tetmesh import TetLocator, barycentric_gradients, tet_adjacency, tet_volumes


@dataclass
class CageGeometry:
    """Precomputed, q/s-independent geometry of the cage.

    vertices : (n, 3) float64; tets : (m, 4) int64 positively oriented; centroids : (m, 3);
    volumes : (m,); bary_grads : (m, 4, 3) gradients of the barycentric coordinates;
    pairs : (k, 2) adjacent tets (L, R); pair_normals : (k, 3) unit normal of the shared face,
    pointing from L into R.
    """

    vertices: np.ndarray
    tets: np.ndarray
    centroids: np.ndarray
    volumes: np.ndarray
    bary_grads: np.ndarray
    pairs: np.ndarray
    pair_normals: np.ndarray

    @classmethod
    def build(cls, vertices: np.ndarray, tets: np.ndarray) -> "CageGeometry":
        """Precompute centroids, volumes, barycentric gradients and face adjacency."""
        vertices = np.asarray(vertices, dtype=np.float64)
        tets = np.asarray(tets, dtype=np.int64)
        vol = tet_volumes(vertices, tets)
        if np.any(vol <= 0):
            from neuralslicer.tetmesh import orient_tets

            tets = orient_tets(vertices, tets)
            vol = tet_volumes(vertices, tets)
        centroids = vertices[tets].mean(axis=1)
        pairs, faces = tet_adjacency(tets)
        p = vertices[faces]
        nrm = np.cross(p[:, 1] - p[:, 0], p[:, 2] - p[:, 0])
        nrm /= np.maximum(np.linalg.norm(nrm, axis=1, keepdims=True), 1e-300)
        side = np.einsum("ij,ij->i", nrm, centroids[pairs[:, 1]] - centroids[pairs[:, 0]])
        nrm *= np.where(side < 0, -1.0, 1.0)[:, None]
        return cls(vertices, tets, centroids, np.abs(vol), barycentric_gradients(vertices, tets), pairs, nrm)

    def locate(self, points: np.ndarray) -> np.ndarray:
        """Containing cage tet (n,) of each point; points outside the cage take the nearest centroid."""
        points = np.asarray(points, dtype=np.float64).reshape(-1, 3)
        if len(points) == 0:
            return np.zeros(0, dtype=np.int64)
        tet, _ = TetLocator(self.vertices, self.tets).locate(points)
        out = tet < 0
        if out.any():
            _, tet[out] = cKDTree(self.centroids).query(points[out])
        return tet

    def barycentric(self, points: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """(containing tet (n,), barycentric coordinates (n,4)) of points; a point outside the cage
        takes the nearest tet, its coordinates extrapolated (G stays linear there)."""
        points = np.asarray(points, dtype=np.float64).reshape(-1, 3)
        tet = self.locate(points)
        bary = 0.25 + np.einsum("nij,nj->ni", self.bary_grads[tet], points - self.centroids[tet])
        return tet, bary


def field_gradient(G: torch.Tensor, tets: torch.Tensor, bary_grads: torch.Tensor) -> torch.Tensor:
    """Per-tet gradient of the piecewise-linear G: sum_i G[v_i] grad a_i, (m,3) from G (n,)."""
    return torch.einsum("ei,eij->ej", G.index_select(0, tets.reshape(-1)).view(tets.shape), bary_grads)


def unit(v: torch.Tensor, eps: float = 1e-12) -> torch.Tensor:
    """Rows of v (n,3) scaled to unit length (zero rows stay ~0)."""
    return v / v.norm(dim=-1, keepdim=True).clamp_min(eps)
