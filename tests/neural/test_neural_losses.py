"""Each loss term against a direct evaluation of its formula (python loops / numpy)."""
from __future__ import annotations

import math

import numpy as np
import torch

from neuralslicer.neural import losses as L
from neuralslicer.neural.field import CageGeometry, field_gradient
from neuralslicer.tetmesh import box_tet_grid

RNG = np.random.default_rng(7)


def _unit(a):
    return a / np.linalg.norm(a, axis=-1, keepdims=True)


def _sig(x):
    return 1.0 / (1.0 + math.exp(-x))


def test_support_free_loss_matches_loop():
    n = 17
    d, nrm, w = _unit(RNG.normal(size=(n, 3))), _unit(RNG.normal(size=(n, 3))), RNG.uniform(0.1, 2, n)
    alpha, k = math.radians(45), 30.0
    ref = sum(w[i] * _sig(k * (-(nrm[i] @ d[i]) - math.sin(alpha))) for i in range(n)) / w.sum()
    got = L.support_free_loss(torch.tensor(d), torch.tensor(nrm), torch.tensor(w), alpha, k)
    assert abs(float(got) - ref) < 1e-12


def test_strength_loss_matches_loop():
    n = 13
    d, tau, w = _unit(RNG.normal(size=(n, 3))), _unit(RNG.normal(size=(n, 3))), RNG.uniform(0.1, 2, n)
    beta, k = math.radians(10), 15.0
    ref = sum(w[i] * _sig(k * (abs(tau[i] @ d[i]) - math.sin(beta))) for i in range(n)) / w.sum()
    got = L.strength_loss(torch.tensor(d), torch.tensor(tau), torch.tensor(w), beta, k)
    assert abs(float(got) - ref) < 1e-12


def test_point_overhang_loss_matches_loop_and_detects_a_minimum():
    pts = RNG.normal(size=(30, 3))
    pts[0] = [0.0, 0.0, -5.0]  # the lowest point: a local minimum along +z
    knn = np.stack([RNG.choice(np.delete(np.arange(30), i), 4, replace=False) for i in range(30)])
    active = np.arange(10)
    d = np.tile([0.0, 0.0, 1.0], (10, 1))
    w = RNG.uniform(0.5, 1.5, 10)
    h = 0.7
    ref = 0.0
    for a, i in enumerate(active):
        m = min((pts[j] - pts[i]) @ d[a] for j in knn[i])
        ref += w[a] * max(0.0, m)
    ref /= w.sum() * h
    assert ref > 0
    got = L.point_overhang_loss(torch.tensor(d), torch.tensor(pts[active]), torch.tensor(knn[active]),
                                torch.tensor(pts), torch.tensor(w), h)
    assert abs(float(got) - ref) < 1e-12


def test_harmonic_losses_match_loops():
    m = 9
    pairs = np.array([[0, 1], [1, 2], [2, 5], [3, 8], [4, 6], [7, 0]])
    vol = RNG.uniform(0.2, 1.0, m)
    s = RNG.uniform(0.5, 2, (m, 3))
    q = _unit(RNG.normal(size=(m, 4)))
    W = sum(0.5 * (vol[i] + vol[j]) for i, j in pairs)
    ref_s = sum(0.5 * (vol[i] + vol[j]) * np.sum((s[i] - s[j]) ** 2) for i, j in pairs) / W
    ref_q = sum(0.5 * (vol[i] + vol[j]) * (1 - q[i] @ q[j]) ** 2 for i, j in pairs) / W
    pw = torch.tensor(0.5 * (vol[pairs[:, 0]] + vol[pairs[:, 1]]))
    assert abs(float(L.harmonic_scale_loss(torch.tensor(s), torch.tensor(pairs), pw)) - ref_s) < 1e-12
    assert abs(float(L.harmonic_quaternion_loss(torch.tensor(q), torch.tensor(pairs), pw)) - ref_q) < 1e-12


def _two_tets(a: float, b: float):
    """Two tets sharing the face x = 0 (L at x < 0, R at x > 0), G = a x + z on L and b x + z on R."""
    V = np.array([[0.0, -1, -1], [0, 1, -1], [0, 0, 1], [-1, 0, 0], [1, 0, 0]])
    T = np.array([[0, 1, 2, 3], [0, 1, 2, 4]])
    geo = CageGeometry.build(V, T)
    G = np.where(V[:, 0] < 0, a * V[:, 0], b * V[:, 0]) + V[:, 2]
    grad = field_gradient(torch.tensor(G), torch.tensor(geo.tets), torch.tensor(geo.bary_grads))
    return geo, grad


def test_crease_sign_and_value_on_a_valley_and_a_ridge():
    # valley: the isoline z = c - a x rises on both sides (a = 1 left, b = -1 right)
    geo, grad = _two_tets(1.0, -1.0)
    assert np.allclose(geo.pair_normals[0], [1, 0, 0]) or np.allclose(geo.pair_normals[0], [-1, 0, 0])
    x, c = L.crease_concavity(grad, torch.tensor(geo.pairs), torch.tensor(geo.pair_normals))
    nl, nr = _unit(np.array([1.0, 0, 1])), _unit(np.array([-1.0, 0, 1]))
    theta = math.acos(nl @ nr)  # 90 degrees between the two isosurface normals
    assert abs(float(x[0]) - math.sin(theta)) < 1e-12 and abs(float(c[0]) - nl @ nr) < 1e-12
    # a cone of apex 120 deg does not fit into a 90 deg valley: violation theta - (pi - phi)
    phi = math.radians(120)
    ca = L.collision_loss(grad, torch.tensor(geo.pairs), torch.tensor(geo.pair_normals), phi)
    assert abs(float(ca) - (theta - (math.pi - phi))) < 1e-12
    # a cone of apex 80 deg fits; a ridge never collides
    assert float(L.collision_loss(grad, torch.tensor(geo.pairs), torch.tensor(geo.pair_normals), math.radians(80))) == 0
    geo, grad = _two_tets(-1.0, 1.0)
    x, _ = L.crease_concavity(grad, torch.tensor(geo.pairs), torch.tensor(geo.pair_normals))
    assert float(x[0]) < 0
    assert float(L.collision_loss(grad, torch.tensor(geo.pairs), torch.tensor(geo.pair_normals), phi)) == 0


def test_crease_is_zero_for_planar_layers_on_a_grid():
    V, T = box_tet_grid((2, 2, 2), np.zeros(3), np.ones(3))
    geo = CageGeometry.build(V, T)
    grad = field_gradient(torch.tensor(V[:, 2] + 0.3 * V[:, 0]), torch.tensor(geo.tets), torch.tensor(geo.bary_grads))
    x, c = L.crease_concavity(grad, torch.tensor(geo.pairs), torch.tensor(geo.pair_normals))
    assert np.abs(x.numpy()).max() < 1e-12 and np.allclose(c.numpy(), 1)
    ca = L.collision_loss(grad, torch.tensor(geo.pairs), torch.tensor(geo.pair_normals), math.radians(170))
    assert float(ca) == 0


def test_tilt_bound_loss_against_hand_computed_values():
    """L_TB = sum w relu((cos b - d_z) / (1 - cos b))^2 / sum w, directions normalised inside."""
    c = math.sqrt(3.0) / 2.0   # cos 30 deg
    a = math.radians(40.0)
    directions = torch.tensor([[0.0, 0.0, 3.0],                    # +z: inside, 0
                               [math.sin(a), 0.0, math.cos(a)],    # 40 deg: 10 deg beyond the bound
                               [0.0, -5.0, 0.0],                   # horizontal: d_z = 0
                               [0.0, 0.0, -2.0],                   # straight down: d_z = -1
                               [0.4, 0.0, 1.0]], dtype=torch.float64)  # 21.8 deg: inside, 0
    w = torch.tensor([1.0, 2.0, 0.5, 0.25, 4.0], dtype=torch.float64)
    e40 = (c - math.cos(a)) / (1.0 - c)
    e90 = c / (1.0 - c)
    e180 = (c + 1.0) / (1.0 - c)
    ref = (2.0 * e40 ** 2 + 0.5 * e90 ** 2 + 0.25 * e180 ** 2) / 7.75
    got = L.tilt_bound_loss(directions, w, math.radians(30.0))
    assert abs(float(got) - ref) < 1e-12 * ref
    # the excess is the same with any lengths of the vectors, zero inside the bound
    ex = L.tilt_excess(directions, math.radians(30.0)).numpy()
    np.testing.assert_allclose(ex, [c - 1.0, c - math.cos(a), c, c + 1.0, c - 1.0 / math.sqrt(1.16)], atol=1e-15)
    assert float(L.tilt_bound_loss(directions[[0, 4]], w[[0, 4]], math.radians(30.0))) == 0.0
    assert float(L.tilt_bound_loss(torch.zeros((0, 3), dtype=torch.float64), w[:0], 0.5)) == 0.0


def test_tilt_bound_loss_gradient_matches_finite_differences():
    rng = np.random.default_rng(11)
    v = rng.normal(size=(40, 3))
    v[:, 2] += 0.8   # some inside the bound, some beyond it
    angles = np.degrees(np.arccos(v[:, 2] / np.linalg.norm(v, axis=1)))
    assert (angles < 30).sum() > 3 and (angles > 30).sum() > 3 and np.abs(angles - 30).min() > 1e-3
    w = torch.tensor(rng.uniform(0.1, 2.0, 40))
    x = torch.tensor(v, requires_grad=True)
    assert torch.autograd.gradcheck(lambda d: L.tilt_bound_loss(d, w, math.radians(30.0)), (x,), eps=1e-6,
                                    atol=1e-8, rtol=1e-5)
    # the gradient pulls every violating direction toward +z and leaves the others alone
    L.tilt_bound_loss(x, w, math.radians(30.0)).backward()
    g = x.grad.numpy()
    assert np.all(g[angles < 30] == 0.0)
    tangential_z = g[:, 2] - (g * v).sum(1) * v[:, 2] / (v * v).sum(1)   # the component that changes d_z
    assert np.all(tangential_z[angles > 30] < 0)
