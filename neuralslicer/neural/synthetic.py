"""Small synthetic inputs (structured tet grids, boundary samples) for tests and benchmarks."""
from __future__ import annotations

import numpy as np
from scipy.spatial import cKDTree

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
