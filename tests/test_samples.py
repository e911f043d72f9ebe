"""Surface samples B: on H = 0, analytic normals, area weights, neighbours, platform flags, PLY."""
from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
import trimesh

from neuralslicer.model.components import MeshComponent, StrutsComponent, TubesComponent
from neuralslicer.model.solid import Solid
from neuralslicer.samples import SurfaceSamples, knn_areas, surface_samples, write_samples_ply


def angle_deg(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """Angle between rows of unit vectors, degrees."""
    return np.degrees(np.arccos(np.clip((a * b).sum(1), -1.0, 1.0)))


def test_sphere_samples_on_surface_with_radial_normals() -> None:
    m = trimesh.creation.icosphere(subdivisions=5, radius=10.0)
    solid = Solid([MeshComponent(m.vertices + [0, 0, 10], m.faces)])
    B = surface_samples(solid, 4000)
    diag = np.linalg.norm(solid.bounds[1] - solid.bounds[0])
    assert np.abs(solid.H(B.points)).max() < 1e-3 * diag and B.residual < 1e-3 * diag
    radial = B.points - [0, 0, 10]
    radial /= np.linalg.norm(radial, axis=1, keepdims=True)
    assert angle_deg(B.normals, radial).max() < 2.0
    # 2D Poisson process: E[d_j²] = j / (π λ), so mean over j = 1..10 is 5.5 A / (π n)
    expected = 5.5 * 4 * np.pi * 100 / (np.pi * len(B))
    assert B.areas.mean() == pytest.approx(expected, rel=0.08)
    # only the polar cap within platform_tol of z = 0 is flagged: area 2π r tol of 4π r²
    assert solid.platform_z == pytest.approx(0.0, abs=1e-6)
    tol = B.attrs["platform_tol"]
    assert np.all(B.points[B.on_platform, 2] <= tol)
    assert B.on_platform.sum() == pytest.approx(len(B) * tol / 20.0, abs=4 * np.sqrt(len(B) * tol / 20) + 1)


def test_tube_and_capsule_samples_against_analytic_normals() -> None:
    R = 1.5
    tube = Solid([TubesComponent(np.array([[[0, 0, -60.0], [0, 0, 60.0]]]), radius=R)])
    # tubes surface extraction runs marching cubes: keep it small with a coarse voxel
    tube.surface_voxel = 0.5
    B = surface_samples(tube, 2000)
    mid = np.abs(B.points[:, 2]) < 30
    radial = B.points[mid] * [1, 1, 0]
    assert np.allclose(np.linalg.norm(radial, axis=1), R, atol=0.01 * 2 * R)
    radial /= np.linalg.norm(radial, axis=1, keepdims=True)
    assert angle_deg(B.normals[mid], radial).max() < 2.0
    caps = Solid([StrutsComponent(np.array([[[0, 0, 0], [8.0, 0, 0]]]), radius=2.0)])
    B = surface_samples(caps, 3000, newton_steps=3)
    assert np.abs(caps.H(B.points)).max() < 1e-9
    t = np.clip(B.points[:, 0], 0, 8)
    exact_n = B.points - np.stack([t, 0 * t, 0 * t], 1)
    exact_n /= np.linalg.norm(exact_n, axis=1, keepdims=True)
    assert angle_deg(B.normals, exact_n).max() < 1e-6


def test_knn_and_platform_flags() -> None:
    box = trimesh.creation.box(extents=(10, 10, 10))
    solid = Solid([MeshComponent(box.vertices + [0, 0, 5], box.faces)])
    B = surface_samples(solid, 3000, k=10, seed=3)
    assert B.knn.shape == (3000, 10) and B.knn.dtype == np.int64
    assert not (B.knn == np.arange(3000)[:, None]).any()
    # brute force neighbours for a few points
    for i in (0, 17, 2999):
        d = np.linalg.norm(B.points - B.points[i], axis=1)
        d[i] = np.inf
        assert set(np.argsort(d)[:10]) == set(B.knn[i])
        assert B.areas[i] == pytest.approx(np.mean(np.sort(d)[:10] ** 2))
    # the bottom face is 1/6 of the area
    assert B.on_platform.mean() == pytest.approx(1 / 6, abs=0.03)
    assert np.all(B.normals[B.on_platform, 2] < -0.99)
    rest = B.without_platform()
    assert len(rest) == (~B.on_platform).sum() and rest.knn.max() < len(rest)
    assert not rest.on_platform.any()
    again = SurfaceSamples.from_arrays(*B.to_arrays())
    assert np.array_equal(again.points, B.points) and again.attrs == B.attrs


def test_knn_areas_with_duplicate_points() -> None:
    pts = np.array([[0.0, 0, 0], [0.0, 0, 0], [1.0, 0, 0], [0, 2.0, 0]])
    areas, knn = knn_areas(pts, k=2)
    assert not (knn == np.arange(4)[:, None]).any()
    assert areas[0] == pytest.approx(0.5 * (0 + 1))


def test_write_samples_ply(tmp_path: Path) -> None:
    import meshio

    solid = Solid([StrutsComponent(np.array([[[0, 0, 0], [4.0, 0, 0]]]), radius=1.0)])
    B = surface_samples(solid, 500)
    write_samples_ply(tmp_path / "b.ply", B)
    mesh = meshio.read(tmp_path / "b.ply")
    assert np.allclose(mesh.points, B.points)
    assert np.allclose(mesh.point_data["nx"], B.normals[:, 0])
    assert np.allclose(mesh.point_data["area"], B.areas)
    assert np.array_equal(mesh.point_data["on_platform"].astype(bool), B.on_platform)
