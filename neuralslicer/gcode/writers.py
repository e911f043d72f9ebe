"""G-code writers: LinuxCNC RS274/NGC (A = filament) and RepRap/Marlin (E), written atomically."""
from __future__ import annotations

import logging
from dataclasses import dataclass
from pathlib import Path
from collections.abc import Iterable, Iterator

import numpy as np

from neuralslicer.motion.planning import FEATURE_NAMES, TRAVEL, MachineProgram, filament_area, program_metrics
from neuralslicer.motion.timing import schedule
from neuralslicer.fileio import atomic_path

MIN_MOVE_S = 1e-4


_POW10 = 10 ** np.arange(19, dtype=np.int64)


def fixed_point(values: np.ndarray, decimals: int | np.ndarray) -> np.ndarray:
    """The integers (n,) int64 that ``"%.{decimals}f"`` of ``np.round(values, decimals)`` writes, without the
    decimal point: ``np.rint(values * 10**decimals)`` (numpy's rounding); decimals a number or one per value."""
    v = np.asarray(values, np.float64)
    if not np.isfinite(v).all():
        raise ValueError("G-code values must be finite: the program holds NaN or infinite coordinates")
    return np.rint(v * np.power(10.0, decimals)).astype(np.int64)


class _Words:
    """One word per line (``letter`` + fixed-point number, ``digits`` the int64 of ``fixed_point``), written where
    ``present``."""

    def __init__(self, letter: str, digits: np.ndarray, decimals: int | np.ndarray, present: np.ndarray | None = None):
        self.letter = letter.encode()
        self.digits = digits
        self.decimals = np.broadcast_to(np.asarray(decimals, np.int64), digits.shape)
        self.present = np.ones(len(digits), bool) if present is None else present

    @classmethod
    def modal(cls, letter: str, digits: np.ndarray, decimals: int, always: np.ndarray | None = None) -> "_Words":
        """Written where the number changed from the previous line (and where ``always``)."""
        changed = np.ones(len(digits), bool)
        changed[1:] = digits[1:] != digits[:-1]
        if always is not None:
            changed |= always
        return cls(letter, digits, decimals, changed)

    def __getitem__(self, rows: slice) -> "_Words":
        return _Words(self.letter.decode(), self.digits[rows], self.decimals[rows], self.present[rows])

    def lengths(self) -> tuple[np.ndarray, np.ndarray]:
        """Characters of each word (0 where absent) and of its digits with the decimal point (without sign)."""
        mag = np.abs(self.digits)
        n_digits = np.maximum(np.searchsorted(_POW10, mag, side="right"), self.decimals + 1)
        body = n_digits + 1                                         # the decimal point (decimals >= 1)
        return np.where(self.present, len(self.letter) + (self.digits < 0) + body, 0), body


def render_lines(prefix: np.ndarray, words: list[_Words]) -> bytes:
    """Lines ``prefix word word ...`` (absent words skipped, one space between) as bytes, newline-terminated,
    formatted in bulk: the same text as joining ``"%.{d}f"`` strings of the rounded numbers."""
    n = len(prefix)
    if n == 0:
        return b""
    vocab, code = np.unique(np.asarray(prefix, str), return_inverse=True)
    vocab_b = [v.encode() for v in vocab]
    sizes = [w.lengths() for w in words]
    line_len = np.array([len(v) for v in vocab_b], np.int64)[code] + 1
    for w, (size, _) in zip(words, sizes):
        line_len += size + w.present
    ends = np.cumsum(line_len)
    buf = np.full(int(ends[-1]), ord(" "), np.uint8)
    buf[ends - 1] = ord("\n")
    pos = ends - line_len                                           # where each line's next word starts
    for j, v in enumerate(vocab_b):
        at = pos[code == j]
        for i, ch in enumerate(v):
            buf[at + i] = ch
    pos = pos + np.array([len(v) for v in vocab_b], np.int64)[code]
    for w, (size, body) in zip(words, sizes):
        rows = np.flatnonzero(w.present)
        at = pos[rows] + 1                                          # after the space
        for i, ch in enumerate(w.letter):
            buf[at + i] = ch
        at = at + len(w.letter)
        neg = w.digits[rows] < 0
        buf[at[neg]] = ord("-")
        last = at + neg + body[rows] - 1                            # the number's last character
        dec = w.decimals[rows]
        buf[last - dec] = ord(".")
        mag = np.abs(w.digits[rows])
        n_dig = body[rows] - 1
        for t in range(int(n_dig.max(initial=0))):                  # digit t from the right
            on = np.flatnonzero(n_dig > t)
            buf[last[on] - t - (t >= dec[on])] = ord("0") + (mag[on] // _POW10[t]) % 10
        pos = pos + size + w.present
    return buf.tobytes()


_CHUNK = 50_000


def _axis_columns(program: MachineProgram, start: int, stop: int) -> list[_Words]:
    """Axis words of moves start..stop-1, modal against move start-1."""
    g = program.profile.gcode
    lx, ly, lz, lb, lc, le = program.axis_letters
    lo = max(start - 1, 0)
    m = program.machine[lo:stop]
    xyz = program.program_xyz(lo, stop)
    first = np.zeros(len(m), bool)
    first[0] = start == 0
    cols = []
    for j, (letter, dec) in enumerate([(lx, g.decimals_linear), (ly, g.decimals_linear), (lz, g.decimals_linear)]):
        cols.append(_Words.modal(letter, fixed_point(xyz[:, j], dec), dec, always=first))
    if program.profile.kinematics.rotary:
        for j, letter in ((3, lb), (4, lc)):
            cols.append(_Words.modal(letter, fixed_point(m[:, j], g.decimals_rotary), g.decimals_rotary, always=first))
    cols.append(_Words.modal(le, fixed_point(program.extruder[lo:stop], g.decimals_extruder), g.decimals_extruder,
                             always=first))
    return [c[start - lo:] for c in cols]


def _layer_segments(program: MachineProgram, times: np.ndarray, first: int = 0) -> Iterator[tuple[int, int, dict | None]]:
    """(start, stop, layer info or None) over moves first..n-1: one segment per layer (info: its number,
    the count, the build-frame z range, the elapsed time and the fraction done at its start), cut into
    chunks of at most _CHUNK moves (info only on a layer's first chunk)."""
    n = len(program)
    layer = program.layer
    starts = np.flatnonzero(np.diff(layer)) + 1
    bounds = np.concatenate([[0], starts, [n]])
    elapsed = np.concatenate([[0.0], np.cumsum(times)])
    total = max(float(elapsed[-1]), 1e-9)       # the estimate under the axis limits (motion/timing.py)
    n_layers = len(bounds) - 1
    iso = program.attrs.get("isovalues") or []
    for k in range(n_layers):
        a, b = int(bounds[k]), int(bounds[k + 1])
        a = max(a, first)
        if a >= b:
            continue
        z = program.forward(slice(a, b))[0][:, 2]
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
    prof = program.profile
    k = prof.kinematics
    _, _, _, lt, lr, _ = program.axis_letters
    v = lambda t: " ".join(f"{x:.4f}" for x in t)  # noqa: E731
    if not k.rotary:
        return [f"machine: {prof.name}, three-axis, XYZ = tool tip, head vertical; printing directions within "
                f"{k.clearance_deg:g} deg of +Z (the head's clearance)"]
    r_span = ("unlimited" if k.rotate_min_deg is None and k.rotate_max_deg is None else
              f"{k.rotate_min_deg if k.rotate_min_deg is not None else '-inf'}.."
              f"{k.rotate_max_deg if k.rotate_max_deg is not None else 'inf'}")
    t_lo, t_hi = program.attrs.get("b_range_deg", (0.0, 0.0))
    r_lo, r_hi = program.attrs.get("c_range_deg", (0.0, 0.0))
    where = {"table-table": "table tilts and turns", "head-head": "head tilts and turns",
             "table-head": "head tilts, table turns"}[k.layout]
    lines = [f"machine: {prof.name}, {prof.layout_words()}, {where}; {lt} about {k.tilt_axis}, {lr} about "
             f"{k.rotate_axis}, right-hand rule"]
    if k.layout == "table-table":
        lines.append(f"machine: tool tip at the {lt} pivot = machine {v(k.pivot)} mm; {lr} axis on the table at pivot + "
                     f"{v(k.c_offset)} mm at {lt} = 0")
    elif k.layout == "head-head":
        lines.append(f"machine: XYZ = tool tip with the head at home; {lt} pivot {v(k.pivot)} mm from the {lr} axis, "
                     f"tool tip {k.tool_length:.4f} mm below the {lt} axis")
    else:
        lines.append(f"machine: XYZ = tool tip with the head at home, tool tip {k.tool_length:.4f} mm below the {lt} "
                     f"axis; {lr} axis on the table top at machine {v(k.c_offset)} mm")
    if k.tcp:
        lines.append(f"machine: TCP ON: XYZ are the tool tip in workpiece coordinates, the part as at {lt} = {lr} = 0; "
                     "the controller's tool-centre-point kinematics must be active, LinuxCNC: trt kins in TCP mode, "
                     "with the pivot values above")
    else:
        lines.append("machine: TCP OFF: XYZ are machine coordinates that already carry the pivot offsets above; run "
                     "with tool-centre-point control off, trivial kinematics, or the offsets are applied twice")
    return lines + [f"machine: {lt} range {k.tilt_min_deg:g}..{k.tilt_max_deg:g} deg, {lr} range {r_span} deg; program "
                    f"{lt} {t_lo:.2f}..{t_hi:.2f} deg, {lr} {r_lo:.2f}..{r_hi:.2f} deg"]


def _summary_comment(program: MachineProgram, met: dict, open_c: str, close_c: str) -> list[str]:
    """What the program is and assumes, with its totals ``met`` (``program_metrics``)."""
    lx, ly, lz, lb, lc, le = program.axis_letters
    k = program.profile.kinematics
    frame = "workpiece" if k.tcp else "machine"
    axes = (f"{lb}: tilt deg; {lc}: rotation deg, unwrapped; " if k.rotary else "")
    return [
        f"{open_c}Neural Slicer {'multi-axis' if k.rotary else 'three-axis non-planar'} program, profile "
        f"{program.profile.name}, {program.profile.layout_words()}{close_c}",
        f"{open_c}{lx}{ly}{lz}: tool tip in {frame} mm; {axes}{le}: filament mm, absolute{close_c}",
        f"{open_c}part offset {'on the rotary axis' if k.layout in ('table-table', 'table-head') else 'on the bed centre'}: "
        f"{' '.join(f'{v:.4f}' for v in program.part_offset)}{close_c}",
        f"{open_c}moves {met['n_moves']}, waypoints {met['n_waypoints']}, est. time "
        f"{met['estimated_print_time_s']:.1f} s, material {met['material_mm3']:.1f} mm3{close_c}",
    ] + [f"{open_c}{line}{close_c}" for line in _machine_comment(program)]


def host_totals(program: MachineProgram, met: dict) -> tuple[int, float, float, int]:
    """(estimated time in whole s, filament mm, filament g, layer count) of a program with totals ``met``
    (``program_metrics``): what print hosts show before a print."""
    t = int(round(met["estimated_print_time_s"]))
    mm = met["filament_mm"]
    grams = mm * filament_area(program.profile) / 1000.0 * program.profile.extrusion.filament_density_g_cm3
    n_layers = int(np.count_nonzero(np.diff(program.layer)) + 1) if len(program) else 0
    return t, mm, grams, n_layers


def host_comments(program: MachineProgram, met: dict) -> list[str]:
    """The keys print hosts show before a print (estimated time, filament length and mass, layer count; ``met``: the
    program's totals), in the Cura spellings (OctoPrint plugins, Duet Web Control) and the PrusaSlicer ones
    (PrusaLink, Duet)."""
    t, mm, grams, n_layers = host_totals(program, met)
    return [";FLAVOR:RepRap", f";TIME:{t}", f";Filament used: {mm / 1000:.5f}m", f";LAYER_COUNT:{n_layers}",
            f"; estimated printing time (normal mode) = {t // 3600}h {t // 60 % 60}m {t % 60}s",
            f"; filament used [mm] = {mm:.2f}", f"; filament used [g] = {grams:.2f}",
            f"; total layers count = {n_layers}"]


def linuxcnc_host_comments(program: MachineProgram, met: dict) -> list[str]:
    """The totals of ``host_comments`` as RS274/NGC comments: the same keys in parentheses, without the flavour and
    the nested "(normal mode)" (LinuxCNC comments do not nest)."""
    t, mm, grams, n_layers = host_totals(program, met)
    return [f"(TIME:{t})", f"(Filament used: {mm / 1000:.5f}m)", f"(LAYER_COUNT:{n_layers})",
            f"(estimated printing time = {t // 3600}h {t // 60 % 60}m {t % 60}s)",
            f"(filament used [mm] = {mm:.2f})", f"(filament used [g] = {grams:.2f})",
            f"(total layers count = {n_layers})"]


def _linuxcnc_body(program: MachineProgram, start: int, stop: int) -> bytes:
    g = program.profile.gcode
    dt = np.maximum(program.time_s[start:stop], MIN_MOVE_S)
    if g.inverse_time:
        feed = _Words("F", fixed_point(60.0 / dt, 3), 3)
    else:
        f = program.profile.feeds
        lo = max(start - 1, 0)
        v = np.where(program.kind[lo:stop] == TRAVEL, f.travel_mm_s, f.print_mm_s) * 60.0
        feed = _Words.modal("F", fixed_point(v, 1), 1)[start - lo:]
    prefix = np.full(stop - start, "G1")
    if start == 0:
        prefix[0] = "G0"
        feed.present = feed.present.copy()
        feed.present[0] = False
    return render_lines(prefix, _axis_columns(program, start, stop) + [feed])


def _text(lines: list[str]) -> bytes:
    return "".join(ln + "\n" for ln in lines).encode()


def _linuxcnc_chunks(program: MachineProgram) -> Iterator[bytes]:
    g = program.profile.gcode
    le = program.axis_letters[5]
    n = len(program)
    times = schedule(program.machine, program.time_s, program.profile.feeds)
    met = program_metrics(program, times)
    head = ["(" + s.strip("()") + ")" for s in _summary_comment(program, met, "", "")]
    head += linuxcnc_host_comments(program, met)
    head += ["G21 G90 G17 G40 G49 G80 G94", "G64 P0.01", f"G92 {le}0"] + list(g.header)
    yield _text(head)
    yield _linuxcnc_body(program, 0, min(1, n))
    yield _text(["G93" if g.inverse_time else "G94"])
    for start, stop, info in _layer_segments(program, times[0], first=1):
        yield _text([f"({_layer_comment(info)})"] if info else []) + _linuxcnc_body(program, start, stop)
    yield _text(["G94", "G92.1"] + list(g.footer) + ["M2"])


def _feed_words(mm_min: np.ndarray) -> _Words:
    """``F`` words rounded to 1e-4 relative at most (1 to 8 decimals): a slow feed keeps its digits."""
    f = np.asarray(mm_min, np.float64)
    dec = np.clip(np.ceil(3.7 - np.log10(f)), 1, 8).astype(np.int64)
    return _Words("F", fixed_point(f, dec), dec)


def _reprap_body(program: MachineProgram, start: int, stop: int) -> bytes:
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
    lin, rot = np.round(program.program_xyz(lo, stop), g.decimals_linear), np.round(m[:, 3:5], g.decimals_rotary)
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
    prefix = np.where(kind == TRAVEL, "G0", "G1")
    if start == 0:
        first = f"{program.profile.feeds.travel_mm_s * 60.0:.1f}"
        feed.digits, feed.decimals = feed.digits.copy(), feed.decimals.copy()
        feed.digits[0], feed.decimals[0] = int(first.replace(".", "")), 1
    return render_lines(prefix, _axis_columns(program, start, stop) + [feed])


def _reprap_chunks(program: MachineProgram) -> Iterator[bytes]:
    g = program.profile.gcode
    times = schedule(program.machine, program.time_s, program.profile.feeds)
    met = program_metrics(program, times)
    head = ["; " + s for s in _summary_comment(program, met, "", "")] + host_comments(program, met)
    head += ["G21", "G90", "M82"]
    if g.bed_temp_c is not None:
        head += [f"M140 S{g.bed_temp_c:.0f}", f"M190 S{g.bed_temp_c:.0f}"]
    if g.nozzle_temp_c is not None:
        head += [f"M104 S{g.nozzle_temp_c:.0f}", f"M109 S{g.nozzle_temp_c:.0f}"]
    head += [f"G92 {program.axis_letters[5]}0"] + list(g.header)
    yield _text(head + thumbnail_comments(program))
    fan = fan_on(program)
    features = program.attrs.get("features") or {"moves": [], "kinds": ""}
    for start, stop, info in _layer_segments(program, times[0]):
        layer = ([f";LAYER:{info['number'] - 1}", f"; {_layer_comment(info)}",
                  f"M73 P{int(100 * info['done'])} R{int(np.ceil(info['remaining_s'] / 60))}"] if info else [])
        if fan and info and info["number"] == 2:
            layer.append(fan)
        yield _text(layer) + b"".join(_typed_body(program, start, stop, features))
    yield _text(["M73 P100 R0"] + (["M107"] if fan else []) + ["M104 S0", "M140 S0"] + list(g.footer) + ["M84"]
                + prusaslicer_totals(program, met))


def _typed_body(program: MachineProgram, start: int, stop: int, features: dict) -> Iterator[bytes]:
    """Moves start..stop-1 with a ``;TYPE:`` line (PrusaSlicer's and Cura's feature tag) before each printing run
    of another feature (``program.attrs["features"]``, from the toolpath kinds)."""
    at = np.asarray(features["moves"], np.int64)
    lo, hi = np.searchsorted(at, start), np.searchsorted(at, stop)
    cuts = [start] + [int(i) for i in at[lo:hi] if i > start] + [stop]
    tags = {int(i): FEATURE_NAMES.get(k, "Perimeter") for i, k in zip(at[lo:hi], features["kinds"][lo:hi])}
    for a, b in zip(cuts[:-1], cuts[1:]):
        yield (_text([f";TYPE:{tags[a]}"]) if a in tags else b"") + _reprap_body(program, a, b)


def linuxcnc_lines(program: MachineProgram) -> list[str]:
    """RS274/NGC for LinuxCNC: G21 G90, G93 inverse-time feeds (or G94), filament on the A-like axis, M2."""
    return b"".join(_linuxcnc_chunks(program)).decode().split("\n")[:-1]


def reprap_lines(program: MachineProgram) -> list[str]:
    """RepRap/Marlin G-code: G21 G90 M82, absolute E, F in mm/min over the profile's feed basis."""
    return b"".join(_reprap_chunks(program)).decode().split("\n")[:-1]


def gcode_lines(program: MachineProgram) -> list[str]:
    """G-code lines in the profile's dialect."""
    if program.profile.gcode.dialect == "linuxcnc":
        return linuxcnc_lines(program)
    return reprap_lines(program)


def gcode_chunks(program: MachineProgram) -> Iterator[bytes]:
    """The program as G-code in its profile's dialect, a header and then one chunk per layer."""
    return _linuxcnc_chunks(program) if program.profile.gcode.dialect == "linuxcnc" else _reprap_chunks(program)


def gcode_bytes(program: MachineProgram) -> bytes:
    """The program as G-code in its profile's dialect (the program step's output)."""
    return b"".join(gcode_chunks(program))


@dataclass(frozen=True)
class GCode:
    """The program step's output: a machine program's G-code in its profile's dialect, made a chunk (a layer) at a
    time each time it is iterated, its size logged at the end (a long print's G-code is never whole in memory)."""

    program: MachineProgram
    log: logging.Logger | logging.LoggerAdapter | None = None

    def __iter__(self) -> Iterator[bytes]:
        """The G-code's chunks."""
        n = 0
        for chunk in gcode_chunks(self.program):
            n += len(chunk)
            yield chunk
        if self.log is not None:
            self.log.info("program: %s G-code, %.1f MB", self.program.profile.gcode.dialect, n / 1e6)

    def __bytes__(self) -> bytes:
        """The whole G-code."""
        return b"".join(self)


def write_gcode(path: str | Path, program: MachineProgram | bytes | Iterable[bytes]) -> Path:
    """Write the program (or its G-code from :func:`gcode_bytes`, whole or in chunks) as G-code in its profile's
    dialect (atomic)."""
    if isinstance(program, bytes):
        chunks: Iterable[bytes] = [program]
    elif isinstance(program, MachineProgram):
        chunks = gcode_chunks(program)
    else:
        chunks = program
    with atomic_path(path) as tmp:
        with open(tmp, "wb") as fh:
            for chunk in chunks:
                fh.write(chunk)
    return Path(path)


#: PrusaSlicer's thumbnail sizes that print hosts show (the file list, the print screen)
THUMBNAIL_SIZES = ((32, 32), (220, 124))
#: at most this many printing moves are drawn in a thumbnail (a 10M-waypoint print takes as long as a small one)
THUMBNAIL_MAX_POINTS = 400_000


def prusaslicer_totals(program: MachineProgram, met: dict) -> list[str]:
    """PrusaSlicer's totals block, which PrusaSlicer writes and Moonraker and PrusaLink read at the end of a file:
    filament length, volume and mass, layer count, estimated time (``met``: the program's totals)."""
    t, mm, grams, n_layers = host_totals(program, met)
    cm3 = mm * filament_area(program.profile) / 1000.0
    return [f"; filament used [mm] = {mm:.2f}", f"; filament used [cm3] = {cm3:.2f}",
            f"; filament used [g] = {grams:.2f}", f"; total filament used [g] = {grams:.2f}", f"; total layers count = {n_layers}",
            f"; estimated printing time (normal mode) = {t // 3600}h {t // 60 % 60}m {t % 60}s"]


def fan_on(program: MachineProgram) -> str | None:
    """``M106 S0-255`` at the profile's ``gcode.fan_percent`` (None without one)."""
    pct = program.profile.gcode.fan_percent
    return None if pct is None else f"M106 S{int(round(pct * 2.55))}"


def thumbnail_png(program: MachineProgram, width: int, height: int) -> bytes:
    """A ``width`` x ``height`` PNG of the printed moves seen from the front, 30 deg above the platform: the part's
    toolpaths (build frame, the tool tips of ``program.forward``) shaded by height, on a transparent background."""
    import zlib

    moves = np.flatnonzero(program.kind[1:] != TRAVEL) + 1                # printing moves, drawn as lines
    steps = 8
    if len(moves) * steps > THUMBNAIL_MAX_POINTS:
        moves = moves[np.linspace(0, len(moves) - 1, THUMBNAIL_MAX_POINTS // steps).astype(np.int64)]
    a, b = program.forward(moves - 1)[0], program.forward(moves)[0]
    t = np.linspace(0.0, 1.0, steps)[None, :, None]
    pts = (a[:, None] + t * (b - a)[:, None]).reshape(-1, 3)
    rgba = np.zeros((height, width, 4), np.uint8)
    if len(pts):
        el = np.radians(30.0)
        u = pts[:, 0] - pts[:, 1]                                          # view from -x -y, 45 deg about z
        depth = (pts[:, 0] + pts[:, 1]) * np.cos(el) - pts[:, 2] * np.sin(el) * np.sqrt(2.0)
        v = pts[:, 2] * np.cos(el) * np.sqrt(2.0) + (pts[:, 0] + pts[:, 1]) * np.sin(el)
        lo, span = np.array([u.min(), v.min()]), max(np.ptp(u) / (width - 2), np.ptp(v) / (height - 2), 1e-9)
        col = np.clip(((u - lo[0]) / span + (width - np.ptp(u) / span) / 2).astype(np.int64), 0, width - 1)
        row = np.clip(height - 1 - ((v - lo[1]) / span + (height - np.ptp(v) / span) / 2).astype(np.int64),
                      0, height - 1)
        z = pts[:, 2]
        shade = (z - z.min()) / max(float(np.ptp(z)), 1e-9)
        order = np.argsort(-depth, kind="stable")                          # far first: near points overwrite
        color = np.stack([200 + 55 * shade, 90 + 110 * shade, 20 + 40 * shade, np.full_like(shade, 255)], axis=1)
        rgba[row[order], col[order]] = color[order].astype(np.uint8)
    raw = b"".join(b"\x00" + rgba[r].tobytes() for r in range(height))

    def chunk(kind: bytes, data: bytes) -> bytes:
        return (len(data).to_bytes(4, "big") + kind + data
                + (zlib.crc32(kind + data) & 0xFFFFFFFF).to_bytes(4, "big"))

    ihdr = width.to_bytes(4, "big") + height.to_bytes(4, "big") + bytes([8, 6, 0, 0, 0])
    return b"\x89PNG\r\n\x1a\n" + chunk(b"IHDR", ihdr) + chunk(b"IDAT", zlib.compress(raw, 9)) + chunk(b"IEND", b"")


def thumbnail_comments(program: MachineProgram, sizes: tuple[tuple[int, int], ...] = THUMBNAIL_SIZES) -> list[str]:
    """PrusaSlicer's thumbnail blocks (``; thumbnail begin WxH LEN``, the PNG in base64 lines of at most 78
    characters, ``; thumbnail end``), one per size: what PrusaLink, Moonraker and OctoPrint's thumbnail plugins
    show."""
    import base64

    lines: list[str] = []
    for w, h in sizes:
        data = base64.b64encode(thumbnail_png(program, w, h)).decode()
        lines += [f"; thumbnail begin {w}x{h} {len(data)}"] + [f"; {data[i:i + 78]}" for i in range(0, len(data), 78)]
        lines += ["; thumbnail end", ";"]
    return lines
