"""The surface sample set B: points on ``H = 0`` with outward normals, area weights and neighbours."""
from __future__ import annotations

from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from neuralslicer.model.solid import Solid
from neuralslicer.types import BoolArray, FloatArray, IndexArray


@dataclass
class SurfaceSamples:
    """The set B of the paper.

    points : (n, 3) float64, on ``H = 0`` (build frame, mm)
    normals : (n, 3) float64, outward unit ``∇H / |∇H|``
    areas : (n,) float64, ``|A_p|`` = mean squared distance to the k nearest samples (mm²)
    knn : (n, k) int64, indices of the k nearest other samples (self excluded)
    on_platform : (n,) bool, on the platform plane with a downward normal
    residual : max ``|H(p)|`` after projection (mm)
    """

    points: FloatArray
    normals: FloatArray
    areas: FloatArray
    knn: IndexArray
    on_platform: BoolArray
    residual: float = 0.0
    attrs: dict = field(default_factory=dict)

    def __len__(self) -> int:
        """Number of samples."""
        return len(self.points)

    def without_platform(self) -> "SurfaceSamples":
        """The samples that are not on the platform, neighbours and weights recomputed among them."""
        keep = ~self.on_platform
        k = self.knn.shape[1]
        pts = self.points[keep]
        areas, knn = knn_areas(pts, k)
        return SurfaceSamples(pts, self.normals[keep], areas, knn, np.zeros(len(pts), bool),
                              self.residual, dict(self.attrs))

    def to_arrays(self) -> tuple[dict[str, np.ndarray], dict]:
        """Plain arrays and JSON attrs for storage."""
        arrays = {"points": self.points, "normals": self.normals, "areas": self.areas,
                  "knn": self.knn, "on_platform": self.on_platform}
        return arrays, {"residual": float(self.residual), **self.attrs}

    @classmethod
    def from_arrays(cls, arrays: dict[str, np.ndarray], attrs: dict) -> "SurfaceSamples":
        """Inverse of :meth:`to_arrays`."""
        extra = {k: v for k, v in attrs.items() if k != "residual"}
        return cls(np.asarray(arrays["points"], np.float64), np.asarray(arrays["normals"], np.float64),
                   np.asarray(arrays["areas"], np.float64), np.asarray(arrays["knn"], np.int64),
                   np.asarray(arrays["on_platform"], bool), float(attrs.get("residual", 0.0)), extra)


def knn_areas(points: FloatArray, k: int = 10) -> tuple[FloatArray, IndexArray]:
    """Area weights ``(n,)`` (mean squared distance to the k nearest) and neighbour ids ``(n, k)``."""
    k = min(k, len(points) - 1)
    from scipy.spatial import cKDTree   # scipy.spatial only where samples are drawn

    dist, idx = cKDTree(points).query(points, k=k + 1)
    # column 0 is normally the point itself; drop self wherever it appears (duplicates)
    n = len(points)
    is_self = idx == np.arange(n)[:, None]
    drop = np.where(is_self.any(1), is_self.argmax(1), k)
    keep = np.ones_like(is_self)
    keep[np.arange(n), drop] = False
    knn = idx[keep].reshape(n, k).astype(np.int64)
    d = dist[keep].reshape(n, k)
    return (d ** 2).mean(axis=1), knn


def surface_samples(solid: Solid, n_samples: int, k: int = 10, platform_tol: float | None = None,
                    platform_normal_z: float = -0.9, newton_steps: int = 4, seed: int = 0) -> SurfaceSamples:
    """Sample B: area-uniform points on the solid's surface, projected onto ``H = 0``.

    Parameters
    ----------
    solid : the implicit solid.
    n_samples : number of samples n.
    k : neighbours per sample (paper: 10) for the area weights and the kNN lists.
    platform_tol : a sample is on the platform when ``|z - platform_z| <= platform_tol`` and its
        normal's z is below ``platform_normal_z``; default ``1e-3 × bbox diagonal``.
    newton_steps : Newton steps ``p -= H ∇H / |∇H|²`` onto ``H = 0``.
    seed : random seed of the area-uniform sampling (deterministic output).
    """
    if n_samples < k + 1:
        raise ValueError(f"n_samples must exceed k = {k}")
    surf = solid.surface()
    rng = np.random.default_rng(seed)
    tri = surf.vertices[surf.faces]
    area = 0.5 * np.linalg.norm(np.cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0]), axis=1)
    face = rng.choice(len(area), size=n_samples, p=area / area.sum())
    u, v = rng.random(n_samples), rng.random(n_samples)
    flip = u + v > 1.0
    u[flip], v[flip] = 1.0 - u[flip], 1.0 - v[flip]
    t = tri[face]
    pts = t[:, 0] + u[:, None] * (t[:, 1] - t[:, 0]) + v[:, None] * (t[:, 2] - t[:, 0])
    pts = solid.project(pts, steps=newton_steps)
    h, g = solid.value_and_grad(pts)
    norm = np.linalg.norm(g, axis=1, keepdims=True)
    normals = g / np.where(norm > 0, norm, 1.0)
    areas, knn = knn_areas(pts, k)
    diag = float(np.linalg.norm(solid.bounds[1] - solid.bounds[0]))
    tol = 1e-3 * diag if platform_tol is None else float(platform_tol)
    on_platform = (np.abs(pts[:, 2] - solid.platform_z) <= tol) & (normals[:, 2] < platform_normal_z)
    return SurfaceSamples(pts, normals, areas, knn, on_platform, float(np.abs(h).max()),
                          {"k": k, "seed": seed, "platform_tol": tol, "newton_steps": newton_steps})


def write_samples_ply(path: str | Path, samples: SurfaceSamples) -> None:
    """Write B as a binary PLY point cloud with ``nx ny nz``, ``area`` and ``on_platform`` properties."""
    n = len(samples)
    dtype = np.dtype([("x", "<f8"), ("y", "<f8"), ("z", "<f8"), ("nx", "<f8"), ("ny", "<f8"),
                      ("nz", "<f8"), ("area", "<f8"), ("on_platform", "u1")])
    rec = np.empty(n, dtype=dtype)
    for i, name in enumerate("xyz"):
        rec[name] = samples.points[:, i]
        rec["n" + name] = samples.normals[:, i]
    rec["area"] = samples.areas
    rec["on_platform"] = samples.on_platform
    header = ("ply\nformat binary_little_endian 1.0\n"
              f"element vertex {n}\n"
              + "".join(f"property double {p}\n" for p in ("x", "y", "z", "nx", "ny", "nz", "area"))
              + "property uchar on_platform\nend_header\n")
    with open(path, "wb") as fh:
        fh.write(header.encode("ascii"))
        fh.write(rec.tobytes())
