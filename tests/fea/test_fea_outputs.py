"""Stress samples T, array round trip, and the files written for people."""
from __future__ import annotations

import json
import math
from pathlib import Path

import numpy as np
import pytest

from neuralslicer.fea import FEAResult, FEASpec, run_fea, stress_samples, write_fea_outputs
from neuralslicer.fea.samples import StressSamples
from neuralslicer.fea.shapes import BoxSolid

EXAMPLE = Path(__file__).resolve().parents[2] / "neuralslicer" / "examples" / "fea_beam"


@pytest.fixture(scope="module")
def beam() -> FEAResult:
    """A small clamped cantilever, 40x10x10 mm, 2 mm voxels, 10 N down at the tip."""
    spec = FEASpec.model_validate(dict(
        supports=[dict(box=[[-1, -1, -1], [0.1, 11, 11]])],
        loads=[dict(box=[[39.9, -1, -1], [41, 11, 11]], force_n=[0, 0, -10])], voxels=500))
    return run_fea(BoxSolid((0, 0, 0), (40, 10, 10)), spec)


def test_stress_samples_are_the_top_fraction(beam: FEAResult) -> None:
    """T holds ceil(f n) voxels, each at least as stressed as any voxel left out."""
    T = stress_samples(beam, 0.1)
    n = beam.grid.n_voxels
    assert len(T) == math.ceil(0.1 * n)
    assert np.all(np.diff(np.abs(T.stress)) <= 0)
    chosen = {tuple(p) for p in np.round(T.points, 9)}
    out = np.array([tuple(p) not in chosen for p in np.round(beam.centres, 9)])
    assert np.abs(T.stress).min() >= np.abs(beam.max_principal[out]).max()
    assert np.allclose(T.volumes, beam.grid.spacing ** 3)
    assert np.allclose(np.linalg.norm(T.tau_max, axis=1), 1.0)
    # the most stressed voxels of a cantilever are at the root, top and bottom, along the axis
    assert T.points[:, 0].max() < 20.0 and np.all(np.abs(T.tau_max[:, 0]) > 0.9)
    back = StressSamples.from_arrays(*T.to_arrays())
    assert np.array_equal(back.points, T.points) and np.array_equal(back.stress, T.stress)


def test_principal_decomposition_reconstructs_stress(beam: FEAResult) -> None:
    """V diag(w) V^T = sigma; tau_max carries the principal value of largest magnitude."""
    V, w = beam.principal_directions, beam.principal_stress
    assert np.allclose(np.einsum("nik,nk,njk->nij", V, w, V), beam.stress, atol=1e-9)
    s_tau = np.einsum("ni,nij,nj->n", beam.tau_max, beam.stress, beam.tau_max)
    assert np.allclose(s_tau, beam.max_principal)
    assert np.all(np.abs(beam.max_principal) >= np.abs(w).max(axis=1) - 1e-12)


def test_result_array_round_trip(beam: FEAResult) -> None:
    """from_arrays(to_arrays()) restores the grid and every field."""
    arrays, attrs = beam.to_arrays()
    json.dumps(attrs)
    back = FEAResult.from_arrays(arrays, attrs)
    assert np.array_equal(back.grid.elements, beam.grid.elements)
    for k in ("displacement", "stress", "strain", "tau_max", "von_mises"):
        assert np.array_equal(getattr(back, k), getattr(beam, k))
    assert back.info["solver"] == beam.info["solver"]


def test_write_outputs(beam: FEAResult, tmp_path: Path) -> None:
    """fea.vtu (voxels, fields), a PNG and metrics.json; no temporary files left behind."""
    import pyvista as pv

    metrics = write_fea_outputs(beam, tmp_path)
    assert sorted(p.name for p in tmp_path.iterdir()) == ["fea.vtu", "fea_von_mises.png",
                                                          "metrics.json"]
    mesh = pv.read(tmp_path / "fea.vtu")
    assert mesh.n_cells == beam.grid.n_voxels and mesh.n_points == beam.grid.n_nodes
    assert np.allclose(mesh.cell_data["von_mises"], beam.von_mises)
    assert np.allclose(mesh.point_data["displacement"], beam.displacement)
    assert mesh.volume == pytest.approx(beam.grid.n_voxels * beam.grid.spacing ** 3)
    saved = json.loads((tmp_path / "metrics.json").read_text())
    assert saved == metrics
    assert metrics["fea.max_von_mises_mpa"] == pytest.approx(beam.von_mises.max())
    assert metrics["fea.max_displacement_mm"] == pytest.approx(
        np.linalg.norm(beam.displacement, axis=1).max())
    assert (tmp_path / "fea_von_mises.png").read_bytes()[:4] == b"\x89PNG"


def test_example_beam_spec_runs() -> None:
    """The shipped example (STL + minimal fea block) loads and bends like Euler-Bernoulli."""
    model = pytest.importorskip("neuralslicer.model")
    spec = model.load_spec(EXAMPLE / "spec.yaml")
    solid = model.implicit_solid(spec)
    assert np.allclose(solid.bounds, [[0, 0, 0], [100, 10, 10]], atol=1e-6)
    fea = spec.fea.model_copy(update={"voxels": 1250})           # 2 mm voxels fit exactly
    res = run_fea(solid, fea)
    assert res.grid.n_voxels == 1250
    tip = res.grid.nodes[:, 0] > 100 - 1e-6
    deflection = -res.displacement[tip, 2].mean()
    exact = 10 * 100 ** 3 / (3 * 2000 * 10 ** 4 / 12)             # 2.0 mm
    assert deflection == pytest.approx(exact, rel=0.05)     # 5 voxels thick: 2.3 % too stiff
