"""The S3-Slicer baseline on small synthetic cases: overhang, identity start, gradients, output contract."""
from __future__ import annotations

import json
import math

import numpy as np
import pytest
import torch
from scipy.spatial.transform import Rotation

from neuralslicer.baselines.s3 import S3Config, optimise_s3
from neuralslicer.baselines.s3 import S3Objective
from neuralslicer.fea.samples import StressSamples
from neuralslicer.metrics import overhang_area_fraction
from neuralslicer.neural.field import CageGeometry
from neuralslicer.neural.problem import FieldProblem
from neuralslicer.neural.synthetic import sphere_samples
from neuralslicer.tetmesh import box_tet_grid




@pytest.fixture(scope="module")
def case():
    V, T = box_tet_grid((5, 5, 5), np.zeros(3), np.full(3, 10.0))
    return V, T, sphere_samples()


def _cfg(**kw) -> S3Config:
    return S3Config.model_validate({"device": "cpu", "steps": 300, **kw})


def _lpd(V: np.ndarray, T: np.ndarray, G: np.ndarray) -> np.ndarray:
    """Unit grad G per tet, computed here from the cage (independently of the result's lpd)."""
    geo = CageGeometry.build(V, T)
    grad = np.einsum("ei,eij->ej", G[geo.tets], geo.bary_grads)
    return grad / np.linalg.norm(grad, axis=1, keepdims=True)


@pytest.fixture(scope="module")
def result(case):
    V, T, B = case
    seen: list[int] = []
    res = optimise_s3(V, T, B, None, ["sf", "po"], _cfg(), 0.0, progress=lambda s, info: seen.append(s))
    return res, seen


def test_s3_field_reduces_the_realised_overhang(case, result):
    V, T, B = case
    res, seen = result
    geo = CageGeometry.build(V, T)
    tet = geo.locate(B.points)
    planar = overhang_area_fraction(B.normals, B.areas, B.on_platform, np.tile([0, 0, 1.0], (len(B), 1)))
    realised = overhang_area_fraction(B.normals, B.areas, B.on_platform, _lpd(V, T, res.G)[tet])
    assert planar > 0.1
    assert realised < 0.5 * planar
    assert realised == pytest.approx(res.satisfaction["overhang_area_fraction"], abs=1e-12)
    assert res.satisfaction["planar_overhang_area_fraction"] == pytest.approx(planar, abs=1e-12)
    # S3's own view: the rotated normals R_e n in the deformed space, recomputed with scipy's rotations
    q = res.quaternions[tet]
    rotated = Rotation.from_quat(q[:, [1, 2, 3, 0]]).apply(B.normals)
    keep = ~B.on_platform
    over = -rotated[keep, 2] > math.sin(math.radians(45))
    deformed = B.areas[keep][over].sum() / B.areas[keep].sum()
    assert deformed == pytest.approx(res.satisfaction["deformed_space_overhang_area_fraction"], abs=1e-9)
    assert deformed < 0.5 * planar
    # the loss went down and every step was reported
    assert res.history["total"][-1] < 0.5 * res.history["total"][0]
    assert seen == list(range(1, res.steps + 1))
    assert res.attrs["ignored_objectives"] == ["po"]


def test_outputs_are_finite_and_follow_the_field_contract(case, result):
    V, T, _ = case
    res, _ = result
    assert res.G.shape == (len(V),) and res.G.dtype == np.float64
    assert np.all(np.isfinite(res.G)) and np.all(np.isfinite(res.deformed_vertices))
    np.testing.assert_array_equal(res.G, res.deformed_vertices[:, 2])
    np.testing.assert_allclose(res.lpd, _lpd(V, T, res.G), atol=1e-12)
    np.testing.assert_allclose(np.linalg.norm(res.quaternions, axis=1), 1.0, atol=1e-12)
    assert res.quaternions.shape == (len(T), 4) and res.intended_lpd.shape == (len(T), 3)
    assert all(len(v) == res.steps for v in res.history.values())
    summary = json.loads(json.dumps(res.summary()))
    assert summary["steps"] == res.steps and summary["n_vertices"] == len(V) and summary["method"] == "s3"
    arrays, attrs = res.to_arrays()
    assert arrays["G"] is res.G and attrs["kind"] == "s3"
    json.dumps(attrs)


def test_zero_steps_is_the_planar_field(case):
    V, T, B = case
    res = optimise_s3(V, T, B, None, ["sf"], _cfg(steps=0), 0.0)
    assert res.steps == 0 and res.history["total"] == []
    np.testing.assert_allclose(res.G, V[:, 2], atol=1e-9)
    np.testing.assert_allclose(res.lpd, np.tile([0, 0, 1.0], (len(T), 1)), atol=1e-9)
    np.testing.assert_array_equal(res.quaternions, np.tile([1.0, 0, 0, 0], (len(T), 1)))
    sat = res.satisfaction
    assert sat["overhang_area_fraction"] == pytest.approx(sat["planar_overhang_area_fraction"], abs=1e-12)


def test_strength_objective_turns_tau_into_the_layers():
    V, T = box_tet_grid((3, 3, 3), np.zeros(3), np.full(3, 6.0))
    B = sphere_samples(60, 2.0, (3.0, 3.0, 3.0))
    pts = np.random.default_rng(1).uniform(1.0, 5.0, (40, 3))
    tau = np.tile([math.sqrt(0.5), 0.0, math.sqrt(0.5)], (40, 1))  # 45 deg: planar layers fail everywhere
    stress = StressSamples(pts, np.ones(40), tau, np.ones(40))
    res = optimise_s3(V, T, B, stress, ["sr"], _cfg(steps=200), 0.0)
    assert res.satisfaction["planar_sr_satisfied_fraction"] == 0.0
    assert res.satisfaction["deformed_space_sr_satisfied_fraction"] > 0.9
    assert res.satisfaction["sr_satisfied_fraction"] > 0.5
    assert res.final["sf"] == 0.0  # sf not asked for


def test_gradient_of_the_s3_loss_wrt_the_quaternions():
    V, T = box_tet_grid((1, 1, 2), np.zeros(3), np.array([2.0, 2.0, 4.0]))
    B = sphere_samples(16, 0.8, (1.0, 1.0, 2.0), k=4)
    rng = np.random.default_rng(0)
    tau = rng.normal(size=(6, 3))
    stress = StressSamples(rng.uniform(0.2, 1.8, (6, 3)) * [1, 1, 2], rng.uniform(0.5, 1, 6),
                           tau / np.linalg.norm(tau, axis=1, keepdims=True), np.ones(6))
    cfg = _cfg(dtype="float64", w_sr=1.0, k_sf=3.0, k_sr=3.0)
    problem = FieldProblem(V, T, B, stress, cfg.neural_config(), 0.0)
    objective = S3Objective(problem, cfg)
    m = len(problem.geometry.tets)
    raw = torch.tensor(np.c_[np.ones(m), 0.4 * rng.normal(size=(m, 3))], dtype=torch.float64, requires_grad=True)
    total, terms = objective(raw)
    assert all(float(v.detach()) > 0 for v in terms.values())
    assert torch.autograd.gradcheck(lambda r: objective(r)[0], (raw,), eps=1e-6, atol=1e-6)
