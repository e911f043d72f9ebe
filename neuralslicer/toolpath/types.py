"""The ``Toolpaths`` result: waypoints in print order with per-waypoint process data."""
from __future__ import annotations

from collections.abc import Iterator
from dataclasses import dataclass, field
from typing import ClassVar

import numpy as np

from neuralslicer.types import BoolArray, FloatArray, IndexArray

TOOLPATHS_SCHEMA_VERSION = 1
#: rows per block of :func:`segment_lengths` (bounds its (rows, 3) temporaries on a long print)
SEGMENT_ROWS = 1 << 19


def segment_lengths(xyz: FloatArray) -> FloatArray:
    """Length (n,) of the move arriving at each of the points (n, 3) from the one before (0 for the first), in
    blocks of rows."""
    n = len(xyz)
    d = np.zeros(n)
    for a in range(1, n, SEGMENT_ROWS):
        z = min(a + SEGMENT_ROWS, n)
        d[a:z] = np.linalg.norm(xyz[a:z] - xyz[a - 1:z - 1], axis=1)
    return d


@dataclass
class Toolpaths:
    """Waypoints of all layers in print order (build frame, mm).

    Attributes
    ----------
    layer : (n,) int64
        Layer index (print order) of each waypoint.
    path : (n,) int64
        Path id, increasing in print order over the whole part; ``-1`` marks the lifted travel
        waypoints inserted between paths (they are not on a layer).
    xyz : (n, 3) float64
        Tool-tip position.
    axis : (n, 3) float64
        Unit tool axis = local printing direction (LPD) interpolated at the waypoint.
    thickness : (n,) float64
        Local layer thickness (distance along ``-axis`` to the layer below, or to the platform).
    width : (n,) float64
        Line width.
    extrude : (n,) bool
        True when the move *arriving* at this waypoint deposits material; the first waypoint of
        every path is reached by a travel and has ``extrude = False``.
    attrs : dict
        JSON-able settings and statistics (config, counts).
    """

    #: the per-waypoint arrays, in the order they are stored
    ARRAYS: ClassVar[tuple[str, ...]] = ("layer", "path", "xyz", "axis", "thickness", "width", "extrude")

    layer: IndexArray
    path: IndexArray
    xyz: FloatArray
    axis: FloatArray
    thickness: FloatArray
    width: FloatArray
    extrude: BoolArray
    attrs: dict = field(default_factory=dict)

    def __len__(self) -> int:
        """Number of waypoints."""
        return int(self.xyz.shape[0])

    @property
    def n_layers(self) -> int:
        """Number of layers that have at least one waypoint (max layer index + 1)."""
        return int(self.layer.max()) + 1 if len(self) else 0

    def segment_lengths(self) -> FloatArray:
        """Length of the move arriving at each waypoint, ``(n,)`` (0 for the first)."""
        return segment_lengths(self.xyz)

    def rows(self, lo: int, hi: int) -> "Toolpaths":
        """The waypoints [lo, hi) as views of these arrays (no copy; no attrs)."""
        return Toolpaths(**{name: getattr(self, name)[lo:hi] for name in self.ARRAYS})

    @property
    def loaded(self) -> bool:
        """Whether the columns are in memory (a stored print's, ``tasks/codec.py: StoredToolpaths``, may not be)."""
        return True

    def load(self) -> "Toolpaths":
        """These toolpaths with every column in memory (read now where they were not)."""
        return self

    def column(self, name: str) -> np.ndarray:
        """One column (one of ``ARRAYS``), without the others where they are not in memory."""
        return getattr(self, name)

    def blocks(self, rows: int) -> Iterator["Toolpaths"]:
        """The waypoints ``rows`` at a time (views; a stored print's read a block at a time)."""
        for lo in range(0, len(self), rows):
            yield self.rows(lo, lo + rows)

    def deposited_volume(self) -> float:
        """Material volume (mm^3): sum over extruding moves of length x mean thickness x width."""
        if len(self) < 2:
            return 0.0
        length = self.segment_lengths()[1:]
        t = 0.5 * (self.thickness[1:] + self.thickness[:-1])
        w = 0.5 * (self.width[1:] + self.width[:-1])
        return float(np.sum(length * t * w * self.extrude[1:]))

    def to_arrays(self) -> tuple[dict[str, np.ndarray], dict]:
        """Store-able form: (arrays, JSON attrs) for one zarr group."""
        arrays = {name: np.ascontiguousarray(getattr(self, name)) for name in self.ARRAYS}
        arrays["extrude"] = arrays["extrude"].astype(np.uint8)
        attrs = {"schema_version": TOOLPATHS_SCHEMA_VERSION, "units": "mm", "frame": "build",
                 **self.attrs}
        return arrays, attrs

    @classmethod
    def from_arrays(cls, arrays: dict[str, np.ndarray], attrs: dict | None = None) -> "Toolpaths":
        """Inverse of ``to_arrays``."""
        return cls(**{name: cls.stored_column(name, arrays[name]) for name in cls.ARRAYS},
                   attrs=cls.stored_attrs(attrs))

    @staticmethod
    def stored_column(name: str, array: np.ndarray) -> np.ndarray:
        """One stored column (of ``ARRAYS``) in its dtype and shape, as ``from_arrays`` reads it."""
        if name == "extrude":
            return np.asarray(array).astype(bool)
        column = np.asarray(array, dtype=np.int64 if name in ("layer", "path") else np.float64)
        return column.reshape(-1, 3) if name in ("xyz", "axis") else column

    @staticmethod
    def stored_attrs(attrs: dict | None) -> dict:
        """The attrs of stored toolpaths without what ``to_arrays`` adds (schema version, units, frame)."""
        attrs = dict(attrs or {})
        for key in ("schema_version", "units", "frame"):
            attrs.pop(key, None)
        return attrs

    @classmethod
    def empty(cls) -> "Toolpaths":
        """Toolpaths without waypoints."""
        return cls(np.zeros(0, np.int64), np.zeros(0, np.int64), np.zeros((0, 3)), np.zeros((0, 3)),
                   np.zeros(0), np.zeros(0), np.zeros(0, bool))
