"""Tilting the tool axis clear of stray collisions: the smallest tilt away from the hit, ramped, judged exactly."""
from __future__ import annotations

import numpy as np
import pytest

from neuralslicer.errors import PlanError
from neuralslicer.motion import check_collisions
from neuralslicer.motion.profile import Nozzle
from neuralslicer.motion.reorient import tilt_away
from neuralslicer.toolpath.types import Toolpaths

NOZZLE = Nozzle(cone_half_angle_deg=30.0, cone_length=8.0, holder_radius=15.0, holder_length=30.0)


def _bump_and_path(bump_top: float) -> Toolpaths:
    """Layer 0: material at x = 2, |y| <= 0.5, z from 3.5 to ``bump_top`` (laid bottom-up); layer 1: a path along y
    at x = z = 0."""
    gz, gy = np.meshgrid(np.arange(3.5, bump_top + 1e-9, 0.25), np.arange(-0.5, 0.51, 0.25), indexing="ij")
    bump = np.column_stack([np.full(gy.size, 2.0), gy.ravel(), gz.ravel()])
    y = np.arange(-10.0, 10.01, 0.5)
    path = np.column_stack([np.zeros_like(y), y, np.zeros_like(y)])
    xyz = np.concatenate([bump, path])
    n0, n1 = len(bump), len(path)
    return Toolpaths(layer=np.r_[np.zeros(n0, np.int64), np.ones(n1, np.int64)],
                     path=np.r_[np.zeros(n0, np.int64), np.ones(n1, np.int64)], xyz=xyz,
                     axis=np.tile([0.0, 0.0, 1.0], (n0 + n1, 1)), thickness=np.full(n0 + n1, 0.5),
                     width=np.full(n0 + n1, 0.5), extrude=np.ones(n0 + n1, bool))


def _angle_deg(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    return np.degrees(np.arccos(np.clip(np.einsum("ij,ij->i", a, b), -1.0, 1.0)))


def test_a_small_tilt_away_from_the_bump_clears_the_head():
    tp = _bump_and_path(4.5)
    before = check_collisions(tp, NOZZLE, platform_z=-10.0)
    assert before.count > 0 and set(tp.layer[before.indices]) == {1}
    tilted, how = tilt_away(tp, before, NOZZLE, platform_z=-10.0, min_height=0.5, max_tilt_deg=15.0, ramp_mm=5.0)
    assert check_collisions(tilted, NOZZLE, platform_z=-10.0).count == 0
    assert len(how.fixed) == before.count and len(how.unfixed) == 0
    # brute force at the waypoint facing the bump: the smallest tilt along -x that clears every bump point,
    # rounded up to the 2.5 deg trial steps, is the one chosen
    bump = tp.xyz[tp.layer == 0]
    theta = np.radians(np.arange(0.0, 15.0, 0.01))
    axes = np.column_stack([-np.sin(theta), np.zeros_like(theta), np.cos(theta)])
    h = bump @ axes.T                                                           # tip at the origin
    radial = np.sqrt(np.maximum((bump ** 2).sum(1)[:, None] - h ** 2, 0.0))
    clear = ~((h <= 8.0) & (radial <= h * np.tan(np.radians(30.0)))).any(axis=0)
    theta_min = np.degrees(theta[np.argmax(clear)])
    centre = int(np.flatnonzero((tp.layer == 1) & (tp.xyz[:, 1] == 0.0))[0])
    assert np.isclose(how.tilt_deg[list(how.fixed).index(centre)], np.ceil(theta_min / 2.5) * 2.5)
    assert how.tilt_deg.max() <= 7.5 + 1e-9
    assert (tilted.axis[before.indices, 0] < 0).all()
    assert np.array_equal(tilted.xyz, tp.xyz)                                   # the layers are untouched
    tilt = _angle_deg(tilted.axis, tp.axis)
    on_path = tp.layer == 1
    assert tilt[~on_path].max() == 0.0                                          # other paths untouched
    assert tilt[on_path].max() <= 7.5 + 1e-9
    far = on_path & (np.abs(tp.xyz[:, 1]) > 2.0 + 5.0)                          # beyond the ramp
    assert tilt[far].max() == 0.0
    step = _angle_deg(tilted.axis[on_path][1:], tilted.axis[on_path][:-1])      # ramped: <= 7.5 deg per 5 mm
    assert step.max() <= 7.5 * 0.5 / 5.0 + 1e-6


def test_a_wall_no_tilt_can_clear_is_reported_not_hidden():
    tp = _bump_and_path(30.0)                                                   # a tall wall: needs > 30 deg
    before = check_collisions(tp, NOZZLE, platform_z=-10.0)
    tilted, how = tilt_away(tp, before, NOZZLE, platform_z=-10.0, min_height=0.5, max_tilt_deg=15.0)
    assert len(how.fixed) == 0 and len(how.unfixed) == before.count
    assert np.array_equal(tilted.axis, tp.axis)


def test_checking_a_subset_agrees_with_the_full_check():
    tp = _bump_and_path(4.5)
    full = check_collisions(tp, NOZZLE, platform_z=-10.0)
    some = np.arange(len(tp))[::3]
    part = check_collisions(tp, NOZZLE, platform_z=-10.0, only=some)
    assert np.array_equal(part.indices, np.intersect1d(full.indices, some))
    merged = full.replaced(some, part)
    assert np.array_equal(merged.indices, full.indices)


def test_plan_print_tilts_then_judges_again():
    from neuralslicer.motion import load_profile
    from neuralslicer.motion.plan import _tilt_clear
    from neuralslicer.toolpath import ToolpathConfig

    profile = load_profile("table_bc_linuxcnc").model_copy(update={"nozzle": NOZZLE})
    tp = _bump_and_path(4.5)
    before = check_collisions(tp, NOZZLE, platform_z=-10.0)
    out, after, summary = _tilt_clear(tp, before, profile, -10.0, ToolpathConfig())
    assert after.count == 0 and check_collisions(out, NOZZLE, platform_z=-10.0).count == 0
    assert summary["n_collisions_before"] == before.count == summary["n_collisions_cleared"]
    assert 0 < summary["max_tilt_deg"] <= 15.0 and summary["n_waypoints_tilted"] > before.count
    off, same, none = _tilt_clear(tp, before, profile, -10.0, ToolpathConfig(collision_tilt_deg=0))
    assert off is tp and same.count == before.count and none["n_waypoints_tilted"] == 0


def test_axes_beyond_the_b_range_are_turned_back_within_the_tilt_bound():
    from neuralslicer.motion import load_profile, plan_motion
    from neuralslicer.motion.reorient import clamp_to_reach

    polar = np.radians(np.array([30.0, 95.0, 105.0, 114.0, 130.0]))
    phi = np.radians(np.array([0.0, 40.0, 80.0, -120.0, 200.0]))
    axis = np.column_stack([np.sin(polar) * np.cos(phi), np.sin(polar) * np.sin(phi), np.cos(polar)])
    n = len(axis)
    tp = Toolpaths(layer=np.zeros(n, np.int64), path=np.zeros(n, np.int64), xyz=np.c_[np.arange(n), np.zeros(n), np.ones(n)],
                   axis=axis, thickness=np.full(n, 0.5), width=np.full(n, 0.5), extrude=np.ones(n, bool))
    out, summary = clamp_to_reach(tp, 100.0, 15.0)
    new_polar = np.degrees(np.arccos(out.axis[:, 2]))
    assert np.allclose(new_polar, [30.0, 95.0, 100.0, 100.0, 130.0])
    assert np.allclose(np.arctan2(out.axis[:, 1], out.axis[:, 0]), np.arctan2(axis[:, 1], axis[:, 0]))   # azimuth kept
    assert summary == {"n_clamped": 2, "max_clamp_deg": pytest.approx(14.0), "n_unreachable": 1}
    profile = load_profile("table_bc_linuxcnc")                                # B within +-100 deg
    for unreachable in (tp, out):                                              # 3, then 1 pose out of range
        with pytest.raises(PlanError, match="outside the machine's range"):
            plan_motion(unreachable, profile, platform_z=0.0)
    turned, _ = clamp_to_reach(tp, 100.0, 180.0)
    assert np.abs(plan_motion(turned, profile, platform_z=0.0).machine[:, 3]).max() <= 100.0 + 1e-9


def test_the_platform_limit_is_the_exact_largest_tilt_and_the_clamp_clears_within_the_bound():
    """platform_polar_limit against a brute-force scan of platform_clearance; clamp_to_platform turns only what
    the bound allows, keeps the azimuth, and what it turned clears the platform exactly."""
    from neuralslicer.motion.collision import platform_clearance
    from neuralslicer.motion.reorient import clamp_to_platform, platform_polar_limit

    rng = np.random.default_rng(3)
    z = rng.uniform(0.05, 45.0, 400)
    limit = platform_polar_limit(z, NOZZLE, platform_z=0.0, margin=0.0)
    scan = np.radians(np.arange(0.0, 180.001, 0.05))
    axes = np.column_stack([np.sin(scan), np.zeros_like(scan), np.cos(scan)])
    low = platform_clearance(np.zeros((len(scan), 3)), axes, NOZZLE, 0.0)           # clearance of a tip at z = 0
    ok = z[:, None] + low[None, :] >= 0
    brute = np.degrees(scan[np.where(ok.all(axis=1), len(scan) - 1, np.argmax(~ok, axis=1) - 1)])
    assert np.all(np.abs(np.minimum(limit, 180.0) - brute) <= 0.05 + 1e-9)
    assert limit.min() < 30.0 and limit.max() >= 180.0           # tight low down, unbounded high up

    polar = np.radians(np.array([20.0, 45.0, 45.0, 55.0, 70.0]))
    phi = np.radians(np.array([0.0, 70.0, -30.0, 150.0, 250.0]))
    axis = np.column_stack([np.sin(polar) * np.cos(phi), np.sin(polar) * np.sin(phi), np.cos(polar)])
    xyz = np.column_stack([np.arange(5.0), np.zeros(5), np.array([1.0, 1.0, 30.0, 4.0, 0.5])])
    n = len(xyz)
    tp = Toolpaths(layer=np.zeros(n, np.int64), path=np.zeros(n, np.int64), xyz=xyz, axis=axis,
                   thickness=np.full(n, 0.5), width=np.full(n, 0.5), extrude=np.ones(n, bool))
    before = platform_clearance(tp.xyz, tp.axis, NOZZLE, 0.0)
    need = np.degrees(polar) - platform_polar_limit(xyz[:, 2], NOZZLE, 0.0)
    assert list(before < 0) == [False, True, False, True, True] and 0 < need[1] < 15 and 0 < need[3] < 15 < need[4]
    out, summary = clamp_to_platform(tp, NOZZLE, platform_z=0.0, max_tilt_deg=15.0)
    after = platform_clearance(out.xyz, out.axis, NOZZLE, 0.0)
    assert summary["n_clamped"] == 2 and summary["n_unreachable"] == 1
    assert np.all(after[[0, 1, 2, 3]] > 0) and after[4] < 0 and np.allclose(out.axis[[0, 2, 4]], axis[[0, 2, 4]])
    assert np.allclose(np.arctan2(out.axis[:, 1], out.axis[:, 0]), np.arctan2(axis[:, 1], axis[:, 0]))
    assert np.all(after[[1, 3]] < 0.05)                                     # turned just far enough
