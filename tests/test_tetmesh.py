"""Tet mesh utilities against direct computations."""
import numpy as np
import pytest

from neuralslicer.tetmesh import (
    TetLocator,
    barycentric_gradients,
    box_tet_grid,
    boundary_faces,
    orient_tets,
    tet_adjacency,
    tet_volumes,
)


def cube_grid(n: int) -> tuple[np.ndarray, np.ndarray]:
    """Unit cube split into n³ cells of 6 tets each."""
    return box_tet_grid(n)


def test_volumes_sum_to_cube_and_orientation():
    V, T = cube_grid(3)
    vol = tet_volumes(V, T)
    assert np.all(vol > 0)
    assert vol.sum() == pytest.approx(1.0)
    flipped = T[:, [0, 1, 3, 2]]
    assert np.all(tet_volumes(V, flipped) < 0)
    assert np.array_equal(orient_tets(V, flipped), T[:, [0, 1, 2, 3]]) or np.all(tet_volumes(V, orient_tets(V, flipped)) > 0)


def test_barycentric_gradients_reproduce_linear_field():
    rng = np.random.default_rng(0)
    V, T = cube_grid(2)
    V = V + 0.05 * rng.standard_normal(V.shape)
    T = orient_tets(V, T)
    a = np.array([0.3, -1.2, 2.5])
    f = V @ a + 0.7
    grads = np.einsum("mi,mij->mj", f[T], barycentric_gradients(V, T))
    assert np.allclose(grads, a, atol=1e-10)
    assert np.allclose(barycentric_gradients(V, T).sum(axis=1), 0.0, atol=1e-10)


def test_locator_finds_every_point_with_correct_barycentrics():
    rng = np.random.default_rng(1)
    V, T = cube_grid(4)
    V = V + 0.02 * rng.standard_normal(V.shape)
    T = orient_tets(V, T)
    pts = rng.uniform(0.05, 0.95, size=(5000, 3))
    tet, bary = TetLocator(V, T).locate(pts)
    assert np.all(tet >= 0)
    assert np.all(bary >= -1e-9)
    assert np.allclose(np.einsum("ni,nij->nj", bary, V[T[tet]]), pts, atol=1e-10)
    outside = np.array([[2.0, 2.0, 2.0], [-1.0, 0.5, 0.5]])
    assert np.all(TetLocator(V, T).locate(outside)[0] == -1)


def test_adjacency_and_boundary_of_cube():
    n = 3
    V, T = cube_grid(n)
    pairs, faces = tet_adjacency(T)
    bnd = boundary_faces(T)
    # every face is interior (shared by two) or on the boundary: 4 m = 2 k + b
    assert 4 * len(T) == 2 * len(pairs) + len(bnd)
    assert len(bnd) == 6 * n * n * 2
    for (a, b), f in zip(pairs[:50], faces[:50]):
        assert set(f) <= set(T[a]) and set(f) <= set(T[b])
    # outward: the boundary normals point away from the centre
    p = V[bnd]
    normal = np.cross(p[:, 1] - p[:, 0], p[:, 2] - p[:, 0])
    assert np.all(np.einsum("ij,ij->i", normal, p.mean(axis=1) - 0.5) > 0)
