"""Print time under axis limits: closed forms, and a time-stepped run of the G-code actually written."""
from __future__ import annotations


import numpy as np
import pytest

from neuralslicer.gcode import parse_gcode, write_gcode
from neuralslicer.motion import load_profile, plan_motion
from neuralslicer.motion.profile import Feeds
from neuralslicer.motion.timing import move_times, program_time
from neuralslicer.toolpath.generate import toolpaths
from neuralslicer.toolpath.synthetic import cap_stack, planar_stack


def _line(points, speed):
    """Poses (k, 5) through XYZ points (B = C = 0) and their planned durations at ``speed``."""
    pts = np.asarray(points, np.float64)
    machine = np.column_stack([pts, np.zeros((len(pts), 2))])
    planned = np.r_[0.0, np.linalg.norm(np.diff(pts, axis=0), axis=1) / speed]
    return machine, planned


# --- the independent check: read the G-code back and run it in small time steps -------------------------

def _read_program(path, letters, feed_basis):
    """Poses (m, 5) and the nominal duration (m,) of each move as the controller reads its F: G93 F = 1/min;
    else F mm/min over the XYZ distance (or all axes), rotary degrees when XYZ is still, else the filament."""
    moves = parse_gcode(path, axes="".join(letters))
    pos = np.column_stack([moves.axes[c] for c in letters[:5]])
    ext = moves.axes[letters[5]]
    nominal = np.zeros(len(pos))
    for i in range(1, len(pos)):
        if moves.inverse_time[i]:
            nominal[i] = 60.0 / moves.feed[i]
            continue
        d = pos[i] - pos[i - 1]
        xyz, rot = float(np.sqrt(d[0] ** 2 + d[1] ** 2 + d[2] ** 2)), float(np.sqrt(d[3] ** 2 + d[4] ** 2))
        dist = np.sqrt(xyz ** 2 + rot ** 2) if feed_basis == "all_axes" else xyz
        if dist == 0.0:
            dist = rot if rot > 0.0 else abs(ext[i] - ext[i - 1])
        nominal[i] = dist / (moves.feed[i] / 60.0)
    return pos, nominal


def _simulate(pos, nominal, feeds: Feeds, dt_max: float = 1e-4):
    """Durations (m,) of the moves run by stepping time: each move's progress s (0..1) speeds up at the
    largest rate no axis exceeds, never above the slowest axis' velocity limit or the programmed rate,
    and brakes in time to meet the next junction's speed (the junction rule of neuralslicer.motion.timing,
    made reachable by a plain backward and forward sweep)."""
    m = len(pos)
    v_lim = np.r_[[feeds.max_axis_mm_s] * 3, [feeds.rotary_deg_s] * 2]
    a_lim = np.r_[[feeds.accel_mm_s2] * 3, [feeds.rotary_accel_deg_s2] * 2]
    rate, accel, length = np.zeros(m), np.zeros(m), np.zeros(m)
    unit = np.zeros((m, 5))
    nom = np.where(nominal > 0, np.maximum(nominal, feeds.min_move_s), 0.0)
    for i in range(1, m):
        d = pos[i] - pos[i - 1]
        w = d / v_lim
        length[i] = np.sqrt(np.sum(w ** 2))
        if length[i] <= 1e-12:
            continue
        nom[i] = max(nominal[i], feeds.min_move_s)
        unit[i] = w / length[i]
        rate[i], accel[i] = 1.0 / nom[i], np.inf
        for j in range(5):
            if d[j] != 0.0:
                rate[i] = min(rate[i], v_lim[j] / abs(d[j]))
                accel[i] = min(accel[i], a_lim[j] / abs(d[j]))
    moving = length > 1e-12
    cap = np.zeros(m)
    for k in range(m - 1):
        if moving[k] and moving[k + 1]:
            cos = float(np.clip(unit[k] @ unit[k + 1], -1.0, 1.0))
            cap[k] = min(rate[k] * length[k], rate[k + 1] * length[k + 1]) * 0.5 * (1.0 + cos)
    for k in range(m - 2, -1, -1):
        cap[k] = min(cap[k], np.sqrt(cap[k + 1] ** 2 + 2.0 * accel[k + 1] * length[k + 1] ** 2))
    before = 0.0
    for k in range(m):
        cap[k] = min(cap[k], np.sqrt(before ** 2 + 2.0 * accel[k] * length[k] ** 2))
        before = cap[k]
    idx = np.flatnonzero(moving)
    lw = length[idx]
    u0, u1 = np.r_[0.0, cap[:-1]][idx] / lw, cap[idx] / lw
    r, a = rate[idx], accel[idx]
    dt = np.minimum(dt_max, nom[idx] / 1000.0)
    s, v, t = np.zeros(len(idx)), np.minimum(u0, r), np.zeros(len(idx))
    out = nom.copy()
    live = np.arange(len(idx))
    while len(live):
        # braking curve at the end of the step: v'^2 = u1^2 + 2 a (1 - s - (v + v') dt / 2)
        adt = a[live] * dt[live]
        rhs = u1[live] ** 2 + 2.0 * a[live] * np.maximum(1.0 - s[live], 0.0) - adt * v[live]
        brake = 0.5 * (-adt + np.sqrt(adt ** 2 + 4.0 * np.maximum(rhs, 0.0)))
        v_new = np.minimum(np.minimum(r[live], v[live] + a[live] * dt[live]), brake)
        s_new = s[live] + 0.5 * (v[live] + v_new) * dt[live]
        done = s_new >= 1.0
        step = np.where(done, dt[live] * (1.0 - s[live]) / np.maximum(s_new - s[live], 1e-300), dt[live])
        t[live] += step
        s[live], v[live] = s_new, v_new
        live = live[~done]
    out[idx] = t
    return out


def _closed_form(length, speed, accel):
    """Rest-to-rest time of a straight move: L/v + v/a, or 2 sqrt(L/a) when v is never reached."""
    return length / speed + speed / accel if length >= speed ** 2 / accel else 2.0 * np.sqrt(length / accel)


# --- closed forms -----------------------------------------------------------------------------------------

@pytest.mark.parametrize("length", [200.0, 0.4, 0.05])
def test_a_straight_move_takes_the_closed_form_time(length):
    feeds = Feeds(min_move_s=0.0)
    machine, planned = _line([[0, 0, 0], [length, 0, 0]], 20.0)
    expected = _closed_form(length, 20.0, feeds.accel_mm_s2)
    assert move_times(machine, planned, feeds)[1] == pytest.approx(expected, rel=1e-12)
    assert _simulate(machine, planned, feeds)[1] == pytest.approx(expected, rel=2e-3)


def test_the_slowest_axis_governs():
    feeds = Feeds(min_move_s=0.0, max_axis_mm_s=1000.0)
    # diagonal in XY: each axis carries 1/sqrt(2) of the path's acceleration, so the path gets sqrt(2) a
    machine, planned = _line([[0, 0, 0], [100, 100, 0]], 40.0)
    L = 100.0 * np.sqrt(2.0)
    assert move_times(machine, planned, feeds)[1] == pytest.approx(_closed_form(L, 40.0, np.sqrt(2.0) * feeds.accel_mm_s2))
    # a programmed speed above the axis limit runs at the limit
    feeds = Feeds(min_move_s=0.0, max_axis_mm_s=50.0)
    machine, planned = _line([[0, 0, 0], [0, 0, 300]], 200.0)
    assert move_times(machine, planned, feeds)[1] == pytest.approx(_closed_form(300.0, 50.0, feeds.accel_mm_s2))
    # a pure rotation: deg, deg/s, deg/s^2
    machine = np.array([[0, 0, 0, 0, 0], [0, 0, 0, 0, 270.0]])
    planned = np.array([0.0, 270.0 / feeds.rotary_deg_s])
    assert move_times(machine, planned, feeds)[1] == pytest.approx(
        _closed_form(270.0, feeds.rotary_deg_s, feeds.rotary_accel_deg_s2))


def test_junctions_collinear_corner_and_reversal():
    feeds = Feeds(min_move_s=0.0)
    a, v = feeds.accel_mm_s2, 20.0
    one = move_times(*_line([[0, 0, 0], [100, 0, 0]], v), feeds).sum()
    pieces = move_times(*_line(np.column_stack([np.linspace(0, 100, 401), np.zeros(401), np.zeros(401)]), v), feeds)
    assert pieces.sum() == pytest.approx(one, rel=1e-9)           # collinear pieces: no slowdown between them
    back = move_times(*_line([[0, 0, 0], [50, 0, 0], [0, 0, 0]], v), feeds)
    assert back.sum() == pytest.approx(2 * _closed_form(50.0, v, a))   # a reversal stops
    corner = move_times(*_line([[0, 0, 0], [50, 0, 0], [50, 50, 0]], v), feeds)
    u = v / 2                                                       # 90 degrees: half speed at the corner
    t = v / a + (v - u) / a + (50 - v ** 2 / (2 * a) - (v ** 2 - u ** 2) / (2 * a)) / v   # up to v, down to u
    assert corner[1] == pytest.approx(t) and corner[2] == pytest.approx(t)


def test_short_moves_take_at_least_min_move_s():
    feeds = Feeds()
    pts = np.column_stack([np.linspace(0, 1.0, 101), np.zeros(101), np.zeros(101)])   # 0.01 mm moves
    machine, planned = _line(pts, 20.0)                                               # planned 0.5 ms each
    t = move_times(machine, planned, feeds)
    assert (t[1:] >= feeds.min_move_s - 1e-15).all()
    assert t[1:].sum() == pytest.approx(_closed_form(1.0, 0.01 / feeds.min_move_s, feeds.accel_mm_s2), rel=1e-9)
    # retract / prime (no axis motion): planned time, at least min_move_s
    machine = np.zeros((3, 5))
    assert np.allclose(move_times(machine, [0.0, 0.001, 0.03], feeds), [0.0, feeds.min_move_s, 0.03])


def test_move_times_on_a_long_program():
    """200k moves at once (its speed is benchmarks/bench_toolpath.py's, not a test's)."""
    rng = np.random.default_rng(0)
    n = 200_000
    machine = np.cumsum(rng.normal(size=(n, 5)) * [1.0, 1.0, 0.1, 0.5, 2.0], axis=0)
    planned = np.r_[0.0, np.linalg.norm(np.diff(machine[:, :3], axis=0), axis=1) / 20.0]
    t = move_times(machine, planned, Feeds())
    assert np.isfinite(t).all() and (t[1:] >= np.maximum(planned[1:], Feeds().min_move_s) - 1e-12).all()


# --- the written G-code, run in time steps ------------------------------------------------------------------

@pytest.fixture(scope="module")
def synthetic_toolpaths():
    """Planar squares (corners, reversals) and spherical caps (rotary motion)."""
    layers = planar_stack(2, size=6.0, n=7) + cap_stack(2, r0=3.0, theta_max_deg=40.0, center=(0, 0, -1.5),
                                                         subdivisions=3)
    return toolpaths(layers, platform_z=0.0)


@pytest.mark.parametrize("profile_name, feed_basis", [("table_bc_linuxcnc", None), ("reprap_5axis", "xyz"),
                                                      ("reprap_5axis", "all_axes")])
def test_estimate_matches_a_time_stepped_run_of_the_gcode(tmp_path, synthetic_toolpaths, profile_name, feed_basis):
    profile = load_profile(profile_name).model_copy(deep=True)
    profile.kinematics.pivot = (5.0, -7.0, 60.0)
    if feed_basis:
        profile.gcode.feed_basis = feed_basis
    program = plan_motion(synthetic_toolpaths, profile, platform_z=0.0)
    path = write_gcode(tmp_path / "print.gcode", program)
    pos, nominal = _read_program(path, program.axis_letters, profile.gcode.feed_basis)
    assert len(pos) == len(program)
    simulated = _simulate(pos, nominal, profile.feeds)
    estimate = move_times(program.machine, program.time_s, profile.feeds)
    assert np.all(np.abs(simulated - estimate) <= 0.01 * estimate + 1e-5)      # every move (seen: 2e-4)
    summary = program_time(program)
    assert summary["estimated_print_time_s"] == pytest.approx(simulated.sum(), rel=2e-3)
    assert summary["estimated_print_time_s"] > summary["nominal_print_time_s"]
    assert 0.0 < summary["accel_limited_fraction"] < 1.0
    assert summary["n_moves_below_min_s"] == int(((program.time_s > 0) & (program.time_s < profile.feeds.min_move_s)).sum())


def test_schedule_in_blocks_equals_one_block(monkeypatch):
    from neuralslicer.motion import timing
    rng = np.random.default_rng(8)
    machine = np.cumsum(rng.normal(size=(4001, 5)), axis=0)
    machine[100:110] = machine[99]                         # moves without axis motion
    planned = rng.uniform(0, 0.1, len(machine))
    feeds = Feeds()
    whole = timing.schedule(machine, planned, feeds)
    monkeypatch.setattr(timing, "_ROWS", 333)
    blocks = timing.schedule(machine, planned, feeds)
    assert np.array_equal(whole[0], blocks[0]) and np.array_equal(whole[1], blocks[1])
    assert np.array_equal(whole[0], move_times(machine, planned, feeds))
    summary = program_time(type("P", (), {"machine": machine, "time_s": planned,
                                          "profile": load_profile("table_bc_linuxcnc").model_copy(update={"feeds": feeds})})())
    assert summary["estimated_print_time_s"] == pytest.approx(float(whole[0].sum()))


def test_the_schedule_in_blocks_is_the_schedule_of_the_whole(monkeypatch):
    """Blocks that end where the machine stands still give the whole program's junction speeds and times, bit for
    bit (a long print holds a block's temporaries)."""
    from neuralslicer.motion import timing

    rng = np.random.default_rng(5)
    feeds = load_profile("table_bc_linuxcnc").feeds
    n = 20_000
    machine = np.cumsum(rng.normal(scale=0.4, size=(n, 5)), axis=0)
    still = np.flatnonzero(rng.random(n) < 0.003)
    still = still[still > 0]
    machine[still] = machine[still - 1]                  # extruder-only moves: the machine at rest
    planned = rng.uniform(0.0, 0.05, n) * (rng.random(n) > 0.02)
    whole = timing.schedule(machine, planned, feeds)
    monkeypatch.setattr(timing, "_ROWS", 500)
    blocks = timing._blocks_at_rest(np.linalg.norm(np.diff(machine, axis=0, prepend=machine[:1]), axis=1) > 0, 500)
    assert len(blocks) > 10 and blocks[0][0] == 0 and blocks[-1][1] == n
    assert all(z == a for (_, z), (a, _) in zip(blocks, blocks[1:]))
    parts = timing.schedule(machine, planned, feeds)
    assert np.array_equal(whole[0], parts[0]) and np.array_equal(whole[1], parts[1])
    assert whole[0].sum() > planned.sum()                # acceleration costs time
