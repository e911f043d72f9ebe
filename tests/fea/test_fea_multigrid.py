"""Matrix-free geometric multigrid: operator, V-cycle and PCG against the assembled matrix."""
from __future__ import annotations

import numpy as np
import pytest
import scipy.sparse.linalg as spla

from neuralslicer.fea import FEASpec, run_fea
from neuralslicer.fea.assembly import assemble_stencil, neighbour_table, stencil_to_bsr
from neuralslicer.fea.element import element_stiffness, isotropic_D
from neuralslicer.fea.grid import VoxelGrid, voxelize
from neuralslicer.fea.multigrid import P_LOC, Multigrid
from neuralslicer.fea.shapes import BoxSolid, CylinderSolid, UnionSolid
from neuralslicer.fea.solver import fixed_dofs, load_vector

E, NU = 2000.0, 0.3


class _Holed:
    """``solid`` minus a vertical cylinder of ``radius`` about (cx, cy)."""

    def __init__(self, solid: object, cx: float, cy: float, radius: float) -> None:
        self.solid, self.c, self.r = solid, np.array([cx, cy]), radius
        self.bounds = solid.bounds                         # type: ignore[attr-defined]
        self.platform_z = solid.platform_z                 # type: ignore[attr-defined]

    def H(self, x: np.ndarray) -> np.ndarray:
        """Signed value: outside the hole and inside the solid is negative."""
        hole = self.r - np.linalg.norm(x[:, :2] - self.c, axis=1)
        return np.maximum(self.solid.H(x), hole)           # type: ignore[attr-defined]


def _holed_l() -> tuple[object, FEASpec]:
    """An L (two boxes) with a hole, clamped at x = 0, a tip load along -z and +y."""
    solid = _Holed(UnionSolid(BoxSolid((0, 0, 0), (30, 10, 8)), BoxSolid((20, 0, 0), (30, 30, 8))),
                   25.0, 20.0, 2.5)
    spec = FEASpec.model_validate(dict(
        supports=[dict(box=[[-1, -1, -1], [1e-6, 11, 9]])],
        loads=[dict(box=[[19, 30 - 1e-6, -1], [31, 31, 9]], force_n=[0, 5, -10])], voxels=4000))
    return solid, spec


def _tube() -> tuple[object, FEASpec]:
    """A tube on the platform, its top pressed down and sideways."""
    solid = _Holed(CylinderSolid(8.0, 0.0, 12.0), 0.0, 0.0, 5.0)
    spec = FEASpec.model_validate(dict(
        supports=[dict(platform=True)],
        loads=[dict(plane=dict(axis="z", value=12.0), force_n=[3, 0, -20])], voxels=5000))
    return solid, spec


def _symmetric_bar() -> tuple[object, FEASpec]:
    """A bar on symmetry planes (one component fixed each; x = 3 is an odd node layer), pulled."""
    solid = BoxSolid((0, 0, 0), (30, 7, 6))
    spec = FEASpec.model_validate(dict(
        supports=[dict(plane=dict(axis="x", value=3.0), fix=[True, False, False]),
                  dict(plane=dict(axis="y", value=0.0), fix=[False, True, False]),
                  dict(plane=dict(axis="z", value=0.0), fix=[False, False, True])],
        loads=[dict(plane=dict(axis="x", value=30.0), pressure_mpa=-2.0)], voxels=30 * 7 * 6))
    return solid, spec


def _system(solid: object, spec: FEASpec) -> tuple[VoxelGrid, np.ndarray, np.ndarray, object,
                                                   np.ndarray]:
    """Grid, fixed mask, load, assembled matrix (BSR) and element matrix of a model."""
    grid = voxelize(solid, spec.voxels)                    # type: ignore[arg-type]
    pz = float(solid.platform_z)                           # type: ignore[attr-defined]
    fixed = fixed_dofs(grid, spec.supports, pz)
    f = load_vector(grid, spec.loads, pz)
    f[fixed] = 0.0
    Ke = element_stiffness(isotropic_D(E, NU), grid.spacing)
    S, has = assemble_stencil(grid, lambda a, b: Ke[3 * a:3 * a + 3, 3 * b:3 * b + 3])
    K = stencil_to_bsr(S, has, neighbour_table(grid), fixed)
    return grid, fixed, f, K, Ke


def test_local_prolongation_keeps_rigid_motion() -> None:
    """Trilinear prolongation of a linear field is that field on each child's corners."""
    from neuralslicer.fea.element import CORNERS
    G = np.array([[0.1, 0.2, -0.3], [0.05, -0.1, 0.4], [0.2, 0.0, 0.3]])
    coarse = (2.0 * CORNERS) @ G.T + 1.0
    for c in range(8):
        child = (CORNERS[c] + CORNERS) @ G.T + 1.0
        assert np.allclose(P_LOC[c] @ coarse.ravel(), child.ravel())


def test_matrix_free_operator_equals_assembled_matrix() -> None:
    """The fine operator (with fixed DOFs) times a random vector equals the BSR matrix times it."""
    grid, fixed, _, K, Ke = _system(*_holed_l())
    mg = Multigrid(grid, Ke, fixed, coarse_dofs=600)
    x = np.random.default_rng(3).standard_normal(K.shape[0])
    y = K @ x
    assert fixed.any() and not fixed.all()
    assert np.abs(mg.A @ x - y).max() < 1e-12 * np.abs(y).max()
    assert np.allclose(mg.A.diagonal(), K.diagonal(), rtol=1e-12)


@pytest.mark.parametrize("model", [_holed_l, _tube, _symmetric_bar])
def test_multigrid_pcg_matches_direct_solve(model) -> None:
    """PCG with the V-cycle (several levels, float32 cycle) gives the sparse LU solution."""
    grid, fixed, f, K, Ke = _system(*model())
    direct = spla.splu(K.tocsc()).solve(f)
    mg = Multigrid(grid, Ke, fixed, coarse_dofs=300)
    assert len(mg.levels) >= 3
    u, iters = mg.solve(f, 1e-10, 200)
    assert iters < 40
    assert np.abs(u - direct).max() < 1e-6 * np.abs(direct).max()
    assert np.all(u[fixed] == 0.0)


def test_vcycle_is_symmetric() -> None:
    """x^T M y == y^T M x for the V-cycle M (exact in float64, to rounding in float32)."""
    grid, fixed, _, _, Ke = _system(*_tube())
    rng = np.random.default_rng(7)
    x, y = rng.standard_normal((2, 3 * grid.n_nodes))
    x[fixed] = y[fixed] = 0.0
    for dtype, tol in ((np.float64, 1e-10), (np.float32, 1e-4)):
        mg = Multigrid(grid, Ke, fixed, coarse_dofs=600, dtype=dtype)
        a, b = x @ mg.precondition(y), y @ mg.precondition(x)
        assert abs(a - b) < tol * abs(a)
        assert x @ mg.precondition(x) > 0 and y @ mg.precondition(y) > 0      # SPD


def test_cantilever_multigrid_matches_euler_bernoulli() -> None:
    """auto picks mg for a large isotropic beam; the tip deflection is the direct/AMG one."""
    spec = FEASpec.model_validate(dict(
        material=dict(youngs_modulus_mpa=E, poisson_ratio=NU),
        supports=[dict(box=[[-1, -1, -1], [1e-6, 11, 11]])],
        loads=[dict(box=[[100 - 1e-6, -1, -1], [101, 11, 11]], force_n=[0, 0, -10])],
        voxels=40_000))
    res = run_fea(BoxSolid((0, 0, 0), (100, 10, 10)), spec)
    assert res.info["solver"] == "mg" and res.info["relative_residual"] < 1e-7
    g = res.grid
    tip = g.nodes[:, 0] > g.nodes[:, 0].max() - 1e-6
    size = (g.ijk.max(axis=0) - g.ijk.min(axis=0) + 1) * g.spacing
    exact = 10 * size[0] ** 3 / (3 * E * size[1] * size[2] ** 3 / 12)
    assert -res.displacement[tip, 2].mean() == pytest.approx(exact, rel=2e-3)


def test_method_choice() -> None:
    """auto: direct when small, mg for the isotropic material, amg for a per-voxel one."""
    from neuralslicer.fea.solver import resolve_method
    from neuralslicer.fea.spec import SolverOptions
    auto, mg = SolverOptions(), SolverOptions(method="mg")
    assert resolve_method(auto, 100, isotropic=True) == "direct"
    assert resolve_method(auto, 10**5, isotropic=True) == "mg"
    assert resolve_method(auto, 10**5, isotropic=False) == "amg"
    assert resolve_method(mg, 10**5, isotropic=False) == "amg"
    assert resolve_method(mg, 100, isotropic=True) == "mg"
