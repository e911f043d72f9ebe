"""The stress of a load case at any point of the part: the FEA's voxel stress tensors, interpolated.

Stress-following infill (``toolpath.infill: stress``) reads it at the vertices of every layer; the
significance of a stress is judged against ``reference_mpa``, the magnitude at which the strength
samples T start (the smallest |max principal stress| among the most stressed voxels).
"""
from __future__ import annotations

from dataclasses import dataclass, field
from typing import TYPE_CHECKING, Protocol

import numpy as np

from neuralslicer.types import FloatArray, IndexArray

if TYPE_CHECKING:
    from scipy.spatial import cKDTree

#: the 8 corners of a grid cell
_CORNERS = np.array([[i, j, k] for k in (0, 1) for j in (0, 1) for i in (0, 1)], np.int64)


class StressLike(Protocol):
    """Anything that gives the stress tensor at points and the magnitude that counts as significant."""

    #: a stress magnitude of the load case that matters (MPa): the threshold of the strength samples T
    reference_mpa: float

    def tensor_at(self, points: FloatArray) -> FloatArray:
        """Stress tensors (n, 3, 3) at points (n, 3), MPa."""


@dataclass
class StressField:
    """Voxel stress tensors on a regular grid, interpolated trilinearly between the centres of active voxels.

    origin : (3,) the grid's lowest corner (mm); spacing : the voxel size (mm); ijk : (n, 3) int64 indices of
    the active voxels; stress : (n, 3, 3) float64 tensors (MPa) at their centres; reference_mpa : the
    significance scale (see the module docstring).
    """

    origin: FloatArray
    spacing: float
    ijk: IndexArray
    stress: FloatArray
    reference_mpa: float
    _index: np.ndarray | None = field(default=None, init=False, repr=False)
    _tree: cKDTree | None = field(default=None, init=False, repr=False)

    @property
    def centres(self) -> FloatArray:
        """Active voxel centres (n, 3)."""
        return np.asarray(self.origin, np.float64) + (self.ijk + 0.5) * self.spacing

    def _lookup(self) -> np.ndarray:
        """Dense grid of active voxel numbers (-1: inactive), padded by one cell on every side."""
        if self._index is None:
            shape = self.ijk.max(axis=0) + 3 if len(self.ijk) else np.ones(3, np.int64)
            self._index = np.full(tuple(shape), -1, np.int64)
            self._index[tuple((self.ijk + 1).T)] = np.arange(len(self.ijk))
        return self._index

    def tensor_at(self, points: FloatArray) -> FloatArray:
        """Stress tensors (n, 3, 3) at points (n, 3): trilinear weights over the active voxel centres of the cell
        around each point (renormalised); a point with none the nearest active voxel's tensor."""
        points = np.asarray(points, np.float64).reshape(-1, 3)
        if len(points) == 0 or len(self.ijk) == 0:
            return np.zeros((len(points), 3, 3))
        index = self._lookup()
        q = (points - self.origin) / self.spacing - 0.5 + 1.0          # in the padded grid's centre coordinates
        base = np.floor(q).astype(np.int64)
        frac = q - base
        c = np.clip(base[:, None, :] + _CORNERS[None], 0, np.asarray(index.shape) - 1)      # (n, 8, 3)
        vox = index[c[..., 0], c[..., 1], c[..., 2]]                                        # (n, 8)
        w = np.prod(np.where(_CORNERS[None] == 1, frac[:, None, :], 1.0 - frac[:, None, :]), axis=2) * (vox >= 0)
        total = w.sum(axis=1)
        found = total > 1e-12
        w[found] /= total[found, None]
        out = np.matmul(w[:, None, :], self.stress.reshape(-1, 9)[np.maximum(vox, 0)]).reshape(-1, 3, 3)
        if not found.all():
            if self._tree is None:
                from scipy.spatial import cKDTree

                self._tree = cKDTree(self.centres)
            out[~found] = self.stress[self._tree.query(points[~found])[1]]
        return out
