"""The build frame: inputs are rotated so that their `up` axis becomes +z."""
from __future__ import annotations

import numpy as np

from neuralslicer.errors import InputError

UP_AXES = ("x", "y", "z", "-x", "-y", "-z")


def up_rotation(up: str) -> np.ndarray:
    """Rotation matrix (3,3) that maps the given up axis onto +z (right-handed, det = +1)."""
    table = {
        "z": [[1, 0, 0], [0, 1, 0], [0, 0, 1]],
        "-z": [[1, 0, 0], [0, -1, 0], [0, 0, -1]],
        "y": [[1, 0, 0], [0, 0, -1], [0, 1, 0]],
        "-y": [[1, 0, 0], [0, 0, 1], [0, -1, 0]],
        "x": [[0, 0, -1], [0, 1, 0], [1, 0, 0]],
        "-x": [[0, 0, 1], [0, 1, 0], [-1, 0, 0]],
    }
    if up not in table:
        raise InputError("up", f"unknown up axis {up!r}; expected one of {', '.join(UP_AXES)}")
    return np.asarray(table[up], dtype=np.float64)


def apply_up(points: np.ndarray, up: str) -> np.ndarray:
    """Points (n,3) from the input frame to the build frame."""
    return np.asarray(points, dtype=np.float64) @ up_rotation(up).T
