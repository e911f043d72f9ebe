"""Toolpaths parked on disk while the motion step plans the machine program of a large print.

The planning (IK, rotary splits, retractions, the program's metrics) reads the toolpaths column by column, once, and
holds its own per-move arrays meanwhile: about 90 bytes a waypoint, where the toolpaths are 81 more. Parked, the
columns live in ``.npy`` files of a temporary folder and each is mapped read-only only while an array of it is held
(``parked.xyz``); ``load()`` reads them all back once the planning is done. The numbers are the same bytes.
"""
from __future__ import annotations

import contextlib
import shutil
import tempfile
from collections.abc import Iterator
from pathlib import Path

import numpy as np

from neuralslicer.toolpath.types import Toolpaths

#: prints with at least this many waypoints are parked on disk while they are planned (smaller ones stay in memory)
PARK_WAYPOINTS = 2_000_000


class ParkedToolpaths:
    """Toolpaths read like ``Toolpaths`` (``len``, ``attrs`` and every column of ``Toolpaths.ARRAYS``), their columns
    either still in memory or in ``.npy`` files of ``folder``, each mapped read-only for as long as its array is held."""

    def __init__(self, tp: Toolpaths, folder: Path | None) -> None:
        """Park ``tp``: with ``folder`` each column is written there and dropped from ``tp`` at once (the print is
        never held twice; ``tp`` is left empty), without it ``tp`` is kept as it is."""
        self.attrs, self._n, self._folder = tp.attrs, len(tp), folder
        self._tp: Toolpaths | None = tp
        if folder is None:
            return
        for name in Toolpaths.ARRAYS:
            np.save(folder / f"{name}.npy", getattr(tp, name), allow_pickle=False)
            setattr(tp, name, getattr(tp, name)[:0].copy())
        self._tp = None

    def __len__(self) -> int:
        """Number of waypoints."""
        return self._n

    def __getattr__(self, name: str) -> np.ndarray:
        """A column: the array in memory, or the file mapped read-only (unmapped when the array is dropped)."""
        if name.startswith("_") or name not in Toolpaths.ARRAYS:
            raise AttributeError(name)
        if self._tp is not None:
            return getattr(self._tp, name)
        return np.load(self._folder / f"{name}.npy", mmap_mode="r")

    @property
    def on_disk(self) -> bool:
        """Whether the columns are in files."""
        return self._tp is None

    def load(self) -> Toolpaths:
        """The toolpaths with every column in memory again."""
        if self._tp is not None:
            return self._tp
        columns = {name: np.load(self._folder / f"{name}.npy", allow_pickle=False) for name in Toolpaths.ARRAYS}
        return Toolpaths(**columns, attrs=self.attrs)


@contextlib.contextmanager
def parked(tp: Toolpaths, scratch: str | Path | None = None, min_waypoints: int | None = None
           ) -> Iterator[ParkedToolpaths]:
    """``tp`` parked (:class:`ParkedToolpaths`) for the block: on disk in a temporary folder inside ``scratch`` (None:
    the system's temporary folder) when it has at least ``min_waypoints`` (default :data:`PARK_WAYPOINTS`) waypoints,
    else in memory. The folder is removed when the block ends, however it ends; ``load()`` the toolpaths back before
    that."""
    if len(tp) < (PARK_WAYPOINTS if min_waypoints is None else min_waypoints):
        yield ParkedToolpaths(tp, None)
        return
    folder = Path(tempfile.mkdtemp(prefix=".neuralslicer-parked-", dir=scratch))
    try:
        yield ParkedToolpaths(tp, folder)
    finally:
        shutil.rmtree(folder, ignore_errors=True)
