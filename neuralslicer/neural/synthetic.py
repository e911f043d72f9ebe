"""Small synthetic inputs (structured tet grids, boundary samples) for tests and benchmarks."""
from __future__ import annotations

import numpy as np
from scipy.spatial import cKDTree

from neuralslicer.samples import SurfaceSamples
from neuralslicer.tetmesh import boundary_faces


def boundary_samples(
    vertices: np.ndarray, tets: np.ndarray, k: int = 10, platform_tol: float = 0.5
) -> dict[str, np.ndarray]:
    """Samples B at the boundary-face centroids of a tet mesh: points, outward normals, areas
    (|A_p| = mean squared distance to k nearest samples), knn (n,k), on_platform (bottom, facing down)."""
    F = boundary_faces(tets)
    p = vertices[F]
    pts = p.mean(axis=1)
    nrm = np.cross(p[:, 1] - p[:, 0], p[:, 2] - p[:, 0])
    nrm /= np.linalg.norm(nrm, axis=1, keepdims=True)
    dist, knn = cKDTree(pts).query(pts, k=k + 1)
    knn, dist = knn[:, 1:], dist[:, 1:]
    areas = (dist**2).mean(axis=1)
    zmin = vertices[:, 2].min()
    on_platform = (pts[:, 2] <= zmin + platform_tol) & (nrm[:, 2] < -0.5)
    return {"points": pts, "normals": nrm, "areas": areas, "knn": knn.astype(np.int64),
            "on_platform": on_platform}


def sphere_samples(n: int = 300, radius: float = 4.0, centre: tuple[float, float, float] = (5.0, 5.0, 5.0),
                   k: int = 10) -> SurfaceSamples:
    """Fibonacci samples B of a sphere (points, outward normals, |A_p| from the k nearest, knn); the cap facing
    straight down (n_z < -0.95) is on the platform. In a 10 mm box its lower half overhangs planar layers."""
    i = np.arange(n) + 0.5
    phi = np.arccos(1 - 2 * i / n)
    th = np.pi * (1 + 5**0.5) * i
    nrm = np.stack([np.cos(th) * np.sin(phi), np.sin(th) * np.sin(phi), np.cos(phi)], axis=1)
    pts = np.asarray(centre) + radius * nrm
    dist, knn = cKDTree(pts).query(pts, k=k + 1)
    return SurfaceSamples(pts, nrm, (dist[:, 1:] ** 2).mean(axis=1), knn[:, 1:], nrm[:, 2] < -0.95)
