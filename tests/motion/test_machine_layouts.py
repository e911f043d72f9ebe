"""Machines as kinematic chains: every layout's IK and FK against an independent chain of homogeneous transforms,
every shipped profile's written program back-plotted within 0.01 mm / 0.01 deg, TCP programs through LinuxCNC's
trt kinematics formulas, three-axis programs (XYZE, vertical head), and `neuralslicer machines`."""
from __future__ import annotations

import re
import shutil
import subprocess

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from neuralslicer.gcode import parse_gcode, write_gcode
from neuralslicer.motion import load_profile, plan_print, profile_names
from neuralslicer.motion.kinematics import forward_kinematics, inverse_kinematics, machine_position, tool_axis
from neuralslicer.motion.profile import Kinematics, MachineProfile
from neuralslicer.toolpath.synthetic import cap_stack, planar_stack

_UNIT = {"+X": (1, 0, 0), "-X": (-1, 0, 0), "+Y": (0, 1, 0), "-Y": (0, -1, 0), "+Z": (0, 0, 1), "-Z": (0, 0, -1)}


def _about(axis: str, deg: np.ndarray, point=(0.0, 0.0, 0.0)) -> np.ndarray:
    """(n, 4, 4) rotations by ``deg`` about the line through ``point`` along the unit ``axis`` (right-hand rule)."""
    rot = Rotation.from_rotvec(np.radians(deg)[:, None] * np.asarray(_UNIT[axis], float)[None]).as_matrix()
    out = np.tile(np.eye(4), (len(deg), 1, 1))
    out[:, :3, :3] = rot
    out[:, :3, 3] = np.asarray(point) - rot @ np.asarray(point)
    return out


def _shift(v) -> np.ndarray:
    out = np.eye(4)
    out[:3, 3] = v
    return out


def _chain_fk(m: np.ndarray, t: np.ndarray, r: np.ndarray, kin: Kinematics, offset) -> tuple[np.ndarray, np.ndarray]:
    """Tool tip and tool axis in the part frame from machine XYZ and the two angles, by composing the chain's
    homogeneous transforms (table: part -> machine; head: tool -> machine), written from the profile's
    description, not from neuralslicer.motion.kinematics."""
    n = len(m)
    piv, c_off, L = np.asarray(kin.pivot), np.asarray(kin.c_offset), kin.tool_length
    table = np.tile(np.eye(4), (n, 1, 1))            # part frame -> machine frame
    head = np.tile(np.eye(4), (n, 1, 1))             # tool frame (tip at the origin, tool along +z) -> machine
    if kin.layout == "table-table":                  # cradle (tilt about the pivot) carries the rotary table
        c_point = piv + c_off
        table = _about(kin.tilt_axis, t, piv) @ _about(kin.rotate_axis, r, c_point) @ _shift(c_point + offset)
    elif kin.layout == "table-head":
        table = _about(kin.rotate_axis, r, c_off) @ _shift(c_off + offset)
    else:                                            # a fixed bed, its centre at c_offset
        table = table @ _shift(c_off + offset)
    tip_home = np.zeros(3)
    if kin.layout == "head-head":                    # the B pivot L above the tip at home, `pivot` off the C axis
        pivot_at_home = np.array([0.0, 0.0, L])
        head = _about(kin.rotate_axis, r, pivot_at_home - piv) @ _about(kin.tilt_axis, t, pivot_at_home)
    elif kin.layout == "table-head":
        head = _about(kin.tilt_axis, t, (0.0, 0.0, L))
    # machine XYZ moves the head's reference (the tip at home) by m
    tip = np.einsum("nij,j->ni", head, np.r_[tip_home, 1.0])[:, :3] + m
    axis = np.einsum("nij,j->ni", head[:, :3, :3], np.array([0.0, 0.0, 1.0]))
    inv = np.linalg.inv(table)
    p = np.einsum("nij,nj->ni", inv, np.c_[tip, np.ones(n)])[:, :3]
    a = np.einsum("nij,nj->ni", inv[:, :3, :3], axis)
    return p, a


def _angle_deg(a, b):
    a = a / np.linalg.norm(a, axis=1, keepdims=True)
    b = b / np.linalg.norm(b, axis=1, keepdims=True)
    return np.degrees(np.arccos(np.clip(np.einsum("ij,ij->i", a, b), -1.0, 1.0)))


LAYOUTS = [
    dict(layout="table-table", tilt_axis="+Y", pivot=(5.0, -7.0, 60.0), c_offset=(1.0, 2.0, 12.0)),
    dict(layout="table-table", tilt_axis="+X", pivot=(-3.0, 4.0, 50.0), c_offset=(0.5, -1.0, 9.0)),
    dict(layout="table-table", tilt_axis="-Y", rotate_axis="-Z", pivot=(2.0, 1.0, 40.0), c_offset=(0.0, 0.0, 5.0)),
    dict(layout="head-head", tilt_axis="+Y", pivot=(1.5, -0.5, 2.0), tool_length=55.0, c_offset=(100.0, 80.0, 2.0)),
    dict(layout="head-head", tilt_axis="-X", rotate_axis="-Z", pivot=(0.0, 0.0, 0.0), tool_length=40.0),
    dict(layout="table-head", tilt_axis="+Y", c_offset=(20.0, -10.0, 3.0), tool_length=45.0),
    dict(layout="table-head", tilt_axis="+X", c_offset=(-5.0, 5.0, 0.0), tool_length=30.0),
]


def test_three_axis_kinematics():
    """Three-axis: the part point at bed centre + p + offset, the tool vertical, IK all zero, tool axes beyond the
    clearance cone flagged."""
    kin = Kinematics(layout="three-axis", c_offset=(110.0, 110.0, 0.5), clearance_deg=30.0)
    rng = np.random.default_rng(5)
    p, off = rng.uniform(-30, 30, (50, 3)), np.array([1.0, -2.0, 0.5])
    m = machine_position(p, 0.0, 0.0, kin, off)
    p_chain, a_chain = _chain_fk(m, np.zeros(50), np.zeros(50), kin, off)
    assert np.abs(p_chain - p).max() < 1e-12 and np.allclose(a_chain, [0, 0, 1])
    assert np.allclose(m, p + off + [110.0, 110.0, 0.5])
    tilt = np.radians([0.0, 29.0, 31.0, 80.0])
    t, r, singular, out = inverse_kinematics(np.c_[np.sin(tilt), 0 * tilt, np.cos(tilt)], kin)
    assert not t.any() and not r.any() and not singular.any() and out.tolist() == [False, False, True, True]


@pytest.mark.parametrize("geometry", LAYOUTS, ids=lambda g: f"{g['layout']}{g['tilt_axis']}{g.get('rotate_axis', '+Z')}")
def test_ik_and_fk_agree_with_an_independent_chain(geometry):
    """Random tool axes and tips: IK, machine position, then the chain of homogeneous transforms reproduces the tip
    and the axis; the library's FK agrees with the chain at random joint values too; both IK branches are used."""
    kin = Kinematics(**geometry, tilt_min_deg=-120.0, tilt_max_deg=120.0)
    rng = np.random.default_rng(3)
    a = rng.normal(size=(400, 3))
    a[:, 2] = np.abs(a[:, 2]) + 0.05
    a /= np.linalg.norm(a, axis=1, keepdims=True)
    p = rng.uniform(-30.0, 30.0, size=(400, 3))
    offset = np.array([1.0, -2.0, 0.5])
    t, r, singular, out = inverse_kinematics(a, kin)
    assert not out.any() and not singular.any()
    m = machine_position(p, t, r, kin, offset)
    p_chain, a_chain = _chain_fk(m, t, r, kin, offset)
    assert np.abs(p_chain - p).max() < 1e-9
    assert np.abs(a_chain - a).max() < 1e-9
    # the library's FK against the chain at arbitrary joint values
    mj, tj, rj = rng.uniform(-50, 50, size=(300, 3)), rng.uniform(-100, 100, 300), rng.uniform(-700, 700, 300)
    p_lib, a_lib = forward_kinematics(mj, tj, rj, kin, offset)
    p_ref, a_ref = _chain_fk(mj, tj, rj, kin, offset)
    assert np.abs(p_lib - p_ref).max() < 1e-9 and np.abs(a_lib - a_ref).max() < 1e-9
    assert np.allclose(tool_axis(tj, rj, kin), a_ref, atol=1e-12)
    # R continuous (unwrapped) along a smooth sweep of the azimuth, and the tilt's sign chosen by continuity
    phi = np.linspace(0, 6 * np.pi, 600)
    sweep = np.c_[np.sin(0.6) * np.cos(phi), np.sin(0.6) * np.sin(phi), np.full(600, np.cos(0.6))]
    ts, rs, _, _ = inverse_kinematics(sweep, kin)
    assert np.abs(np.diff(rs)).max() < 2.0 and np.abs(np.diff(ts)).max() < 1e-9 and abs(abs(rs[-1] - rs[0]) - 1080) < 1.0


def test_the_second_solution_is_taken_across_the_vertical():
    """A tool axis swinging through +z in one plane flips T's sign instead of turning R half a turn, in every
    layout (the two IK solutions)."""
    beta = np.radians(np.linspace(-40, 40, 81))
    swing = np.c_[np.sin(beta), np.zeros_like(beta), np.cos(beta)]
    swing[40] = [1e-9, 0.0, 1.0]
    for geometry in LAYOUTS:
        kin = Kinematics(**geometry)
        t, r, singular, _ = inverse_kinematics(swing, kin)
        assert np.ptp(r[~singular]) < 1e-6, geometry
        assert t[0] * t[-1] < 0 and np.abs(np.diff(t)).max() < 1.0 + 1e-6, geometry


def _back_plot(path, prog) -> tuple[np.ndarray, np.ndarray, object]:
    """Tool tip and axis of every parsed move of a written program through the independent chain."""
    moves = parse_gcode(path)
    lx, ly, lz, lt, lr, _ = prog.axis_letters
    kin = prog.profile.kinematics
    xyz = np.column_stack([moves.axes[lx], moves.axes[ly], moves.axes[lz]])
    n = len(xyz)
    t = moves.axes[lt] if kin.rotary else np.zeros(n)
    r = moves.axes[lr] if kin.rotary else np.zeros(n)
    if kin.tcp:     # workpiece coordinates: the part at home; machine XYZ = the home chain's point turned
        home_p, _ = _chain_fk(xyz, np.zeros(n), np.zeros(n), kin, prog.part_offset)
        ref_m = machine_position(home_p, t, r, kin, prog.part_offset)
        xyz = ref_m
    p, a = _chain_fk(xyz, t, r, kin, prog.part_offset)
    return p, a, moves


def _written_rows(prog) -> np.ndarray:
    """Indices of the program's moves that the G-code writes with an axis word (a move that changes nothing as
    written, rounded, is a line without axis words, which the parser does not count as a move)."""
    g = prog.profile.gcode
    cols = [np.round(prog.program_xyz(), g.decimals_linear), np.round(prog.extruder, g.decimals_extruder)[:, None]]
    if prog.profile.kinematics.rotary:
        cols.append(np.round(prog.machine[:, 3:5], g.decimals_rotary))
    state = np.hstack(cols)
    changed = np.ones(len(state), bool)
    changed[1:] = np.any(state[1:] != state[:-1], axis=1)
    return np.flatnonzero(changed)


@pytest.fixture(scope="module")
def layers():
    return cap_stack(3, r0=8.0, theta_max_deg=40.0, center=(3.0, -2.0, 0.0), subdivisions=4)


def _measured(profile: MachineProfile) -> MachineProfile:
    """The shipped profile with non-zero offsets where its layout uses them (as a real machine has)."""
    prof = profile.model_copy(deep=True)
    k = prof.kinematics
    if k.layout == "table-table":
        k.pivot, k.c_offset = (5.0, -7.0, 60.0), (1.0, 2.0, 12.0)
    elif k.layout == "head-head":
        k.pivot, k.c_offset = (1.5, -0.5, 2.0), (100.0, 80.0, 2.0)
    elif k.layout == "table-head":
        k.c_offset = (20.0, -10.0, 3.0)
    return prof


@pytest.mark.parametrize("name", profile_names())
def test_every_shipped_profile_back_plots_its_program(tmp_path, layers, name):
    """The written program, parsed and run through the independent chain, reproduces the planned tool tip and tool
    axis of every move (0.01 mm, 0.01 deg); no rotary axis leaves its limits; the layout is in the header."""
    prof = _measured(load_profile(name))
    tp, prog, metrics, _ = plan_print(layers, platform_z=0.0, profile=prof)
    path = write_gcode(tmp_path / "print.gcode", prog)
    p, a, moves = _back_plot(path, prog)
    assert len(moves) == len(prog)
    tip, axis = prog.forward()
    assert np.abs(p - tip).max() < 0.01
    assert _angle_deg(a, axis).max() < 0.01
    on = prog.source >= 0                                 # the toolpath waypoints themselves
    assert np.abs(p[on] - tp.xyz[prog.source[on]]).max() < 0.01
    k = prof.kinematics
    text = path.read_text()
    assert prof.layout_words() in "\n".join(text.splitlines()[:12])
    if k.rotary:
        _, _, _, lt, lr, _ = prog.axis_letters
        assert _angle_deg(a[on], tp.axis[prog.source[on]]).max() < 0.01
        t, r = moves.axes[lt], moves.axes[lr]
        assert t.min() >= k.tilt_min_deg - 1e-6 and t.max() <= k.tilt_max_deg + 1e-6
        if k.rotate_min_deg is not None:
            assert r.min() >= k.rotate_min_deg - 1e-6 and r.max() <= k.rotate_max_deg + 1e-6
        assert np.ptp(t) > 20.0                            # the caps really tilt the tool
    else:
        assert not re.search(r"^G[01].*\b[ABC]-?\d", text, re.M)     # XYZE: no rotary word anywhere
        assert np.allclose(a, [0.0, 0.0, 1.0])                      # the head stays vertical
        assert metrics["three_axis"]["max_printing_angle_deg"] > 0.0


def test_a_head_with_limited_turns_unwinds(tmp_path, layers):
    """head_bc_linuxcnc allows two turns of C each way: the caps' C sweep (about 1000 deg) is unwound within it."""
    prof = load_profile("head_bc_linuxcnc").model_copy(deep=True)
    prof.kinematics.rotate_min_deg, prof.kinematics.rotate_max_deg = -360.0, 360.0
    _, prog, metrics, _ = plan_print(layers, platform_z=0.0, profile=prof)
    assert metrics["n_c_unwinds"] >= 1
    assert prog.machine[:, 4].min() >= -360.0 - 1e-6 and prog.machine[:, 4].max() <= 360.0 + 1e-6
    p, a, _ = _back_plot(write_gcode(tmp_path / "p.ngc", prog), prog)
    assert np.abs(p - prog.forward()[0]).max() < 0.01


# LinuxCNC's trt kinematics (src/emc/kinematics/trtfuncs: xyzbc / xyzac inverse kinematics, world -> joints, with
# the default "unconventional" directions, con = -1), as its documentation gives them.
def _xyzbc_trt_inverse(w, b_deg, c_deg, rot_point, x_offset, z_offset, tool_offset=0.0):
    con = -1.0
    b, c = np.radians(b_deg), np.radians(c_deg)
    dx, dz = x_offset, z_offset + tool_offset
    dpx = -np.cos(b) * dx + np.sin(b) * dz + dx
    dpz = -np.sin(b) * dx - np.cos(b) * dz + dz
    x, y, z = (w[:, i] - rot_point[i] for i in range(3))
    jx = np.cos(c) * np.cos(b) * x + con * np.sin(c) * np.cos(b) * y - con * np.sin(b) * z + dpx + rot_point[0]
    jy = -con * np.sin(c) * x + np.cos(c) * y + rot_point[1]
    jz = con * np.cos(c) * np.sin(b) * x + np.sin(c) * np.sin(b) * y + np.cos(b) * z + dpz + rot_point[2]
    return np.c_[jx, jy, jz]


def _xyzac_trt_inverse(w, a_deg, c_deg, rot_point, y_offset, z_offset, tool_offset=0.0):
    con = -1.0
    a, c = np.radians(a_deg), np.radians(c_deg)
    dy, dz = y_offset, z_offset + tool_offset
    x, y, z = (w[:, i] - rot_point[i] for i in range(3))
    jx = np.cos(c) * x + con * np.sin(c) * y + rot_point[0]
    jy = (-con * np.sin(c) * np.cos(a) * x + np.cos(c) * np.cos(a) * y + con * np.sin(a) * z - np.cos(a) * dy
          - con * np.sin(a) * dz + dy + rot_point[1])
    jz = (np.sin(c) * np.sin(a) * x - con * np.cos(c) * np.sin(a) * y + np.cos(a) * z + con * np.sin(a) * dy
          - np.cos(a) * dz + dz + rot_point[2])
    return np.c_[jx, jy, jz]


@pytest.mark.parametrize("name", ["table_bc_linuxcnc", "table_ac_linuxcnc"])
def test_tcp_program_matches_machine_program_through_linuxcnc_trt_kins(tmp_path, layers, name):
    """The same print written for a TCP controller (workpiece coordinates) and for trivial kinematics (machine
    coordinates): LinuxCNC's xyzbc/xyzac-trt-kins inverse kinematics of the first, with x/y/z-rot-point at the
    rotary axis on the table, give the second (0.001 mm, the written precision), rotary words identical."""
    prof = load_profile(name).model_copy(deep=True)
    # xyzbc: the B axis through the C axis (its x/z-offset terms turn against B in LinuxCNC's formulas); xyzac: both
    c_offset = (0.0, 4.0, 0.0) if name == "table_bc_linuxcnc" else (0.0, 4.0, 12.0)
    prof.kinematics.pivot, prof.kinematics.c_offset = (5.0, -7.0, 60.0), c_offset
    _, prog, _, _ = plan_print(layers, platform_z=0.0, profile=prof)
    machine = parse_gcode(write_gcode(tmp_path / "machine.ngc", prog))
    tcp_prof = prof.model_copy(deep=True)
    tcp_prof.kinematics.tcp = True
    prog.profile = tcp_prof
    tcp_path = write_gcode(tmp_path / "tcp.ngc", prog)
    world = parse_gcode(tcp_path)
    lt, lr = prof.axes.tilt, prof.axes.rotate
    assert np.array_equal(world.axes[lt], machine.axes[lt]) and np.array_equal(world.axes[lr], machine.axes[lr])
    w = np.column_stack([world.axes["X"], world.axes["Y"], world.axes["Z"]])
    rot_point = np.asarray(prof.kinematics.pivot) + np.asarray(prof.kinematics.c_offset)
    if name == "table_bc_linuxcnc":
        joints = _xyzbc_trt_inverse(w, world.axes["B"], world.axes["C"], rot_point, 0.0, 0.0)
    else:
        joints = _xyzac_trt_inverse(w, world.axes["A"], world.axes["C"], rot_point, -4.0, -12.0)
    ref = np.column_stack([machine.axes["X"], machine.axes["Y"], machine.axes["Z"]])
    assert np.abs(joints - ref).max() < 2e-3
    assert not np.allclose(w, ref, atol=1.0)              # the two programs really differ
    head = "\n".join(tcp_path.read_text().splitlines()[:12])
    assert "TCP ON" in head and "5.0000 -7.0000 60.0000" in head


def _rs274(tmp_path, ngc, coordinates):
    var, tbl, ini = tmp_path / "rs274.var", tmp_path / "tool.tbl", tmp_path / "rs274.ini"
    var.write_text("")
    tbl.write_text("T1 P1 Z0 D0.4 ;nozzle\n")
    ini.write_text(f"[RS274NGC]\nPARAMETER_FILE = {var}\n[TRAJ]\nCOORDINATES = {coordinates}\nLINEAR_UNITS = mm\n"
                   "ANGULAR_UNITS = degree\n")
    out = tmp_path / "canon.txt"
    res = subprocess.run(["rs274", "-i", str(ini), "-t", str(tbl), "-g", str(ngc), str(out)],
                         capture_output=True, text=True, timeout=120)
    return res, out.read_text() if out.exists() else ""


@pytest.mark.skipif(shutil.which("rs274") is None, reason="LinuxCNC's rs274 not installed (apt-get install linuxcnc-uspace)")
@pytest.mark.parametrize("name", [n for n in profile_names() if load_profile(n).gcode.dialect == "linuxcnc"])
@pytest.mark.parametrize("tcp", [False, True])
def test_rs274_reads_every_linuxcnc_program(tmp_path, name, tcp):
    """LinuxCNC's interpreter reads each LinuxCNC-dialect profile's program (TCP or not) without a message."""
    layers = planar_stack(2, size=6.0, n=7) + cap_stack(2, r0=3.0, theta_max_deg=40.0, center=(0, 0, -1.5),
                                                         subdivisions=3)
    prof = _measured(load_profile(name))
    prof.kinematics.tcp = tcp
    _, prog, _, _ = plan_print(layers, platform_z=0.0, profile=prof)
    res, canon = _rs274(tmp_path, write_gcode(tmp_path / "print.ngc", prog), "XYZABCUVW")
    assert res.returncode == 0 and "PROGRAM_END" in canon, res.stdout + res.stderr
    assert not re.search(r"error|unknown|bad", res.stdout + res.stderr, re.I), res.stdout + res.stderr


def test_profiles_refuse_what_their_layout_does_not_use():
    from neuralslicer.errors import InputError
    from neuralslicer.motion.profile import _validate

    with pytest.raises(InputError, match="kinematics.tool_length: not used by a table-table machine"):
        _validate({"kinematics": {"tool_length": 50.0}}, "x.yaml")
    with pytest.raises(InputError, match="kinematics.pivot: not used by a three-axis machine"):
        _validate({"kinematics": {"layout": "three-axis", "pivot": [1, 0, 0]}}, "x.yaml")
    with pytest.raises(InputError, match="more than the vertical head clears"):
        _validate({"kinematics": {"layout": "three-axis", "clearance_deg": 50.0}}, "x.yaml")
    with pytest.raises(InputError, match="tilt_axis"):
        _validate({"kinematics": {"tilt_axis": "+Z"}}, "x.yaml")
    # programs stored before layouts existed still load
    old = {"kinematics": {"kind": "table_bc", "b_min_deg": -80.0, "c_max_deg": 720.0, "c_min_deg": -720.0}}
    k = _validate(old, "old.yaml").kinematics
    assert (k.layout, k.tilt_min_deg, k.rotate_max_deg) == ("table-table", -80.0, 720.0)


def test_machines_command_lists_every_profile_with_its_layout(capsys):
    from neuralslicer.cli.main import main

    assert main(["machines"]) == 0
    out = capsys.readouterr().out
    for words in ("table-table B/C", "table-table A/C", "head-head B/C", "table-head B/C", "three-axis"):
        assert words in out, words
    lines = [ln for ln in out.splitlines() if ln.split() and ln.split()[0] in profile_names()]
    assert len(lines) == len(profile_names())


@pytest.mark.slow   # a short ring slice in this process, then its layers planned for every profile: ~1-2 min
def test_the_ring_prints_on_every_shipped_profile(ring_path, tmp_path):
    """The paper's Ring (curved layers, tool axes tilted to 90 deg and beyond) planned for every shipped profile:
    each written program back-plots onto its planned tool tips and axes (0.01 mm, 0.01 deg) and stays in range."""
    from conftest import fast_config

    from neuralslicer.config import SliceConfig
    from neuralslicer.model.spec import spec_for_file
    from neuralslicer.run.in_process import slice_model

    config = SliceConfig.model_validate(fast_config(
        samples={"n_samples": 4000}, cage={"n_elements": 3000}, neural={"optim": {"max_steps": 60}}))
    chain, _ = slice_model(spec_for_file(ring_path, "y"), config)
    layers, platform_z = chain.printed.layers.meshes, chain.model.solid.platform_z
    for name in profile_names():
        prof = _measured(load_profile(name))
        tp, prog, metrics, _ = plan_print(layers, platform_z=platform_z, profile=prof)
        path = write_gcode(tmp_path / f"{name}.gcode", prog)
        p, a, moves = _back_plot(path, prog)
        rows = _written_rows(prog)
        assert len(rows) == len(moves), name
        tip, axis = prog.forward(rows)
        assert np.abs(p - tip).max() < 0.01, name
        assert _angle_deg(a, axis).max() < 0.01, name
        on = prog.source[rows] >= 0
        assert np.abs(p[on] - tp.xyz[prog.source[rows][on]]).max() < 0.01, name
        k = prof.kinematics
        if k.rotary:
            assert k.tilt_min_deg - 1e-6 <= prog.machine[:, 3].min() and prog.machine[:, 3].max() <= k.tilt_max_deg + 1e-6
            if k.rotate_min_deg is not None:
                assert k.rotate_min_deg - 1e-6 <= prog.machine[:, 4].min() <= prog.machine[:, 4].max() <= k.rotate_max_deg + 1e-6
            assert np.degrees(np.arccos(np.clip(a[on, 2], -1, 1))).max() > 20.0, name   # the tool really tilts
        else:
            assert np.allclose(a, [0.0, 0.0, 1.0]) and "three_axis" in metrics


@pytest.mark.slow   # a short optimisation of the L part with the three-axis bound, in this process: ~1 min
def test_a_three_axis_slice_keeps_printing_directions_in_the_clearance_cone(small_part, tmp_path):
    """The L part (a 12 mm overhanging arm) sliced for the three-axis profile: every printed waypoint's printing
    direction (the layer's normal) within the head's clearance, the head vertical for every move, an XYZE program."""
    from conftest import fast_config

    from neuralslicer.config import SliceConfig
    from neuralslicer.model.spec import spec_for_file
    from neuralslicer.run.in_process import slice_model

    config = SliceConfig.model_validate(fast_config(      # the profile's 0.4 mm nozzle: 0.3 mm layers, 0.8 mm lines
        neural={"optim": {"max_steps": 150}}, machine="three_axis_reprap",
        layers={"layer_height": 0.3, "thickness_samples": 2000},
        toolpath={"line_width": 0.8, "spacing": 1.0, "n_shells": 1, "infill_density": 0.5}))
    chain, metrics = slice_model(spec_for_file(small_part, "z"), config, tmp_path / "run")
    clearance = load_profile("three_axis_reprap").kinematics.clearance_deg
    assert metrics["three_axis.clearance_deg"] == clearance
    assert metrics["three_axis.n_printing_beyond_clearance"] == 0
    assert 1.0 < metrics["three_axis.max_printing_angle_deg"] <= clearance + 1e-6      # curved, and bounded
    prog = chain.printed.motion.program
    assert np.allclose(prog.forward()[1], [0.0, 0.0, 1.0]) and not prog.machine[:, 3:5].any()
    text = (tmp_path / "run" / "print.gcode").read_text()
    assert "three-axis" in text[:2000] and not re.search(r"^G[01].*\b[ABC]-?\d", text, re.M)
    # (the L's flat underside needs a 90 deg turn: a 30 deg slope cannot remove it; benchmarks/bench_examples.py
    # measures the gains on the ring, the bunny and the bracket)
