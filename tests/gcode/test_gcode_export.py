"""G-code and robot export: forward kinematics of parsed moves, extrusion, LinuxCNC rs274, metrics."""
from __future__ import annotations

import re
import shutil
import subprocess

import numpy as np
import pytest

from neuralslicer.gcode import (ROBOT_COLUMNS, parse_gcode, quaternion_to_matrix, robot_table, tool_frames,
                                write_gcode, write_robot_csv, write_robot_json)
from neuralslicer.gcode.writers import MIN_MOVE_S
from neuralslicer.motion import (PRINT, RETRACT, forward_kinematics, load_profile, plan_motion, plan_print,
                                 program_metrics)
from neuralslicer.motion.planning import MachineProgram
from neuralslicer.run.outputs import write_print_outputs
from neuralslicer.toolpath.generate import toolpaths
from neuralslicer.toolpath.synthetic import cap_stack, disc_layer, planar_stack
from neuralslicer.toolpath.types import Toolpaths


def _angle_deg(a, b):
    return np.degrees(np.arccos(np.clip(np.einsum("ij,ij->i", a, b), -1.0, 1.0)))


@pytest.fixture(scope="module")
def curved():
    """A curved part with rotary motion: concentric caps (LPD radial), continuous C."""
    layers = cap_stack(3, r0=8.0, theta_max_deg=40.0, center=(3.0, -2.0, 0.0), subdivisions=4)
    profile = load_profile("table_bc_linuxcnc").model_copy(deep=True)
    profile.kinematics.pivot = (5.0, -7.0, 60.0)
    profile.kinematics.c_offset = (0.0, 0.0, 12.0)
    tp, prog, metrics, _ = plan_print(layers, platform_z=0.0, profile=profile)
    return tp, prog, metrics


@pytest.mark.parametrize("profile_name", ["table_bc_linuxcnc", "reprap_5axis"])
def test_forward_kinematics_of_parsed_gcode_reproduces_waypoints(tmp_path, curved, profile_name):
    tp, prog, _ = curved
    profile = load_profile(profile_name)
    profile.kinematics.pivot = (5.0, -7.0, 60.0)
    program = plan_motion(tp, profile, platform_z=0.0)
    path = write_gcode(tmp_path / "print.gcode", program)
    lx, ly, lz, lb, lc, le = program.axis_letters
    moves = parse_gcode(path, axes=lx + ly + lz + lb + lc + le)
    assert len(moves) == len(program)
    xyz = np.column_stack([moves.axes[lx], moves.axes[ly], moves.axes[lz]])
    p, a = forward_kinematics(xyz, moves.axes[lb], moves.axes[lc], profile.kinematics, program.part_offset)
    src = program.source
    w = src >= 0
    assert np.abs(p[w] - tp.xyz[src[w]]).max() < 1e-3
    assert _angle_deg(a[w], tp.axis[src[w]]).max() < 0.1
    assert np.abs(p - program.forward()[0]).max() < 1e-3      # inserted moves too
    # continuity: no C flips, every rotary step within the profile's maximum (+ rounding)
    step = profile.kinematics.max_rotary_step_deg + 1e-4
    assert np.abs(np.diff(moves.axes[lc])).max() <= step and np.abs(np.diff(moves.axes[lb])).max() <= step
    # extrusion read back from the file: filament x area = deposited volume
    de = np.diff(moves.axes[le])
    area = np.pi * 0.25 * profile.extrusion.filament_diameter ** 2
    printed = program.kind[1:] == PRINT
    assert np.isclose(de[printed].sum() * area, tp.deposited_volume(), rtol=1e-3)
    assert np.allclose(de[program.kind[1:] == RETRACT].__abs__(),
                       np.r_[profile.extrusion.retract_mm, profile.extrusion.prime_mm].max(), atol=1e-4)


def test_extruded_volume_matches_a_cylinder():
    layers = [disc_layer(0.5 * (i + 1), radius=8.0, n_rings=16, n_sectors=64) for i in range(6)]
    H = lambda p: np.maximum(np.linalg.norm(p[:, :2], axis=1) - 8.0, np.maximum(-p[:, 2], p[:, 2] - 3.0))  # noqa: E731
    tp, prog, metrics, _ = plan_print(layers, platform_z=0.0, solid_H=H)
    assert metrics["n_waypoints_outside_solid"] == 0 and metrics["max_H_at_waypoints"] <= 1e-3
    volume = np.pi * 8.0 ** 2 * 3.0
    assert abs(metrics["material_mm3"] / volume - 1.0) < 0.15
    assert metrics["n_collisions"] == 0 and metrics["n_rotary_out_of_range"] == 0
    for key in ("estimated_print_time_s", "toolpath_length_mm", "n_waypoints", "material_mm3"):
        assert metrics[key] > 0
    # time >= length / print speed
    assert metrics["estimated_print_time_s"] >= metrics["toolpath_length_mm"] / prog.profile.feeds.print_mm_s


def test_linuxcnc_dialect_words(tmp_path, curved):
    _, prog, _ = curved
    text = write_gcode(tmp_path / "p.ngc", prog).read_text()
    assert not re.search(r"\bM10[49]\b|\bM8[24]\b|\bE-?\d", text)       # no Marlin codes
    assert "G93" in text and "G21" in text and "G90" in text
    assert text.rstrip().endswith("M2")
    g1 = [ln for ln in text.splitlines() if ln.startswith("G1")]
    in_g93 = text.split("G93", 1)[1].split("G94", 1)[0]
    assert all(" F" in ln for ln in in_g93.splitlines() if ln.startswith("G1")) and g1


def _rs274_ini(tmp_path):
    ini = tmp_path / "rs274.ini"
    var = tmp_path / "rs274.var"
    var.write_text("")
    tbl = tmp_path / "tool.tbl"
    tbl.write_text("T1 P1 Z0 D0.4 ;nozzle\n")
    ini.write_text(f"[RS274NGC]\nPARAMETER_FILE = {var}\n[TRAJ]\nCOORDINATES = XYZABC\nLINEAR_UNITS = mm\n"
                   "ANGULAR_UNITS = degree\n")
    return ini, tbl


@pytest.mark.skipif(shutil.which("rs274") is None, reason="LinuxCNC's rs274 not installed (apt-get install linuxcnc-uspace)")
def test_linuxcnc_rs274_accepts_the_program(tmp_path):
    layers = planar_stack(3, size=6.0, n=7) + cap_stack(2, r0=3.0, theta_max_deg=40.0, center=(0, 0, -1.5),
                                                         subdivisions=3)
    tp, prog, _, _ = plan_print(layers, platform_z=0.0)
    ngc = write_gcode(tmp_path / "print.ngc", prog)
    ini, tbl = _rs274_ini(tmp_path)
    out = tmp_path / "canon.txt"
    res = subprocess.run(["rs274", "-i", str(ini), "-t", str(tbl), "-g", str(ngc), str(out)],
                         capture_output=True, text=True, timeout=120)
    canon = out.read_text()
    assert res.returncode == 0, res.stdout + res.stderr
    assert "PROGRAM_END" in canon
    # the print hosts' totals of the header are comments the interpreter reads as such
    for key in ("TIME:", "Filament used: ", "LAYER_COUNT:", "estimated printing time = ", "filament used [mm] = ",
                "filament used [g] = ", "total layers count = "):
        assert re.search(r'COMMENT\("' + re.escape(key) + r'[^"]+"\)', canon), key
    feeds = re.findall(r"STRAIGHT_(?:FEED|TRAVERSE)\(([^)]*)\)", canon)
    assert len(feeds) == len(prog)
    vals = np.array([[float(v) for v in f.split(",")[:6]] for f in feeds])      # X Y Z A B C
    assert np.allclose(vals[:, :3], prog.machine[:, :3], atol=1e-3)
    assert np.allclose(vals[:, 4:6], prog.machine[:, 3:5], atol=1e-4)
    assert np.allclose(vals[:, 3], prog.extruder, atol=1e-4)


def _col(table, name):
    return table[:, ROBOT_COLUMNS.index(name)]


def test_robot_export_orientation_and_extrusion(tmp_path, curved):
    tp, prog, _ = curved
    table = robot_table(tp, profile=prog.profile)
    assert table.shape == (len(tp), len(ROBOT_COLUMNS))
    rot = quaternion_to_matrix(table[:, 6:10])
    assert np.allclose(rot[:, :, 2], -tp.axis, atol=1e-7)                 # tool z = -LPD
    assert np.allclose(np.einsum("nij,nik->njk", rot, rot), np.eye(3), atol=1e-7)
    # the quaternion is the frame, whose x axis is the xx, xy, xz columns
    assert np.allclose(rot, tool_frames(tp.axis, tp.xyz, tp.extrude), atol=1e-7)
    assert np.allclose(rot[:, :, 0], table[:, [ROBOT_COLUMNS.index(c) for c in ("xx", "xy", "xz")]], atol=1e-7)
    assert np.isclose(table[:, 11].sum(), tp.deposited_volume())
    assert np.array_equal(_col(table, "layer_height"), tp.thickness)
    assert np.array_equal(_col(table, "extruder_toggle"), np.r_[tp.extrude[1:], False])
    import json
    doc = json.loads(write_robot_json(tmp_path / "r.json", tp, profile=prog.profile).read_text())
    assert doc["columns"][6:10] == ["qw", "qx", "qy", "qz"] and len(doc["rows"]) == len(tp)
    assert doc["columns"] == list(ROBOT_COLUMNS) and "wait_time" in doc["notes"]
    csv = np.loadtxt(write_robot_csv(tmp_path / "r.csv", tp, profile=prog.profile), delimiter=",", skiprows=1)
    assert csv.shape == table.shape and np.allclose(csv, table, atol=1e-5)


def _loop(n=72, radius=10.0, tilt=0.0):
    """One closed printed loop (a regular n-gon, closed by its first point) with tool axes tipped outwards by
    ``tilt`` (a cap's rim), reached by a travel from the centre."""
    phi = np.linspace(0.0, 2 * np.pi, n, endpoint=False)
    ring = np.column_stack([radius * np.cos(phi), radius * np.sin(phi), np.full(n, 1.0)])
    xyz = np.vstack([[0.0, 0.0, 1.0], ring, ring[:1]])
    axis = np.column_stack([tilt * np.cos(phi), tilt * np.sin(phi), np.ones(n)])
    axis = np.vstack([[0.0, 0.0, 1.0], axis, axis[:1]])
    axis /= np.linalg.norm(axis, axis=1, keepdims=True)
    m = len(xyz)
    extrude = np.r_[False, False, np.ones(m - 2, bool)]
    return Toolpaths(layer=np.zeros(m, np.int64), path=np.zeros(m, np.int64), xyz=xyz, axis=axis,
                     thickness=np.full(m, 0.4), width=np.full(m, 0.8), extrude=extrude)


def _angles(a, b):
    return np.degrees(np.arccos(np.clip(np.einsum("ij,ij->i", a, b), -1.0, 1.0)))


@pytest.mark.parametrize("tilt", [0.0, 0.6])
def test_robot_frame_follows_a_closed_loop_without_jumps(tilt):
    tp = _loop(tilt=tilt)
    x = tool_frames(tp.axis, tp.xyz, tp.extrude)[:, :, 0]
    d = np.diff(tp.xyz, axis=0)
    u = d / np.linalg.norm(d, axis=1, keepdims=True).clip(1e-300)
    turn = np.r_[0.0, _angles(u[:-1], u[1:]), 0.0]                     # the path's turn at each point
    turn[np.linalg.norm(np.r_[d, [[0, 0, 0]]], axis=1) == 0] = 0.0
    loop = np.arange(1, len(tp) - 1)                                    # the ring (the last point closes it)
    jump = _angles(x[loop[:-1]], x[loop[1:]])
    tool_turn = _angles(tp.axis[loop[:-1]], tp.axis[loop[1:]])
    allowed = np.maximum(turn[loop[:-1]], turn[loop[1:]]) + tool_turn + 1e-6
    assert (jump <= allowed).all() and jump.max() < 10.0
    # x points along the path: forward, orthogonal to the tool axis
    chord = tp.xyz[loop + 1] - tp.xyz[loop - 1]
    assert (np.einsum("ij,ij->i", x[loop], chord) > 0).all()
    assert np.abs(np.einsum("ij,ij->i", x, tp.axis)).max() < 1e-9
    if tilt == 0.0:                          # planar: x is the chord's direction; at the start, the first edge's
        assert _angles(x[loop[1:]], chord[1:] / np.linalg.norm(chord[1:], axis=1, keepdims=True)).max() < 1e-6
        assert _angles(x[1:2], d[1:2] / np.linalg.norm(d[1:2]))[0] < 1e-6
    # the closing point and the travel's start carry the neighbouring frame over
    assert _angles(x[-2:-1], x[-1:])[0] <= 5.0 + 1e-6


def test_robot_velocities_waits_and_blends_follow_the_profile(curved):
    tp, _, _ = curved
    profile = load_profile("reprap_5axis")
    table = robot_table(tp, profile=profile)
    f, ex = profile.feeds, profile.extrusion
    v = _col(table, "velocity")
    first = tp.layer == 0
    assert np.all(v[tp.extrude & first] == f.first_layer_mm_s) and np.all(v[tp.extrude & ~first] == f.print_mm_s)
    assert np.all(v[~tp.extrude] == f.travel_mm_s) and (tp.extrude & ~first).any()
    # waits: the prime time where the G-code program primes (after each retraction, and at the start)
    prog = plan_motion(tp, profile, platform_z=0.0)
    wait = _col(table, "wait_time")
    assert np.count_nonzero(wait) == prog.attrs["n_retractions"] + 1
    assert np.allclose(wait[wait > 0], ex.prime_mm / f.retract_mm_s)
    toggle = _col(table, "extruder_toggle").astype(bool)
    assert (toggle[wait > 0] & ~np.r_[False, toggle[:-1]][wait > 0]).all()     # where the extruder turns on
    # blends: within the width fraction and the neighbouring segments, zero at path ends and on travels
    r = _col(table, "blend_radius")
    seg = tp.segment_lengths()
    inner = np.r_[False, tp.extrude[1:-1] & tp.extrude[2:], False]
    assert (r[~inner] == 0).all() and (r > 0).any()
    assert (r <= 0.5 * tp.width + 1e-12).all() and (r[1:-1] <= 0.3 * np.minimum(seg[1:-1], seg[2:]) + 1e-12).all()


@pytest.mark.parametrize("feed_basis", ["xyz", "all_axes"])
def test_reprap_feed_gives_every_move_its_planned_time(tmp_path, feed_basis):
    """Under the firmware's rule (NIST RS274 rule A, RepRapFirmware / Marlin), distance / F = planned time."""
    layers = planar_stack(2, size=6.0, n=7) + cap_stack(2, r0=3.0, theta_max_deg=40.0, center=(0, 0, -1.5),
                                                         subdivisions=3)
    profile = load_profile("reprap_5axis").model_copy(deep=True)
    profile.kinematics.pivot = (5.0, -7.0, 60.0)
    profile.gcode.feed_basis = feed_basis
    program = plan_motion(toolpaths(layers, platform_z=0.0), profile, platform_z=0.0)
    letters = program.axis_letters
    moves = parse_gcode(write_gcode(tmp_path / "p.gcode", program), axes="".join(letters))
    assert len(moves) == len(program)
    pos = np.column_stack([moves.axes[c] for c in letters[:5]])
    d = np.diff(pos, axis=0)
    xyz, rot = np.linalg.norm(d[:, :3], axis=1), np.linalg.norm(d[:, 3:5], axis=1)
    de = np.abs(np.diff(moves.axes[letters[5]]))
    dist = np.hypot(xyz, rot) if feed_basis == "all_axes" else xyz
    dist = np.where(dist > 0, dist, np.where(rot > 0, rot, de))        # linear axes, else rotary, else filament
    seconds = dist / (moves.feed[1:] / 60.0)
    planned = np.maximum(program.time_s[1:], MIN_MOVE_S)
    assert np.allclose(seconds, planned, rtol=1e-4, atol=0.0)
    kinds = {"rotary-only": (xyz == 0) & (rot > 0), "filament-only": (xyz == 0) & (rot == 0),
             "mixed": (xyz > 0) & (rot > 0)}
    assert all(k.any() for k in kinds.values()), {n: int(k.sum()) for n, k in kinds.items()}


def test_outputs_and_program_round_trip(tmp_path, curved):
    tp, prog, metrics = curved
    files = write_print_outputs(tmp_path, tp, prog, metrics, robot=True)
    for key in ("waypoints_csv", "gcode", "vtp", "png", "robot_csv", "robot_json", "metrics"):
        assert files[key].exists() and files[key].stat().st_size > 0
    assert files["waypoints_csv"] == tmp_path / "toolpaths" / "waypoints.csv"
    arrays, attrs = prog.to_arrays()
    back = MachineProgram.from_arrays(arrays, attrs)
    assert np.array_equal(back.machine, prog.machine) and back.profile == prog.profile
    assert program_metrics(back) == program_metrics(prog)


@pytest.mark.parametrize("profile_name", ["table_bc_linuxcnc", "reprap_5axis"])
def test_chunked_writing_equals_one_piece(tmp_path, monkeypatch, curved, profile_name):
    import neuralslicer.gcode.writers as writers

    tp, _, _ = curved
    prog = plan_motion(tp, load_profile(profile_name), platform_z=0.0)
    whole = write_gcode(tmp_path / "a.gcode", prog).read_text()
    monkeypatch.setattr(writers, "_CHUNK", 7)
    pieces = write_gcode(tmp_path / "b.gcode", prog).read_text()
    assert pieces == whole


@pytest.mark.parametrize("profile_name", ["table_bc_linuxcnc", "reprap_5axis"])
def test_every_layer_is_marked_before_its_first_move(tmp_path, curved, profile_name):
    tp, _, _ = curved
    program = plan_motion(tp, load_profile(profile_name), platform_z=0.0)
    lines = write_gcode(tmp_path / "print.gcode", program).read_text().splitlines()
    marks = [i for i, ln in enumerate(lines) if "LAYER " in ln and "/ " in ln]
    n_layers = len(np.unique(program.layer))
    assert len(marks) == n_layers
    numbers = [int(re.search(r"LAYER (\d+) / (\d+)", lines[i]).group(1)) for i in marks]
    assert numbers == list(range(1, n_layers + 1))
    # the moves between two marks are exactly one layer's moves, in program order
    lx, ly, lz, lb, lc, le = program.axis_letters
    moves = parse_gcode("\n".join(lines) + "\n", axes=lx + ly + lz + lb + lc + le)
    move_line = moves.line - 1
    layer_of_move = np.searchsorted(np.asarray(marks), move_line) - 1
    layer_of_move[layer_of_move < 0] = 0                         # the approach move before the first mark
    assert np.array_equal(layer_of_move, np.unique(program.layer, return_inverse=True)[1])
    assert "machine: " in "\n".join(lines[:12])
    if profile_name == "reprap_5axis":
        progress = [int(re.match(r"M73 P(\d+)", ln).group(1)) for ln in lines if ln.startswith("M73")]
        assert progress[0] == 0 and progress[-1] == 100 and np.all(np.diff(progress) >= 0)


def test_layer_marks_carry_the_isovalue(tmp_path, curved):
    tp, prog, _ = curved
    lines = write_gcode(tmp_path / "print.ngc", prog).read_text().splitlines()
    values = [float(m.group(1)) for ln in lines if (m := re.search(r"LAYER \d+ / \d+, .*isovalue G = ([-0-9.e+]+)", ln))]
    expected = [tp.attrs["isovalues"][k] for k in np.unique(prog.layer)]
    assert len(values) == len(expected) and np.allclose(values, expected, rtol=1e-5)


def test_program_starts_and_ends_clear_of_the_part(curved):
    from neuralslicer.motion import machine_position
    from neuralslicer.motion.planning import TRAVEL

    tp, _, _ = curved
    profile = load_profile("table_bc_linuxcnc").model_copy(deep=True)
    profile.kinematics.pivot = (5.0, -7.0, 60.0)
    profile.kinematics.c_offset = (0.0, 0.0, 12.0)
    profile.gcode.park_xy = (100.0, 50.0)
    prog = plan_motion(tp, profile, platform_z=0.0)
    z_safe = prog.attrs["safe_z"]
    src = np.flatnonzero(prog.source >= 0)
    head, tail = np.arange(src[0]), np.arange(src[-1] + 1, len(prog))
    # brute force: at the safe height, the tool tip is outside the part at every B/C of a 5 deg grid
    part = tp.xyz + prog.part_offset
    kin = profile.kinematics
    for b in np.arange(-90, 91, 5.0):
        for c in np.arange(0, 360, 5.0):
            zs = machine_position(tp.xyz, np.full(len(part), b), np.full(len(part), c), kin, prog.part_offset)[:, 2]
            assert zs.max() < z_safe
    # start: first move at the safe height with B = C = 0, rotary axes turned up there, then the approach
    # straight down the tool axis (machine X, Y fixed), then a prime before the first printing move
    assert np.allclose(prog.machine[0, 2:], [z_safe, 0.0, 0.0])
    up = head[prog.machine[head, 2] >= z_safe - 1e-9]
    assert np.allclose(prog.machine[up, :2], prog.machine[0, :2])
    assert np.allclose(prog.machine[up[-1], 3:5], prog.machine[src[0], 3:5])
    first_print = int(np.flatnonzero(prog.kind == PRINT)[0])
    primes = np.flatnonzero(prog.kind[:first_print] == RETRACT)
    assert len(primes) == 1 and primes[0] > up[-1] and prog.extruder[first_print - 1] == pytest.approx(profile.extrusion.prime_mm)
    # end: retract, lift in place, B home and C to a full turn, park
    assert prog.kind[tail[0]] == RETRACT and np.allclose(prog.machine[tail[0]], prog.machine[src[-1]])
    assert (prog.machine[tail[1:], 2] >= z_safe - 1e-9).all() and (prog.kind[tail[1:]] == TRAVEL).all()
    assert prog.machine[-1, 3] == 0.0 and prog.machine[-1, 4] % 360.0 == pytest.approx(0.0, abs=1e-9)
    assert np.allclose(prog.machine[-1, :2], [100.0, 50.0])
    assert np.abs(np.diff(prog.machine[:, 3:5], axis=0)).max() <= kin.max_rotary_step_deg + 1e-9


def test_safe_end_adds_no_move_where_the_program_already_ends_there(curved):
    from neuralslicer.motion.planning import _with_safe_start_end, safe_height

    tp, _, _ = curved
    profile = load_profile("table_bc_linuxcnc").model_copy(deep=True)
    profile.gcode.safe_start_end = False
    prog = plan_motion(tp, profile, platform_z=0.0)
    z_safe = safe_height(prog)              # of the part's moves (the tips of the moves below would raise it)
    prog.machine[-1] = [prog.machine[-1, 0], prog.machine[-1, 1], z_safe, 0.0, 0.0]   # already home, up
    out = _with_safe_start_end(prog, z_safe)
    n_start = int(np.argmax(out.source >= 0)) - 2          # start moves before the approach and the prime
    assert len(out) == len(prog) + n_start + 2             # + prime + retract, no end moves
    assert len(out.time_s) == len(out.machine) == len(out.kind) == len(out.layer)


@pytest.mark.parametrize("profile_name", ["table_bc_linuxcnc", "reprap_5axis"])
def test_the_written_program_starts_and_ends_safely(tmp_path, curved, profile_name):
    """Walk the parsed G-code: first motion at the safe height with B = C = 0 there, rotary axes turned
    before the tool comes down, filament primed before the first printing move; at the end a retract, a lift
    to the safe height, B home and C on a whole turn."""
    tp, _, _ = curved
    profile = load_profile(profile_name).model_copy(deep=True)
    profile.kinematics.pivot = (5.0, -7.0, 60.0)
    prog = plan_motion(tp, profile, platform_z=0.0)
    moves = parse_gcode(write_gcode(tmp_path / "p.gcode", prog))
    lx, ly, lz, lb, lc, le = prog.axis_letters
    z, b, c, e = (moves.axes[k] for k in (lz, lb, lc, le))
    z_safe = prog.attrs["safe_z"]
    assert z[0] == pytest.approx(z_safe, abs=1e-3) and b[0] == 0.0 and c[0] % 360.0 == pytest.approx(0.0, abs=1e-4)
    down = int(np.argmax(z < z_safe - 1e-3))                       # the first move below the safe height
    assert np.allclose([b[down - 1], c[down - 1]], [b[down], c[down]], atol=1e-4)   # turned up there first
    prime = int(np.argmax(np.diff(e) > 1e-6)) + 1                  # the first filament push: a prime in place
    xyz = np.column_stack([moves.axes[lx], moves.axes[ly], z])
    assert prime > down and np.allclose(xyz[prime], xyz[prime - 1]) and e[prime] == pytest.approx(profile.extrusion.prime_mm)
    last_print = len(e) - 1 - int(np.argmax(np.diff(e)[::-1] > 1e-6))
    assert e[last_print + 1] < e[last_print]                       # retract after the last printing move
    assert np.all(z[last_print + 2:] >= z_safe - 1e-3)             # then only at the safe height
    assert b[-1] == pytest.approx(0.0) and c[-1] % 360.0 == pytest.approx(0.0, abs=1e-4)


def test_bulk_number_formatting_matches_printf():
    from neuralslicer.gcode.writers import _Words, fixed_point, render_lines
    rng = np.random.default_rng(11)
    n = 3000
    vals = np.concatenate([rng.normal(0, 300, n // 3), rng.uniform(-1e-3, 1e-3, n // 3),
                           np.round(rng.uniform(-50, 50, n - 2 * (n // 3)), 4) + 5e-5])   # ties at the last digit
    vals[:4] = [0.0, -0.0, -0.00004, 123456.789]
    dec = rng.integers(1, 9, n)
    present = rng.uniform(size=n) < 0.8
    prefix = np.where(rng.uniform(size=n) < 0.5, "G0", "G1")
    got = render_lines(prefix, [_Words("X", fixed_point(vals, 4), 4), _Words("F", fixed_point(vals, dec), dec, present)])

    def printf(v, d):
        r = np.round(v, d)
        return f"{0.0 if r == 0 else r:.{d}f}"

    expected = "".join(f"{p} X{printf(v, 4)}" + (f" F{printf(v, d)}" if on else "") + "\n"
                       for p, v, d, on in zip(prefix, vals, dec, present))
    assert got.decode() == expected
    modal = _Words.modal("Y", fixed_point(np.array([1.0, 1.00001, 1.2, 1.2]), 4), 4)
    assert modal.present.tolist() == [True, False, True, False]
    with pytest.raises(ValueError):
        fixed_point(np.array([1.0, np.nan]), 3)


def header_totals(path, program, profile, open_c: str, close_c: str, layer_mark: str, normal_mode: str) -> dict:
    """Check a G-code header's print-host keys against what the file holds (E read back from the moves, the layer
    marks, the summary's estimated time); ``open_c``/``close_c`` wrap a comment in the dialect. Returns the totals."""
    text = path.read_text()
    head = text[:text.index("G21")]
    key = lambda pattern: re.search(open_c + pattern + close_c, head).group(1)  # noqa: E731
    moves = parse_gcode(path, axes="".join(program.axis_letters))
    filament = np.diff(moves.axes[program.axis_letters[5]])[program.kind[1:] == PRINT].sum()
    assert float(key(r" ?filament used \[mm\] = ([\d.]+)")) == pytest.approx(filament, abs=0.01)
    assert float(key(r"Filament used: ([\d.]+)m")) == pytest.approx(filament / 1000, abs=1e-5)
    grams = filament * np.pi * 0.25 * profile.extrusion.filament_diameter ** 2 * 1.24e-3
    assert float(key(r" ?filament used \[g\] = ([\d.]+)")) == pytest.approx(grams, abs=0.01)
    n_layers = len(re.findall(layer_mark, text, flags=re.M))
    assert int(key(r"LAYER_COUNT:(\d+)")) == n_layers == int(key(r" ?total layers count = (\d+)")) > 1
    t = int(key(r"TIME:(\d+)"))
    assert t == round(float(re.search(r"est\. time ([\d.]+) s", head).group(1)))
    h, m, s = map(int, re.search(open_c + rf" ?estimated printing time{normal_mode} = (\d+)h (\d+)m (\d+)s" + close_c,
                                 head).groups())
    assert 3600 * h + 60 * m + s == t
    return {"filament": filament, "n_layers": n_layers, "head": head}


def test_the_header_carries_what_print_hosts_show(tmp_path, curved):
    """RepRap dialect: ;TIME, filament length and mass, layer count in the Cura and PrusaSlicer spellings, equal to
    what the file itself holds."""
    tp, _, _ = curved
    profile = load_profile("reprap_5axis")
    program = plan_motion(tp, profile, platform_z=0.0)
    header_totals(write_gcode(tmp_path / "print.gcode", program), program, profile, ";", "", r"^;LAYER:",
                  r" \(normal mode\)")


def test_the_linuxcnc_header_carries_the_same_totals(tmp_path, curved):
    """LinuxCNC dialect: the RepRap header's time, filament length and mass and layer count, as parenthesised
    comments (no semicolons, no nested brackets), equal to what the file holds."""
    tp, _, _ = curved
    profile = load_profile("table_bc_linuxcnc")
    program = plan_motion(tp, profile, platform_z=0.0)
    path = write_gcode(tmp_path / "print.ngc", program)
    found = header_totals(path, program, profile, r"\(", r"\)", r"^\(LAYER \d+ / ", "")
    keys = [ln for ln in found["head"].splitlines() if re.match(r"\((TIME|Filament used|LAYER_COUNT|estimated printing|"
                                                                 r"filament used|total layers)", ln)]
    assert len(keys) == 7
    assert all(ln.endswith(")") and ln.count("(") == 1 == ln.count(")") and ";" not in ln for ln in keys)
    filament, n_layers = found["filament"], found["n_layers"]
    # the same totals as the RepRap header of the same program
    reprap = write_gcode(tmp_path / "print.gcode", plan_motion(tp, load_profile("reprap_5axis"), platform_z=0.0))
    rhead = reprap.read_text().split("G21", 1)[0]
    assert re.search(r";LAYER_COUNT:(\d+)", rhead).group(1) == str(n_layers)
    assert float(re.search(r"; filament used \[mm\] = ([\d.]+)", rhead).group(1)) == pytest.approx(filament, abs=0.01)


def test_the_reprap_file_ends_with_prusaslicers_totals(tmp_path, curved):
    """PrusaSlicer's totals block (what PrusaSlicer, PrusaLink and Moonraker read at the end of a file) after the
    last command, in PrusaSlicer's order, equal to what the file holds and to the header's keys."""
    tp, _, _ = curved
    profile = load_profile("reprap_5axis")
    program = plan_motion(tp, profile, platform_z=0.0)
    path = write_gcode(tmp_path / "print.gcode", program)
    found = header_totals(path, program, profile, ";", "", r"^;LAYER:", r" \(normal mode\)")
    lines = path.read_text().splitlines()
    tail = lines[lines.index("M84") + 1:]
    keys = [re.match(r"; ([^=]+) = (.+)$", ln).groups() for ln in tail]
    assert [k for k, _ in keys] == ["filament used [mm]", "filament used [cm3]", "filament used [g]",
                                    "total filament used [g]", "total layers count",
                                    "estimated printing time (normal mode)"]
    value = dict(keys)
    filament = found["filament"]                                  # E read back from the moves
    assert float(value["filament used [mm]"]) == pytest.approx(filament, abs=0.01)
    area = np.pi * 0.25 * profile.extrusion.filament_diameter ** 2
    assert float(value["filament used [cm3]"]) == pytest.approx(filament * area / 1000, abs=0.01)
    assert float(value["filament used [g]"]) == float(value["total filament used [g]"]) == pytest.approx(
        filament * area * 1.24e-3, abs=0.01)
    assert int(value["total layers count"]) == found["n_layers"]
    head_time = re.search(r"^; estimated printing time \(normal mode\) = (.+)$", found["head"], re.M).group(1)
    assert value["estimated printing time (normal mode)"] == head_time


def _thumbnails(text: str) -> list[tuple[int, int, int, str]]:
    """(width, height, stated length, base64 text) of every PrusaSlicer thumbnail block, read line by line."""
    out, block = [], None
    for ln in text.splitlines():
        if m := re.fullmatch(r"; thumbnail begin (\d+)x(\d+) (\d+)", ln):
            block = [int(m[1]), int(m[2]), int(m[3]), ""]
        elif ln == "; thumbnail end":
            out.append(tuple(block))
            block = None
        elif block is not None:
            assert ln.startswith("; ") and len(ln) <= 80
            block[3] += ln[2:]
    assert block is None
    return out


def test_the_reprap_file_carries_prusaslicer_thumbnails_of_the_part(tmp_path, curved):
    import base64
    import io

    from PIL import Image

    tp, _, _ = curved
    program = plan_motion(tp, load_profile("reprap_5axis"), platform_z=0.0)
    text = write_gcode(tmp_path / "print.gcode", program).read_text()
    thumbs = _thumbnails(text)
    assert [(w, h) for w, h, _, _ in thumbs] == [(32, 32), (220, 124)]
    assert text.index("; thumbnail begin") < text.index(";LAYER:0")     # in the header, before any move
    for w, h, n, data in thumbs:
        assert n == len(data)
        image = Image.open(io.BytesIO(base64.b64decode(data, validate=True)))
        assert image.format == "PNG" and image.size == (w, h) and image.mode == "RGBA"
        alpha = np.asarray(image)[:, :, 3]
        rows, cols = np.flatnonzero(alpha.any(axis=1)), np.flatnonzero(alpha.any(axis=0))
        # the part fills the picture in one direction (centred, margins of one pixel) and not all of it
        assert 0.02 < (alpha > 0).mean() < 0.9
        assert cols[-1] - cols[0] >= w - 3 or rows[-1] - rows[0] >= h - 3
    # an empty program still gives valid, empty pictures
    from neuralslicer.gcode.writers import thumbnail_png
    still = _nothing_printed(program)
    assert Image.open(io.BytesIO(thumbnail_png(still, 16, 8))).size == (16, 8)


def _nothing_printed(program: MachineProgram) -> MachineProgram:
    """The program with every move a travel (nothing printed)."""
    import dataclasses

    return dataclasses.replace(program, kind=np.zeros_like(program.kind))


@pytest.mark.parametrize("fan_percent", [None, 40.0])
def test_fan_turns_on_at_the_second_layer_and_off_at_the_end(tmp_path, curved, fan_percent):
    tp, _, _ = curved
    profile = load_profile("reprap_5axis").model_copy(deep=True)
    profile.gcode.fan_percent = fan_percent
    lines = write_gcode(tmp_path / "print.gcode", plan_motion(tp, profile, platform_z=0.0)).read_text().splitlines()
    on = [i for i, ln in enumerate(lines) if ln.startswith("M106")]
    off = [i for i, ln in enumerate(lines) if ln.startswith("M107")]
    if fan_percent is None:
        assert on == off == []
        return
    assert [lines[i] for i in on] == ["M106 S102"] and len(off) == 1          # 40 % of 255
    moves = [i for i, ln in enumerate(lines) if ln.startswith(("G0 ", "G1 "))]
    second = lines.index(";LAYER:1")
    # after the second layer's mark and before its first move; off after the last move
    assert second < on[0] < min(i for i in moves if i > second) and off[0] > moves[-1]
    with pytest.raises(ValueError):
        profile.model_validate({**profile.model_dump(), "gcode": {**profile.gcode.model_dump(), "fan_percent": 120}})


def test_feature_tags_name_shells_and_infill(tmp_path):
    """;TYPE: lines (PrusaSlicer's names) before each printing run of another feature: one per change of the
    toolpaths' path kind along the printed waypoints, each followed by an extruding move, none in LinuxCNC output."""
    layers = planar_stack(3, size=12.0, n=9)
    profile = load_profile("reprap_5axis")
    tp, prog, _, _ = plan_print(layers, platform_z=0.0, profile=profile)
    kinds = tp.attrs["path_kinds"]
    assert len(kinds) == tp.attrs["n_paths"] and set(kinds) == {"0", "1"}        # shells and zig-zag infill
    names = {"0": "Perimeter", "1": "Internal infill", "2": "Internal infill"}
    printed = tp.extrude & (tp.path >= 0)
    label = [names[kinds[p]] for p in tp.path[printed]]
    expected = [label[0]] + [b for a, b in zip(label[:-1], label[1:]) if a != b]
    lines = write_gcode(tmp_path / "p.gcode", prog).read_text().splitlines()
    tags = [i for i, ln in enumerate(lines) if ln.startswith(";TYPE:")]
    assert [lines[i][6:] for i in tags] == expected
    for i in tags:
        assert lines[i + 1].startswith("G1") and " E" in lines[i + 1]
    linuxcnc = plan_print(layers, platform_z=0.0)[1]
    assert ";TYPE:" not in write_gcode(tmp_path / "p.ngc", linuxcnc).read_text()
