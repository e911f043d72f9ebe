"""The small G-code reader: comments, modal words, G92, G93/G94, and its errors."""
from __future__ import annotations

import numpy as np
import pytest

from neuralslicer.errors import InputError
from neuralslicer.gcode import parse_gcode

TEXT = """(header comment with X99 inside)
G21 G90 G94
G92 A0
G0 X1 Y2 Z3 B0 C0 A0 ; rapid
G93
G1 X1.5 A0.25 F600.0
G1 C-10.5 F120 (rotation only)
G1 A-1 F60
G94
G92 A5
G1 Y-.5 A6
M2
"""


def test_modal_state_after_each_move():
    m = parse_gcode(TEXT, axes="XYZABC")
    assert len(m) == 5
    assert np.allclose(m.axes["X"], [1, 1.5, 1.5, 1.5, 1.5])
    assert np.allclose(m.axes["Y"], [2, 2, 2, 2, -0.5])
    assert np.allclose(m.axes["C"], [0, 0, -10.5, -10.5, -10.5])
    assert np.allclose(m.axes["A"], [0, 0.25, 0.25, -1, 6])
    assert m.motion.tolist() == [0, 1, 1, 1, 1]
    assert m.inverse_time.tolist() == [False, True, True, True, False]
    assert np.allclose(m.feed, [0, 600, 120, 60, 60])
    assert m.line.tolist() == [4, 6, 7, 8, 11]


def test_relative_mode_is_rejected():
    with pytest.raises(InputError, match="G91"):
        parse_gcode("G91\nG1 X1\n")
