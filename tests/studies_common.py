"""Helpers of the study tests: a tiny torus, a fast study configuration, one warm store per session."""
from __future__ import annotations

from pathlib import Path

import pytest
import trimesh

from neuralslicer.config import SliceConfig


def torus_file(folder: Path) -> Path:
    """A small closed torus (genus 1, 432 faces) as an STL file."""
    path = folder / "torus.stl"
    if not path.is_file():
        mesh = trimesh.creation.torus(major_radius=10.0, minor_radius=4.0, major_sections=18, minor_sections=12)
        mesh.export(path)
    return path


def tiny_config(max_steps: int = 8, checkpoint_every: int = 4, objectives: list[str] | None = None,
                cage_elements: int = 1000) -> SliceConfig:
    """A configuration that runs a branch in seconds once the cage is built (the cage dominates)."""
    return SliceConfig.model_validate({
        "objectives": ["sf", "po"] if objectives is None else objectives,
        "samples": {"n_samples": 400},
        "cage": {"n_elements": cage_elements},
        "neural": {"network": "small", "init": {"pretrain_steps": 5},
                   # run to the budget (no stop on met constraints): step counts are what the tests check
                   "optim": {"max_steps": max_steps, "checkpoint_every": checkpoint_every, "target_overhang": 0}},
        "layers": {"layer_height": 1.1, "t_min": 0.6, "t_max": 1.2, "thickness_samples": 1000},  # <= the 1.2 mm bead
        "toolpath": {"line_width": 1.0, "spacing": 1.5, "n_shells": 1, "infill_density": 0.3},  # the nozzle lays <= 1 mm
        "collision_refinements": 0,
        "collision_retries": 0,
        "collision_fallback": "none",
    })


def shared_store(factory: pytest.TempPathFactory) -> Path:
    """One artifact store for the study tests of a session (content-addressed: the cage is built once)."""
    return factory.getbasetemp() / "studies-store.zarr"
