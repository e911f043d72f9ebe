"""Differentiable scale-controlled ARAP deformation of the cage (SPEC step 6).

The deformed vertices xi solve ``(A^T A + gamma I) xi = A^T b(q, s) + gamma xi0``. The system matrix
does not depend on q or s: it is factored once (sparse) and the same factor serves every forward
solve and every backward solve (K is symmetric, so the adjoint of ``xi = K^-1 r`` is ``K^-1 g``).
With the centring matrix N = I - 1/4, ``A^T b`` is just the scatter-add of each element's rotated
and scaled centred rest shape ``T_e = (N V_e) S_e R_e^T`` onto its four vertices.
"""
from __future__ import annotations

from typing import Callable

import numpy as np
import scipy.sparse as sp
import scipy.sparse.linalg as spla
import torch

from neuralslicer.neural.config import DeformationConfig
from neuralslicer.neural.networks import quaternion_to_matrix, quaternion_to_z_row

#: centring matrix N = I_4 - 1/4 * ones
CENTRING = np.eye(4) - 0.25


def arap_matrix(n_vertices: int, tets: np.ndarray, gamma: float) -> sp.csc_matrix:
    """K = A^T A + gamma I (n,n) sparse: per element the 4x4 block N scattered on its vertices."""
    tets = np.asarray(tets, dtype=np.int64)
    rows = np.repeat(tets, 4, axis=1).ravel()
    cols = np.tile(tets, (1, 4)).ravel()
    vals = np.tile(CENTRING.ravel(), len(tets))
    K = sp.coo_matrix((vals, (rows, cols)), shape=(n_vertices, n_vertices)).tocsc()
    K = K + gamma * sp.identity(n_vertices, format="csc")
    K.sum_duplicates()
    return K.tocsc()


def factorize(K: sp.spmatrix, solver: str = "auto") -> tuple[Callable[[np.ndarray], np.ndarray], str]:
    """Factor the SPD matrix K once; returns (solve(b (n,) or (n,k)) -> x, name of the backend)."""
    K = sp.csc_matrix(K)
    if solver in ("auto", "cholmod"):
        try:
            from sksparse.cholmod import cholesky  # type: ignore[import-not-found]

            factor = cholesky(K)
            return (lambda b: factor(b)), "cholmod"
        except ImportError:
            if solver == "cholmod":
                raise
    if solver in ("auto", "cholespy"):
        try:
            return _cholespy_solver(K), "cholespy"
        except ImportError:
            if solver == "cholespy":
                raise
    lu = spla.splu(K, permc_spec="MMD_AT_PLUS_A", options={"SymmetricMode": True})
    return lu.solve, "splu"


def _cholespy_solver(K: sp.spmatrix) -> Callable[[np.ndarray], np.ndarray]:
    """Sparse Cholesky (cholespy, CPU) of K; solve(b (n,) or (n,k) float64) -> x."""
    from cholespy import CholeskySolverD, MatrixType  # type: ignore[import-not-found]

    coo = sp.coo_matrix(K)
    factor = CholeskySolverD(
        coo.shape[0],
        torch.as_tensor(coo.row, dtype=torch.int32),
        torch.as_tensor(coo.col, dtype=torch.int32),
        torch.as_tensor(coo.data, dtype=torch.float64),
        MatrixType.COO,
    )

    def solve(b: np.ndarray) -> np.ndarray:
        """x = K^-1 b on the CPU."""
        rhs = torch.as_tensor(np.ascontiguousarray(b, dtype=np.float64))
        x = torch.zeros_like(rhs)
        factor.solve(rhs, x)
        return x.numpy()

    return solve


class _FactorSolve(torch.autograd.Function):
    """x = S(r) for a fixed symmetric linear map S (a factor solve); backward g -> S(g)."""

    @staticmethod
    def forward(ctx, rhs: torch.Tensor, solve: Callable[[np.ndarray], np.ndarray]) -> torch.Tensor:  # type: ignore[override]
        ctx.solve = solve
        x = solve(rhs.detach().cpu().numpy().astype(np.float64))
        return torch.as_tensor(x, dtype=rhs.dtype, device=rhs.device)

    @staticmethod
    def backward(ctx, grad: torch.Tensor) -> tuple[torch.Tensor, None]:  # type: ignore[override]
        g = ctx.solve(grad.detach().cpu().numpy().astype(np.float64))
        return torch.as_tensor(g, dtype=grad.dtype, device=grad.device), None


def factor_solve(rhs: torch.Tensor, solve: Callable[[np.ndarray], np.ndarray]) -> torch.Tensor:
    """Differentiable x = S(rhs) for a symmetric linear map S given by a sparse factor solve."""
    return _FactorSolve.apply(rhs, solve)


class ArapDeformation:
    """The cage's ARAP system, factored once; maps per-element (q, s) to deformed vertices.

    Parameters
    ----------
    vertices : (n, 3) float64 cage vertices (build frame, z up).
    tets : (m, 4) int64 cage tets.
    config : gamma, platform pinning, solver backend.
    platform_z : height of the platform, used only when ``config.pin_platform``.

    With ``pin_platform`` the z coordinate of every vertex with ``z <= platform_z + tol`` is
    eliminated from the z system (hard constraint, ``v^d_z = v_z``); x and y stay free. The z system
    then has its own factor of the free-free block ``K_ff``; ``z_f = K_ff^-1 (r_f - K_fc z_c)``.
    """

    def __init__(
        self,
        vertices: np.ndarray,
        tets: np.ndarray,
        config: DeformationConfig | None = None,
        platform_z: float | None = None,
    ) -> None:
        self.config = config or DeformationConfig()
        self.vertices = np.asarray(vertices, dtype=np.float64)
        self.tets = np.asarray(tets, dtype=np.int64)
        n = len(self.vertices)
        self.gamma = float(self.config.gamma)
        #: centred rest shape per element N V_e : (m, 4, 3)
        self.rest_local = self.vertices[self.tets] - self.vertices[self.tets].mean(axis=1, keepdims=True)
        self._cache: dict[tuple, torch.Tensor] = {}
        self.K = arap_matrix(n, self.tets, self.gamma)
        self._solve_xyz, self.backend = factorize(self.K, self.config.solver)
        self.pinned = np.zeros(n, dtype=bool)
        if self.config.pin_platform:
            pz = float(self.vertices[:, 2].min() if platform_z is None else platform_z)
            self.pinned = self.vertices[:, 2] <= pz + self.config.platform_tolerance
        if self.pinned.any():
            free = ~self.pinned
            Kff = self.K[free][:, free]
            Kfc = self.K[free][:, self.pinned]
            solve_ff, _ = factorize(Kff, self.config.solver)
            free_idx = np.flatnonzero(free)
            shift = np.zeros(n)
            shift[self.pinned] = self.vertices[self.pinned, 2]
            shift[free] = -solve_ff(Kfc @ self.vertices[self.pinned, 2])
            self._z_shift = shift

            def solve_z_linear(b: np.ndarray) -> np.ndarray:
                """Linear part of the pinned z solve: K_ff^-1 on the free rows, 0 on pinned."""
                out = np.zeros_like(b)
                out[free_idx] = solve_ff(b[free_idx])
                return out

            self._solve_z_linear = solve_z_linear
        else:
            self._z_shift = None
            self._solve_z_linear = self._solve_xyz

    def _const(self, name: str, like: torch.Tensor, index: bool = False) -> torch.Tensor:
        """Cached torch copy of a constant array on like's device (and dtype unless index)."""
        dtype = torch.int64 if index else like.dtype
        key = (name, dtype, like.device)
        if key not in self._cache:
            arr = {"rest": self.rest_local, "idx": self.tets.ravel(), "xyz": self.vertices,
                   "z": self.vertices[:, 2]}[name]
            self._cache[key] = torch.as_tensor(np.ascontiguousarray(arr), dtype=dtype, device=like.device)
        return self._cache[key]

    @property
    def n_vertices(self) -> int:
        """Number of cage vertices."""
        return len(self.vertices)

    def rhs(self, rotations: torch.Tensor, scales: torch.Tensor) -> torch.Tensor:
        """A^T b + gamma xi0 (n,3) for per-element rotations (m,3,3) and scale ratios (m,3)."""
        P = self._const("rest", scales)
        target = torch.einsum("eij,ej,ekj->eik", P, scales, rotations)  # (N V_e) S R^T : (m,4,3)
        out = self.gamma * self._const("xyz", scales)
        return out.index_add(0, self._const("idx", scales, index=True), target.reshape(-1, 3))

    def rhs_z(self, rotations: torch.Tensor, scales: torch.Tensor) -> torch.Tensor:
        """z column of A^T b + gamma xi0 (n,): only the third row of R_e is needed (rotations (m,3,3), or their
        third rows (m,3))."""
        P = self._const("rest", scales)
        row = rotations[:, 2, :] if rotations.dim() == 3 else rotations
        target = torch.einsum("eij,ej,ej->ei", P, scales, row)  # (m,4)
        out = self.gamma * self._const("z", scales)
        return out.index_add(0, self._const("idx", scales, index=True), target.reshape(-1))

    def solve_xyz(self, rhs: torch.Tensor) -> torch.Tensor:
        """Differentiable K^-1 rhs for rhs (n,k), all columns in one factor solve (no pinning)."""
        return factor_solve(rhs, self._solve_xyz)

    def solve_z(self, rhs_z: torch.Tensor) -> torch.Tensor:
        """Differentiable z solve (n,), honouring platform pinning."""
        z = factor_solve(rhs_z, self._solve_z_linear)
        if self._z_shift is not None:
            z = z + torch.as_tensor(self._z_shift, dtype=z.dtype, device=z.device)
        return z

    def deform(self, quaternions: torch.Tensor, scales: torch.Tensor) -> torch.Tensor:
        """Deformed cage vertices V^d (n,3) from unit quaternions (m,4) and scales (m,3)."""
        R = quaternion_to_matrix(quaternions)
        rhs = self.rhs(R, scales)
        if self._z_shift is None:
            return self.solve_xyz(rhs)
        xy = self.solve_xyz(rhs[:, :2])
        return torch.cat([xy, self.solve_z(rhs[:, 2])[:, None]], dim=1)

    def deformed_height(self, quaternions: torch.Tensor, scales: torch.Tensor) -> torch.Tensor:
        """z of the deformed cage vertices (n,), i.e. G at the cage vertices (SPEC step 7); of each rotation only
        the third row is formed."""
        return self.solve_z(self.rhs_z(quaternion_to_z_row(quaternions), scales))
