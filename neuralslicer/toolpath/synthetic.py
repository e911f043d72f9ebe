"""Synthetic curved layers for tests and benchmarks: planar squares/discs, spherical caps, tilted stacks."""
from __future__ import annotations

import numpy as np
import trimesh


def _with_lpd(vertices: np.ndarray, faces: np.ndarray, lpd: np.ndarray, isovalue: float) -> trimesh.Trimesh:
    m = trimesh.Trimesh(np.asarray(vertices, np.float64), np.asarray(faces, np.int64), process=False)
    m.vertex_attributes["lpd"] = np.asarray(lpd, np.float64)
    m.metadata["isovalue"] = float(isovalue)
    return m


def square_layer(z: float, size: float = 10.0, n: int = 11, center: tuple[float, float] = (0.0, 0.0)
                 ) -> trimesh.Trimesh:
    """Planar square ``size`` x ``size`` at height z, grid of n x n vertices, LPD +z."""
    xs = np.linspace(-size / 2, size / 2, n)
    gx, gy = np.meshgrid(xs + center[0], xs + center[1], indexing="ij")
    v = np.column_stack([gx.ravel(), gy.ravel(), np.full(gx.size, z)])
    idx = np.arange(n * n).reshape(n, n)
    a, b, c, d = idx[:-1, :-1].ravel(), idx[1:, :-1].ravel(), idx[1:, 1:].ravel(), idx[:-1, 1:].ravel()
    f = np.concatenate([np.stack([a, b, c], 1), np.stack([a, c, d], 1)])
    return _with_lpd(v, f, np.tile([0.0, 0.0, 1.0], (len(v), 1)), z)


def disc_layer(z: float, radius: float = 5.0, n_rings: int = 10, n_sectors: int = 48) -> trimesh.Trimesh:
    """Planar disc of ``radius`` at height z (polar grid), LPD +z."""
    r = np.linspace(0, radius, n_rings + 1)[1:]
    t = np.linspace(0, 2 * np.pi, n_sectors, endpoint=False)
    rr, tt = np.meshgrid(r, t, indexing="ij")
    v = np.vstack([[0.0, 0.0, z], np.column_stack([(rr * np.cos(tt)).ravel(), (rr * np.sin(tt)).ravel(),
                                                    np.full(rr.size, z)])])
    ring = lambda i, j: 1 + i * n_sectors + (j % n_sectors)  # noqa: E731
    j = np.arange(n_sectors)
    faces = [np.stack([np.zeros(n_sectors, int), ring(0, j), ring(0, j + 1)], 1)]
    for i in range(n_rings - 1):
        faces.append(np.stack([ring(i, j), ring(i + 1, j), ring(i + 1, j + 1)], 1))
        faces.append(np.stack([ring(i, j), ring(i + 1, j + 1), ring(i, j + 1)], 1))
    return _with_lpd(v, np.concatenate(faces), np.tile([0.0, 0.0, 1.0], (len(v), 1)), z)


def cap_layer(radius: float, theta_max_deg: float, center: tuple[float, float, float] = (0.0, 0.0, 0.0),
              subdivisions: int = 5) -> trimesh.Trimesh:
    """Spherical cap ``|x - center| = radius`` within ``theta_max_deg`` of +z, LPD radial (outward)."""
    s = trimesh.creation.icosphere(subdivisions=subdivisions, radius=1.0)
    keep = np.all(s.vertices[s.faces][:, :, 2] >= np.cos(np.radians(theta_max_deg)), axis=1)
    f = s.faces[keep]
    used, inv = np.unique(f, return_inverse=True)
    n = s.vertices[used] / np.linalg.norm(s.vertices[used], axis=1, keepdims=True)
    return _with_lpd(n * radius + np.asarray(center), inv.reshape(-1, 3), n, radius)


def planar_stack(n_layers: int, thickness: float = 0.5, size: float = 10.0, n: int = 11,
                 platform_z: float = 0.0) -> list[trimesh.Trimesh]:
    """Box ``size`` x ``size`` x ``n_layers * thickness`` sliced into planar squares (top of each layer)."""
    return [square_layer(platform_z + thickness * (i + 1), size, n) for i in range(n_layers)]


def cap_stack(n_layers: int, thickness: float = 0.5, r0: float = 10.0, theta_max_deg: float = 40.0,
              center: tuple[float, float, float] = (0.0, 0.0, 0.0), subdivisions: int = 5
              ) -> list[trimesh.Trimesh]:
    """Concentric spherical caps r0 + (i+1) t: a shell sector printed outwards (LPD radial)."""
    return [cap_layer(r0 + thickness * (i + 1), theta_max_deg, center, subdivisions) for i in range(n_layers)]


def tilted_stack(n_layers: int, tilt_deg: float = 30.0, thickness: float = 0.5, size: float = 10.0,
                 n: int = 11, lift: float = 8.0) -> list[trimesh.Trimesh]:
    """Planar squares tilted by ``tilt_deg`` about +y, stacked along their normal (LPD = normal)."""
    c, s = np.cos(np.radians(tilt_deg)), np.sin(np.radians(tilt_deg))
    rot = np.array([[c, 0, s], [0, 1, 0], [-s, 0, c]])
    normal = rot @ np.array([0.0, 0.0, 1.0])
    out = []
    for i in range(n_layers):
        m = square_layer(0.0, size, n)
        v = m.vertices @ rot.T + normal * thickness * (i + 1) + np.array([0.0, 0.0, lift])
        out.append(_with_lpd(v, m.faces, np.tile(normal, (len(v), 1)), thickness * (i + 1)))
    return out
