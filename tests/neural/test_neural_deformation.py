"""Differentiable ARAP deformation and the field G: gradchecks, closed forms, a dense reference."""
from __future__ import annotations

import numpy as np
import pytest
import torch

from neuralslicer.neural.config import DeformationConfig, NetworkConfig
from neuralslicer.neural.deformation import CENTRING, ArapDeformation, arap_matrix, factor_solve
from neuralslicer.neural.field import CageGeometry, field_gradient
from neuralslicer.neural.networks import DeformationFields, quaternion_to_matrix
from neuralslicer.tetmesh import box_tet_grid


@pytest.fixture(scope="module")
def small_cage():
    """A 2x2x3 box of 72 tets, slightly jittered so that nothing is axis-aligned by accident."""
    V, T = box_tet_grid((2, 2, 3), np.array([0.0, 0.0, 0.0]), np.array([2.0, 3.0, 4.0]))
    rng = np.random.default_rng(1)
    V = V + 0.05 * rng.standard_normal(V.shape)
    return V, T


def _random_qs(m: int, seed: int = 0) -> tuple[torch.Tensor, torch.Tensor]:
    g = torch.Generator().manual_seed(seed)
    q = torch.randn(m, 4, generator=g, dtype=torch.float64)
    s = 0.5 + torch.rand(m, 3, generator=g, dtype=torch.float64)
    return q, s


def _dense_reference(V, T, R, S, gamma):
    """Solve the ARAP least squares by building A and b row by row (dense, loops)."""
    n, m = len(V), len(T)
    A = np.zeros((4 * m, n))
    b = np.zeros((4 * m, 3))
    for e in range(m):
        Ve = V[T[e]]
        target = (R[e] @ np.diag(S[e]) @ (CENTRING @ Ve).T).T  # (4,3)
        for i in range(4):
            for j in range(4):
                A[4 * e + i, T[e, j]] += CENTRING[i, j]
            b[4 * e + i] = target[i]
    K = A.T @ A + gamma * np.eye(n)
    return np.linalg.solve(K, A.T @ b + gamma * V), K


def test_matrix_and_solution_match_dense_loops(small_cage):
    V, T = small_cage
    arap = ArapDeformation(V, T, DeformationConfig(gamma=0.01))
    q, s = _random_qs(len(T))
    q = q / q.norm(dim=1, keepdim=True)
    R = quaternion_to_matrix(q)
    ref, K = _dense_reference(V, T, R.numpy(), s.numpy(), 0.01)
    np.testing.assert_allclose(arap_matrix(len(V), T, 0.01).toarray(), K, atol=1e-12)
    np.testing.assert_allclose(arap.deform(q, s).numpy(), ref, atol=1e-9)
    np.testing.assert_allclose(arap.deformed_height(q, s).numpy(), ref[:, 2], atol=1e-9)


def test_gradcheck_factor_solve(small_cage):
    V, T = small_cage
    arap = ArapDeformation(V, T)
    rhs = torch.randn(len(V), 3, dtype=torch.float64, requires_grad=True)
    assert torch.autograd.gradcheck(lambda r: factor_solve(r, arap._solve_xyz), (rhs,))


@pytest.mark.parametrize("pin", [False, True])
def test_gradcheck_deformation_wrt_q_and_s(small_cage, pin):
    V, T = small_cage
    arap = ArapDeformation(V, T, DeformationConfig(gamma=0.05, pin_platform=pin, platform_tolerance=0.2),
                           platform_z=0.0)
    q, s = _random_qs(len(T), seed=3)
    q.requires_grad_(True)
    s.requires_grad_(True)

    def deform(q, s):
        return arap.deform(q / q.norm(dim=1, keepdim=True), s)

    assert torch.autograd.gradcheck(deform, (q, s))


def test_gradcheck_G_and_gradG_wrt_q_and_s(small_cage):
    V, T = small_cage
    geo = CageGeometry.build(V, T)
    arap = ArapDeformation(geo.vertices, geo.tets)
    tets = torch.as_tensor(geo.tets)
    grads = torch.as_tensor(geo.bary_grads)
    q, s = _random_qs(len(T), seed=4)
    q.requires_grad_(True)
    s.requires_grad_(True)

    def G_and_grad(q, s):
        G = arap.deformed_height(q / q.norm(dim=1, keepdim=True), s)
        return G, field_gradient(G, tets, grads)

    assert torch.autograd.gradcheck(G_and_grad, (q, s))


def test_pinned_platform_keeps_height(small_cage):
    V, T = small_cage
    arap = ArapDeformation(V, T, DeformationConfig(pin_platform=True, platform_tolerance=0.2), platform_z=0.0)
    assert arap.pinned.sum() >= 9
    q, s = _random_qs(len(T), seed=5)
    Vd = arap.deform(q / q.norm(dim=1, keepdim=True), s).numpy()
    np.testing.assert_allclose(Vd[arap.pinned, 2], V[arap.pinned, 2], atol=1e-12)
    assert np.abs(Vd[~arap.pinned, 2] - V[~arap.pinned, 2]).max() > 1e-3


def test_identity_networks_reproduce_height(small_cage):
    V, T = small_cage
    geo = CageGeometry.build(V, T)
    torch.manual_seed(0)
    fields = DeformationFields(NetworkConfig(), np.stack([V.min(0), V.max(0)])).double()
    q, s = fields(torch.as_tensor(geo.centroids))
    np.testing.assert_array_equal(q.detach().numpy(), np.tile([1.0, 0, 0, 0], (len(T), 1)))
    np.testing.assert_array_equal(s.detach().numpy(), np.ones((len(T), 3)))
    G = ArapDeformation(V, T).deformed_height(q, s).detach().numpy()
    np.testing.assert_allclose(G, V[:, 2], atol=1e-6)


def test_constant_rotation_and_scale_closed_form(small_cage):
    """Zero ARAP energy for a rigid motion; the gamma term only fixes the translation (gamma -> 0)."""
    V, T = small_cage
    arap = ArapDeformation(V, T, DeformationConfig(gamma=1e-7))
    axis = np.array([1.0, 2.0, 0.5]) / np.linalg.norm([1.0, 2.0, 0.5])
    angle = 0.7
    q = torch.tensor([[np.cos(angle / 2), *(np.sin(angle / 2) * axis)]], dtype=torch.float64).repeat(len(T), 1)
    R = quaternion_to_matrix(q[:1])[0].numpy()
    c = V.mean(axis=0)
    Vd = arap.deform(q, torch.ones(len(T), 3, dtype=torch.float64)).numpy()
    np.testing.assert_allclose(Vd, (V - c) @ R.T + c, atol=1e-6)  # rotated height field
    Gd = arap.deformed_height(q, torch.ones(len(T), 3, dtype=torch.float64)).numpy()
    np.testing.assert_allclose(Gd, ((V - c) @ R.T + c)[:, 2], atol=1e-6)
    s = torch.tensor([[1.0, 1.0, 2.0]], dtype=torch.float64).repeat(len(T), 1)
    ident = torch.tensor([[1.0, 0, 0, 0]], dtype=torch.float64).repeat(len(T), 1)
    Gs = arap.deformed_height(ident, s).numpy()
    np.testing.assert_allclose(Gs, 2 * (V[:, 2] - c[2]) + c[2], atol=1e-6)


def test_quaternion_to_matrix_is_rotation():
    q = torch.randn(50, 4, dtype=torch.float64)
    R = quaternion_to_matrix(q / q.norm(dim=1, keepdim=True))
    np.testing.assert_allclose((R @ R.transpose(1, 2)).numpy(), np.tile(np.eye(3), (50, 1, 1)), atol=1e-12)
    np.testing.assert_allclose(torch.linalg.det(R).numpy(), 1.0, atol=1e-12)


def test_field_gradient_of_linear_field_is_exact(small_cage):
    V, T = small_cage
    geo = CageGeometry.build(V, T)
    a = np.array([0.3, -1.2, 2.0])
    G = torch.as_tensor(V @ a + 4.0)
    g = field_gradient(G, torch.as_tensor(geo.tets), torch.as_tensor(geo.bary_grads)).numpy()
    np.testing.assert_allclose(g, np.tile(a, (len(T), 1)), atol=1e-10)


@pytest.mark.parametrize("solver", ["splu", "cholespy"])
def test_backends_agree(small_cage, solver):
    if solver == "cholespy":
        pytest.importorskip("cholespy")
    V, T = small_cage
    q, s = _random_qs(len(T), seed=9)
    q = q / q.norm(dim=1, keepdim=True)
    ref, _ = _dense_reference(V, T, quaternion_to_matrix(q).numpy(), s.numpy(), 1e-4)
    arap = ArapDeformation(V, T, DeformationConfig(solver=solver))
    assert arap.backend == solver
    np.testing.assert_allclose(arap.deform(q, s).numpy(), ref, atol=1e-8)
