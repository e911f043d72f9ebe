"""Table-table B/C kinematics: IK/FK round trip, continuity, singular rule, limits, profiles."""
from __future__ import annotations

import numpy as np
import pytest

from neuralslicer.errors import InputError
from neuralslicer.motion import (MachineProfile, forward_kinematics, inverse_kinematics, load_profile,
                                 machine_position, plan_motion, profile_names)
from neuralslicer.motion.profile import Kinematics
from neuralslicer.toolpath import toolpaths
from neuralslicer.toolpath.synthetic import cap_stack


def _angle_deg(a, b):
    return np.degrees(np.arccos(np.clip(np.einsum("ij,ij->i", a, b), -1.0, 1.0)))


def test_ik_fk_round_trip_random():
    rng = np.random.default_rng(1)
    kin = Kinematics(pivot=(12.0, -3.0, 40.0), c_offset=(0.5, -1.0, 7.0), tilt_min_deg=-180, tilt_max_deg=180)
    a = rng.normal(size=(500, 3))
    a /= np.linalg.norm(a, axis=1, keepdims=True)
    p = rng.uniform(-30, 30, size=(500, 3))
    off = np.array([1.0, 2.0, -3.0])
    b, c, singular, out = inverse_kinematics(a, kin)
    assert not out.any()
    m = machine_position(p, b, c, kin, off)
    p2, a2 = forward_kinematics(m, b, c, kin, off)
    assert np.abs(p2 - p).max() < 1e-9
    assert _angle_deg(a, a2).max() < 1e-5
    # the machine sees the tool axis along +Z: R_y(B) R_z(C) a = z, checked independently
    br, cr = np.radians(b), np.radians(c)
    rz = np.stack([np.cos(cr) * a[:, 0] - np.sin(cr) * a[:, 1], np.sin(cr) * a[:, 0] + np.cos(cr) * a[:, 1], a[:, 2]], 1)
    z = -np.sin(br) * rz[:, 0] + np.cos(br) * rz[:, 2]
    assert np.allclose(z, 1.0, atol=1e-9)


def test_axis_through_the_vertical_changes_b_sign_without_c_flip():
    t = np.radians(np.linspace(-40, 40, 81))
    for phi in (0.0, 1.0, 2.5):
        a = np.stack([np.sin(t) * np.cos(phi), np.sin(t) * np.sin(phi), np.cos(t)], 1)
        b, c, singular, _ = inverse_kinematics(a, Kinematics())
        assert np.abs(np.diff(c)).max() < 1e-9             # C constant along the sweep
        assert b[0] * b[-1] < 0 and np.abs(np.diff(b)).max() < 1.0 + 1e-9
        assert singular.sum() == 1                         # the exactly vertical one


def test_singular_rule_keeps_previous_c():
    kin = Kinematics(singular_tol_deg=0.5)
    a = np.array([[np.sin(0.3), 0, np.cos(0.3)], [1e-4, 1e-4, 1], [-1e-4, 2e-4, 1], [0, np.sin(0.3), np.cos(0.3)]])
    a /= np.linalg.norm(a, axis=1, keepdims=True)
    b, c, singular, _ = inverse_kinematics(a, kin)
    assert singular.tolist() == [False, True, True, False]
    assert b[1] == 0 and b[2] == 0 and c[1] == c[0] and c[2] == c[0]
    # C changes by 90 deg in total (azimuth 0 -> 90 deg), not by 270
    assert np.isclose(abs(c[3] - c[0]), 90.0)


def test_c_is_unwrapped_over_many_turns():
    t = np.linspace(0, 6 * np.pi, 2000)
    a = np.stack([0.5 * np.cos(t), 0.5 * np.sin(t), np.full_like(t, np.sqrt(0.75))], 1)
    b, c, _, _ = inverse_kinematics(a, Kinematics())
    assert np.abs(np.diff(c)).max() < 1.0
    assert np.isclose(abs(c[-1] - c[0]), 1080.0, atol=1e-6)
    assert np.allclose(b, b[0])


def test_b_limits_pick_the_other_branch():
    a = np.array([[np.sin(1.2), 0, np.cos(1.2)]])                   # 68.8 deg tilt
    kin = Kinematics(tilt_min_deg=-90.0, tilt_max_deg=10.0)
    b, c, _, out = inverse_kinematics(a, kin)
    assert b[0] < 0 and not out.any()
    kin = Kinematics(tilt_min_deg=-10.0, tilt_max_deg=10.0)
    _, _, _, out = inverse_kinematics(a, kin)
    assert out.all()


def test_planned_program_respects_max_rotary_step_and_reproduces_waypoints():
    layers = cap_stack(2, r0=8.0, theta_max_deg=35.0, subdivisions=4)
    tp = toolpaths(layers, platform_z=-20.0)
    profile = load_profile("table_bc_linuxcnc")
    prog = plan_motion(tp, profile, platform_z=-20.0)
    step = np.abs(np.diff(prog.machine[:, 3:5], axis=0)).max()
    assert step <= profile.kinematics.max_rotary_step_deg + 1e-9
    p, a = prog.forward()
    src = prog.source >= 0
    assert np.array_equal(np.sort(prog.source[src]), np.arange(len(tp)))
    assert np.abs(p[src] - tp.xyz[prog.source[src]]).max() < 1e-9
    assert _angle_deg(a[src], tp.axis[prog.source[src]]).max() < 0.1


def test_shipped_profiles_load_and_bad_profiles_raise(tmp_path):
    assert {"table_bc_linuxcnc", "reprap_5axis"} <= set(profile_names())
    lin, rep = load_profile("table_bc_linuxcnc"), load_profile("reprap_5axis")
    assert lin.axes.extruder == "A" and lin.gcode.dialect == "linuxcnc"
    assert rep.axes.extruder == "E" and rep.gcode.dialect == "reprap"
    bad = tmp_path / "bad.yaml"
    bad.write_text("name: x\nfeeds: {print_mm_s: -1}\n")
    with pytest.raises(InputError, match="feeds.print_mm_s"):
        load_profile(bad)
    with pytest.raises(InputError, match="no such machine profile"):
        load_profile("no_such_machine")
    with pytest.raises(ValueError):
        MachineProfile(axes={"extruder": "E"})           # LinuxCNC has no E axis


def test_alternating_loops_unwind_the_c_axis():
    from neuralslicer.toolpath import ToolpathConfig

    layers = cap_stack(4, r0=8.0, theta_max_deg=30.0, subdivisions=4)
    spans = {}
    for alt in (False, True):
        tp = toolpaths(layers, platform_z=-20.0, config=ToolpathConfig(infill="contour", alternate_loops=alt))
        c = plan_motion(tp, load_profile("table_bc_linuxcnc"), platform_z=-20.0).machine[:, 4]
        spans[alt] = c.max() - c.min()
    n_loops = 20                         # well below the ~34 loops around the C axis in total
    assert spans[False] > 0.9 * 360 * n_loops
    assert spans[True] < 2 * 360


def test_kinematics_in_blocks_equal_one_block(monkeypatch):
    import neuralslicer.motion.kinematics as K
    from neuralslicer.motion.kinematics import tool_axis
    rng = np.random.default_rng(4)
    kin = Kinematics(pivot=(12.0, -3.0, 40.0), c_offset=(0.5, -1.0, 7.0), tilt_min_deg=-180, tilt_max_deg=180)
    p, off = rng.uniform(-30, 30, size=(1000, 3)), np.array([1.0, 2.0, -3.0])
    b, c = rng.uniform(-90, 90, 1000), rng.uniform(-720, 720, 1000)
    whole = machine_position(p, b, c, kin, off), forward_kinematics(p, b, c, kin, off), tool_axis(b, c, kin)
    monkeypatch.setattr(K, "ROWS_PER_BLOCK", 7)
    out = np.zeros((1000, 5))
    machine_position(p, b, c, kin, off, out=out[:, :3])
    assert np.array_equal(out[:, :3], whole[0])
    fk = forward_kinematics(p, b, c, kin, off)
    assert np.array_equal(fk[0], whole[1][0]) and np.array_equal(fk[1], whole[1][1])
    # the tool axis alone is forward kinematics' axis, and that is R_z(-C) R_y(-B) +Z
    assert np.array_equal(tool_axis(b, c, kin), whole[2]) and np.array_equal(whole[2], whole[1][1])
    br, cr = np.radians(b), np.radians(c)
    assert np.allclose(whole[2], np.c_[-np.cos(cr) * np.sin(br), np.sin(cr) * np.sin(br), np.cos(br)], atol=1e-15)


def test_split_rotary_moves_end_exactly_on_their_waypoints():
    from neuralslicer.motion.planning import _split_rotary
    rng = np.random.default_rng(2)
    m = 50
    mv = {"xyz": rng.uniform(-10, 10, (m, 3)), "b": np.cumsum(rng.uniform(-3, 3, m)),
          "c": np.cumsum(rng.uniform(-9, 9, m)), "de": rng.uniform(0, 1, m), "dt": rng.uniform(0, 1, m),
          "extrude": rng.uniform(size=m) < 0.7, "layer": np.arange(m) // 10, "source": np.arange(-1, m - 1)}
    mv["drot"] = np.r_[0.0, np.maximum(np.abs(np.diff(mv["b"])), np.abs(np.diff(mv["c"])))]
    given = dict(mv)
    out = _split_rotary(given, 2.0)
    assert not given                                  # the moves' arrays are handed over (freed as they are split)
    assert len(out["xyz"]) > m
    on = out["source"] >= 0
    assert np.array_equal(out["xyz"][on], mv["xyz"][out["source"][on] + 1])
    assert np.array_equal(out["c"][on], mv["c"][out["source"][on] + 1])
    assert np.abs(np.diff(out["c"])).max() <= 2.0 + 1e-9 and np.abs(np.diff(out["b"])).max() <= 2.0 + 1e-9
    assert np.isclose(out["de"].sum(), mv["de"].sum()) and np.isclose(out["dt"].sum(), mv["dt"].sum())
    # nothing to split: the same arrays, not copies
    still = _split_rotary(dict(mv), 100.0)
    assert still["xyz"] is mv["xyz"] and still["c"] is mv["c"] and np.array_equal(still["source"], mv["source"])
