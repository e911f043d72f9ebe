"""A small G-code reader (LinuxCNC and RepRap subsets we emit), used by the tests."""
from __future__ import annotations

import re
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from neuralslicer.errors import InputError

_WORD = re.compile(r"([A-Za-z])\s*([-+]?(?:\d+\.?\d*|\.\d+))")
_PAREN = re.compile(r"\([^)]*\)")


@dataclass
class ParsedMoves:
    """Motion lines (G0/G1) with the modal axis state *after* each move.

    axes : letter -> (n,) float64; feed : (n,) F in force; motion : (n,) 0 or 1;
    inverse_time : (n,) bool (G93 active); line : (n,) 1-based line number.
    """

    axes: dict[str, np.ndarray]
    feed: np.ndarray
    motion: np.ndarray
    inverse_time: np.ndarray
    line: np.ndarray

    def __len__(self) -> int:
        """Number of moves."""
        return int(len(self.line))


def parse_gcode(source: str | Path, axes: str = "XYZABCUVWE") -> ParsedMoves:
    """Parse G0/G1 moves from a file path or G-code text (absolute mode; G92 resets axis values)."""
    text = Path(source).read_text() if isinstance(source, Path) or "\n" not in str(source) else str(source)
    state = {a: 0.0 for a in axes}
    feed, motion, inv = 0.0, 0, False
    out_axes: dict[str, list] = {a: [] for a in axes}
    out_f, out_m, out_i, out_l = [], [], [], []
    for lineno, raw in enumerate(text.splitlines(), start=1):
        line = _PAREN.sub(" ", raw).split(";", 1)[0].strip()     # a ';' inside ( ) is comment text
        if not line or line == "%":
            continue
        words = [(w.upper(), float(v)) for w, v in _WORD.findall(line)]
        gcodes = [v for w, v in words if w == "G"]
        is_move = False
        for gv in gcodes:
            if gv in (0.0, 1.0):
                motion, is_move = int(gv), True
            elif gv == 91.0:
                raise InputError(f"gcode line {lineno}", "relative mode (G91) is not supported")
            elif gv == 93.0:
                inv = True
            elif gv == 94.0:
                inv = False
        if 92.0 in gcodes:
            for w, v in words:
                if w in state:
                    state[w] = v
            continue
        has_axis = False
        for w, v in words:
            if w == "F":
                feed = v
            elif w in state:
                state[w] = v
                has_axis = True
        if (is_move or (not gcodes and has_axis)) and has_axis:
            for a in axes:
                out_axes[a].append(state[a])
            out_f.append(feed)
            out_m.append(motion)
            out_i.append(inv)
            out_l.append(lineno)
    return ParsedMoves({a: np.asarray(v, np.float64) for a, v in out_axes.items()},
                       np.asarray(out_f, np.float64), np.asarray(out_m, np.int64),
                       np.asarray(out_i, bool), np.asarray(out_l, np.int64))
