"""Voxelisation of an implicit solid: active voxels (H(centre) <= 0) and their node numbering."""
from __future__ import annotations

from dataclasses import dataclass
from typing import Protocol, runtime_checkable

import numpy as np

from neuralslicer.errors import InputError
from neuralslicer.fea.element import CORNERS


@runtime_checkable
class SolidLike(Protocol):
    """What the FEA needs of a solid: ``H`` (< 0 inside), ``bounds`` (2, 3), ``platform_z``."""

    bounds: np.ndarray
    platform_z: float

    def H(self, x: np.ndarray) -> np.ndarray:
        """Signed implicit value (n,) at points (n, 3), negative inside."""
        ...


@dataclass
class VoxelGrid:
    """Active cube voxels of side ``spacing`` on a regular grid and their 8-node hexahedra.

    origin : (3,) float64, the lowest grid corner; shape : (3,) int64 voxels per axis;
    ijk : (n, 3) int64 voxel indices; nodes_ijk : (m, 3) int64 grid-node indices of the used nodes,
    in increasing lexicographic order (z slowest, x fastest); elements : (n, 8) int64 node numbers
    in VTK_HEXAHEDRON order.
    """

    origin: np.ndarray
    spacing: float
    shape: np.ndarray
    ijk: np.ndarray
    nodes_ijk: np.ndarray
    elements: np.ndarray

    @property
    def n_voxels(self) -> int:
        """Number of active voxels."""
        return int(self.ijk.shape[0])

    @property
    def n_nodes(self) -> int:
        """Number of nodes used by the active voxels."""
        return int(self.nodes_ijk.shape[0])

    @property
    def centres(self) -> np.ndarray:
        """Voxel centres (n, 3) float64, build frame."""
        return self.origin + (self.ijk + 0.5) * self.spacing

    @property
    def nodes(self) -> np.ndarray:
        """Node positions (m, 3) float64, build frame."""
        return self.origin + self.nodes_ijk * self.spacing

    @property
    def voxel_volume(self) -> float:
        """Volume of one voxel, mm^3."""
        return float(self.spacing ** 3)

    def node_linear(self, ijk: np.ndarray) -> np.ndarray:
        """Lexicographic grid-node index (z slowest) of node indices (k, 3)."""
        nx, ny = int(self.shape[0]) + 1, int(self.shape[1]) + 1
        return (ijk[..., 2] * ny + ijk[..., 1]) * nx + ijk[..., 0]

    def subset(self, keep: np.ndarray) -> "VoxelGrid":
        """The grid restricted to the voxels ``keep`` (bool (n,)), nodes renumbered."""
        return VoxelGrid.from_ijk(self.origin, self.spacing, self.shape, self.ijk[keep])

    @classmethod
    def from_ijk(cls, origin: np.ndarray, spacing: float, shape: np.ndarray,
                 ijk: np.ndarray) -> "VoxelGrid":
        """Build the node numbering and hexahedra of the voxels ``ijk`` (n, 3) int64."""
        shape = np.asarray(shape, dtype=np.int64)
        ijk = np.asarray(ijk, dtype=np.int64).reshape(-1, 3)
        nx, ny = int(shape[0]) + 1, int(shape[1]) + 1
        corner_ijk = ijk[:, None, :] + CORNERS[None, :, :]                 # (n, 8, 3)
        lin = (corner_ijk[..., 2] * ny + corner_ijk[..., 1]) * nx + corner_ijk[..., 0]
        used, inverse = np.unique(lin.ravel(), return_inverse=True)        # sorted: lexicographic
        k, rem = np.divmod(used, nx * ny)
        j, i = np.divmod(rem, nx)
        nodes_ijk = np.stack([i, j, k], axis=1).astype(np.int64)
        elements = inverse.reshape(-1, 8).astype(np.int64)
        return cls(np.asarray(origin, dtype=np.float64), float(spacing), shape, ijk,
                   nodes_ijk, elements)


def grid_for_bounds(bounds: np.ndarray, n_target: int) -> tuple[np.ndarray, float, np.ndarray]:
    """Cube grid covering ``bounds`` (2, 3) with about ``n_target`` voxels: (origin, h, shape).

    The spacing is ``(bounding-box volume / n_target)^(1/3)``; the grid is centred on the box in x
    and y and starts at the box's lowest z (so the bottom node layer lies on the platform).
    """
    bounds = np.asarray(bounds, dtype=np.float64).reshape(2, 3)
    ext = bounds[1] - bounds[0]
    if not np.all(np.isfinite(ext)) or np.any(ext < 0):
        raise InputError("fea", f"the solid's bounds {bounds.tolist()} are not a valid box")
    big = max(float(ext.max()), 1e-12)
    ext_safe = np.maximum(ext, big * 1e-6)
    h = float((np.prod(ext_safe) / n_target) ** (1.0 / 3.0))
    shape = np.maximum(1, np.ceil(ext / h - 1e-9)).astype(np.int64)
    origin = bounds[0] - 0.5 * (shape * h - ext)
    origin[2] = bounds[0, 2]
    return origin, h, shape


def voxelize(solid: SolidLike, n_target: int, chunk: int = 262_144) -> VoxelGrid:
    """Active voxels of ``solid``: cubes of the bounding-box grid whose centre has H <= 0."""
    origin, h, shape = grid_for_bounds(np.asarray(solid.bounds), n_target)
    nx, ny, nz = (int(s) for s in shape)
    total = nx * ny * nz
    inside = np.zeros(total, dtype=bool)
    for start in range(0, total, chunk):          # bounded memory for H on large grids
        lin = np.arange(start, min(start + chunk, total), dtype=np.int64)
        k, rem = np.divmod(lin, nx * ny)
        j, i = np.divmod(rem, nx)
        c = origin + (np.stack([i, j, k], axis=1) + 0.5) * h
        inside[start:start + lin.size] = np.asarray(solid.H(c)).reshape(-1) <= 0.0
    lin = np.flatnonzero(inside)
    if lin.size == 0:
        raise InputError("fea.voxels", f"no voxel centre lies inside the solid (H <= 0) at "
                         f"spacing {h:.4g} mm: the model has zero volume at this resolution; "
                         "check the model or raise 'voxels'")
    k, rem = np.divmod(lin, nx * ny)
    j, i = np.divmod(rem, nx)
    return VoxelGrid.from_ijk(origin, h, shape, np.stack([i, j, k], axis=1))
