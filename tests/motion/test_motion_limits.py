"""Machine limits are enforced, not counted: no pose outside the B range is written, C is unwound into its range."""
from __future__ import annotations

import numpy as np
import pytest

from neuralslicer.errors import PlanError
from neuralslicer.gcode import parse_gcode, write_gcode
from neuralslicer.motion import forward_kinematics, load_profile, plan_motion, plan_print
from neuralslicer.motion.planning import PRINT, TRAVEL, c_turns
from neuralslicer.toolpath.synthetic import cap_stack
from neuralslicer.toolpath.types import Toolpaths


def _angle_deg(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    return np.degrees(np.arccos(np.clip(np.einsum("ij,ij->i", a, b), -1.0, 1.0)))


def _winding_paths(n_paths: int = 3, turns: float = 4.0, polar_deg: float = 30.0, per_turn: int = 72) -> Toolpaths:
    """Helical paths whose tool axis (polar ``polar_deg``) circles the vertical ``turns`` times per path, so a
    table C axis follows it round: each path alone spans 360 * turns degrees of C."""
    rows = []
    for p in range(n_paths):
        s = np.linspace(0.0, 2 * np.pi * turns, int(per_turn * turns) + 1)
        r = 10.0
        xyz = np.column_stack([r * np.cos(s), r * np.sin(s), 1.0 + p + s / (2 * np.pi * turns)])
        pol = np.radians(polar_deg)
        axis = np.column_stack([np.sin(pol) * np.cos(s), np.sin(pol) * np.sin(s), np.full(len(s), np.cos(pol))])
        rows.append((p, xyz, axis))
    n = sum(len(x) for _, x, _ in rows)
    return Toolpaths(layer=np.concatenate([np.full(len(x), p) for p, x, _ in rows]).astype(np.int64),
                     path=np.concatenate([np.full(len(x), p) for p, x, _ in rows]).astype(np.int64),
                     xyz=np.concatenate([x for _, x, _ in rows]), axis=np.concatenate([a for _, _, a in rows]),
                     thickness=np.full(n, 0.5), width=np.full(n, 0.5),
                     extrude=np.concatenate([np.r_[False, np.ones(len(x) - 1, bool)] for _, x, _ in rows]))


def _limited(c_lo: float | None, c_hi: float | None):
    profile = load_profile("table_bc_linuxcnc").model_copy(deep=True)
    profile.kinematics.rotate_min_deg, profile.kinematics.rotate_max_deg = c_lo, c_hi
    profile.kinematics.pivot = (0.0, 0.0, 40.0)
    return profile


def test_c_turns_keep_one_count_while_it_fits_and_change_at_path_starts():
    kind = np.array([TRAVEL, PRINT, PRINT, TRAVEL, PRINT, PRINT, TRAVEL, PRINT])
    c = np.array([0.0, 100.0, 300.0, 310.0, 500.0, 650.0, 700.0, 800.0])
    assert (c_turns(c, kind, -1000.0, 1000.0) == 0).all()
    assert (c_turns(c, kind, -760.0, 100.0) == -2).all()              # one count for all when one fits
    # [-360, 360]: path 2 (310..650) needs -1 turn from its start on, path 3 (700..800) -2
    turns = c_turns(c, kind, -360.0, 360.0)
    assert list(turns) == [0, 0, 0, -1, -1, -1, -2, -2]
    assert ((c + 360 * turns >= -360) & (c + 360 * turns <= 360)).all()


def test_c_turns_unwind_inside_a_path_that_spans_more_than_the_range():
    c = np.linspace(0.0, 2000.0, 201)
    kind = np.r_[TRAVEL, np.full(200, PRINT)]
    turns = c_turns(c, kind, -360.0, 360.0)
    out = c + 360 * turns
    assert out.min() >= -360 and out.max() <= 360
    assert np.count_nonzero(np.diff(turns)) == 2   # 2000 deg from the bottom of a 720 deg range: two unwinds (of 2 turns)


def test_the_pose_turned_at_fits_the_new_count():
    """Where the count changes the axis turns at the move before: with the path's first move or an unwinding move
    just inside the range's far end, that pose (one step short of it) must fit the new count too (the 200 mm bunny
    on a head with C in +-720 deg put 21 turned poses 0.3-1.5 deg outside before)."""
    # a path rising through the top of [-360, 360]: the unwind at 361 would turn the pose at 359.5 to -0.5 - 360
    c = np.r_[np.linspace(0.0, 359.5, 240), np.linspace(361.0, 1100.0, 300)]
    kind = np.r_[TRAVEL, np.full(len(c) - 1, PRINT)]
    turns = c_turns(c, kind, -360.0, 360.0)
    change = np.flatnonzero(np.diff(turns)) + 1
    assert len(change) and ((c + 360 * turns >= -360) & (c + 360 * turns <= 360)).all()
    turned_at = c[change - 1] + 360 * turns[change]
    assert ((turned_at >= -360) & (turned_at <= 360)).all()
    # a new path whose count must change, the travel's first move 1.5 deg from the previous pose
    c2 = np.array([0.0, 200.0, 359.0, 360.5, 500.0, 800.0])
    kind2 = np.array([TRAVEL, PRINT, PRINT, TRAVEL, PRINT, PRINT])
    t2 = c_turns(c2, kind2, -360.0, 360.0)
    at = np.flatnonzero(np.diff(t2)) + 1
    assert ((c2 + 360 * t2 >= -360) & (c2 + 360 * t2 <= 360)).all()
    assert len(at) and ((c2[at - 1] + 360 * t2[at] >= -360) & (c2[at - 1] + 360 * t2[at] <= 360)).all()


def test_c_is_unwound_into_a_configured_range_at_a_safe_height(tmp_path):
    tp = _winding_paths()
    free = plan_motion(tp, _limited(None, None), platform_z=0.0)
    assert np.ptp(free.machine[:, 4]) > 3000.0                   # unlimited C winds up
    profile = _limited(-400.0, 400.0)
    prog = plan_motion(tp, profile, platform_z=0.0)
    c = prog.machine[:, 4]
    assert c.min() >= -400.0 - 1e-9 and c.max() <= 400.0 + 1e-9
    assert prog.attrs["n_c_unwinds"] >= 3 and prog.attrs["c_range_deg"][1] <= 400.0
    # every waypoint still reached with its own tool axis (forward kinematics of the program)
    src = prog.source >= 0
    p, a = forward_kinematics(prog.machine[src, :3], prog.machine[src, 3], c[src], profile.kinematics, prog.part_offset)
    assert np.allclose(p, tp.xyz[prog.source[src]], atol=1e-6)
    assert _angle_deg(a, tp.axis[prog.source[src]]).max() < 1e-4
    # C only turns by more than one rotary step's worth of path where the tool is at the safe height
    z_safe = prog.attrs["safe_z"]
    big = np.flatnonzero(np.abs(np.diff(c)) > 1e-9)
    unwinding = np.zeros(len(c), bool)
    for j in np.flatnonzero(np.abs(np.diff(c)) > 0):
        if prog.machine[j, 2] >= z_safe - 1e-9 and prog.machine[j + 1, 2] >= z_safe - 1e-9:
            unwinding[j + 1] = True
    assert len(big) and np.abs(np.diff(c)).max() <= profile.kinematics.max_rotary_step_deg + 1e-9
    total_turn = np.abs(np.diff(c))[unwinding[1:]].sum()
    assert total_turn >= 360.0 * prog.attrs["n_c_unwinds"] - 1e-6   # whole turns happen up there
    # no extrusion while unwinding, and the material extruded is the same as without limits
    assert (prog.kind[unwinding] == TRAVEL).all()
    assert prog.extruder[prog.kind == PRINT].max() == pytest.approx(free.extruder[free.kind == PRINT].max())
    # the written program stays in range too
    moves = parse_gcode(write_gcode(tmp_path / "p.ngc", prog))
    assert moves.axes["C"].min() >= -400.0 - 1e-4 and moves.axes["C"].max() <= 400.0 + 1e-4


def test_the_program_ends_with_c_home_inside_the_range():
    prog = plan_motion(_winding_paths(1, turns=1.5), _limited(30.0, 800.0), platform_z=0.0)
    for c in (prog.machine[0, 4], prog.machine[-1, 4]):          # C at home: a whole turn, inside [30, 800]
        assert c % 360.0 == pytest.approx(0.0, abs=1e-9) and 30.0 <= c <= 800.0
    assert (prog.machine[:, 4] >= 30.0 - 1e-9).all() and (prog.machine[:, 4] <= 800.0 + 1e-9).all()


def test_c_range_narrower_than_a_turn_is_refused():
    from neuralslicer.errors import InputError
    from neuralslicer.motion.profile import _validate

    with pytest.raises(InputError, match="rotary range must span at least 360"):
        _validate({"kinematics": {"rotate_min_deg": -90.0, "rotate_max_deg": 90.0}}, "narrow.yaml")


def test_no_pose_outside_a_narrow_b_range_is_written(tmp_path):
    layers = cap_stack(3, r0=8.0, theta_max_deg=60.0, center=(0.0, 0.0, 0.0), subdivisions=4)
    profile = load_profile("table_bc_linuxcnc").model_copy(deep=True)
    profile.kinematics.tilt_min_deg, profile.kinematics.tilt_max_deg = -20.0, 20.0
    tp, prog, metrics, _ = plan_print(layers, platform_z=0.0, profile=profile)
    assert (np.abs(prog.machine[:, 3]) <= 20.0 + 1e-9).all()
    assert metrics["axis_reach"]["n_clamped"] > 0 and metrics["axis_reach"]["n_beyond_tilt_bound"] > 0
    assert metrics["axis_reach"]["max_clamp_deg"] > 15.0
    moves = parse_gcode(write_gcode(tmp_path / "p.ngc", prog))
    assert np.abs(moves.axes["B"]).max() <= 20.0 + 1e-4
    # the plan refuses instead when asked to, naming the layers
    profile.kinematics.beyond_reach = "fail"
    with pytest.raises(PlanError, match=r"beyond the machine's reach \(20 deg.*in layers"):
        plan_print(layers, platform_z=0.0, profile=profile)
    # and plan_motion on its own never writes an unreachable pose
    with pytest.raises(PlanError, match="outside the machine's range"):
        plan_motion(tp.__class__(**{**tp.__dict__, "axis": np.tile([1.0, 0.0, 0.0], (len(tp), 1))}), profile, 0.0)


def test_moves_shorter_than_the_controller_executes_are_merged():
    from neuralslicer.motion.planning import merge_short_moves

    rng = np.random.default_rng(0)
    x = np.sort(np.r_[np.arange(0.0, 20.01, 0.5), rng.uniform(0.0, 20.0, 60)])   # 60 tiny moves among 0.5 mm ones
    n = len(x)
    tp = Toolpaths(layer=np.ones(n, np.int64), path=np.zeros(n, np.int64), xyz=np.column_stack([x, np.zeros(n), np.ones(n)]),
                   axis=np.tile([0.0, 0.0, 1.0], (n, 1)), thickness=np.full(n, 0.5), width=np.full(n, 0.5),
                   extrude=np.r_[False, np.ones(n - 1, bool)])
    profile = load_profile("table_bc_linuxcnc")
    f = profile.feeds
    v = f.first_layer_mm_s                                          # the only layer is the first
    short = tp.segment_lengths()[1:] / v < f.min_move_s
    assert short.sum() > 10
    out, n_merged = merge_short_moves(tp, profile)
    assert n_merged >= short.sum() - 2 and len(out) == n - n_merged
    t = out.segment_lengths()[1:] / v
    assert (t[:-1] >= f.min_move_s - 1e-12).all()                 # only the path's last move may stay short
    assert np.allclose(out.xyz[[0, -1]], tp.xyz[[0, -1]])          # the path keeps its ends
    assert out.deposited_volume() == pytest.approx(tp.deposited_volume(), rel=1e-9)   # collinear: same material
    prog = plan_motion(out, profile, platform_z=0.0)
    src = prog.source >= 0
    assert np.allclose(prog.forward(src)[0], out.xyz[prog.source[src]], atol=1e-9)
