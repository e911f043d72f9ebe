"""Collision-driven refinement of L_GC's pool and warm starts: the points added, the pairs they bring, the
network weights a result carries, and a closed loop whose coarse pool misses collisions the exact check finds."""
from __future__ import annotations

import numpy as np
import pytest
import torch
from scipy.spatial import cKDTree

from neuralslicer.errors import InputError
from neuralslicer.motion.collision import CollisionReport, check_collisions
from neuralslicer.neural import NeuralConfig, optimise_field
from neuralslicer.neural.field import CageGeometry, field_gradient
from neuralslicer.neural.head_collision import (
    CollisionPool, HeadCollision, HeadShape, collision_pool, link_pairs, refine_pool,
)
from neuralslicer.neural.optimise import FieldResult, Refinement, optimise_for_solid
from neuralslicer.neural.synthetic import sphere_samples
from neuralslicer.samples import SurfaceSamples
from neuralslicer.scalar_field import ScalarField
from neuralslicer.tetmesh import box_tet_grid
from neuralslicer.toolpath.types import Toolpaths
from test_neural_head_collision import NOZZLE, R_MAJOR, R_MINOR, torus_H, torus_samples


# --- a thin strut on a slab: a pool 2 mm apart has hardly a point in the 1 mm strut ------------------------
def strut_H(x: np.ndarray) -> np.ndarray:
    """A 1 x 1 x 20 mm vertical strut at (10, 10) on a 20 x 20 x 4 mm slab (max-distance, < 0 inside)."""
    x = np.asarray(x, float)
    strut = np.maximum.reduce([np.abs(x[:, 0] - 10) - 0.5, np.abs(x[:, 1] - 10) - 0.5, -x[:, 2], x[:, 2] - 20])
    slab = np.maximum.reduce([np.abs(x[:, 2] - 2) - 2, np.abs(x[:, 0] - 10) - 10, np.abs(x[:, 1] - 10) - 10])
    return np.minimum(strut, slab)


STRUT_BOUNDS = np.array([[0.0, 0.0, 0.0], [20.0, 20.0, 20.0]])
HITS = np.array([[10.0, 10.0, 14.0], [10.2, 10.1, 14.3], [10.0, 10.0, 17.0]])
WITNESSES = np.array([[10.0, 10.0, 11.0], [10.1, 10.0, 11.2], [np.nan, np.nan, np.nan]])


@pytest.fixture(scope="module")
def strut_pool() -> CollisionPool:
    return collision_pool(strut_H, STRUT_BOUNDS, 400 * 4 + 16, np.zeros((0, 3)), 200)


def test_refined_points_lie_in_the_solid_near_the_hits_within_the_cap(strut_pool):
    pool = strut_pool
    assert pool.n_base == len(pool.points) and pool.n_refined == 0
    refined = refine_pool(pool, HITS, WITNESSES, strut_H)
    np.testing.assert_array_equal(refined.points[:pool.n_base], pool.points)   # the base pool first, unchanged
    added = refined.points[pool.n_base:]
    assert refined.fine_spacing == pytest.approx(pool.spacing / 3)
    assert refined.link_radius == pytest.approx(2 * pool.spacing)
    assert len(added) > 20 and np.all(strut_H(added) < 0)
    centres = np.concatenate([HITS, WITNESSES[:2]])   # the NaN witness adds nothing
    dist = np.linalg.norm(added[:, None] - centres[None], axis=2).min(axis=1)
    assert dist.max() <= refined.link_radius
    # the strut near the hits is resolved: every point of it within half the radius of a hit has an added point
    # within 1.5 fine spacings (a jittered lattice's bound: (0.5 + 0.35) sqrt(3)), where the base pool has a
    # single point in the whole strut
    rng = np.random.default_rng(0)
    probe = rng.uniform([9.5, 9.5, 12.0], [10.5, 10.5, 16.0], (2000, 3))
    probe = probe[np.linalg.norm(probe[:, None] - HITS[None, :2], axis=2).min(axis=1) < 0.5 * refined.link_radius]
    assert cKDTree(added).query(probe)[0].max() < 1.5 * refined.fine_spacing
    assert cKDTree(pool.points).query(probe)[0].max() > pool.spacing
    # links: each hit with its witness and each centre with itself, thinned to one per cell of half the radius:
    # fifty neighbouring waypoints of one colliding stretch give a few links
    assert 0 < len(refined.links) <= 2 + len(centres)
    stretch = np.linspace([10.0, 10.0, 13.0], [10.0, 10.0, 15.0], 50)
    assert len(refine_pool(pool, stretch, stretch - [0.0, 0.0, 3.0], strut_H).links) <= 3 * 8
    # the cap keeps the points nearest to the hits: the first ones of the uncapped order
    capped = refine_pool(pool, HITS, WITNESSES, strut_H, max_points=7)
    assert capped.n_refined == 7
    np.testing.assert_array_equal(capped.points, refined.points[:pool.n_base + 7])
    # deterministic for a seed, another seed jitters otherwise; refining again around the same hits adds nothing
    np.testing.assert_array_equal(refine_pool(pool, HITS, WITNESSES, strut_H).points, refined.points)
    other = refine_pool(pool, HITS, WITNESSES, strut_H, seed=1)
    assert other.n_refined and not np.array_equal(other.points[pool.n_base:pool.n_base + 5], added[:5])
    again = refine_pool(refined, HITS, WITNESSES, strut_H)
    assert again.n_refined == refined.n_refined and len(again.links) == len(refined.links)
    with pytest.raises(ValueError, match="one per hit"):
        refine_pool(pool, HITS, WITNESSES[:2], strut_H)


def test_link_pairs_pair_the_added_points_along_the_links_within_the_budget(strut_pool):
    refined = refine_pool(strut_pool, HITS, WITNESSES, strut_H)
    n, pts, r = refined.n_base, refined.points, refined.link_radius
    pairs, thinned = link_pairs(pts, n, refined.links, r, 30.0, 10**8)
    assert thinned == 0 and len(pairs)
    assert np.all((pairs[:, 0] >= n) | (pairs[:, 1] >= n)) and np.all(pairs[:, 0] != pairs[:, 1])
    assert len(np.unique(pairs, axis=0)) == len(pairs)
    assert {tuple(p) for p in pairs} == {tuple(p) for p in pairs[:, ::-1]}   # both ways
    # a point near the first hit is paired with every point near its witness (and the other way)
    near_hit = np.flatnonzero(np.linalg.norm(pts - HITS[0], axis=1) < 0.5 * r)
    near_wit = np.flatnonzero(np.linalg.norm(pts - WITNESSES[0], axis=1) < 0.5 * r)
    want = {(p, x) for p in near_hit for x in near_wit if p != x and (p >= n or x >= n)}
    assert want and want <= {tuple(p) for p in pairs}
    # the head's reach bounds them; under a budget every link keeps a share of its pairs
    short, _ = link_pairs(pts, n, refined.links, r, 1.0, 10**8)
    assert 0 < len(short) < len(pairs) and np.linalg.norm(pts[short[:, 0]] - pts[short[:, 1]], axis=1).max() <= 1.0
    few, thinned = link_pairs(pts, n, refined.links, r, 30.0, len(pairs) // 4)
    assert thinned > 0 and len(few) <= len(pairs) // 4 and {tuple(p) for p in few} <= {tuple(p) for p in pairs}
    tree = cKDTree(pts)
    for a, b in refined.links:
        ia, ib = set(tree.query_ball_point(a, r)), set(tree.query_ball_point(b, r))
        assert any(p in ia and x in ib for p, x in few), "a link lost all its pairs"
    again, _ = link_pairs(pts, n, refined.links, r, 30.0, len(pairs) // 4)
    np.testing.assert_array_equal(again, few)  # seeded: the same pool gives the same loss
    # HeadCollision: the base pairs as before plus the link pairs; normalised by the base pool
    V, T = box_tet_grid((4, 4, 4), np.zeros(3), np.full(3, 20.0))
    geometry = CageGeometry.build(V, T)
    head = HeadShape.from_nozzle(NOZZLE, 0.3)

    def gc(points, **kw):
        tet, bary = geometry.barycentric(points)
        return HeadCollision(points, tet, bary, geometry.tets, head, 0.0, 1.0, 0.1, 2.0, 1.0, torch.device("cpu"),
                             torch.float64, **kw)

    base = gc(strut_pool.points)
    both = gc(pts, n_base=n, links=refined.links, link_radius=r)
    near = both.near.numpy()
    base_near = near[(near < n).all(axis=1)]
    assert {tuple(p) for p in base_near} == {tuple(p) for p in base.near.numpy()}
    assert len(near) == len(base.near) + both.n_link_pairs and both.links_thinned == 0
    with pytest.warns(RuntimeWarning, match="links thinned"):
        gc(pts, n_base=n, links=refined.links, link_radius=r, max_link_pairs=10)
    G = torch.from_numpy(V[:, 2] + 3.0 * np.sin(V[:, 0] / 2.0))
    grad = field_gradient(G, torch.from_numpy(geometry.tets), torch.from_numpy(geometry.bary_grads))
    base.refresh(G, grad)
    both.refresh(G, grad)
    assert both.count(G, grad)["refined_points"] == len(pts) - n
    # the base pool's share of the loss is the same with and without the added points
    base_pairs = both.pairs[(both.pairs < n).all(dim=1)]
    assert len(base_pairs) == len(base.pairs)
    assert float(base.loss(G, grad)) > 0


# --- weights: a result carries them, a warm start reads them back ------------------------------------------
def _small_run(**optim) -> NeuralConfig:
    return NeuralConfig.model_validate({"network": "small", "device": "cpu",
                                        "optim": {"max_steps": 15, "target_overhang": 0, **optim}})


def test_weights_round_trip_through_the_arrays_and_warm_start_the_same_field():
    V, T = box_tet_grid((4, 4, 4), np.zeros(3), np.full(3, 10.0))
    samples = sphere_samples()
    first = optimise_field(V, T, samples, config=_small_run(), platform_z=0.0)
    arrays, _ = first.to_arrays()
    weights = FieldResult.weights_of(arrays)
    assert weights is not None and set(weights) == set(first.weights)
    assert all(k.startswith("weights/") for k in arrays if k.split("/")[-1] in weights)
    assert all(isinstance(v, np.ndarray) and v.dtype.kind == "f" for v in weights.values())
    assert FieldResult.weights_of({"G": first.G}) is None
    # no step: the warm start is the field that was stored, exactly; no pre-training of the guess
    cfg = NeuralConfig.model_validate({**_small_run(max_steps=0).model_dump(), "init": {"kind": "heat"}})
    same = optimise_field(V, T, samples, config=cfg, platform_z=0.0, warm_start=weights)
    np.testing.assert_array_equal(same.G, first.G)
    assert len(same.pretrain_history) == 0
    for k in weights:
        np.testing.assert_array_equal(same.weights[k], weights[k])
    # a few steps on from there continue from the stored loss, not from planar layers
    on = optimise_field(V, T, samples, config=_small_run(max_steps=3), platform_z=0.0, warm_start=weights)
    assert on.history["total"][0] == pytest.approx(first.final["total"], rel=1e-4)
    with pytest.raises(InputError, match="do not fit"):
        optimise_field(V, T, samples, config=NeuralConfig.model_validate({**cfg.model_dump(), "network": "default"}),
                       platform_z=0.0, warm_start=weights)


# --- a closed loop whose coarse pool misses collisions the exact check finds -------------------------------
class TorusSolid:
    """The torus of test_neural_head_collision as the solid optimise_for_solid reads (H, bounds, volume, platform)."""

    platform_z = 0.0
    bounds = np.array([[-16.5, -4.5, 0.0], [16.5, 4.5, 32.5]])   # the torus's box, half a mm larger

    @staticmethod
    def H(x: np.ndarray) -> np.ndarray:
        return torus_H(x)

    @staticmethod
    def volume() -> float:
        return 2 * np.pi ** 2 * R_MAJOR * R_MINOR ** 2


@pytest.fixture(scope="module")
def loop():
    lo, hi = np.array([-17.0, -5.0, -0.5]), np.array([17.0, 5.0, 32.5])
    V, T = box_tet_grid((17, 5, 16), lo, hi)
    B = torus_samples()
    samples = SurfaceSamples(B["points"], B["normals"], B["areas"], B["knn"], B["on_platform"])
    probe = np.random.default_rng(3).uniform(lo, hi, (60_000, 3))
    return V, T, samples, probe[torus_H(probe) < 0]


def exact_collisions(V, T, G, probe, only=None):
    """The motion planner's check of the probe points printed in 0.5 mm slabs of G along their LPDs, in the order of
    G (L_GC's model of the print order): (colliding points (k,3), the material each hit (k,3), report with indices
    into ``probe``) -- an independent judge of the field's head."""
    g, d, _ = ScalarField(V, T, G).sample(probe)
    n = len(probe)
    order = np.argsort(g, kind="stable")
    tp = Toolpaths(layer=np.floor((g[order] - g.min()) / 0.5).astype(np.int64), path=np.zeros(n, np.int64),
                   xyz=probe[order], axis=d[order], thickness=np.full(n, 0.5), width=np.full(n, 0.3),
                   extrude=np.ones(n, bool))
    rank = np.empty(n, np.int64)
    rank[order] = np.arange(n)
    found = check_collisions(tp, NOZZLE, 0.0, min_height=0.3, only=None if only is None else rank[only])
    report = CollisionReport(order[found.indices], found.locations, found.kind)
    return probe[report.indices], report.locations, report


def _coarse_config(floor: bool) -> NeuralConfig:
    """100 grid points: 3.4 mm apart in a tube 8 mm thick (plus the surface samples, one per cell)."""
    return NeuralConfig.model_validate({
        "network": "small", "device": "cpu",
        "loss": {"head": NOZZLE.model_dump(), "head_min_height": 0.3, "gc_points": 100, "gc_floor": floor},
        "optim": {"max_steps": 600, "seed": 0, "refine": {"steps": 200}},
    })


@pytest.mark.slow   # over 10 s: the full suite runs it, `make test-fast` does not
def test_the_floor_term_clears_what_the_coarse_pool_misses_at_the_platform(loop):
    """The same coarse pool with the floor of the platform term (the default): the field the exact check judges
    collision-free, no refinement needed, and still support-free."""
    V, T, samples, probe = loop
    res = optimise_for_solid(TorusSolid(), V, T, samples, None, ["sf", "po", "gc", "ca"], _coarse_config(True))
    assert res.converged and res.attrs["head_collision"]["floor_tets"] > 0
    assert exact_collisions(V, T, res.G, probe)[2].count == 0
    assert res.satisfaction["overhang_area_fraction"] < 0.05 * res.satisfaction["planar_overhang_area_fraction"]


@pytest.mark.slow   # over 10 s: the full suite runs it, `make test-fast` does not
def test_refinement_clears_the_collisions_the_coarse_pool_missed(loop):
    V, T, samples, probe = loop
    cfg = _coarse_config(False)     # without the floor, so that the coarse pool misses collisions
    objectives = ["sf", "po", "gc", "ca"]
    coarse = optimise_for_solid(TorusSolid(), V, T, samples, None, objectives, cfg)
    assert coarse.converged and coarse.attrs["head_collision"]["colliding_points"] == 0   # clean on its pool
    hits, witnesses, report = exact_collisions(V, T, coarse.G, probe)
    assert report.count > 10                                                               # not on the part
    # on the refined pool the same field collides: the added points see what the base pool missed
    no_step = cfg.optim.refine.model_copy(update={"steps": 0})
    look = cfg.model_copy(update={"optim": cfg.optim.model_copy(update={"refine": no_step})})
    seen = optimise_for_solid(TorusSolid(), V, T, samples, None, objectives, look,
                              refine=Refinement(hits, witnesses, coarse.weights))
    np.testing.assert_array_equal(seen.G, coarse.G)
    assert seen.attrs["head_collision"]["refined_points_hit"] > 0
    assert seen.attrs["refinement"]["added_points"] == seen.attrs["head_collision"]["refined_points"] > 100
    # warm-started on the refined pool, the run stops once its points are clear: the exact check agrees
    refined = optimise_for_solid(TorusSolid(), V, T, samples, None, objectives, cfg,
                                 refine=Refinement(hits, witnesses, coarse.weights))
    assert refined.converged and refined.steps <= 200 and refined.attrs["refinement"]["warm_start"]
    assert refined.attrs["head_collision"]["colliding_points"] == 0
    again = exact_collisions(V, T, refined.G, probe, only=report.indices)[2]
    assert again.count == 0                                                     # no longer hits there
    assert exact_collisions(V, T, refined.G, probe)[2].count == 0               # nor anywhere else
    over = refined.satisfaction["overhang_area_fraction"]
    assert over <= coarse.satisfaction["overhang_area_fraction"] + cfg.optim.refine.overhang_slack
    assert over < 0.5 * refined.satisfaction["planar_overhang_area_fraction"]   # the support-free gain is kept
