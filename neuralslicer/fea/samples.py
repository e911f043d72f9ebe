"""The strength-reinforcement sample set T: the most stressed voxel centres."""
from __future__ import annotations

import math
from dataclasses import dataclass
from typing import TYPE_CHECKING

import numpy as np

from neuralslicer.errors import InputError
from neuralslicer.stress_field import StressField

if TYPE_CHECKING:  # the solver's scipy.sparse only where an FEA is run or read
    from neuralslicer.fea.solver import FEAResult


@dataclass
class StressSamples:
    """The set T of the paper: points where the layers should reinforce strength.

    points : (n, 3) float64 voxel centres (build frame); volumes : (n,) float64 voxel volumes |V_e|;
    tau_max : (n, 3) float64 unit direction of the principal stress of largest magnitude;
    stress : (n,) float64 that principal stress, signed (MPa).  Sorted by decreasing |stress|.
    """

    points: np.ndarray
    volumes: np.ndarray
    tau_max: np.ndarray
    stress: np.ndarray

    def __len__(self) -> int:
        """Number of samples."""
        return int(self.points.shape[0])

    def to_arrays(self) -> tuple[dict[str, np.ndarray], dict]:
        """Store-able (arrays, json attrs)."""
        return ({"points": self.points, "volumes": self.volumes, "tau_max": self.tau_max,
                 "stress": self.stress}, {"schema_version": 1, "units": {"length": "mm",
                                                                         "stress": "MPa"}})

    @classmethod
    def from_arrays(cls, arrays: dict[str, np.ndarray], attrs: dict | None = None
                    ) -> "StressSamples":
        """Inverse of ``to_arrays``."""
        return cls(*(np.asarray(arrays[k], dtype=np.float64)
                     for k in ("points", "volumes", "tau_max", "stress")))


def stress_samples(result: FEAResult, fraction: float = 0.10) -> StressSamples:
    """T = voxel centres in the top ``fraction`` of |max principal stress|, weight = voxel volume."""
    idx = top_stress_indices(result, fraction)
    return StressSamples(points=result.grid.centres[idx],
                         volumes=np.full(len(idx), result.grid.voxel_volume),
                         tau_max=result.tau_max[idx].copy(),
                         stress=result.max_principal[idx].copy())


def stress_field(result: FEAResult, fraction: float = 0.10) -> StressField:
    """The FEA's stress at any point (stress-following infill); its reference magnitude is the threshold of T
    (the smallest |max principal stress| among the samples T)."""
    idx = top_stress_indices(result, fraction)
    g = result.grid
    return StressField(np.asarray(g.origin, np.float64), float(g.spacing), np.asarray(g.ijk, np.int64), result.stress,
                       float(abs(result.max_principal[idx[-1]])))


def top_stress_indices(result: FEAResult, fraction: float = 0.10) -> np.ndarray:
    """The voxels (k,) int64 in the top ``fraction`` of |max principal stress| (the region of T), by decreasing
    |stress|."""
    if not 0.0 < fraction <= 1.0:
        raise InputError("fea.top_fraction", f"must be in (0, 1], got {fraction}")
    mag = np.abs(result.max_principal)
    n = mag.size
    k = max(1, math.ceil(fraction * n - 1e-9))
    idx = np.argpartition(-mag, k - 1)[:k] if k < n else np.arange(n)
    return idx[np.argsort(-mag[idx], kind="stable")]
