"""Small synthetic inputs (structured tet grids, boundary samples) for tests and benchmarks."""
from __future__ import annotations

import numpy as np
from scipy.spatial import cKDTree

from neuralslicer.tetmesh import boundary_faces, orient_tets

# Kuhn subdivision of the unit cube into 6 tets (all share the diagonal 0-7).
_CUBE_TETS = np.array(
    [[0, 1, 3, 7], [0, 1, 5, 7], [0, 2, 3, 7], [0, 2, 6, 7], [0, 4, 5, 7], [0, 4, 6, 7]]
)


def grid_tets(shape: tuple[int, int, int], lo: np.ndarray, hi: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Structured tet mesh of a box: (vertices (n,3), tets (6 nx ny nz, 4)) positively oriented."""
    nx, ny, nz = shape
    axes = [np.linspace(lo[i], hi[i], s + 1) for i, s in enumerate(shape)]
    X, Y, Z = np.meshgrid(*axes, indexing="ij")
    V = np.stack([X.ravel(), Y.ravel(), Z.ravel()], axis=1)
    idx = np.arange(V.shape[0]).reshape(nx + 1, ny + 1, nz + 1)
    i, j, k = np.meshgrid(np.arange(nx), np.arange(ny), np.arange(nz), indexing="ij")
    i, j, k = i.ravel(), j.ravel(), k.ravel()
    corners = np.stack(
        [idx[i + (c >> 2 & 1), j + (c >> 1 & 1), k + (c & 1)] for c in range(8)], axis=1
    )
    T = corners[:, _CUBE_TETS].reshape(-1, 4)
    return V, orient_tets(V, T)


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


def read_tet(path: str) -> tuple[np.ndarray, np.ndarray]:
    """Read a `.tet` file (N vertices / M tets / xyz lines / '4 a b c d' lines)."""
    with open(path) as fh:
        lines = fh.read().split("\n")
    n = int(lines[0].split()[0])
    m = int(lines[1].split()[0])
    V = np.array([ln.split()[:3] for ln in lines[2 : 2 + n]], dtype=np.float64)
    T = np.array([ln.split()[1:5] for ln in lines[2 + n : 2 + n + m]], dtype=np.int64)
    return V, T
