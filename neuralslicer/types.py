"""Shared array aliases used in signatures and docstrings."""
from __future__ import annotations

import numpy as np
import numpy.typing as npt

#: float64 array; shapes are given in docstrings, e.g. ``points : (n, 3) float64``.
FloatArray = npt.NDArray[np.float64]
#: int64 array of indices, e.g. ``faces : (m, 3) int64``.
IndexArray = npt.NDArray[np.int64]
#: boolean mask.
BoolArray = npt.NDArray[np.bool_]
