"""The global collision term L_GC: head geometry against the motion planner's exact test, its
gradient against finite differences, and a closed loop whose support-free optimum collides."""
from __future__ import annotations

import math

import numpy as np
import pytest
import torch
from scipy.spatial import cKDTree

from neuralslicer.motion.collision import _inside_head, check_collisions, platform_clearance
from neuralslicer.motion.profile import Nozzle
from neuralslicer.neural import NeuralConfig, optimise_field
from neuralslicer.samples import SurfaceSamples
from neuralslicer.neural.field import CageGeometry, field_gradient
from neuralslicer.neural.head_collision import FloorTets, HeadCollision, HeadShape, collision_pool
from neuralslicer.scalar_field import ScalarField
from neuralslicer.tetmesh import box_tet_grid
from neuralslicer.toolpath.types import Toolpaths

NOZZLE = Nozzle(cone_half_angle_deg=30.0, cone_length=6.0, holder_radius=8.0, holder_length=20.0)


def _unit(v: np.ndarray) -> np.ndarray:
    return v / np.linalg.norm(v, axis=1, keepdims=True)


def test_head_depth_sign_is_the_exact_membership_of_the_motion_planner(rng):
    head = HeadShape.from_nozzle(Nozzle(), 0.5)
    offsets = rng.uniform(-40, 45, (100_000, 3))
    axes = _unit(rng.normal(size=(100_000, 3)))
    inside = _inside_head(offsets, axes, Nozzle(), 0.5)
    depth = head.depth(torch.from_numpy(offsets), torch.from_numpy(axes)).numpy()
    assert 0.01 < inside.mean() < 0.2
    np.testing.assert_array_equal(depth > 0, inside)
    # inflating grows the head sideways and at the top, never below min_height (even by more than the cone)
    h = np.einsum("ij,ij->i", offsets, axes)
    for inflate in (1.0, 12.0):
        grown = head.depth(torch.from_numpy(offsets), torch.from_numpy(axes), inflate).numpy() > 0
        assert grown[inside].all() and grown.sum() > inside.sum()
        assert not grown[h < 0.5].any()


def test_lowest_rim_is_the_platform_clearance_of_the_motion_planner(rng):
    head = HeadShape.from_nozzle(Nozzle(), 0.5)
    axes = _unit(rng.normal(size=(5000, 3)))
    low = head.lowest(torch.from_numpy(axes)).numpy()
    exact = platform_clearance(np.zeros((5000, 3)), axes, Nozzle(), 0.0)
    np.testing.assert_allclose(np.minimum(low, 0.0), exact, atol=1e-9)


def test_turned_lowest_rim_clears_the_platform_where_the_planners_turn_does(rng):
    """L_GC's platform terms with the planner's turn (``toolpath.collision_tilt_deg``): a head whose lowest rim,
    the axis turned toward +z by up to 15°, lies above the platform is exactly one the planner's turn
    (``clamp_to_platform``) leaves clear of it, by the exact platform clearance of the turned axis."""
    from neuralslicer.motion.reorient import clamp_to_platform

    n = 20_000
    head, turn = HeadShape.from_nozzle(Nozzle(), 0.5), 15.0
    tips = np.column_stack([rng.uniform(-20, 20, (n, 2)), rng.uniform(0.0, 45.0, n)])
    axes = _unit(rng.normal(size=(n, 3)))
    tp = Toolpaths(layer=np.zeros(n, np.int64), path=np.arange(n), xyz=tips, axis=axes, thickness=np.full(n, 0.3),
                   width=np.full(n, 0.5), extrude=np.ones(n, bool))
    turned, _ = clamp_to_platform(tp, Nozzle(), 0.0, turn)
    cleared = platform_clearance(tips, turned.axis, Nozzle(), 0.0) >= 0.0
    above = tips[:, 2] + head.lowest(torch.from_numpy(axes), math.radians(turn)).numpy()
    # the planner keeps a 0.01 mm margin (also at the tip itself); axes pointing down past 120° (no layer is printed
    # so) have their lowest rim rise again as they turn, which the planner's bound leaves out
    decided = (np.abs(above) > 0.05) & (tips[:, 2] > 0.05) & (axes[:, 2] > -0.5)
    assert 0.1 < cleared[decided].mean() < 0.9 and decided.mean() > 0.7
    np.testing.assert_array_equal(cleared[decided], above[decided] >= 0.0)
    # more room than without the turn, and none for an axis already within the turn of +z
    plain = head.lowest(torch.from_numpy(axes)).numpy()
    assert (tips[:, 2] + plain >= 0).sum() < (above >= 0).sum()
    near = axes[:, 2] > math.cos(math.radians(turn))
    np.testing.assert_allclose(above[near] - tips[near, 2], head.cone_length, atol=1e-9)   # upright: the cone base


def _box_problem(rng, n_points: int = 300, clearance: float = 1.0):
    """A 20 mm box cage, a pool of points inside it and a curved field G (valleys that collide)."""
    V, T = box_tet_grid((5, 5, 5), np.zeros(3), np.full(3, 20.0))
    geometry = CageGeometry.build(V, T)
    points = rng.uniform([1.0, 1.0, 0.0], [19.0, 19.0, 19.0], (n_points, 3))  # some at the platform
    tet, bary = geometry.barycentric(points)
    head = HeadShape.from_nozzle(NOZZLE, 0.3)
    floor = FloorTets.of(V, T, geometry.volumes, np.ones(len(T), bool), 0.0, head)
    gc = HeadCollision(points, tet, bary, geometry.tets, head, 0.0, clearance=clearance, lift=0.5,
                       length=2.0, margin=2.0, device=torch.device("cpu"), dtype=torch.float64, floor=floor)
    G = V[:, 2] + 3.0 * np.sin(V[:, 0] / 2.0)  # wavy layers: the holder hits the valleys' walls
    return geometry, gc, torch.tensor(G, dtype=torch.float64)


def test_gc_gradient_matches_finite_differences(rng):
    geometry, gc, G = _box_problem(rng)
    tets = torch.from_numpy(geometry.tets)
    grads = torch.from_numpy(geometry.bary_grads)
    assert gc.refresh(G, field_gradient(G, tets, grads)) > 0

    def loss(g: torch.Tensor) -> torch.Tensor:
        return gc.loss(g, field_gradient(g, tets, grads))

    assert float(loss(G)) > 0
    pair, platform = gc.penalties(G, field_gradient(G, tets, grads))
    assert (pair > 0).sum() > 10 and (platform > 0).sum() > 0   # both terms take part in the check
    assert (gc.floor_clear(field_gradient(G, tets, grads)) < gc.floor_clearance).sum() > 0   # the floor tets too
    assert torch.autograd.gradcheck(loss, (G.clone().requires_grad_(True),), eps=1e-6, atol=1e-7, rtol=1e-4)


def test_floor_term_is_the_exact_platform_clearance_at_each_tets_lowest_solid_point(rng):
    """The floor tets (solid within the head's reach of the platform): the head's lowest rim along the tet's LPD,
    placed at the tet's lowest solid point, is the motion planner's exact platform clearance there, and no
    point of the tet above the platform is closer: a floor tet that is clear is clear everywhere."""
    geometry, gc, G = _box_problem(rng)
    tets, grads = torch.from_numpy(geometry.tets), torch.from_numpy(geometry.bary_grads)
    grad = field_gradient(G, tets, grads)
    clear = gc.floor_clear(grad).numpy()
    floor = gc.floor_tets.numpy()
    lpd = _unit(grad.numpy()[floor])
    low = np.maximum(geometry.vertices[geometry.tets[floor]].min(axis=1)[:, 2], 0.0)
    assert gc.n_floor == len(floor) > 0 and (clear < 0).sum() > 5 and (clear > 0).sum() > 5
    exact = platform_clearance(np.c_[np.zeros((len(floor), 2)), low], lpd, NOZZLE, 0.0)
    np.testing.assert_allclose(np.minimum(clear, low), exact, atol=1e-9)
    w = rng.dirichlet(np.ones(4), size=len(floor))
    inside = np.einsum("fk,fkj->fj", w, geometry.vertices[geometry.tets[floor]])
    above = inside[:, 2] >= 0.0
    assert (platform_clearance(inside, lpd, NOZZLE, 0.0)[above] >= exact[above] - 1e-9).all()
    # the count reports the floor tets whose head reaches below the platform
    assert gc.count(G, grad)["floor_tets_hit"] == int((clear < 0).sum())


@pytest.mark.parametrize("clearance", [1.0, 10.0])
def test_gc_is_zero_for_planar_layers_and_counts_agree_with_its_pairs(rng, clearance):
    geometry, gc, G = _box_problem(rng, clearance=clearance)
    tets, grads = torch.from_numpy(geometry.tets), torch.from_numpy(geometry.bary_grads)
    planar = torch.from_numpy(geometry.vertices[:, 2].copy())
    gc.refresh(planar, field_gradient(planar, tets, grads))
    assert float(gc.loss(planar, field_gradient(planar, tets, grads))) == 0.0
    assert gc.count(planar, field_gradient(planar, tets, grads))["colliding_points"] == 0
    grad = field_gradient(G, tets, grads)
    count = gc.count(G, grad)
    assert count["colliding_pairs"] > 0
    # every pair counted without margins is a pair the loss penalises
    gc.refresh(G, grad)
    pair, _ = gc.penalties(G, grad)
    assert int((pair > 0).sum()) >= count["colliding_pairs"]


# --- a closed loop: a torus standing on the platform ----------------------------------------------
R_MAJOR, R_MINOR = 12.0, 4.0
CENTRE = np.array([0.0, 0.0, R_MAJOR + R_MINOR])


def torus_H(x: np.ndarray) -> np.ndarray:
    """Signed distance to a torus whose axis is y (it stands on z = 0 like a wheel)."""
    p = np.asarray(x, float) - CENTRE
    q = np.hypot(p[:, 0], p[:, 2]) - R_MAJOR
    return np.hypot(q, p[:, 1]) - R_MINOR


def torus_samples(n_u: int = 120, n_v: int = 24, k: int = 10) -> dict[str, np.ndarray]:
    """Surface samples B with outward normals, |A_p|, kNN and platform flags."""
    u, v = np.meshgrid(np.linspace(0, 2 * np.pi, n_u, endpoint=False), np.linspace(0, 2 * np.pi, n_v, endpoint=False))
    u, v = u.ravel(), v.ravel()
    ring = np.stack([np.cos(u), np.zeros_like(u), np.sin(u)], axis=1)
    normal = np.cos(v)[:, None] * ring + np.sin(v)[:, None] * np.array([0.0, 1.0, 0.0])
    points = CENTRE + R_MAJOR * ring + R_MINOR * normal
    dist, knn = cKDTree(points).query(points, k=k + 1)
    return {"points": points, "normals": normal, "areas": (dist[:, 1:] ** 2).mean(axis=1),
            "knn": knn[:, 1:].astype(np.int64), "on_platform": points[:, 2] < 0.3}


def printed_collisions(field: ScalarField, points: np.ndarray, layer: float = 0.5) -> int:
    """Exact head collisions (the motion planner's check) of the points printed in slabs of G in the order of G
    (L_GC's model of the print order), each along its LPD, against the points printed before and the platform."""
    g, d, _ = field.sample(points)
    ok = np.isfinite(g)
    g, d, points = g[ok], d[ok], points[ok]
    order = np.argsort(g, kind="stable")
    g, d, points = g[order], d[order], points[order]
    n = len(points)
    tp = Toolpaths(layer=np.floor((g - g.min()) / layer).astype(np.int64), path=np.zeros(n, np.int64), xyz=points,
                   axis=d, thickness=np.full(n, layer), width=np.full(n, 0.3), extrude=np.ones(n, bool))
    return check_collisions(tp, NOZZLE, 0.0, min_height=0.3).count


@pytest.fixture(scope="module")
def torus():
    lo, hi = np.array([-17.0, -5.0, -0.5]), np.array([17.0, 5.0, 32.5])
    V, T = box_tet_grid((17, 5, 16), lo, hi)
    B = torus_samples()
    rng = np.random.default_rng(3)
    probe = rng.uniform(lo, hi, (60_000, 3))
    probe = probe[torus_H(probe) < 0]
    return V, T, B, probe


def _optimise(torus, objectives: set[str]):
    V, T, B, _ = torus
    cfg = NeuralConfig.model_validate({
        "network": "small", "device": "cpu",
        "loss": {"w_gc": 1.0 if "gc" in objectives else 0.0, "collision": True, "head": NOZZLE.model_dump(),
                 "head_min_height": 0.3},
        # without L_GC the paper's optimiser runs to its loss target (the most support-free field)
        "optim": {"max_steps": 600, "seed": 0, "target_overhang": 1e-3 if "gc" in objectives else 0.0},
    })
    pool = None
    if "gc" in objectives:
        volume = 2 * np.pi ** 2 * R_MAJOR * R_MINOR ** 2
        pool = collision_pool(torus_H, np.array([V.min(0), V.max(0)]), volume, B["points"], 1500)
    samples = SurfaceSamples(B["points"], B["normals"], B["areas"], B["knn"], B["on_platform"])
    return optimise_field(V, T, samples, config=cfg, platform_z=0.0, collision_pool=pool)


@pytest.mark.slow
def test_gc_removes_the_collisions_of_a_closed_loop(torus):
    V, T, B, probe = torus
    planar = ScalarField.height(V, T)
    assert printed_collisions(planar, probe) == 0
    sf = _optimise(torus, {"sf", "po"})
    assert sf.satisfaction["overhang_area_fraction"] < 0.5 * sf.satisfaction["planar_overhang_area_fraction"]
    assert printed_collisions(ScalarField(V, T, sf.G), probe) > 100   # the support-free optimum collides
    gc = _optimise(torus, {"sf", "po", "gc"})
    assert gc.attrs["head_collision"]["colliding_points"] == 0
    assert gc.final["gc_colliding_pairs"] == 0
    assert printed_collisions(ScalarField(V, T, gc.G), probe) == 0
    assert gc.satisfaction["overhang_area_fraction"] < 0.5 * gc.satisfaction["planar_overhang_area_fraction"]
    assert gc.attrs["collision"]["violating_pairs"] == 0   # L_CA = 0 holds in the stored field
    assert math.isclose(gc.attrs["collision"]["phi_deg"], 2 * NOZZLE.cone_half_angle_deg)
