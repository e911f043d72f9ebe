"""The resumable optimiser, initial guesses and result bookkeeping on small synthetic cases."""
from __future__ import annotations

import io
import json
import math

import numpy as np
import pytest
import torch
from scipy.spatial import cKDTree

from conftest import Planted
from neuralslicer.neural import NeuralConfig, optimise_field
from neuralslicer.neural.device import resolve_device
from neuralslicer.neural.initial_guess import heat_geodesic, height_matched, user_field_on_cage
from neuralslicer.neural.synthetic import sphere_samples
from neuralslicer.samples import SurfaceSamples
from neuralslicer.tetmesh import box_tet_grid




@pytest.fixture(scope="module")
def problem():
    V, T = box_tet_grid((4, 4, 4), np.zeros(3), np.full(3, 10.0))
    return V, T, sphere_samples()


def _cfg(**optim) -> NeuralConfig:
    return NeuralConfig.model_validate({
        "network": "small", "device": "cpu",
        # target_overhang 0: run to the budget, the step counts are what these tests check
        "optim": {"max_steps": 30, "checkpoint_every": 5, "convergence_window": 1000, "target_overhang": 0, **optim},
    })


def _run(problem, cfg, **kw):
    V, T, samples = problem
    return optimise_field(V, T, samples, config=cfg, platform_z=0.0, **kw)


class Killed(Exception):
    pass


def _killed_run(problem, cfg, step: int, **kw) -> dict[int, bytes]:
    """Run until the checkpoint of `step` is saved, then die (Killed); the checkpoints saved, by step."""
    store: dict[int, bytes] = {}

    def save_then_die(blob: bytes, at: int) -> None:
        store[at] = blob
        if at == step:
            raise Killed

    with pytest.raises(Killed):
        _run(problem, cfg, save_checkpoint=save_then_die, **kw)
    return store


def _sphere_pool(spacing: float = 1.5):
    """A grid of points inside the sphere of the problem fixture (L_GC's pool)."""
    from neuralslicer.neural.head_collision import CollisionPool

    axis = np.arange(1.0, 9.5, spacing)
    grid = np.stack(np.meshgrid(axis, axis, axis, indexing="ij"), -1).reshape(-1, 3)
    return CollisionPool(grid[np.linalg.norm(grid - 5.0, axis=1) < 4.0], spacing)


@pytest.mark.parametrize("gc", [False, True], ids=["sf", "sf+gc"])
def test_kill_and_resume_follows_the_same_trajectory(problem, gc):
    cfg = _cfg(max_steps=20)
    kw = {}
    if gc:  # a small head, so that L_GC has pairs to follow
        loss = {"w_gc": 1.0, "head": {"cone_half_angle_deg": 30, "cone_length": 1, "holder_radius": 6,
                                      "holder_length": 6}, "head_min_height": 0.3}
        data = cfg.model_dump()
        data["loss"].update(loss)
        cfg = NeuralConfig.model_validate(data)
        kw["collision_pool"] = _sphere_pool()
    final: dict[str, bytes] = {}
    full = _run(problem, cfg, save_checkpoint=lambda b, s: final.__setitem__("full", b), **kw)
    store = _killed_run(problem, cfg, 10, **kw)
    assert max(store) == 10
    resumed = _run(problem, cfg, load_checkpoint=lambda: store[10],
                   save_checkpoint=lambda b, s: final.__setitem__("resumed", b), **kw)
    if gc:
        assert np.any(full.history["gc"] > 0)
    assert resumed.steps == full.steps == 20
    a = torch.load(io.BytesIO(final["full"]), weights_only=False)["fields"]
    b = torch.load(io.BytesIO(final["resumed"]), weights_only=False)["fields"]
    assert a.keys() == b.keys()
    for k in a:
        assert torch.allclose(a[k], b[k], atol=1e-6, rtol=0), k
    np.testing.assert_allclose(full.history["total"], resumed.history["total"], rtol=0, atol=1e-7)
    np.testing.assert_allclose(full.G, resumed.G, atol=1e-6)


def test_optimisation_reduces_sphere_overhang_and_logs_every_term(problem):
    cfg = _cfg(max_steps=60)
    seen = []
    res = _run(problem, cfg, progress=lambda step, info: seen.append((step, info)))
    assert [s for s, _ in seen] == list(range(1, 61))
    for key in ("total", "sf", "sr", "po", "hs", "hq", "ca", "lr"):
        assert len(res.history[key]) == 60 and key in seen[-1][1]
    assert res.history["total"][-1] < 0.8 * res.history["total"][0]
    sat = res.satisfaction
    assert sat["overhang_area_fraction"] < sat["planar_overhang_area_fraction"]
    # planar figure by hand: overhang iff -n_z > sin 45 among non-platform samples
    _, _, samples = problem
    nrm, area, pf = samples.normals, samples.areas, samples.on_platform
    over = (-nrm[:, 2] > math.sin(math.radians(45))) & ~pf
    assert abs(sat["planar_overhang_area_fraction"] - area[over].sum() / area[~pf].sum()) < 1e-12
    # the returned LPDs are the normalised gradients of the returned G
    assert np.allclose(np.linalg.norm(res.lpd, axis=1), 1)
    assert np.allclose(res.G, res.deformed_vertices[:, 2])
    arrays, attrs = res.to_arrays()
    assert arrays["G"].shape == (len(problem[0]),) and attrs["steps"] == 60
    assert json.loads(json.dumps(attrs))["satisfaction"] == attrs["satisfaction"]


def test_zero_steps_is_the_planar_field(problem):
    res = _run(problem, _cfg(max_steps=0))
    assert res.steps == 0
    np.testing.assert_allclose(res.G, problem[0][:, 2], atol=1e-5)
    np.testing.assert_allclose(res.lpd, np.tile([0, 0, 1.0], (len(problem[1]), 1)), atol=1e-5)
    assert res.satisfaction["overhang_area_fraction"] == res.satisfaction["planar_overhang_area_fraction"]


def test_heat_geodesic_on_a_box_is_the_height():
    V, T = box_tet_grid((3, 3, 6), np.zeros(3), np.array([3.0, 3.0, 6.0]))
    phi = heat_geodesic(V, T, V[:, 2] <= 1e-9)
    assert np.abs(phi - V[:, 2]).max() < 0.07 * V[:, 2].max()  # coarse-mesh error of the method
    assert np.corrcoef(phi, V[:, 2])[0, 1] > 0.995
    assert np.all(phi[V[:, 2] <= 1e-9] == 0)


def test_height_matching_and_user_field_interpolation():
    V, T = box_tet_grid((2, 2, 2), np.zeros(3), np.array([1.0, 1.0, 4.0]))
    f = height_matched(3 * V[:, 0] + 1, V)
    assert np.isclose(f.min(), 0) and np.isclose(f.max(), 4)
    pts = np.random.default_rng(0).uniform(-0.2, 1.2, (400, 3)) * [1, 1, 4]
    on_cage = user_field_on_cage(V, pts @ [1.0, 2.0, 0.5], pts)
    inside = np.all((V > 0.2) & (V < [0.8, 0.8, 3.2]), axis=1)
    np.testing.assert_allclose(on_cage[inside], (V @ [1.0, 2.0, 0.5])[inside], atol=1e-9)


@pytest.mark.parametrize("kind", ["heat", "user"])
def test_non_identity_guess_is_pretrained(problem, kind):
    V = problem[0]
    cfg = NeuralConfig.model_validate({
        "network": "small", "device": "cpu", "optim": {"max_steps": 0},
        "init": {"kind": kind, "pretrain_steps": 80, "pretrain_lr": 3e-3},
    })
    user = V[:, 2] + 0.4 * (V[:, 0] - 5.0)  # a tilted height field
    phases = []
    res = _run(problem, cfg, user_field=user, progress=lambda step, info: phases.append(info["phase"]))
    assert phases == ["pretrain"] * 80
    # heat on a box is already close to the height: a smaller relative gain is expected
    assert res.pretrain_history[-1] < (0.3 if kind == 'user' else 0.7) * res.pretrain_history[0]
    if kind == "user":
        target = height_matched(user, V)
        assert np.corrcoef(res.G, target)[0, 1] > 0.98


def test_device_auto():
    assert resolve_device("auto").type == ("cuda" if torch.cuda.is_available() else "cpu")
    assert resolve_device("cpu").type == "cpu"


def _valley_config(collision: bool, max_steps: int = 0, **loss) -> NeuralConfig:
    return NeuralConfig.model_validate({
        "network": "small", "device": "cpu",
        "optim": {"max_steps": max_steps, "convergence_window": 1000, "target_overhang": 0},
        "loss": {"collision": collision, "phi_deg": 120.0, **loss},
        "init": {"kind": "user", "pretrain_steps": 60, "pretrain_lr": 3e-3},
    })


@pytest.mark.parametrize("max_steps", [0, 4])
def test_collision_constraint_is_enforced_to_zero_violating_pairs(problem, max_steps):
    """A user field with a V-shaped valley (90 deg opening, cone apex 120 deg) violates L_CA = 0;
    the DC3 correction leaves no violating adjacent pair, before every step and at the end."""
    V = problem[0]
    valley = V[:, 2] - np.abs(V[:, 0] - 5.0)
    free = _run(problem, _valley_config(False, max_steps), user_field=valley)
    before = free.attrs["collision"]
    assert not before["enforced"] and before["violating_pairs"] > 0 and before["ca"] > 1e-3
    res = _run(problem, _valley_config(True, max_steps), user_field=valley)
    after = res.attrs["collision"]
    assert after["enforced"] and after["violating_pairs"] == 0 and after["ca"] == 0.0
    assert after["max_excess_rad"] <= 0 and res.final["ca"] == 0 and res.final["ca_violating_pairs"] == 0
    if max_steps:
        assert np.all(res.history["ca"] == 0) and res.history["corrections"][0] >= 1
    else:
        assert after["final_corrections"] >= 1
    # the stored field itself is feasible: recompute the excess from G in float64
    from neuralslicer.neural.field import CageGeometry
    from neuralslicer.neural.losses import collision_excess

    geo = CageGeometry.build(V, problem[1])
    grad = np.einsum("ei,eij->ej", res.G[geo.tets], geo.bary_grads)
    e = collision_excess(torch.tensor(grad), torch.tensor(geo.pairs), torch.tensor(geo.pair_normals),
                         math.radians(120))
    assert int((e > 0).sum()) == 0


def test_target_loss_ends_the_run_and_the_best_iterate_is_returned(problem):
    reached = _run(problem, _cfg(max_steps=30, target_loss=10.0))  # any loss meets it
    assert reached.steps == 1 and reached.converged
    full = _run(problem, _cfg(max_steps=30, target_loss=0.0))
    assert full.steps == 30 and not full.converged
    best = int(np.argmin(full.history["total"]))
    assert full.attrs["best_step"] == best + 1
    # the returned field is the best iterate (re-evaluated: same weights, same loss)
    assert full.final["total"] == pytest.approx(full.history["total"][best], rel=1e-5)


@pytest.mark.slow   # over 10 s: the full suite runs it, `make test-fast` does not
def test_a_diverging_step_is_rolled_back_to_the_best_iterate(problem):
    cfg = _cfg(max_steps=25, lr=0.3, target_loss=0.0)  # far too large: steps blow up
    res = _run(problem, cfg)
    assert res.attrs["rollbacks"] >= 1
    lr = res.history["lr"]
    assert lr[-1] < 0.3 and np.all(np.diff(lr) <= 0)
    assert res.final["total"] <= res.history["total"][0] * (1 + 1e-5)
    off = _run(problem, _cfg(max_steps=25, lr=0.3, target_loss=0.0, divergence_factor=0.0,
                             return_best=False, restart_from_best=False))
    assert off.attrs["rollbacks"] == 0 and off.final["total"] > res.final["total"]


def test_harmonic_pretraining_fits_the_guess_with_smoother_fields(problem):
    V = problem[0]
    user = V[:, 2] + 0.4 * (V[:, 0] - 5.0) + 0.5 * np.sin(V[:, 1])

    def fit(weight: float):
        cfg = NeuralConfig.model_validate({
            "network": "small", "device": "cpu", "optim": {"max_steps": 0},
            "loss": {"collision": False},
            "init": {"kind": "user", "pretrain_steps": 80, "pretrain_lr": 3e-3, "pretrain_harmonic": weight},
        })
        return _run(problem, cfg, user_field=user)

    plain, smooth = fit(0.0), fit(10.0)
    assert smooth.final["hs"] + smooth.final["hq"] < 0.5 * (plain.final["hs"] + plain.final["hq"])
    target = height_matched(user, V)
    assert np.corrcoef(smooth.G, target)[0, 1] > 0.98


def test_a_run_stops_once_the_constraints_are_met(problem):
    """Support-free within target_overhang (and L_CA = 0): that iterate is the result, found at a check."""
    planar = _run(problem, _cfg(max_steps=0)).satisfaction["planar_overhang_area_fraction"]
    res = _run(problem, _cfg(max_steps=400, target_loss=0.0, target_overhang=0.5 * planar))
    assert res.converged and res.steps < 400 and res.steps % 10 == 0 and res.attrs["stop"] == "constraints"
    assert res.satisfaction["overhang_area_fraction"] <= 0.5 * planar
    assert res.attrs["collision"]["violating_pairs"] == 0
    # the same run without the rule goes on to its budget
    budget = _run(problem, _cfg(max_steps=res.steps + 20, target_loss=0.0))
    assert budget.steps == res.steps + 20 and budget.attrs["stop"] == "budget"


def test_the_late_overhang_target_applies_from_late_after(problem):
    """The constraint stop accepts target_overhang before late_after and target_overhang_late from it on."""
    from neuralslicer.neural.problem import FieldProblem

    V, T, samples = problem
    planar = _run(problem, _cfg(max_steps=0)).satisfaction["planar_overhang_area_fraction"]
    assert planar > 0

    def met(step: int, late: float) -> bool:
        cfg = _cfg(target_overhang=0.5 * planar, target_overhang_late=late, late_after=100)
        fp = FieldProblem(V, T, samples, None, cfg, 0.0, None)
        return fp.constraints_met(fp.new_fields(), step)            # identity networks: planar layers

    assert not met(0, 2 * planar) and not met(99, 2 * planar)
    assert met(100, 2 * planar) and met(5000, 2 * planar)
    assert not met(100, 0.5 * planar) and not met(100, 0.0)


def _stall_cfg(**optim) -> NeuralConfig:
    """Constraint stop out of reach (overhang 1e-9), loss stall and loss target off: only the progress test can stop."""
    return _cfg(**{"target_overhang": 1e-9, "target_overhang_late": 1e-9, "target_loss": 0.0, "late_after": 100,
                   "progress_window": 50, "progress_every": 10, **optim})


def test_the_progress_stall_test_stops_a_run_whose_overhang_no_longer_falls(problem):
    """Weights that barely move (lr 1e-9): the overhang is the same at every measurement, so the run stops at
    late_after, the first step the test may fire; with the test off it runs its budget. A killed run resumes to
    the same stop."""
    res = _run(problem, _stall_cfg(max_steps=400, lr=1e-9))
    assert res.steps == 100 and res.attrs["stalled_progress"] and res.converged and res.attrs["stop"] == "progress"
    assert [r["step"] for r in res.attrs["progress"]] == list(range(50, 101, 10))
    assert _run(problem, _stall_cfg(max_steps=150, lr=1e-9, progress_window=0)).steps == 150
    store = _killed_run(problem, _stall_cfg(max_steps=400, lr=1e-9, checkpoint_every=75), 75)
    resumed = _run(problem, _stall_cfg(max_steps=400, lr=1e-9, checkpoint_every=75), load_checkpoint=lambda: store[75])
    assert resumed.steps == 100 and resumed.attrs["progress"] == res.attrs["progress"]


@pytest.fixture(scope="module")
def unsupportable():
    """The sphere's samples B plus 20 points that each carry six samples with normals +-x, +-y, +-z: at
    alpha = 20 deg no print direction supports all six (|d_x|, |d_y|, |d_z| <= sin 20 deg has no unit d), so
    the overhang falls from planar layers' and levels off above zero."""
    V, T = box_tet_grid((4, 4, 4), np.zeros(3), np.full(3, 10.0))
    s = sphere_samples()
    rng = np.random.default_rng(0)
    centres = np.repeat(rng.uniform(3, 7, size=(20, 3)), 6, axis=0) + 0.01 * rng.normal(size=(120, 3))
    pts = np.vstack([s.points, centres])
    nrm = np.vstack([s.normals, np.tile(np.vstack([np.eye(3), -np.eye(3)]), (20, 1))])
    knn = cKDTree(pts).query(pts, k=11)[1][:, 1:]
    samples = SurfaceSamples(pts, nrm, np.full(len(pts), s.areas.mean()), knn, np.r_[s.on_platform, np.zeros(120, bool)])
    return V, T, samples


@pytest.mark.slow   # over 10 s: the full suite runs it, `make test-fast` does not
def test_the_progress_stall_test_fires_only_without_gain_over_its_window(unsupportable):
    """On a run whose overhang falls, then levels off, every measurement from late_after on is judged again
    from the recorded progress: the run goes on while the window's best overhang beats the best before it by
    5 %, and stops at the first measurement where it does not."""
    cfg = _stall_cfg(max_steps=1500, lr=1e-4).model_dump()
    cfg["loss"]["alpha_deg"] = 20.0
    res = _run(unsupportable, NeuralConfig.model_validate(cfg))
    rec = res.attrs["progress"]
    assert rec[0]["overhang"] > 1.5 * rec[-1]["overhang"] > 0           # progress on the way, then a floor
    assert 100 < res.steps < 1500 and res.attrs["stalled_progress"]

    def stalls(step: int) -> bool:
        before = [r["overhang"] for r in rec if r["step"] <= step - 50]
        within = [r["overhang"] for r in rec if step - 50 < r["step"] <= step]
        return not min(within) < 0.95 * min(before)

    judged = [r["step"] for r in rec if r["step"] >= 100]
    assert not any(stalls(k) for k in judged[:-1])
    assert stalls(judged[-1]) == res.attrs["stalled_progress"] == (res.steps < 1500)


def test_a_planted_checkpoint_cannot_run_code(problem, tmp_path):
    import io

    marker = tmp_path / "owned"
    buf = io.BytesIO()
    torch.save({"version": 2, "fields": Planted(str(marker))}, buf)
    with pytest.warns(RuntimeWarning, match="older format was ignored"):
        r = _run(problem, _cfg(max_steps=5), load_checkpoint=lambda: buf.getvalue())
    assert not marker.exists()
    assert r.steps == 5  # started over
