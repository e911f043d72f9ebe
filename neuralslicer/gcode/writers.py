"""G-code writers: LinuxCNC RS274/NGC (A = filament) and RepRap/Marlin (E), written atomically."""
from __future__ import annotations

from pathlib import Path
from typing import Iterator

import numpy as np

from neuralslicer.motion.planning import TRAVEL, MachineProgram, program_metrics
from neuralslicer.motion.timing import move_times
from neuralslicer.fileio import atomic_path

MIN_MOVE_S = 1e-4


def _fmt(values: np.ndarray, decimals: int) -> np.ndarray:
    """Fixed-point strings without negative zero."""
    v = np.round(np.asarray(values, np.float64), decimals)
    v[v == 0] = 0.0
    return np.char.mod(f"%.{decimals}f", v)


def _words(letter: str, strings: np.ndarray, always: np.ndarray | None = None) -> np.ndarray:
    """``letter + value`` where the value changed from the previous line (modal), else ''."""
    changed = np.ones(len(strings), bool)
    changed[1:] = strings[1:] != strings[:-1]
    if always is not None:
        changed |= always
    return np.where(changed, np.char.add(letter, strings), "")


def _join_lines(prefix: np.ndarray, cols: list[np.ndarray]) -> list[str]:
    return [" ".join(w for w in words if w) for words in zip(prefix, *cols)]


_CHUNK = 50_000


def _axis_columns(program: MachineProgram, start: int, stop: int) -> list[np.ndarray]:
    """Axis words of moves start..stop-1, modal against move start-1."""
    g = program.profile.gcode
    lx, ly, lz, lb, lc, le = program.axis_letters
    lo = max(start - 1, 0)
    m = program.machine[lo:stop]
    first = np.zeros(len(m), bool)
    first[0] = start == 0
    cols = []
    for j, (letter, dec) in enumerate([(lx, g.decimals_linear), (ly, g.decimals_linear),
                                       (lz, g.decimals_linear), (lb, g.decimals_rotary),
                                       (lc, g.decimals_rotary)]):
        cols.append(_words(letter, _fmt(m[:, j], dec), always=first))
    cols.append(_words(le, _fmt(program.extruder[lo:stop], g.decimals_extruder), always=first))
    return [c[start - lo:] for c in cols]


def _layer_segments(program: MachineProgram, first: int = 0) -> Iterator[tuple[int, int, dict | None]]:
    """(start, stop, layer info or None) over moves first..n-1: one segment per layer (info: its number,
    the count, the build-frame z range, the elapsed time and the fraction done at its start), cut into
    chunks of at most _CHUNK moves (info only on a layer's first chunk)."""
    n = len(program)
    layer = program.layer
    starts = np.flatnonzero(np.diff(layer)) + 1
    bounds = np.concatenate([[0], starts, [n]])
    elapsed = np.concatenate([[0.0], np.cumsum(move_times(program.machine, program.time_s, program.profile.feeds))])
    total = max(float(elapsed[-1]), 1e-9)       # the estimate under the axis limits (motion/timing.py)
    n_layers = len(bounds) - 1
    iso = program.attrs.get("isovalues") or []
    for k in range(n_layers):
        a, b = int(bounds[k]), int(bounds[k + 1])
        a = max(a, first)
        if a >= b:
            continue
        z = program.part_xyz[a:b, 2]
        li = int(layer[a])
        info = {"number": k + 1, "count": n_layers, "z": (float(z.min()), float(z.max())),
                "isovalue": iso[li] if 0 <= li < len(iso) else None,
                "elapsed_s": float(elapsed[a]), "done": float(elapsed[a] / total), "remaining_s": total - float(elapsed[a])}
        for c in range(a, b, _CHUNK):
            yield c, min(c + _CHUNK, b), info if c == a else None


def _layer_comment(info: dict) -> str:
    """``LAYER k / n, build z lo..hi mm, isovalue G = g, at h:mm:ss, p % of the time`` (no brackets: LinuxCNC comments do not nest)."""
    t = int(round(info["elapsed_s"]))
    iso = f", isovalue G = {info['isovalue']:.6g}" if info.get("isovalue") is not None else ""
    return (f"LAYER {info['number']} / {info['count']}, build z {info['z'][0]:.3f}..{info['z'][1]:.3f} mm{iso}, "
            f"at {t // 3600}:{t // 60 % 60:02d}:{t % 60:02d}, {100 * info['done']:.1f} % of the time")


def _machine_comment(program: MachineProgram) -> list[str]:
    """The kinematic set-up the program was computed for (what the operator must match on the machine)."""
    k = program.profile.kinematics
    v = lambda t: " ".join(f"{x:.4f}" for x in t)  # noqa: E731
    c_span = ("unlimited" if k.c_min_deg is None and k.c_max_deg is None
              else f"{k.c_min_deg if k.c_min_deg is not None else '-inf'}..{k.c_max_deg if k.c_max_deg is not None else 'inf'}")
    b_lo, b_hi = program.attrs.get("b_range_deg", (0.0, 0.0))
    c_lo, c_hi = program.attrs.get("c_range_deg", (0.0, 0.0))
    return [f"machine: {program.profile.name}, table B/C, tool tip at the pivot = machine {v(k.pivot)} mm",
            f"machine: C axis on the table at pivot + {v(k.c_offset)} mm at B = 0; B range {k.b_min_deg:g}..{k.b_max_deg:g} deg, "
            f"C range {c_span} deg",
            f"machine: program B {b_lo:.2f}..{b_hi:.2f} deg, C {c_lo:.2f}..{c_hi:.2f} deg"]


def _summary_comment(program: MachineProgram, open_c: str, close_c: str) -> list[str]:
    met = program_metrics(program)
    lx, ly, lz, lb, lc, le = program.axis_letters
    return [
        f"{open_c}Neural Slicer multi-axis program, profile {program.profile.name}{close_c}",
        f"{open_c}{lx}{ly}{lz}: tool tip in machine mm; {lb}: table tilt deg; {lc}: table rotation deg, "
        f"unwrapped; {le}: filament mm, absolute{close_c}",
        f"{open_c}part offset on the C axis: {' '.join(f'{v:.4f}' for v in program.part_offset)}{close_c}",
        f"{open_c}moves {met['n_moves']}, waypoints {met['n_waypoints']}, est. time "
        f"{met['estimated_print_time_s']:.1f} s, material {met['material_mm3']:.1f} mm3{close_c}",
    ] + [f"{open_c}{line}{close_c}" for line in _machine_comment(program)]


def _linuxcnc_body(program: MachineProgram, start: int, stop: int) -> list[str]:
    g = program.profile.gcode
    dt = np.maximum(program.time_s[start:stop], MIN_MOVE_S)
    if g.inverse_time:
        feed = np.char.add("F", _fmt(60.0 / dt, 3))
    else:
        f = program.profile.feeds
        lo = max(start - 1, 0)
        v = np.where(program.kind[lo:stop] == TRAVEL, f.travel_mm_s, f.print_mm_s) * 60.0
        feed = _words("F", _fmt(v, 1))[start - lo:]
    prefix = np.full(stop - start, "G1", dtype=object)
    if start == 0:
        prefix[0] = "G0"
        feed[0] = ""
    return _join_lines(prefix, _axis_columns(program, start, stop) + [feed])


def _linuxcnc_chunks(program: MachineProgram):
    g = program.profile.gcode
    le = program.axis_letters[5]
    n = len(program)
    head = ["(" + s.strip("()") + ")" for s in _summary_comment(program, "", "")]
    head += ["G21 G90 G17 G40 G49 G80 G94", "G64 P0.01", f"G92 {le}0"] + list(g.header)
    yield head
    yield _linuxcnc_body(program, 0, min(1, n))
    yield ["G93" if g.inverse_time else "G94"]
    for start, stop, info in _layer_segments(program, first=1):
        yield ([f"({_layer_comment(info)})"] if info else []) + _linuxcnc_body(program, start, stop)
    yield ["G94", "G92.1"] + list(g.footer) + ["M2"]


def _feed_words(mm_min: np.ndarray) -> np.ndarray:
    """``F`` words rounded to 1e-4 relative at most (1 to 8 decimals): a slow feed keeps its digits."""
    f = np.asarray(mm_min, np.float64)
    dec = np.clip(np.ceil(3.7 - np.log10(f)), 1, 8).astype(np.int64)
    out = np.empty(len(f), dtype=object)
    for d in np.unique(dec):
        sel = dec == d
        out[sel] = np.char.add("F", _fmt(f[sel], int(d)))
    return out


def _reprap_body(program: MachineProgram, start: int, stop: int) -> list[str]:
    """G0/G1 lines of moves start..stop-1 with F (mm/min) such that the firmware's distance over F is the
    move's planned time: the distance as RepRapFirmware and Marlin measure it (NIST RS274 rule A) from the
    coordinates as written (rounded): with ``feed_basis`` "xyz" the XYZ distance when a linear axis moves,
    else the B/C vector (deg), else the filament; with "all_axes" the XYZ and B/C vector together (B, C
    counted as linear axes); the extruder counts only in filament-only moves."""
    g = program.profile.gcode
    lo = max(start - 1, 0)
    dt = np.maximum(program.time_s[lo:stop], MIN_MOVE_S)
    m = program.machine[lo:stop]
    k = len(m)
    lin, rot = np.round(m[:, :3], g.decimals_linear), np.round(m[:, 3:5], g.decimals_rotary)
    ext = np.round(program.extruder[lo:stop], g.decimals_extruder)
    dxyz, drot, de = np.zeros(k), np.zeros(k), np.zeros(k)
    dxyz[1:] = np.linalg.norm(np.diff(lin, axis=0), axis=1)
    drot[1:] = np.linalg.norm(np.diff(rot, axis=0), axis=1)
    de[1:] = np.abs(np.diff(ext))
    dist = np.sqrt(dxyz ** 2 + drot ** 2) if g.feed_basis == "all_axes" else dxyz
    dist = np.where(dist > 0, dist, np.where(drot > 0, drot, de))
    rate = np.where(dist > 0, dist / dt * 60.0, program.profile.feeds.travel_mm_s * 60.0)
    feed = _feed_words(rate)[start - lo:]
    kind = program.kind[start:stop]
    prefix = np.where(kind == TRAVEL, "G0", "G1").astype(object)
    if start == 0:
        feed[0] = "F" + f"{program.profile.feeds.travel_mm_s * 60.0:.1f}"
    return _join_lines(prefix, _axis_columns(program, start, stop) + [feed])


def _reprap_chunks(program: MachineProgram):
    g = program.profile.gcode
    head = ["; " + s for s in _summary_comment(program, "", "")]
    head += ["G21", "G90", "M82"]
    if g.bed_temp_c is not None:
        head += [f"M140 S{g.bed_temp_c:.0f}", f"M190 S{g.bed_temp_c:.0f}"]
    if g.nozzle_temp_c is not None:
        head += [f"M104 S{g.nozzle_temp_c:.0f}", f"M109 S{g.nozzle_temp_c:.0f}"]
    head += [f"G92 {program.axis_letters[5]}0"] + list(g.header)
    yield head
    for start, stop, info in _layer_segments(program):
        layer = ([f";LAYER:{info['number'] - 1}", f"; {_layer_comment(info)}",
                  f"M73 P{int(100 * info['done'])} R{int(np.ceil(info['remaining_s'] / 60))}"] if info else [])
        yield layer + _reprap_body(program, start, stop)
    yield ["M73 P100 R0", "M104 S0", "M140 S0"] + list(g.footer) + ["M84"]


def linuxcnc_lines(program: MachineProgram) -> list[str]:
    """RS274/NGC for LinuxCNC: G21 G90, G93 inverse-time feeds (or G94), filament on the A-like axis, M2."""
    return [ln for chunk in _linuxcnc_chunks(program) for ln in chunk]


def reprap_lines(program: MachineProgram) -> list[str]:
    """RepRap/Marlin G-code: G21 G90 M82, absolute E, F in mm/min over the profile's feed basis."""
    return [ln for chunk in _reprap_chunks(program) for ln in chunk]


def gcode_lines(program: MachineProgram) -> list[str]:
    """G-code lines in the profile's dialect."""
    if program.profile.gcode.dialect == "linuxcnc":
        return linuxcnc_lines(program)
    return reprap_lines(program)


def write_gcode(path: str | Path, program: MachineProgram) -> Path:
    """Write the program as G-code in its profile's dialect (atomic)."""
    chunks = _linuxcnc_chunks(program) if program.profile.gcode.dialect == "linuxcnc" else _reprap_chunks(program)
    with atomic_path(path) as tmp:
        with open(tmp, "w") as fh:
            for lines in chunks:
                if lines:
                    fh.write("\n".join(lines))
                    fh.write("\n")
    return Path(path)
