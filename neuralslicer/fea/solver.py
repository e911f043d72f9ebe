"""Linear elasticity on voxels: supports, loads, the solve and the per-voxel stress state."""
from __future__ import annotations

import time
from dataclasses import dataclass, field, fields
from typing import Any

import numpy as np
import scipy.sparse as sp
import scipy.sparse.csgraph as csgraph
import scipy.sparse.linalg as spla

from neuralslicer.errors import InputError, NeuralSlicerError
from neuralslicer.fea.assembly import assemble_stencil, neighbour_table, stencil_to_bsr
from neuralslicer.fea.element import (
    element_stiffness,
    isotropic_D,
    stiffness_basis,
    strain_matrix,
    voigt_to_tensor,
)
from neuralslicer.fea.grid import SolidLike, VoxelGrid, voxelize
from neuralslicer.fea.multigrid import Multigrid
from neuralslicer.fea.spec import FEASpec, Load, SolverOptions, Support, _Region

SCHEMA_VERSION = 1
_AXES = {"x": 0, "y": 1, "z": 2}
_NO_SUPPORTS = ("no supports: the model is unconstrained (free to move as a rigid body); add "
                "e.g. '- platform: true' or a 'box' support")


# --------------------------------------------------------------------------- regions, BCs
def region_nodes(region: _Region, points: np.ndarray, spacing: float,
                 platform_z: float, plane_tol: float = 0.5) -> np.ndarray:
    """Mask (n,) bool of ``points`` (n, 3) inside a support/load region (box, plane or platform).

    A plane without ``tol`` keeps points within ``plane_tol * spacing`` of it (nodes: half a
    voxel; face centres: a quarter, so the side faces next to an end face are not taken).
    """
    eps = 1e-9 * max(1.0, float(np.abs(points).max(initial=0.0)))
    if region.box is not None:
        lo, hi = np.asarray(region.box, dtype=np.float64)
        return np.all((points >= lo - eps) & (points <= hi + eps), axis=1)
    if region.plane is not None:
        tol = plane_tol * spacing if region.plane.tol is None else region.plane.tol
        return np.abs(points[:, _AXES[region.plane.axis]] - region.plane.value) <= tol + eps
    return points[:, 2] <= platform_z + 0.5 * spacing + eps


def fixed_dofs(grid: VoxelGrid, supports: list[Support], platform_z: float,
               strict: bool = True) -> np.ndarray:
    """Mask (3m,) bool of the DOFs held by ``supports``; a support selecting nothing is an error."""
    if strict and not supports:
        raise InputError("fea.supports", _NO_SUPPORTS)
    nodes = grid.nodes
    fixed = np.zeros((grid.n_nodes, 3), dtype=bool)
    for i, s in enumerate(supports):
        sel = region_nodes(s, nodes, grid.spacing, platform_z)
        if strict and not sel.any():
            raise InputError(f"fea.supports[{i}]", f"the support region ({s.describe()}) selects "
                             "no node of the voxel model; the model is unconstrained there. Check "
                             "the coordinates (build frame, mm, +z up)")
        fixed[np.ix_(sel, np.asarray(s.fix, dtype=bool))] = True
    return fixed.ravel()


def _boundary_faces(grid: VoxelGrid) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Boundary voxel faces: (voxel index (k,), outward axis normal (k, 3), face node ids (k, 4))."""
    from neuralslicer.fea.element import CORNERS
    shape = grid.shape
    total = int(np.prod(shape))
    lin = (grid.ijk[:, 2] * shape[1] + grid.ijk[:, 1]) * shape[0] + grid.ijk[:, 0]
    occupied = np.zeros(total, dtype=bool)
    occupied[lin] = True
    vox, normals, fnodes = [], [], []
    for axis in range(3):
        for side in (-1, 1):
            q = grid.ijk.copy()
            q[:, axis] += side
            inside = (q[:, axis] >= 0) & (q[:, axis] < shape[axis])
            qlin = (q[:, 2] * shape[1] + q[:, 1]) * shape[0] + q[:, 0]
            free = ~inside | ~occupied[np.where(inside, qlin, 0)]
            local = np.flatnonzero(CORNERS[:, axis] == (1 if side > 0 else 0))
            idx = np.flatnonzero(free)
            n = np.zeros(3)
            n[axis] = side
            vox.append(idx)
            normals.append(np.broadcast_to(n, (idx.size, 3)))
            fnodes.append(grid.elements[idx][:, local])
    return np.concatenate(vox), np.concatenate(normals), np.concatenate(fnodes)


def load_vector(grid: VoxelGrid, loads: list[Load], platform_z: float,
                strict: bool = True) -> np.ndarray:
    """Nodal force vector (3m,) [N]: each ``force_n`` split evenly over the nodes it selects,
    each ``pressure_mpa`` integrated over the boundary voxel faces whose centre it selects."""
    f = np.zeros((grid.n_nodes, 3))
    nodes = grid.nodes
    faces = None
    for i, load in enumerate(loads):
        if load.force_n is not None:
            sel = np.flatnonzero(region_nodes(load, nodes, grid.spacing, platform_z))
            if sel.size == 0:
                if strict:
                    raise InputError(f"fea.loads[{i}]", f"the load region ({load.describe()}) "
                                     "selects no node of the voxel model. Check the coordinates "
                                     "(build frame, mm, +z up)")
            else:
                f[sel] += np.asarray(load.force_n) / sel.size
        if load.pressure_mpa is not None:
            if faces is None:
                faces = _boundary_faces(grid)
            vox, nrm, fn = faces
            centre = nodes[fn].mean(axis=1)
            sel = region_nodes(load, centre, grid.spacing, platform_z, plane_tol=0.25)
            if not sel.any():
                if strict:
                    raise InputError(f"fea.loads[{i}]", f"the pressure region ({load.describe()})"
                                     " contains no boundary face of the voxel model")
                continue
            force = -load.pressure_mpa * grid.spacing ** 2 / 4.0 * nrm[sel]     # per face node
            for c in range(4):
                np.add.at(f, fn[sel, c], force)
    if strict and loads and not np.any(f):
        raise InputError("fea.loads", "all loads are zero")
    return f.ravel()


def rigid_body_modes(points: np.ndarray) -> np.ndarray:
    """Rigid-body displacement basis (3n, 6) at ``points`` (n, 3): 3 translations, 3 rotations."""
    c = points - points.mean(axis=0)
    c = c / max(float(np.abs(c).max(initial=0.0)), 1e-12)
    n = points.shape[0]
    B = np.zeros((n, 3, 6))
    B[:, 0, 0] = B[:, 1, 1] = B[:, 2, 2] = 1.0
    B[:, 1, 3], B[:, 2, 3] = -c[:, 2], c[:, 1]           # rotation about x
    B[:, 0, 4], B[:, 2, 4] = c[:, 2], -c[:, 0]           # about y
    B[:, 0, 5], B[:, 1, 5] = -c[:, 1], c[:, 0]           # about z
    return B.reshape(3 * n, 6)


def constrained_modes(points: np.ndarray, fixed: np.ndarray) -> int:
    """How many of the 6 rigid-body modes of ``points`` (n, 3) the fixed DOFs (3n,) bool stop."""
    if not fixed.any():
        return 0
    M = rigid_body_modes(points)[fixed]
    s = np.linalg.svd(M.T @ M, compute_uv=False)
    return int(np.sum(s > 1e-10 * s[0]))


def voxel_components(grid: VoxelGrid) -> np.ndarray:
    """Label (n,) int64 of the face-connected component of each voxel."""
    shape = grid.shape
    total = int(np.prod(shape))
    lin = (grid.ijk[:, 2] * shape[1] + grid.ijk[:, 1]) * shape[0] + grid.ijk[:, 0]
    vid = np.full(total, -1, dtype=np.int64)
    vid[lin] = np.arange(grid.n_voxels)
    rows, cols = [], []
    for axis in range(3):
        q = grid.ijk.copy()
        q[:, axis] += 1
        ok = q[:, axis] < shape[axis]
        qlin = (q[ok, 2] * shape[1] + q[ok, 1]) * shape[0] + q[ok, 0]
        other = vid[qlin]
        hit = other >= 0
        rows.append(np.flatnonzero(ok)[hit])
        cols.append(other[hit])
    r, c = np.concatenate(rows), np.concatenate(cols)
    A = sp.coo_matrix((np.ones(r.size, dtype=np.int8), (r, c)),
                      shape=(grid.n_voxels, grid.n_voxels))
    return csgraph.connected_components(A, directed=False)[1].astype(np.int64)


def held_voxels(grid: VoxelGrid, fixed: np.ndarray, force: np.ndarray) -> np.ndarray:
    """Mask (n,) of voxels in face-connected parts whose supports stop all 6 rigid-body modes.

    A part that is not held and carries load is an error; an unloaded loose part (a voxelisation
    island) is dropped.
    """
    labels = voxel_components(grid)
    n_comp = int(labels.max()) + 1
    fixed_n = fixed.reshape(-1, 3)
    loaded_n = np.any(force.reshape(-1, 3) != 0, axis=1)
    keep = np.zeros(n_comp, dtype=bool)
    comp_has_fixed = np.zeros(n_comp, dtype=bool)
    comp_loaded = np.zeros(n_comp, dtype=bool)
    el_fixed = fixed_n.any(axis=1)[grid.elements].any(axis=1)
    el_loaded = loaded_n[grid.elements].any(axis=1)
    np.logical_or.at(comp_has_fixed, labels, el_fixed)
    np.logical_or.at(comp_loaded, labels, el_loaded)
    order = np.argsort(labels, kind="stable")
    starts = np.searchsorted(labels[order], np.arange(n_comp + 1))
    worst = 6
    for c in np.flatnonzero(comp_has_fixed):                 # loop over parts, not elements
        vox = order[starts[c]:starts[c + 1]]
        nid = np.unique(grid.elements[vox])
        k = constrained_modes(grid.nodes[nid], fixed_n[nid].ravel())
        keep[c] = k == 6
        if comp_loaded[c] and k < 6:
            worst = min(worst, k)
    bad = comp_loaded & ~keep
    if bad.any():
        if not comp_has_fixed[bad].all():
            msg = ("a loaded part of the model is not connected to any support (it would move as "
                   "a rigid body)")
        else:
            msg = (f"the supports leave rigid-body motion free: they stop only {worst} of the 6 "
                   "rigid-body modes (a support on a single point or line lets the part "
                   "rotate); fix a larger region or more components")
        raise InputError("fea.supports", msg)
    if not keep.any():
        raise InputError("fea.supports", "the supports leave the model free to move as a rigid "
                         "body")
    return keep[labels]


# --------------------------------------------------------------------------- solve
def resolve_method(opts: SolverOptions, n_dofs: int, isotropic: bool) -> str:
    """The solver of ``opts.method`` for n_dofs: auto is direct when small, else mg (isotropic,
    matrix-free geometric multigrid) or amg (per-voxel material, assembled); mg needs equal
    voxels, so a per-voxel material takes auto's choice among direct and amg instead."""
    if opts.method not in ("auto", "mg"):
        return opts.method
    if opts.method == "mg" and isotropic:
        return "mg"
    if n_dofs <= opts.direct_max_dofs:
        return "direct"
    return "mg" if isotropic else "amg"


def _checked(u: np.ndarray, residual: np.ndarray, f: np.ndarray, method: str, rtol: float
             ) -> float:
    """Relative residual ||K u - f|| / ||f||; an error when not finite or above the tolerance."""
    r = float(np.linalg.norm(residual)) / (float(np.linalg.norm(f)) or 1.0)
    if not np.all(np.isfinite(u)) or not r <= max(1e-4, 100 * rtol):
        raise NeuralSlicerError(f"FEA solve ({method}) did not converge: relative residual {r:.3g}")
    return r


def solve_system(K: sp.bsr_matrix, f: np.ndarray, points: np.ndarray, spec: FEASpec
                 ) -> tuple[np.ndarray, str, int, float]:
    """Solve K u = f: sparse LU when small, else CG preconditioned by smoothed-aggregation AMG."""
    opts = spec.solver
    n = K.shape[0]
    method = opts.method
    if method in ("auto", "mg"):             # an assembled matrix: mg is for solve_multigrid
        method = "direct" if n <= opts.direct_max_dofs else "amg"
    if method == "direct":
        try:
            lu = spla.splu(K.tocsc(), permc_spec="COLAMD")
        except RuntimeError as exc:             # exactly singular
            raise NeuralSlicerError(f"FEA stiffness matrix is singular: {exc}") from exc
        u = lu.solve(f)
        iters = 1
    else:
        import pyamg
        ml = pyamg.smoothed_aggregation_solver(
            K, B=rigid_body_modes(points), BH=None, symmetry="symmetric",
            strength=("symmetric", {"theta": 0.0}), smooth=("jacobi", {"omega": 4.0 / 3.0}),
            improve_candidates=None, max_coarse=500, coarse_solver="splu")
        res: list[float] = []
        u = ml.solve(f, tol=opts.rtol, accel="cg", maxiter=opts.maxiter, residuals=res)
        iters = len(res) - 1
    return u, method, iters, _checked(u, K @ u - f, f, method, opts.rtol)


def solve_multigrid(mg: Multigrid, f: np.ndarray, spec: FEASpec
                    ) -> tuple[np.ndarray, str, int, float]:
    """Solve A u = f with CG preconditioned by the geometric multigrid V-cycle ``mg``."""
    opts = spec.solver
    u, iters = mg.solve(f, opts.rtol, opts.maxiter)
    return u, "mg", iters, _checked(u, mg.A @ u - f, f, "mg", opts.rtol)


# --------------------------------------------------------------------------- results
@dataclass
class FEAResult:
    """Solution on the active voxels (build frame; MPa, mm).

    grid : the voxels; displacement : (m, 3) per node; strain : (n, 3, 3) tensor at voxel centres;
    stress : (n, 3, 3); principal_stress : (n, 3) ascending; principal_directions : (n, 3, 3),
    column k is the direction of principal_stress[:, k]; tau_max : (n, 3) unit direction of the
    principal stress of largest magnitude; max_principal : (n,) that principal stress, signed;
    von_mises : (n,).
    """

    grid: VoxelGrid
    displacement: np.ndarray
    strain: np.ndarray
    stress: np.ndarray
    principal_stress: np.ndarray
    principal_directions: np.ndarray
    tau_max: np.ndarray
    max_principal: np.ndarray
    von_mises: np.ndarray
    info: dict[str, Any] = field(default_factory=dict)

    @property
    def centres(self) -> np.ndarray:
        """Voxel centres (n, 3)."""
        return self.grid.centres

    def to_arrays(self) -> tuple[dict[str, np.ndarray], dict[str, Any]]:
        """Store-able (arrays, json attrs)."""
        g = self.grid
        arrays = {
            "ijk": g.ijk.astype(np.int32), "nodes": g.nodes,
            "elements": g.elements.astype(np.int32),
            "centres": g.centres, "displacement": self.displacement, "strain": self.strain,
            "stress": self.stress, "principal_stress": self.principal_stress,
            "principal_directions": self.principal_directions, "tau_max": self.tau_max,
            "max_principal": self.max_principal, "von_mises": self.von_mises,
        }
        attrs = {"schema_version": SCHEMA_VERSION, "origin": g.origin.tolist(),
                 "spacing": g.spacing, "shape": [int(s) for s in g.shape],
                 "units": {"length": "mm", "stress": "MPa", "force": "N"}, **self.info}
        return arrays, attrs

    @classmethod
    def from_arrays(cls, arrays: dict[str, np.ndarray], attrs: dict[str, Any]) -> "FEAResult":
        """Inverse of ``to_arrays``."""
        grid = VoxelGrid.from_ijk(np.asarray(attrs["origin"]), float(attrs["spacing"]),
                                  np.asarray(attrs["shape"]), np.asarray(arrays["ijk"]))
        info = {k: v for k, v in attrs.items()
                if k not in ("schema_version", "origin", "spacing", "shape", "units")}
        return cls(grid, *(np.asarray(arrays[k]) for k in (
            "displacement", "strain", "stress", "principal_stress", "principal_directions",
            "tau_max", "max_principal", "von_mises")), info=info)


#: the strain figures of a printed part's FEA (``verify.printed_fea_of``), kept in its attributes
PRINTED_FIGURES = ("max_strain", "max_strain_p99", "max_displacement_mm", "tau_turn_median_deg", "tau_turn_p90_deg")


@dataclass
class PrintedFEA(FEAResult):
    """The FEA of a part as printed (``verify.printed_fea_of``): an FEA result (a strength round samples its T from
    it) with the print's strain figures and ``turn``, how the printed material turned tau_max at T's voxels
    (``verify.stress_turn``)."""

    figures: dict[str, float] = field(default_factory=dict)
    turn: dict[str, np.ndarray] = field(default_factory=dict)

    @classmethod
    def of(cls, result: FEAResult, figures: dict[str, float], turn: dict[str, np.ndarray]) -> "PrintedFEA":
        """``result`` with the print's strain figures and how tau_max turned."""
        return cls(**{f.name: getattr(result, f.name) for f in fields(FEAResult)}, figures=figures, turn=turn)

    def to_arrays(self) -> tuple[dict[str, np.ndarray], dict[str, Any]]:
        """The FEA's arrays with ``turn/*``, its attributes with the figures."""
        arrays, attrs = super().to_arrays()
        return {**arrays, **{f"turn/{k}": v for k, v in self.turn.items()}}, {**attrs, **self.figures}

    @classmethod
    def from_arrays(cls, arrays: dict[str, np.ndarray], attrs: dict[str, Any]) -> "PrintedFEA":
        """Inverse of ``to_arrays``."""
        base = FEAResult.from_arrays(arrays, attrs)
        figures = {k: float(attrs[k]) for k in PRINTED_FIGURES if k in attrs}
        base.info = {k: v for k, v in base.info.items() if k not in figures}
        turn = {k.split("/", 1)[1]: np.asarray(v) for k, v in arrays.items() if k.startswith("turn/")}
        return cls.of(base, figures, turn)


def principal(stress: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """Principal values (n,3) ascending, directions (n,3,3), tau_max (n,3), signed max (n,)."""
    w, v = np.linalg.eigh(stress)
    k = np.argmax(np.abs(w), axis=1)
    rows = np.arange(w.shape[0])
    return w, v, v[rows, :, k], w[rows, k]


def von_mises(stress: np.ndarray) -> np.ndarray:
    """Von Mises equivalent stress (n,) of stress tensors (n, 3, 3)."""
    s = stress
    return np.sqrt(0.5 * ((s[:, 0, 0] - s[:, 1, 1]) ** 2 + (s[:, 1, 1] - s[:, 2, 2]) ** 2
                          + (s[:, 2, 2] - s[:, 0, 0]) ** 2)
                   + 3.0 * (s[:, 0, 1] ** 2 + s[:, 1, 2] ** 2 + s[:, 0, 2] ** 2))


# --------------------------------------------------------------------------- driver
def solve_on_grid(grid: VoxelGrid, spec: FEASpec, platform_z: float,
                  D: np.ndarray | None = None) -> FEAResult:
    """Assemble and solve on ``grid`` with the isotropic material, or per-voxel D (n, 6, 6)."""
    t0 = time.perf_counter()
    fixed = fixed_dofs(grid, spec.supports, platform_z)
    f = load_vector(grid, spec.loads, platform_z)
    keep = held_voxels(grid, fixed, f)
    dropped = int(grid.n_voxels - keep.sum())
    if dropped:
        grid = grid.subset(keep)
        if D is not None:
            D = D[keep]
        fixed = fixed_dofs(grid, spec.supports, platform_z, strict=False)
        f = load_vector(grid, spec.loads, platform_z, strict=False)
    h = grid.spacing
    method = resolve_method(spec.solver, 3 * grid.n_nodes, isotropic=D is None)
    f[fixed] = 0.0
    if D is None:
        Diso = isotropic_D(spec.material.youngs_modulus_mpa, spec.material.poisson_ratio)
        Ke = element_stiffness(Diso, h)
    u = None
    fallback = None
    if method == "mg":
        try:
            mg = Multigrid(grid, Ke, fixed)
            n_dofs, nnz = mg.A.n, None
            t1 = time.perf_counter()
            u, method, iters, res = solve_multigrid(mg, f, spec)
        except (RuntimeError, NeuralSlicerError) as exc:     # singular coarse level, no convergence
            if spec.solver.method == "mg":
                raise
            u, fallback = None, f"mg: {exc}"          # auto: the assembled AMG solve instead, recorded
        mg = None
    if u is None:
        if D is None:
            S, has = assemble_stencil(grid, lambda a, b: Ke[3 * a:3 * a + 3, 3 * b:3 * b + 3])
        else:
            Q = stiffness_basis()
            Dflat = D.reshape(-1, 36)

            def block(a: int, b: int) -> np.ndarray:
                q = Q[:, :, 3 * a:3 * a + 3, 3 * b:3 * b + 3].reshape(36, 9)
                return (h * (Dflat @ q)).reshape(-1, 3, 3)
            S, has = assemble_stencil(grid, block)
        nbr = neighbour_table(grid)
        K = stencil_to_bsr(S, has, nbr, fixed)
        del S, has, nbr
        n_dofs, nnz = int(K.shape[0]), int(K.nnz)
        t1 = time.perf_counter()
        u, method, iters, res = solve_system(K, f, grid.nodes, spec)
        del K
    t2 = time.perf_counter()
    u = u.reshape(-1, 3)
    B0 = strain_matrix(np.zeros(3), h)                                     # (6, 24) at centre
    ue = u[grid.elements].reshape(-1, 24)
    eps_v = ue @ B0.T                                                      # (n, 6) engineering
    if D is None:
        sig_v = eps_v @ Diso.T
    else:
        sig_v = np.einsum("npq,nq->np", D, eps_v)
    stress = voigt_to_tensor(sig_v)
    w, v, tau, smax = principal(stress)
    info = {"n_voxels": grid.n_voxels, "n_nodes": grid.n_nodes, "dropped_voxels": dropped,
            "solver": method, "iterations": iters, "relative_residual": res,
            "n_dofs": n_dofs, "n_fixed_dofs": int(fixed.sum()), "nnz": nnz,
            "assembly_s": t1 - t0, "solve_s": t2 - t1,
            "total_force_n": f.reshape(-1, 3).sum(axis=0).tolist()}
    if fallback is not None:
        info["solver_fallback"] = fallback
    return FEAResult(grid, u, voigt_to_tensor(eps_v, engineering_shear=True), stress, w, v, tau,
                     smax, von_mises(stress), info)


def check_spec(spec: FEASpec) -> None:
    """Errors that need no geometry: no supports, no loads."""
    if not spec.supports:
        raise InputError("fea.supports", _NO_SUPPORTS)
    if not spec.loads:
        raise InputError("fea.loads", "no loads: give at least one load with 'force_n' or "
                         "'pressure_mpa'")


def run_fea(solid: SolidLike, spec: FEASpec) -> FEAResult:
    """Isotropic voxel FEA of ``solid`` (H <= 0) with the supports and loads of ``spec``."""
    check_spec(spec)
    grid = voxelize(solid, spec.voxels)
    res = solve_on_grid(grid, spec, float(solid.platform_z))
    res.info["material"] = spec.material.model_dump()
    return res
