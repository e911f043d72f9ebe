"""Matrix-free geometric multigrid for the isotropic voxel model (CG preconditioned by a V-cycle).

The fine operator is the sum of equal cube element matrices ``Ke`` (24, 24): gather the element
DOFs, one matrix product per element type, scatter-add.  Fixed DOFs are eliminated exactly as in
``assembly.stencil_to_bsr``: their rows and columns are dropped from the element matrices and the
diagonal there is ``scale`` (the mean free diagonal), so ``A = M K M + scale (I - M)``.

A coarse voxel is a 2x2x2 block of fine voxels; fine nodes take the trilinear interpolation of the
coarse corners (``P``, free fine DOFs only).  Coarse element matrices are Galerkin products per
element, ``K_c = sum_children P_loc^T K_child P_loc``; an element's matrix depends only on the types
of its children, so each level stores a small table of matrices and a type per element.  The
coarsest level is factorised (sparse LU).  The smoother is a Chebyshev polynomial in ``D^-1 A``,
the same before and after the coarse correction, so the V-cycle is symmetric and PCG is valid.
"""
from __future__ import annotations

import copy
from dataclasses import dataclass

import numpy as np
import scipy.sparse as sp
import scipy.sparse.linalg as spla

from neuralslicer.fea.element import CORNERS
from neuralslicer.fea.grid import VoxelGrid

_GROUP_MIN = 16            # element types with fewer members keep per-element matrices
_BLAS_MIN = 131_072        # smaller element blocks use einsum (a threaded GEMM call costs ~ms)


def _local_prolongation() -> np.ndarray:
    """P_loc (8, 24, 24): corner DOFs of child ``c`` from the 8 corner DOFs of its parent voxel."""
    P = np.zeros((8, 24, 24))
    for c in range(8):
        t = (CORNERS[c][None, :] + CORNERS) / 2.0                        # (8 child corners, 3)
        w = np.prod(np.where(CORNERS[None, :, :] == 1, t[:, None, :], 1.0 - t[:, None, :]),
                    axis=2)                                              # (a, b)
        P[c] = np.kron(w, np.eye(3))
    return P


P_LOC = _local_prolongation()
#: Child slot (0..7, CORNERS order) of the offset ``dx + 2 dy + 4 dz``.
_CHILD_SLOT = np.array([int(np.flatnonzero(np.all(CORNERS == [i & 1, (i >> 1) & 1, i >> 2],
                                                  axis=1))[0]) for i in range(8)])


def element_dofs(elements: np.ndarray) -> np.ndarray:
    """DOF numbers (n, 24) int64 of hexahedra with node numbers (n, 8)."""
    return (3 * elements[:, :, None] + np.arange(3)).reshape(-1, 24).astype(np.int64)


class ElementOperator:
    """``y = M (sum_e K_e) M x + scale (1 - M) x`` with K_e from a per-type table (matrix free).

    dofs : (n, 24) int64; types : (n,) int64 into table (T, 24, 24); mask : (N,) bool free DOFs.
    The element values are kept transposed, (24, n), so that the gather is one ``np.take``, the
    product one wide matrix product per type, and the scatter-add one sparse product with the
    0/1 assembly matrix ``G^T`` (N, 24 n), stored by columns.
    """

    def __init__(self, dofs: np.ndarray, types: np.ndarray, table: np.ndarray, mask: np.ndarray,
                 scale: float) -> None:
        """Group the elements by type (large groups first) and build the scatter matrix."""
        self.dtype = np.dtype(np.float64)
        order = np.argsort(types, kind="stable")
        counts = np.bincount(types, minlength=table.shape[0])
        big = counts >= _GROUP_MIN
        order = order[np.argsort(~big[types[order]], kind="stable")]   # big groups first
        self.dofsT = np.ascontiguousarray(dofs[order].T)               # (24, n)
        n_el = self.dofsT.shape[1]
        t = types[order]
        self.groups: list[tuple[int, int, np.ndarray]] = []
        start = 0
        for k in np.flatnonzero(big):                    # sorted by type inside the big block
            self.groups.append((start, start + int(counts[k]), table[k]))
            start += int(counts[k])
        self.tail = start
        self.tail_K = table[t[start:]]
        self.n = int(mask.size)
        self.set_mask(mask, scale)
        idx_t = np.int32 if max(24 * n_el, self.n) < np.iinfo(np.int32).max else np.int64
        self.GT = sp.csc_matrix((np.ones(24 * n_el), self.dofsT.ravel().astype(idx_t),
                                 np.arange(24 * n_el + 1, dtype=idx_t)),
                                shape=(self.n, 24 * n_el))        # one 1 per column: no sorting
        self._buf: tuple[np.ndarray, np.ndarray] | None = None

    def set_mask(self, mask: np.ndarray, scale: float) -> None:
        """Free DOFs (N,) bool and the diagonal ``scale`` that the fixed ones get."""
        self.mask = mask.astype(np.float64)
        self.fixed_scale = scale * (1.0 - self.mask)

    @property
    def n_elements(self) -> int:
        """Number of elements."""
        return int(self.dofsT.shape[1])

    def astype(self, dtype: type) -> "ElementOperator":
        """A copy computing in ``dtype`` (float32 for the preconditioner); shares the DOF arrays."""
        op = copy.copy(self)
        op.dtype = np.dtype(dtype)
        op.groups = [(s, e, K.astype(dtype)) for s, e, K in self.groups]
        op.tail_K = self.tail_K.astype(dtype)
        op.mask = self.mask.astype(dtype)
        op.fixed_scale = self.fixed_scale.astype(dtype)
        G = self.GT
        op.GT = sp.csc_matrix((G.data.astype(dtype), G.indices, G.indptr), shape=G.shape)
        op._buf = None
        return op

    @property
    def shape(self) -> tuple[int, int]:
        """(N, N)."""
        return (self.n, self.n)

    def element_products(self, x: np.ndarray) -> np.ndarray:
        """Element forces (24, n): each element matrix times its gathered DOFs of ``x``."""
        if self._buf is None:
            self._buf = (np.empty(self.dofsT.shape, self.dtype),
                         np.empty(self.dofsT.shape, self.dtype))
        ue, ye = self._buf
        np.take(x, self.dofsT, out=ue, mode="wrap")      # valid indices: no buffered check
        for s, e, K in self.groups:
            if e - s >= _BLAS_MIN:
                np.matmul(K, ue[:, s:e], out=ye[:, s:e])
            else:                                # no BLAS thread start-up on small blocks
                np.einsum("ij,jk->ik", K, ue[:, s:e], out=ye[:, s:e])
        if self.tail < self.n_elements:
            ye[:, self.tail:] = np.einsum("kij,jk->ik", self.tail_K, ue[:, self.tail:])
        return ye

    def __matmul__(self, x: np.ndarray) -> np.ndarray:
        """Apply the operator to x (N,)."""
        x = np.asarray(x, dtype=self.dtype)
        ye = self.element_products(self.mask * x)
        y = self.GT @ ye.ravel()
        y *= self.mask
        y += self.fixed_scale * x
        return y

    def element_diagonal(self) -> np.ndarray:
        """Diagonal (N,) of the element sum, before masking."""
        dT = np.empty(self.dofsT.shape)
        for s, e, K in self.groups:
            dT[:, s:e] = np.diag(K).astype(np.float64)[:, None]
        dT[:, self.tail:] = np.einsum("kii->ik", self.tail_K)
        G = self.GT
        if G.dtype != np.float64:
            G = sp.csc_matrix((G.data.astype(np.float64), G.indices, G.indptr), shape=G.shape)
        return G @ dT.ravel()

    def diagonal(self) -> np.ndarray:
        """Operator diagonal (N,)."""
        return self.element_diagonal() * self.mask + self.fixed_scale

    def to_sparse(self) -> sp.csc_matrix:
        """The operator as a sparse matrix (for the coarsest level and tests)."""
        dofs = self.dofsT.T
        Ks = np.empty((self.n_elements, 24, 24))
        for s, e, K in self.groups:
            Ks[s:e] = K
        Ks[self.tail:] = self.tail_K
        rows = np.broadcast_to(dofs[:, :, None], Ks.shape).ravel()
        cols = np.broadcast_to(dofs[:, None, :], Ks.shape).ravel()
        A = sp.coo_matrix((Ks.ravel(), (rows, cols)), shape=self.shape).tocsr()
        M = sp.diags(self.mask.astype(np.float64))
        return (M @ A @ M + sp.diags(self.fixed_scale.astype(np.float64))).tocsc()


def node_prolongation(fine: VoxelGrid, coarse: VoxelGrid) -> sp.csr_matrix:
    """Trilinear interpolation (m_fine, m_coarse) from the coarse grid's nodes to the fine ones."""
    n = fine.nodes_ijk
    lo, odd = n // 2, n % 2
    clin = coarse.node_linear(coarse.nodes_ijk)
    rows, cols, vals = [], [], []
    w = np.where(odd == 1, 0.5, 1.0).prod(axis=1)
    for s in CORNERS:
        use = np.all(s[None, :] <= odd, axis=1)
        q = coarse.node_linear(lo[use] + s)
        pos = np.searchsorted(clin, q)
        if not np.array_equal(clin[np.minimum(pos, clin.size - 1)], q):
            raise AssertionError("a coarse corner node is missing")
        rows.append(np.flatnonzero(use))
        cols.append(pos)
        vals.append(w[use])
    return sp.csr_matrix((np.concatenate(vals), (np.concatenate(rows), np.concatenate(cols))),
                         shape=(fine.n_nodes, coarse.n_nodes))


def coarsen(grid: VoxelGrid, types: np.ndarray, table: np.ndarray
            ) -> tuple[VoxelGrid, np.ndarray, np.ndarray]:
    """Coarse grid (2x2x2 blocks), its element types (nc,) and Galerkin table (U, 24, 24)."""
    cijk = grid.ijk // 2
    cshape = (grid.shape + 1) // 2
    lin = (cijk[:, 2] * cshape[1] + cijk[:, 1]) * cshape[0] + cijk[:, 0]
    uniq, inv = np.unique(lin, return_inverse=True)
    k, rem = np.divmod(uniq, cshape[0] * cshape[1])
    j, i = np.divmod(rem, cshape[0])
    coarse = VoxelGrid.from_ijk(grid.origin, 2.0 * grid.spacing, cshape,
                                np.stack([i, j, k], axis=1))
    off = grid.ijk % 2
    slot = _CHILD_SLOT[off[:, 0] + 2 * off[:, 1] + 4 * off[:, 2]]
    children = np.full((uniq.size, 8), -1, dtype=np.int64)
    children[inv.ravel(), slot] = types
    combos, ctypes = np.unique(children, axis=0, return_inverse=True)
    ctable = np.zeros((combos.shape[0], 24, 24))
    for c in range(8):
        has = combos[:, c] >= 0
        Kc = table[combos[has, c]]
        ctable[has] += np.einsum("ia,kij,jb->kab", P_LOC[c], Kc, P_LOC[c], optimize=True)
    return coarse, ctypes.ravel().astype(np.int64), ctable


def fine_types(dofs: np.ndarray, Ke: np.ndarray, fixed: np.ndarray
               ) -> tuple[np.ndarray, np.ndarray]:
    """Element types (n,) and table (T, 24, 24): type 0 is Ke, the others Ke with fixed DOFs cut."""
    types = np.zeros(dofs.shape[0], dtype=np.int64)
    el_fixed = fixed[dofs]
    hit = np.flatnonzero(el_fixed.any(axis=1))
    if hit.size == 0:
        return types, Ke[None].copy()
    pats, inv = np.unique(el_fixed[hit], axis=0, return_inverse=True)
    keep = ~pats
    table = np.concatenate([Ke[None], Ke[None] * keep[:, :, None] * keep[:, None, :]])
    types[hit] = 1 + inv.ravel()
    return types, table


@dataclass
class Level:
    """One level: smoothing operator, inverse diagonal, Chebyshev bound, prolongation from it."""

    A: ElementOperator
    dinv: np.ndarray
    lam_max: float
    P: sp.csr_matrix | None = None          # nodes of this level <- nodes of the next coarser
    PT: sp.csr_matrix | None = None


def lambda_max(A: ElementOperator, dinv: np.ndarray, steps: int = 10, seed: int = 0) -> float:
    """Largest eigenvalue of D^-1 A by ``steps`` Lanczos steps on D^-1/2 A D^-1/2."""
    s = np.sqrt(dinv.astype(np.float64))
    v = np.random.default_rng(seed).standard_normal(A.n)
    v /= np.linalg.norm(v)
    v_prev = np.zeros_like(v)
    alphas: list[float] = []
    betas: list[float] = []
    beta = 0.0
    for _ in range(steps):
        w = s * (A @ (s * v)).astype(np.float64) - beta * v_prev
        alpha = float(w @ v)
        w -= alpha * v
        alphas.append(alpha)
        beta = float(np.linalg.norm(w))
        if beta <= 1e-12 * abs(alpha):
            break
        betas.append(beta)
        v_prev, v = v, w / beta
    off = betas[:len(alphas) - 1]
    return float(np.linalg.eigvalsh(np.diag(alphas) + np.diag(off, 1) + np.diag(off, -1)).max())


def _inverse(d: np.ndarray) -> np.ndarray:
    """1 / d where d > 0, else 0."""
    return np.where(d > 0, 1.0 / np.where(d > 0, d, 1.0), 0.0)


class Multigrid:
    """V-cycle hierarchy for the isotropic voxel model; ``solve`` runs PCG on the fine operator.

    The V-cycle computes in ``dtype`` (float32 by default: half the memory traffic); CG and its
    residual stay in float64, with the flexible (Polak-Ribiere) step so the rounding of the
    preconditioner does not stall it.
    """

    def __init__(self, grid: VoxelGrid, Ke: np.ndarray, fixed: np.ndarray, *,
                 coarse_dofs: int = 12_000, degree: int = 3, dtype: type = np.float32) -> None:
        """Coarsen until ``coarse_dofs`` or less, then factor the coarsest level once (SuperLU)."""
        dofs = element_dofs(grid.elements)
        free = ~fixed
        types, table = fine_types(dofs, Ke, fixed)
        A = ElementOperator(dofs, types, table, free, 1.0)
        d_el = A.element_diagonal()
        A.set_mask(free, float(d_el[free].mean()) if free.any() else 1.0)
        self.A = A
        self.degree = degree
        self.dtype = np.dtype(dtype)
        self.levels: list[Level] = []
        while True:
            d = d_el * A.mask + A.fixed_scale
            dinv = _inverse(d).astype(dtype)
            S = A.astype(dtype)
            if A.n <= coarse_dofs or grid.n_voxels <= 8:
                break
            cgrid, ctypes, ctable = coarsen(grid, types, table)
            if cgrid.n_nodes * 3 >= 0.7 * A.n:
                break
            P = node_prolongation(grid, cgrid).astype(dtype)
            self.levels.append(Level(S, dinv, lambda_max(S, dinv), P, P.T.tocsr()))
            grid, types, table = cgrid, ctypes, ctable
            cdofs = element_dofs(grid.elements)
            A = ElementOperator(cdofs, types, table, np.ones(3 * grid.n_nodes, dtype=bool), 0.0)
            d_el = A.element_diagonal()
            A.set_mask(d_el > 1e-12 * max(float(d_el.max(initial=0.0)), 1e-300), 1.0)
        self.levels.append(Level(S, dinv, 0.0))
        if A.n > 20 * coarse_dofs:
            raise RuntimeError(f"multigrid coarsening stalled at {A.n} DOFs")
        self.coarse_lu = spla.splu(A.to_sparse(), permc_spec="MMD_AT_PLUS_A",
                                   options={"SymmetricMode": True})

    def _smooth(self, lv: Level, b: np.ndarray, x: np.ndarray | None) -> np.ndarray:
        """Chebyshev smoothing of A x = b on [lam_max / 30, 1.1 lam_max] of D^-1 A."""
        upper = 1.1 * lv.lam_max
        lower = upper / 30.0
        theta, delta = 0.5 * (upper + lower), 0.5 * (upper - lower)
        sigma = theta / delta
        rho = 1.0 / sigma
        r = b.copy() if x is None else b - lv.A @ x
        x = np.zeros_like(b) if x is None else x
        dvec = lv.dinv * r * b.dtype.type(1.0 / theta)
        for k in range(self.degree):
            x += dvec
            if k == self.degree - 1:
                break
            r -= lv.A @ dvec
            rho_new = 1.0 / (2.0 * sigma - rho)
            dvec *= b.dtype.type(rho_new * rho)
            dvec += b.dtype.type(2.0 * rho_new / delta) * (lv.dinv * r)
            rho = rho_new
        return x

    def vcycle(self, b: np.ndarray, level: int = 0) -> np.ndarray:
        """One symmetric V-cycle on ``level`` for the right-hand side b (N,): about A^-1 b."""
        lv = self.levels[level]
        if level == len(self.levels) - 1:
            return self.coarse_lu.solve(b.astype(np.float64)).astype(b.dtype)
        x = self._smooth(lv, b, None)
        r = (b - lv.A @ x) * lv.A.mask
        rc = (lv.PT @ r.reshape(-1, 3)).ravel()
        ec = self.vcycle(rc, level + 1)
        x += lv.A.mask * (lv.P @ ec.reshape(-1, 3)).ravel()
        return self._smooth(lv, b, x)

    def precondition(self, r: np.ndarray) -> np.ndarray:
        """One V-cycle in the working precision for the float64 residual r (N,)."""
        return self.vcycle(r.astype(self.dtype)).astype(np.float64)

    def solve(self, f: np.ndarray, rtol: float, maxiter: int) -> tuple[np.ndarray, int]:
        """PCG on the fine operator from zero: (u, iterations) to ||r|| <= rtol ||f||."""
        A = self.A
        u = np.zeros_like(f)
        r = f.copy()
        fn = float(np.linalg.norm(f)) or 1.0
        z = self.precondition(r)
        p = z.copy()
        rz = float(r @ z)
        it = 0
        while it < maxiter and float(np.linalg.norm(r)) > rtol * fn:
            q = A @ p
            alpha = rz / float(p @ q)
            u += alpha * p
            r -= alpha * q
            it += 1
            z_new = self.precondition(r)
            rz_new = float(r @ z_new)
            beta = (rz_new - float(r @ z)) / rz            # flexible (Polak-Ribiere) step
            z = z_new
            p *= beta
            p += z
            rz = rz_new
        return u, it
