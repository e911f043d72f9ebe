"""The per-element parameterisation of q, s (ablation of the Q-S networks) on a small synthetic case."""
from __future__ import annotations

import io

import numpy as np
import pytest
import torch

from neuralslicer.neural import NeuralConfig, optimise_field
from neuralslicer.neural.config import NETWORK_PRESETS, NetworkConfig
from neuralslicer.neural.networks import DeformationFields
from neuralslicer.neural.problem import FieldProblem
from neuralslicer.neural.synthetic import sphere_samples
from neuralslicer.tetmesh import box_tet_grid




@pytest.fixture(scope="module")
def case():
    V, T = box_tet_grid((4, 4, 4), np.zeros(3), np.full(3, 10.0))
    return V, T, sphere_samples()


def _cfg(**optim) -> NeuralConfig:
    return NeuralConfig.model_validate({
        "network": "per_element", "device": "cpu", "loss": {"collision": False},
        "optim": {"max_steps": 40, "lr": 1e-2, "checkpoint_every": 5, "convergence_window": 1000,
                  "target_overhang": 0, **optim},
    })


def _run(case, cfg, **kw):
    V, T, B = case
    return optimise_field(V, T, B, config=cfg, platform_z=0.0, **kw)


def test_preset_and_identity_start(case):
    V, T, B = case
    assert NETWORK_PRESETS["per_element"].kind == "per_element"
    problem = FieldProblem(V, T, B, None, _cfg(), 0.0)
    fields = problem.new_fields()
    assert isinstance(fields, DeformationFields)
    n_params = sum(p.numel() for p in fields.parameters())
    assert n_params == 7 * len(problem.geometry.tets)  # one raw quaternion and one raw scale per tet
    _, q, s = problem.height(fields)
    np.testing.assert_array_equal(q.detach().numpy(), np.tile([1.0, 0, 0, 0], (len(q), 1)))
    np.testing.assert_array_equal(s.detach().numpy(), np.ones((len(s), 3)))
    G64 = problem.arap.deformed_height(q.detach().double(), s.detach().double()).numpy()
    np.testing.assert_allclose(G64, problem.geometry.vertices[:, 2], atol=1e-9)  # float64: the stored field
    with pytest.raises(ValueError, match="centroids"):
        fields(problem.centroids_t[:3])
    with pytest.raises(ValueError, match="n_elements"):
        DeformationFields(NetworkConfig(kind="per_element"), np.array([[0.0] * 3, [1.0] * 3]))


def test_per_element_fields_reduce_the_overhang(case):
    res = _run(case, _cfg())
    sf = res.history["sf"]
    assert res.steps == 40 and len(sf) == 40
    assert sf[-1] < 0.8 * sf[0]
    assert res.satisfaction["overhang_area_fraction"] < res.satisfaction["planar_overhang_area_fraction"]
    # same output contract as the networks: unit quaternions, bounded scales, G = deformed z
    assert np.allclose(np.linalg.norm(res.quaternions, axis=1), 1)
    assert np.all(res.scales > 1 / 5) and np.all(res.scales < 5)
    assert np.allclose(res.G, res.deformed_vertices[:, 2])
    assert res.G.shape == (len(case[0]),)


def test_checkpoint_round_trip_follows_the_same_trajectory(case):
    cfg = _cfg(max_steps=12)
    final: dict[str, bytes] = {}
    full = _run(case, cfg, save_checkpoint=lambda b, s: final.__setitem__("full", b))
    store: dict[int, bytes] = {}

    class Killed(Exception):
        pass

    def save_then_die(blob: bytes, step: int) -> None:
        store[step] = blob
        if step == 5:
            raise Killed

    with pytest.raises(Killed):
        _run(case, cfg, save_checkpoint=save_then_die)
    resumed = _run(case, cfg, load_checkpoint=lambda: store[5],
                   save_checkpoint=lambda b, s: final.__setitem__("resumed", b))
    assert resumed.steps == full.steps == 12
    a = torch.load(io.BytesIO(final["full"]), weights_only=True)["fields"]
    b = torch.load(io.BytesIO(final["resumed"]), weights_only=True)["fields"]
    assert set(a) == set(b) and {"q_net.values", "s_net.values"} <= set(a)
    for k in a:
        assert torch.allclose(a[k], b[k], atol=1e-6, rtol=0), k
    np.testing.assert_allclose(full.history["total"], resumed.history["total"], rtol=0, atol=1e-7)
    np.testing.assert_allclose(full.G, resumed.G, atol=1e-6)
