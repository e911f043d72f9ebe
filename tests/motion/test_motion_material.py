"""The material printed so far (one structure for the whole print): the same hits as a brute-force check on random
prints, material of the pose's own layer and the beads' height seen, one structure per plan."""
from __future__ import annotations

import numpy as np
import pytest
import trimesh

from neuralslicer.motion import check_collisions
from neuralslicer.motion.collision import PART, PLATFORM, TRAVEL_PATH, default_min_height, travel_samples
from neuralslicer.motion.head import platform_clearance
from neuralslicer.motion.material import PrintedMaterial
from neuralslicer.motion.profile import Nozzle
from neuralslicer.toolpath import toolpaths
from neuralslicer.toolpath.synthetic import _with_lpd, cap_stack
from neuralslicer.toolpath.types import Toolpaths

from head_reference import NOZZLE, inside_head


def brute_force(tp: Toolpaths, nz: Nozzle, platform_z: float, min_height: float, spacing: float = 2.0,
                earlier_layers_only: bool = False) -> dict[int, int]:
    """{waypoint: kind} of every collision, each pose tested against every bead laid before it (top and bottom)."""
    on = np.flatnonzero(tp.path >= 0)
    tops = tp.xyz[on]
    beads = np.concatenate([tops, tops - tp.thickness[on, None] * tp.axis[on]])
    laid_at = np.concatenate([on, on])                     # the waypoint that lays each point
    layer_of = tp.layer[laid_at]

    def hit(tip: np.ndarray, axis: np.ndarray, i: int) -> bool:
        seen = laid_at < i
        if earlier_layers_only:
            seen &= layer_of < tp.layer[i]
        return bool(inside_head(beads[seen], tip, axis, nz, min_height).any())

    found: dict[int, int] = {}
    clear = platform_clearance(tp.xyz, tp.axis, nz, platform_z)
    for i in range(len(tp)):
        if clear[i] < -1e-6:
            found[i] = PLATFORM
        elif hit(tp.xyz[i], tp.axis[i], i):
            found[i] = PART
    s_xyz, s_axis, s_to = travel_samples(tp, spacing)
    for tip, axis, i in zip(s_xyz, s_axis, s_to):
        if int(i) not in found and hit(tip, axis, int(i)):
            found[int(i)] = TRAVEL_PATH
    return found


def _rotate_about(axis: np.ndarray, rotvec: np.ndarray) -> np.ndarray:
    """Unit vectors (n, 3) rotated by rotation vectors (n, 3) (Rodrigues)."""
    angle = np.linalg.norm(rotvec, axis=1, keepdims=True)
    k = rotvec / np.where(angle > 0, angle, 1.0)
    out = axis * np.cos(angle) + np.cross(k, axis) * np.sin(angle) + k * (k * axis).sum(1, keepdims=True) * (1 - np.cos(angle))
    return out / np.linalg.norm(out, axis=1, keepdims=True)


def random_print(seed: int) -> Toolpaths:
    """Curved caps printed with the tool axis leaning by a smooth random field (up to 90 deg), some layers printed
    in reverse order: heads meet the layers below and their own layer's earlier paths."""
    rng = np.random.default_rng(seed)
    tp = toolpaths(cap_stack(4, thickness=0.7, r0=8.0, theta_max_deg=55.0, subdivisions=3), platform_z=-30.0)
    k, phase = rng.normal(size=(3, 3)) * 0.6, rng.uniform(0, 2 * np.pi, 3)
    rotvec = np.radians(90.0) * np.sin(tp.xyz @ k.T + phase) / np.sqrt(3)
    axis = _rotate_about(tp.axis, rotvec)
    order = np.arange(len(tp))
    for layer in np.unique(tp.layer):                      # print about half of the layers backwards
        rows = np.flatnonzero(tp.layer == layer)
        if rng.random() < 0.5:
            order[rows] = rows[::-1]
    return Toolpaths(layer=tp.layer[order], path=tp.path[order], xyz=tp.xyz[order], axis=axis[order],
                     thickness=tp.thickness[order] * rng.uniform(0.5, 1.5, len(tp)), width=tp.width[order],
                     extrude=tp.extrude[order])


@pytest.mark.parametrize("seed", [0, 1, 2])
def test_the_print_structure_finds_the_hits_of_a_brute_force_check(seed):
    tp = random_print(seed)
    min_height = default_min_height(tp)
    report = check_collisions(tp, NOZZLE, platform_z=-30.0)
    expected = brute_force(tp, NOZZLE, -30.0, min_height)
    assert dict(zip(report.indices.tolist(), report.kind.tolist())) == expected
    assert 20 < len(expected) < len(tp) - 20 and PART in expected.values()
    # every witness is a bead laid before its waypoint, inside the head there
    on = np.flatnonzero(tp.path >= 0)
    for i, q, kind in zip(report.indices, report.locations, report.kind):
        if kind == PART:
            assert inside_head(q[None], tp.xyz[i], tp.axis[i], NOZZLE, min_height)[0]
            tops, bottoms = tp.xyz[on], tp.xyz[on] - tp.thickness[on, None] * tp.axis[on]
            laid = on[np.all(np.isclose(tops, q), axis=1) | np.all(np.isclose(bottoms, q), axis=1)]
            assert len(laid) and laid.min() < i
    # a subset is judged against the whole print's material
    some = np.arange(len(tp))[seed::3]
    part = check_collisions(tp, NOZZLE, platform_z=-30.0, only=some)
    assert np.array_equal(part.indices, np.intersect1d(report.indices, some))


def bowl_layer(radius: float = 14.0, theta_max_deg: float = 70.0, bottom: float = 1.0) -> trimesh.Trimesh:
    """The inside of a sphere below its centre: a curved layer rising 10 mm to its rim, LPD toward the centre."""
    s = trimesh.creation.icosphere(subdivisions=4, radius=1.0)
    keep = np.all(s.vertices[s.faces][:, :, 2] <= -np.cos(np.radians(theta_max_deg)), axis=1)
    used, inv = np.unique(s.faces[keep], return_inverse=True)
    n = s.vertices[used] / np.linalg.norm(s.vertices[used], axis=1, keepdims=True)
    centre = np.array([0.0, 0.0, radius + bottom])
    return _with_lpd(centre + radius * n, inv.reshape(-1, 3)[:, ::-1], -n, 0.0)


def test_a_curved_layer_hits_only_its_own_earlier_paths():
    """One bowl-shaped layer, its rim printed first: the holder at the bottom of the bowl sweeps over the rim's
    beads, material of the same layer only (there is no earlier layer). The check finds what a brute-force test of
    the same layer's earlier beads finds, and nothing is found when only earlier layers count."""
    tp = toolpaths([bowl_layer()], platform_z=-50.0)
    min_height = default_min_height(tp)
    report = check_collisions(tp, NOZZLE, platform_z=-50.0)
    expected = brute_force(tp, NOZZLE, -50.0, min_height)
    assert dict(zip(report.indices.tolist(), report.kind.tolist())) == expected
    part = report.kind == PART
    assert part.sum() > 20 and np.all(tp.layer[report.indices] == 0)
    assert brute_force(tp, NOZZLE, -50.0, min_height, earlier_layers_only=True) == {}
    # among them, at the bottom of the bowl a vertical head meets the bowl's wall, laid earlier, far above its tip
    bottom = part & (tp.axis[report.indices, 2] > 0.99)
    assert bottom.any() and np.all(report.locations[bottom, 2] - tp.xyz[report.indices[bottom], 2] > 5.0)


def test_the_bead_height_counts():
    """A bead whose top lies just outside the cone but whose bottom lies inside it is a hit."""
    tip, axis = np.zeros(3), np.array([0.0, 0.0, 1.0])
    # laid earlier: a bead with its top 3 mm beside the axis at h = 5 (the cone's radius there: 2.89) and its
    # bottom 0.9 mm further along its own axis (-x), at 2.1 mm: inside
    tp = Toolpaths(layer=np.array([0, 1]), path=np.array([0, 1]), xyz=np.array([[3.0, 0.0, 5.0], tip]),
                   axis=np.array([[1.0, 0.0, 0.0], axis]), thickness=np.array([0.9, 0.5]), width=np.full(2, 0.5),
                   extrude=np.array([False, False]))
    assert not inside_head(tp.xyz[:1], tip, axis, NOZZLE, 0.5).any()
    report = check_collisions(tp, NOZZLE, platform_z=-50.0, travel_spacing=0.0)
    assert list(report.indices) == [1] and np.allclose(report.locations[0], [2.1, 0.0, 5.0])


def test_the_structure_answers_for_every_moment():
    """Prefix ends and the top of the material agree with a direct count at random moments."""
    rng = np.random.default_rng(1)
    pts = rng.uniform(-20, 20, (3000, 3))
    time = rng.integers(0, 200, 3000)
    material = PrintedMaterial.of_points(pts, time, 200, cell=2.0)
    assert len(material.points) == 3000 and np.all(np.diff(material.start) >= 0)
    cubes = np.flatnonzero(np.diff(material.start))
    cube = rng.choice(cubes, 500)
    seen = rng.integers(0, 201, 500)
    end = material.prefix_end(cube, seen)
    for c, v, e in zip(cube, seen, end):
        t = material.time[material.start[c]:material.start[c + 1]]
        assert np.all(np.diff(t) >= 0) and e - material.start[c] == (t < v).sum()
    v = rng.integers(0, 201, 100)
    assert np.allclose(material.top_before(v), [pts[time < x, 2].max(initial=-np.inf) for x in v])


def test_plan_print_builds_one_structure(monkeypatch):
    """The check, the travel lifts, the tilts and the reach re-checks share one structure of the print."""
    from neuralslicer.motion import plan
    from neuralslicer.motion.profile import load_profile

    built = []
    of_toolpaths = PrintedMaterial.of_toolpaths.__func__

    def counting(cls, tp, *args, **kwargs):
        built.append(len(tp))
        return of_toolpaths(cls, tp, *args, **kwargs)

    monkeypatch.setattr(PrintedMaterial, "of_toolpaths", classmethod(counting))
    layers = cap_stack(6, thickness=0.6, r0=6.0, theta_max_deg=75.0, subdivisions=3)
    tp, _, metrics, report = plan.plan_print(layers, platform_z=-12.0)
    assert len(built) == 1
    assert metrics["axis_tilt"]["n_collisions_before"] > 0 or metrics["travel_lift"]["n_travels_lifted"] > 0
    assert report.count == check_collisions(tp, load_profile("table_bc_linuxcnc").nozzle, -12.0).count


def test_the_print_structure_is_that_of_its_beads_tops_and_bottoms():
    """``of_toolpaths`` (built without the beads' (2n, 3) point arrays) is ``of_points`` of every printing waypoint's
    top and bottom laid at its rank, array for array; travel waypoints lay nothing."""
    layers = cap_stack(4, thickness=0.6, r0=6.0, theta_max_deg=70.0, subdivisions=3)
    tp = toolpaths(layers, platform_z=-8.0)
    tp.path[::37] = -1                                  # some waypoints that are not on a layer
    on = tp.path >= 0
    top = tp.xyz[on]
    bottom = top - tp.thickness[on, None] * tp.axis[on]
    rank = np.arange(int(on.sum()))
    for cell in (0.7, 1.5):
        lean = PrintedMaterial.of_toolpaths(tp, cell=cell)
        ref = PrintedMaterial.of_points(np.concatenate([top, bottom]), np.concatenate([rank, rank]), len(rank), cell)
        for name in ("columns", "time", "origin", "start", "top"):
            assert np.array_equal(getattr(lean, name), getattr(ref, name)), name
            assert getattr(lean, name).dtype == getattr(ref, name).dtype
        assert (lean.cell, lean.stride, lean.n_ranks) == (ref.cell, ref.stride, ref.n_ranks)
        assert all(np.array_equal(a, b) for a, b in zip(lean.dims, ref.dims))
        assert all(np.array_equal(a, b) for a, b in zip(lean.first, ref.first))


def test_the_motion_step_can_take_over_the_toolpaths():
    """``consume=True`` (the pipeline's motion step) leaves the caller's toolpaths empty, so they are not held beside
    the program, and plans what the caller's copy plans."""
    import dataclasses

    from neuralslicer.motion.plan import plan_motion_of
    from neuralslicer.toolpath.plan import plan_toolpaths

    tp = plan_toolpaths(cap_stack(4, thickness=0.6, r0=6.0, theta_max_deg=60.0, subdivisions=3), platform_z=-8.0)
    given = dataclasses.replace(tp, **{k: getattr(tp, k).copy() for k in ("layer", "path", "xyz", "axis", "thickness",
                                                                          "width", "extrude")}, attrs=dict(tp.attrs))
    taken = plan_motion_of(given, platform_z=-8.0, consume=True)
    kept = plan_motion_of(tp, platform_z=-8.0)
    assert len(given) == 0 and len(tp) > 1000
    assert np.array_equal(taken[0].xyz, kept[0].xyz) and np.array_equal(taken[1].machine, kept[1].machine)
    assert {k: v for k, v in taken[2].items() if k != "timings_s"} == {k: v for k, v in kept[2].items() if k != "timings_s"}
