"""Vectorised sparse assembly of the voxel stiffness matrix, straight into block CSR (BSR).

All voxels are equal cubes on one grid, so two nodes couple only when their grid indices differ
by at most one in each axis: the 27-point stencil.  The assembly accumulates, for each of the 64
local node pairs ``(a, b)`` of the hexahedron, the 3x3 blocks of every voxel into a per-node
stencil array ``S[node, offset, i, j]`` (no duplicate indices within one pair, so a plain fancy
``+=`` is exact), then emits the 3x3-block rows directly (columns already sorted: node numbers grow
with the lexicographic grid index).  Memory: ``n_nodes * 243`` floats for ``S`` plus the matrix.
"""
from __future__ import annotations

from typing import Callable

import numpy as np
import scipy.sparse as sp

from neuralslicer.fea.element import CORNERS
from neuralslicer.fea.grid import VoxelGrid

#: Offsets (27, 3) int64 of the stencil, z slowest then y then x (so neighbour numbers increase).
STENCIL = np.array([[dx, dy, dz] for dz in (-1, 0, 1) for dy in (-1, 0, 1) for dx in (-1, 0, 1)],
                   dtype=np.int64)


def _offset_index(d: np.ndarray) -> int:
    """Stencil index of an offset (3,) in {-1,0,1}^3."""
    return int((d[2] + 1) * 9 + (d[1] + 1) * 3 + (d[0] + 1))


def neighbour_table(grid: VoxelGrid) -> np.ndarray:
    """Node number (m, 27) int64 of each stencil neighbour of each node, -1 where none."""
    nx, ny, nz = (int(s) + 1 for s in grid.shape)
    lookup_lin = grid.node_linear(grid.nodes_ijk)
    nbr = np.full((grid.n_nodes, 27), -1, dtype=np.int64)
    for o, d in enumerate(STENCIL):
        q = grid.nodes_ijk + d
        ok = np.all((q >= 0) & (q < np.array([nx, ny, nz])), axis=1)
        lin = grid.node_linear(q[ok])
        pos = np.searchsorted(lookup_lin, lin)
        pos = np.minimum(pos, lookup_lin.size - 1)
        hit = lookup_lin[pos] == lin
        idx = np.flatnonzero(ok)
        nbr[idx[hit], o] = pos[hit]
    return nbr


BlockFn = Callable[[int, int], np.ndarray]
"""``block(a, b)`` -> the (3, 3) or (n_voxels, 3, 3) stiffness block between local nodes a, b."""


def assemble_stencil(grid: VoxelGrid, block: BlockFn) -> tuple[np.ndarray, np.ndarray]:
    """Per-node stencil blocks S (m, 27, 3, 3) float64 and coupling mask (m, 27) bool."""
    S = np.zeros((grid.n_nodes, 27, 3, 3))
    has = np.zeros((grid.n_nodes, 27), dtype=bool)
    for a in range(8):
        na = grid.elements[:, a]
        for b in range(8):
            o = _offset_index(CORNERS[b] - CORNERS[a])
            S[na, o] += block(a, b)          # na has no repeats: plain fancy += is exact
            has[na, o] = True
    return S, has


def stencil_to_bsr(S: np.ndarray, has: np.ndarray, nbr: np.ndarray,
                   fixed: np.ndarray) -> sp.bsr_matrix:
    """Block-CSR (3m, 3m), 3x3 node blocks, with the fixed DOFs eliminated.

    fixed : (3m,) bool.  Rows and columns of fixed DOFs are zeroed and their diagonal set to the
    mean free diagonal, so that with a zero right-hand side there they solve to exactly zero and
    the free equations are those of the reduced system.  ``S`` is modified in place.
    """
    m = S.shape[0]
    fx = fixed.reshape(m, 3)
    diag = np.einsum("nii->ni", S[:, 13])
    scale = float(np.mean(diag[~fx])) if np.any(~fx) else 1.0
    S *= (~fx)[:, None, :, None]                                   # rows of fixed DOFs
    S *= (~fx[np.maximum(nbr, 0)])[:, :, None, :]                  # columns of fixed DOFs
    d = np.einsum("nii->ni", S[:, 13])                             # a writable view
    d[fx] = scale
    mask = has & (nbr >= 0)
    counts = mask.sum(axis=1)
    n = 3 * m
    idx_t = np.int32 if int(counts.sum()) < np.iinfo(np.int32).max else np.int64
    indptr = np.zeros(m + 1, dtype=idx_t)
    np.cumsum(counts, out=indptr[1:])
    K = sp.bsr_matrix((S[mask], nbr[mask].astype(idx_t), indptr), shape=(n, n))
    K.has_sorted_indices = True
    return K
