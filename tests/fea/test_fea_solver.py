"""Voxel FEA against closed forms: element invariants, cantilever, bar in tension, solvers."""
from __future__ import annotations

import numpy as np
import pytest

from neuralslicer.fea import FEASpec, run_fea
from neuralslicer.fea.element import (
    CORNERS,
    element_stiffness,
    isotropic_D,
    strain_matrix,
    gauss_points,
)
from neuralslicer.fea.grid import grid_for_bounds, voxelize
from neuralslicer.fea.shapes import BoxSolid, CylinderSolid

E, NU = 2000.0, 0.3


def _spec(supports: list, loads: list, voxels: int, **kw: object) -> FEASpec:
    """An isotropic FEASpec from plain dicts."""
    return FEASpec.model_validate(dict(material=dict(youngs_modulus_mpa=E, poisson_ratio=NU),
                                       supports=supports, loads=loads, voxels=voxels, **kw))


def test_element_stiffness_kernel_is_rigid_motion() -> None:
    """The hexahedron's stiffness is symmetric PSD with exactly the 6 rigid-body modes as kernel."""
    h = 0.7
    K = element_stiffness(isotropic_D(E, NU), h)
    assert np.allclose(K, K.T)
    w = np.linalg.eigvalsh(K)
    assert np.sum(np.abs(w) < 1e-9 * w.max()) == 6 and w.min() > -1e-9 * w.max()
    x = CORNERS * h
    rot = np.cross(np.array([0.3, -0.2, 0.5]), x) + np.array([1.0, 2.0, -3.0])
    assert np.abs(K @ rot.ravel()).max() < 1e-9 * w.max()


def test_strain_matrix_reproduces_linear_field() -> None:
    """Patch test: a linear displacement gives its exact (constant) strain at every Gauss point."""
    h = 1.3
    G = np.array([[0.1, 0.2, -0.3], [0.05, -0.1, 0.4], [0.2, 0.0, 0.3]])  # u = G x
    u = (CORNERS * h) @ G.T
    eps = 0.5 * (G + G.T)
    expected = np.array([eps[0, 0], eps[1, 1], eps[2, 2], 2 * eps[1, 2], 2 * eps[0, 2],
                         2 * eps[0, 1]])
    for xi in np.vstack([gauss_points(), np.zeros((1, 3))]):
        assert np.allclose(strain_matrix(xi, h) @ u.ravel(), expected)


def test_grid_fits_box_and_counts_voxels() -> None:
    """A box whose volume / target is a cube of an exact divisor is voxelised exactly."""
    g = voxelize(BoxSolid((0, 0, 0), (40, 10, 20)), 40 * 10 * 20 // 8)    # h = 2
    assert g.spacing == pytest.approx(2.0)
    assert g.n_voxels == 20 * 5 * 10 and g.n_nodes == 21 * 6 * 11
    assert np.allclose(g.nodes.min(axis=0), [0, 0, 0]) and np.allclose(g.nodes.max(axis=0),
                                                                       [40, 10, 20])
    origin, h, shape = grid_for_bounds(np.array([[0, 0, 5.0], [10, 10, 15]]), 1000)
    assert origin[2] == 5.0 and tuple(shape) == (10, 10, 10)


def _cantilever_tip(n_thick: int, method: str = "direct") -> float:
    """Mean tip deflection of a clamped 200x10x10 beam under a 10 N tip load, n_thick voxels."""
    L, t = 200.0, 10.0
    spec = _spec([dict(box=[[-1, -1, -1], [1e-6, 11, 11]])],
                 [dict(box=[[L - 1e-6, -1, -1], [L + 1, 11, 11]], force_n=[0, 0, -10])],
                 voxels=int(L / t) * n_thick ** 3, solver=dict(method=method))
    res = run_fea(BoxSolid((0, 0, 0), (L, t, t)), spec)
    assert res.grid.n_voxels == int(L / t) * n_thick ** 3
    tip = res.grid.nodes[:, 0] > L - 1e-6
    return float(-res.displacement[tip, 2].mean())


def test_cantilever_tip_deflection_converges_to_euler_bernoulli() -> None:
    """Tip deflection F L^3 / (3 E I) (slenderness 20): within 5 % and closer when refined."""
    L, t, F = 200.0, 10.0, 10.0
    exact = F * L ** 3 / (3 * E * t ** 4 / 12)                            # 16 mm
    coarse, fine = _cantilever_tip(4), _cantilever_tip(8)   # slender: banded LU is quick
    err_coarse, err_fine = abs(coarse / exact - 1), abs(fine / exact - 1)
    assert err_fine < 0.05
    assert err_fine < 0.5 * err_coarse                                    # ~h^2 convergence
    assert fine < exact * 1.01                # full-integration hexahedra are stiffer, not softer


def _tension_bar(method: str = "direct") -> tuple[FEASpec, BoxSolid, object]:
    """80x10x10 bar clamped at x=0, 100 N along +x at x=80, 2 mm voxels."""
    L = 80.0
    spec = _spec([dict(plane=dict(axis="x", value=0.0))],
                 [dict(plane=dict(axis="x", value=L), force_n=[100.0, 0, 0])],
                 voxels=int(L * 100 / 8), solver=dict(method=method))
    solid = BoxSolid((0, 0, 0), (L, 10, 10))
    return spec, solid, run_fea(solid, spec)


def test_bar_in_tension_stress_and_direction() -> None:
    """Away from the ends sigma_xx = F/A within 1 %, tau_max along the bar within 1 degree."""
    _, _, res = _tension_bar()
    x = res.centres[:, 0]
    mid = (x > 25) & (x < 55)
    sigma = 100.0 / 100.0
    assert np.allclose(res.stress[mid, 0, 0], sigma, rtol=0.01)
    assert np.allclose(res.max_principal[mid], sigma, rtol=0.01)
    assert np.allclose(res.von_mises[mid], sigma, rtol=0.01)
    angle = np.degrees(np.arccos(np.minimum(1.0, np.abs(res.tau_max[mid, 0]))))
    assert angle.max() < 1.0
    assert np.allclose(np.linalg.norm(res.tau_max, axis=1), 1.0)
    # axial strain and lateral contraction of uniaxial stress
    assert np.allclose(res.strain[mid, 0, 0], sigma / E, rtol=0.01)
    assert np.allclose(res.strain[mid, 1, 1], -NU * sigma / E, rtol=0.02)
    # equilibrium: reactions balance the applied load (sum of the free-node forces)
    assert res.info["total_force_n"] == pytest.approx([100.0, 0.0, 0.0], abs=1e-9)


def test_amg_and_direct_agree() -> None:
    """The AMG-preconditioned CG and the sparse LU give the same displacements."""
    _, _, direct = _tension_bar("direct")
    _, _, amg = _tension_bar("amg")
    assert amg.info["solver"] == "amg" and direct.info["solver"] == "direct"
    scale = np.abs(direct.displacement).max()
    assert np.abs(amg.displacement - direct.displacement).max() < 1e-6 * scale


def test_cylinder_on_platform_section_force_balances_load() -> None:
    """A cylinder on the platform pressed on its top: mean axial stress = F / (voxel area)."""
    cyl = CylinderSolid(5.0, 0.0, 30.0)
    spec = _spec([dict(platform=True)],
                 [dict(plane=dict(axis="z", value=30.0), force_n=[0, 0, -50.0])], voxels=3000)
    res = run_fea(cyl, spec)
    h = res.grid.spacing
    layer = res.grid.ijk[:, 2]
    band = layer == layer.max() // 2                                      # one voxel layer
    area = band.sum() * h * h
    assert res.stress[band, 2, 2].sum() * h * h == pytest.approx(-50.0, rel=1e-6)
    assert np.abs(res.stress[band, 2, 2]).max() < 1.3 * 50.0 / area
    assert np.all(res.max_principal[band] < 0)                            # compression
