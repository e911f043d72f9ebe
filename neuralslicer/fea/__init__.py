"""Voxel finite-element analysis: stresses for strength reinforcement (T), isotropic or with a printed material.

Public API: ``run_fea(solid, spec) -> FEAResult``, ``stress_samples(result, fraction) ->
StressSamples``, ``write_fea_outputs(result, out_dir) -> dict``; configuration ``FEASpec``. Judging a print with
it (the part's strain as printed against planar layers) is :mod:`neuralslicer.verify`'s.
"""
from __future__ import annotations

from neuralslicer.fea.spec import (
    AnisotropicMaterial,
    FEASpec,
    IsotropicMaterial,
    Load,
    PlaneRegion,
    SolverOptions,
    Support,
)

__all__ = [
    "AnisotropicMaterial",
    "FEAResult",
    "FEASpec",
    "IsotropicMaterial",
    "Load",
    "PlaneRegion",
    "SolidLike",
    "SolverOptions",
    "StressSamples",
    "Support",
    "VoxelGrid",
    "fea_metrics",
    "run_fea",
    "stress_samples",
    "voxelize",
    "write_fea_outputs",
]


def __getattr__(name: str) -> object:
    """Lazy access to the solver API (keeps ``from neuralslicer.fea import FEASpec`` light)."""
    if name in ("FEAResult", "run_fea"):
        from neuralslicer.fea import solver
        return getattr(solver, name)
    if name in ("SolidLike", "VoxelGrid", "voxelize"):
        from neuralslicer.fea import grid
        return getattr(grid, name)
    if name in ("StressSamples", "stress_samples"):
        from neuralslicer.fea import samples
        return getattr(samples, name)
    if name in ("write_fea_outputs", "fea_metrics"):
        from neuralslicer.fea import io
        return getattr(io, name)
    raise AttributeError(f"module 'neuralslicer.fea' has no attribute {name!r}")
