"""The tilt bound of a three-axis printer: L_TB in the optimisation, the final correction, the held-out figures,
the configuration from a machine profile and L_GC's vertical head."""
from __future__ import annotations

import math

import numpy as np
import pytest
import torch

from neuralslicer.motion.profile import Nozzle
from neuralslicer.neural import NeuralConfig, optimise_field
from neuralslicer.neural.field import CageGeometry, field_gradient
from neuralslicer.neural.head_collision import HeadCollision, HeadShape
from neuralslicer.neural.optimise import heldout_tilt
from neuralslicer.neural.synthetic import sphere_samples
from neuralslicer.tetmesh import box_tet_grid

BOUND = 20.0


@pytest.fixture(scope="module")
def problem():
    V, T = box_tet_grid((4, 4, 4), np.zeros(3), np.full(3, 10.0))
    return V, T, sphere_samples()


def _cfg(steps: int = 150, **loss) -> NeuralConfig:
    return NeuralConfig.model_validate({
        "network": "small", "device": "cpu", "loss": loss,
        "optim": {"max_steps": steps, "convergence_window": 1000, "target_overhang": 0}})


def _angles(lpd: np.ndarray) -> np.ndarray:
    return np.degrees(np.arccos(np.clip(lpd[:, 2], -1.0, 1.0)))


def _b_tets(problem) -> np.ndarray:
    V, T, samples = problem
    return np.unique(CageGeometry.build(V, T).locate(samples.points))   # platform samples' tets hold solid too


@pytest.fixture(scope="module")
def runs(problem):
    V, T, samples = problem
    run = {name: optimise_field(V, T, samples, config=_cfg(**loss), platform_z=0.0) for name, loss in {
        "free": {}, "bound": {"tilt_bound_deg": BOUND},
        # a weak penalty and no correction: what the correction has to fix
        "penalty": {"tilt_bound_deg": BOUND, "w_tb": 1.0, "tilt_correction_steps": 0},
        "weak": {"tilt_bound_deg": BOUND, "w_tb": 1.0}}.items()}
    return run


def test_unbounded_runs_are_unchanged_and_tilt_beyond_the_bound(runs, problem):
    free = runs["free"]
    assert "tb" not in free.history and "tb" not in free.final and "tilt_bound" not in free.attrs
    # the sphere's lower half needs LPDs far from +z: the unbounded optimum tilts beyond 20 deg
    assert _angles(free.lpd[_b_tets(problem)]).max() > 40.0
    assert free.satisfaction["overhang_area_fraction"] < 0.01


def test_the_bound_holds_in_every_tet_of_the_solid(runs, problem):
    tets = _b_tets(problem)   # without solid_tets: the tets holding samples
    for name in ("bound", "weak"):
        res = runs[name]
        angles = _angles(res.lpd[tets])
        assert angles.max() <= BOUND, name
        rec = res.attrs["tilt_bound"]
        assert rec["tets"] == len(tets) and rec["violating_tets"] == 0 and rec["violating_volume_fraction"] == 0.0
        assert rec["max_deg"] == pytest.approx(angles.max(), abs=1e-9)
        assert rec["p99_deg"] == pytest.approx(np.percentile(angles, 99), abs=1e-9)
        assert res.final["tb_violating_tets"] == 0 and "tb" in res.history and len(res.history["tb"]) == res.steps
    # the bound costs overhang: less support-free than unbounded, more than planar layers
    over = runs["bound"].satisfaction
    assert runs["free"].satisfaction["overhang_area_fraction"] < over["overhang_area_fraction"]
    assert over["overhang_area_fraction"] < 0.5 * over["planar_overhang_area_fraction"]


def test_the_final_correction_removes_what_the_penalty_leaves(runs, problem):
    tets = _b_tets(problem)
    left = runs["penalty"]
    angles = _angles(left.lpd[tets])
    assert left.attrs["tilt_bound"]["corrections"] == 0
    assert left.attrs["tilt_bound"]["violating_tets"] == int((angles > BOUND).sum()) > 0
    fixed = runs["weak"]
    assert fixed.attrs["tilt_bound"]["corrections"] > 0 and _angles(fixed.lpd[tets]).max() <= BOUND
    # the same run up to the correction: the correction moves the field by little
    assert (np.abs(fixed.satisfaction["overhang_area_fraction"] - left.satisfaction["overhang_area_fraction"])
            < 0.05)


def test_tilt_term_matches_the_formula_on_the_result(runs, problem):
    V, T, _ = problem
    res = runs["penalty"]   # no correction: the final terms are those of the stored weights
    tets = _b_tets(problem)
    g = CageGeometry.build(V, T)
    c = math.cos(math.radians(BOUND))
    x = np.maximum((c - res.lpd[tets, 2]) / (1 - c), 0.0) ** 2
    ref = (g.volumes[tets] * x).sum() / g.volumes[tets].sum()
    assert res.final["tb"] == pytest.approx(ref, rel=1e-3, abs=1e-9)   # float32 evaluation


class _Ball:
    """A ball of radius 4 at (5, 5, 5): H, bounds, volume, as a Solid gives them."""

    def H(self, x):
        return np.linalg.norm(np.asarray(x) - 5.0, axis=1) - 4.0

    bounds = np.array([[1.0] * 3, [9.0] * 3])

    def volume(self):
        return 4.0 / 3.0 * math.pi * 4.0 ** 3


def test_heldout_tilt_is_the_volume_fraction_beyond_the_bound():
    V, T = box_tet_grid((8, 8, 8), np.zeros(3), np.full(3, 10.0))
    centroids = V[T].mean(axis=1)
    lpd = np.tile([0.0, 0.0, 1.0], (len(T), 1))
    tilted = centroids[:, 0] < 5.0   # the grid's tets do not straddle x = 5: half the ball
    a = math.radians(35.0)
    lpd[tilted] = [math.sin(a), 0.0, math.cos(a)]
    held = heldout_tilt(_Ball(), V, T, lpd, 30.0, seed=3)
    assert held["heldout_points"] > 15_000
    assert held["heldout_violation_fraction"] == pytest.approx(0.5, abs=0.02)
    assert held["heldout_max_deg"] == pytest.approx(35.0) and held["heldout_p99_deg"] == pytest.approx(35.0)
    assert heldout_tilt(_Ball(), V, T, lpd, 40.0)["heldout_violation_fraction"] == 0.0


class _Profile:
    """Stand-in for a machine profile: only the bound."""

    def __init__(self, bound):
        self.bound = bound

    def printing_direction_bound_deg(self):
        return self.bound


def test_with_tilt_bound_sets_the_bound_and_the_vertical_head_unless_set():
    base = NeuralConfig()
    assert base.with_tilt_bound(_Profile(None).printing_direction_bound_deg()) is base
    three = base.with_tilt_bound(_Profile(30.0).printing_direction_bound_deg())
    assert three.loss.tilt_bound_deg == 30.0 and three.loss.gc_vertical_head
    assert base.loss.tilt_bound_deg is None and not base.loss.gc_vertical_head
    own = NeuralConfig.model_validate({"loss": {"tilt_bound_deg": 20.0}}).with_tilt_bound(30.0)
    assert own.loss.tilt_bound_deg == 20.0 and own.loss.gc_vertical_head
    # a configuration round trip keeps it (the field step's cache key and attrs)
    assert NeuralConfig.model_validate(three.model_dump(mode="json")) == three


def test_the_shipped_three_axis_profile_bounds_the_printing_direction():
    from neuralslicer.motion.profile import load_profile, profile_names

    if "three_axis_reprap" not in profile_names():
        pytest.skip("no three_axis_reprap profile shipped yet")
    profile = load_profile("three_axis_reprap")
    assert profile.printing_direction_bound_deg() == pytest.approx(30.0)
    assert load_profile("table_bc_linuxcnc").printing_direction_bound_deg() is None


# --- L_GC with a vertical head --------------------------------------------------------------------------------
NOZZLE = Nozzle(cone_half_angle_deg=30.0, cone_length=8.0, holder_radius=8.0, holder_length=20.0)


def _gc(points: np.ndarray, vertical: bool, platform_z: float | None = None, cells: int = 2):
    V, T = box_tet_grid((cells,) * 3, np.full(3, -20.0), np.full(3, 20.0))
    g = CageGeometry.build(V, T)
    tet, bary = g.barycentric(points)
    gc = HeadCollision(points, tet, bary, g.tets, HeadShape.from_nozzle(NOZZLE, 0.3), platform_z, 0.0, 0.0,
                       1.0, 0.5, torch.device("cpu"), torch.float64, vertical=vertical)
    return g, gc


def test_a_vertical_head_hits_material_above_its_tip_that_a_tilted_head_misses():
    """p at the origin, x 6 mm above it and 3 mm aside: in the vertical cone at p (3 < 6 tan 30), behind the tip
    of a head tilted 70 deg away along the LPD. With the LPD tilted 70 deg toward -x, x is printed before p."""
    points = np.array([[0.0, 0.0, 0.0], [3.0, 0.0, 6.0]])
    a = math.radians(70.0)
    d = np.array([-math.sin(a), 0.0, math.cos(a)])
    assert points[1] @ d < 0   # x printed first
    for vertical, expected in ((False, 0), (True, 1)):
        g, gc = _gc(points, vertical)
        G = torch.from_numpy(g.vertices @ d)
        grad = field_gradient(G, torch.from_numpy(g.tets), torch.from_numpy(g.bary_grads))
        assert gc.count(G, grad)["colliding_pairs"] == expected
        gc.refresh(G, grad)
        assert (float(gc.loss(G, grad)) > 0) == bool(expected)


def test_a_vertical_head_is_the_lpd_head_of_a_field_whose_gradients_point_up(rng):
    """L_GC with the vertical head equals the ordinary L_GC evaluated with every per-tet gradient turned to +z
    (same G, same |grad G|): only the head's axis changes, the print order stays G's."""
    points = rng.uniform(-12.0, 12.0, (300, 3))
    points[:, 2] = np.abs(points[:, 2])
    g, vert = _gc(points, True, platform_z=-0.5, cells=4)
    _, tilted = _gc(points, False, platform_z=-0.5, cells=4)
    x, y, z = g.vertices.T   # layers tilted by 60-75 deg, varying from tet to tet
    G = torch.from_numpy(z + 2.5 * x + 0.02 * x * x + 0.5 * np.sin(y / 3.0))
    grad = field_gradient(G, torch.from_numpy(g.tets), torch.from_numpy(g.bary_grads))
    up = torch.zeros_like(grad)
    up[:, 2] = grad.norm(dim=1)
    assert vert.refresh(G, grad) == tilted.refresh(G, up) > 0
    assert float(vert.loss(G, grad)) == pytest.approx(float(tilted.loss(G, up)), rel=1e-12)
    assert float(vert.loss(G, grad)) > 0 and vert.count(G, grad)["colliding_pairs"] > 0
    assert float(vert.loss(G, grad)) != pytest.approx(float(tilted.loss(G, grad)), rel=1e-3)
    assert vert.count(G, grad) == tilted.count(G, up)


class _Stop(Exception):
    pass


@pytest.mark.parametrize("bound, configured, expected", [(None, None, None), (30.0, None, 30.0), (30.0, 25.0, 25.0)])
def test_the_slice_passes_a_three_axis_profiles_bound_to_the_optimisation(monkeypatch, bound, configured, expected):
    """run_chain: the field's NeuralConfig carries the profile's bound (the configuration's own wins) and the
    vertical head; a five-axis profile leaves the configuration as it was."""
    import types

    from neuralslicer.config import SliceConfig
    from neuralslicer.run import pipeline

    class Steps:
        def run(self, step, **parameters):
            return None

        def release(self, printed):
            return None

    profile = _Profile(bound)
    profile.nozzle = NOZZLE
    seen = {}

    def capture(policy, attempt, release=None):
        seen["neural"] = policy.first.neural
        raise _Stop

    monkeypatch.setattr(pipeline, "load_profile", lambda name: profile)
    monkeypatch.setattr(pipeline, "run_policy", capture)
    config = SliceConfig.model_validate({"neural": {"loss": {"tilt_bound_deg": configured}}})
    with pytest.raises(_Stop):
        pipeline.run_chain(Steps(), types.SimpleNamespace(fea=None), config)
    loss = seen["neural"].loss
    assert loss.tilt_bound_deg == expected and loss.gc_vertical_head == (bound is not None)
    assert loss.head == NOZZLE   # with_head still applies
