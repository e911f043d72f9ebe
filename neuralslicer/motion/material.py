"""The material printed so far, at every moment of a print, in one structure built once.

Every printed bead is two points, both laid at its waypoint's printing rank (``time``): its top (the waypoint, on
its layer) and its bottom (``thickness`` below it along the tool axis, on the layer under it). A pose sees the
points with ``time < visible``: for the pose at a waypoint, every bead laid before it, those of its own layer
included.

The points are binned in cubes of edge ``cell`` and sorted by (cube, time), so that the material of a cube at any
moment is a prefix of its list: adding a path appends its points to the lists of its cubes and changes nothing
else, and the whole print is added at once by one sort. A pyramid of coarser grids (edge doubled per level) holds
for every cube the first point laid in it (time and index); a cube whose first point is not yet laid is empty at
that moment. Nothing is rebuilt per layer or per query, and a query at any moment sees exactly the material of
that moment (``scan``, in ``motion/scan.py``).
"""
from __future__ import annotations

from dataclasses import dataclass
from functools import lru_cache

import numpy as np

from neuralslicer.toolpath.types import Toolpaths
from neuralslicer.types import BoolArray, FloatArray, IndexArray

#: first key of a cube with no point
EMPTY = np.iinfo(np.int64).max
#: finest cube edge (mm) for parts of ordinary size; larger parts get larger cubes (at most MAX_CELLS cubes)
CELL_SIZE = 1.5
MAX_CELLS = 24_000_000
#: coarser levels above the finest
N_LEVELS = 5
#: points gathered at a time when a print's structure is built (bounds the gathers' temporaries)
BUILD_ROWS = 1 << 22


def rank_dtype(n_ranks: int) -> np.dtype:
    """The dtype of printing ranks up to ``n_ranks``: int32 where they fit (half the bytes), int64 beyond."""
    return np.dtype(np.int32 if n_ranks < np.iinfo(np.int32).max else np.int64)


@dataclass
class PrintedMaterial:
    """Material points in (cube, time) order with their cubes' lists and the pyramid of first points.

    columns : (3, m) float64, the points' x, y, z, sorted by (finest cube, time) (``points`` is its (m, 3) view);
    time : (m,) printing rank that laid each (int32 below 2**31 ranks: 8 bytes a bead where int64 took 16);
    start : (n_cubes + 1,) int64 where each finest cube's points begin; first[level] : flat int64 array over that
    level's cubes of ``time * stride + index`` of the first point laid in the cube (``EMPTY`` if none);
    top : (n_ranks + 1,) highest z of the points laid before each rank (-inf before any).
    """

    columns: FloatArray
    time: IndexArray
    origin: FloatArray
    cell: float
    dims: list[np.ndarray]
    start: IndexArray
    first: list[IndexArray]
    top: FloatArray
    stride: int
    n_ranks: int

    @classmethod
    def of_points(cls, points: FloatArray, time: IndexArray, n_ranks: int | None = None,
                  cell: float = CELL_SIZE) -> "PrintedMaterial":
        """The structure of points (m, 3) laid at ranks ``time`` (m,) (any order)."""
        points = np.asarray(points, np.float64).reshape(-1, 3)
        time = np.asarray(time, np.int64).reshape(-1)
        n_ranks = int(time.max(initial=-1)) + 1 if n_ranks is None else int(n_ranks)
        by_time = np.argsort(time, kind="stable")
        points, time = points[by_time], time[by_time]
        top = _top_by_rank(points, time, n_ranks)
        lo = points.min(axis=0) if len(points) else np.zeros(3)
        hi = points.max(axis=0) if len(points) else np.zeros(3)
        cell, origin, dims0 = _grid(lo, hi, cell)
        flat = _cube_keys([points[:, d] for d in range(3)], origin, cell, dims0)
        order = np.argsort(flat, kind="stable")          # time order kept within a cube
        counts = np.bincount(flat, minlength=int(np.prod(dims0)))
        columns = np.empty((3, len(points)))
        for d in range(3):
            np.take(points[:, d], order, out=columns[d])
        return cls._indexed(columns, time[order].astype(rank_dtype(n_ranks)), counts, origin, cell, dims0, top,
                            n_ranks)

    @classmethod
    def of_toolpaths(cls, tp: Toolpaths, cell: float = CELL_SIZE) -> "PrintedMaterial":
        """The beads of a print: top and bottom of every printing waypoint (``path >= 0``), laid at its rank.

        The same structure as ``of_points`` of the tops and bottoms, built without the (2n, 3) point arrays and
        their sorted copies (a tenth of a long print's memory): point ``2 r`` is the top of the ``r``-th printing
        waypoint, ``2 r + 1`` its bottom, so the ranks are sorted already and one stable sort by cube orders them."""
        on = np.flatnonzero(tp.path >= 0)
        m = 2 * len(on)
        lo, hi, top = np.zeros(3), np.zeros(3), np.full(len(on) + 1, -np.inf)
        for d in range(3):
            tops, bottoms = _bead_ends(tp, on, d)
            if len(on):
                lo[d], hi[d] = min(tops.min(), bottoms.min()), max(tops.max(), bottoms.max())
            if d == 2 and len(on):
                np.maximum(tops, bottoms, out=top[1:])
                np.maximum.accumulate(top, out=top)
        cell, origin, dims0 = _grid(lo, hi, cell)
        flat = np.zeros(m, np.int64)
        for d in range(3):                                   # the cube keys, coordinate by coordinate
            tops, bottoms = _bead_ends(tp, on, d)
            coord = np.empty(m)
            coord[0::2], coord[1::2] = tops, bottoms
            del tops, bottoms
            _add_axis_key(flat, coord, origin[d], cell, dims0, d)
            del coord
        order = np.argsort(flat, kind="stable")              # rank order (and top before bottom) kept within a cube
        counts = np.bincount(flat, minlength=int(np.prod(dims0)))
        del flat
        time = (order >> 1).astype(rank_dtype(len(on)))
        bottom = (order & 1).astype(bool)
        del order
        columns = np.empty((3, m))
        for a in range(0, m, BUILD_ROWS):                    # in blocks: the gathers' temporaries are a block's
            z = min(a + BUILD_ROWS, m)
            waypoint, low = on[time[a:z]], np.flatnonzero(bottom[a:z])
            for d in range(3):
                np.take(tp.xyz[:, d], waypoint, out=columns[d, a:z])
                columns[d, a + low] -= tp.thickness[waypoint[low]] * tp.axis[waypoint[low], d]
        del bottom
        return cls._indexed(columns, time, counts, origin, cell, dims0, top, len(on))

    @classmethod
    def _indexed(cls, columns: FloatArray, time: IndexArray, counts: IndexArray, origin: FloatArray, cell: float,
                 dims0: np.ndarray, top: FloatArray, n_ranks: int) -> "PrintedMaterial":
        """The structure of points (``columns``, ``time``) sorted by (cube, time), with their count per finest cube."""
        n_cells = len(counts)
        start = np.zeros(n_cells + 1, np.int64)
        np.cumsum(counts, out=start[1:])
        stride = max(columns.shape[1], 1)
        first0 = np.full(n_cells, EMPTY, np.int64)
        occupied = np.flatnonzero(counts)
        del counts
        first0[occupied] = time[start[occupied]].astype(np.int64) * stride + start[occupied]
        dims, first = [dims0], [first0]
        for _ in range(N_LEVELS):
            d, f = _pooled(first[-1].reshape(dims[-1]))
            dims.append(d)
            first.append(f)
        return cls(columns, time, origin, cell, dims, start, first, top, stride, n_ranks)

    @property
    def points(self) -> FloatArray:
        """The points (m, 3) in (cube, time) order."""
        return self.columns.T

    def printing_of(self, tp: Toolpaths) -> BoolArray:
        """The printing waypoints of ``tp`` (n,) (``path >= 0``), which must be as many as the ranks held here."""
        on = tp.path >= 0
        if int(on.sum()) != self.n_ranks:
            raise ValueError(f"the material holds {self.n_ranks} printing waypoints, the toolpaths {int(on.sum())}")
        return on

    def visible_at(self, tp: Toolpaths) -> IndexArray:
        """Per waypoint of ``tp`` (n,), the ranks it sees: the printing waypoints before it (``time < visible``), in
        the ranks' dtype."""
        on = self.printing_of(tp)
        visible = np.cumsum(on, dtype=rank_dtype(self.n_ranks))
        visible -= on
        return visible

    def cell_size(self, level: int) -> float:
        """Edge (mm) of a cube of ``level``."""
        return self.cell * 2 ** level

    def cube_of(self, xyz: FloatArray, level: int) -> IndexArray:
        """Integer cube coordinates (k, 3) of points at ``level`` (may lie outside the grid)."""
        return np.floor((xyz - self.origin) / self.cell_size(level)).astype(np.int64)

    def cube_centre(self, coords: IndexArray, level: int) -> FloatArray:
        """Centres (k, 3) of cubes."""
        return self.origin + (coords + 0.5) * self.cell_size(level)

    def stencil(self, radius: float, level: int) -> IndexArray:
        """Offsets (k, 3) of the cubes of ``level`` that can hold a point within ``radius`` of a point in cube 0."""
        return _stencil(round(radius / self.cell_size(level), 9))

    def prefix_end(self, cube: IndexArray, visible: IndexArray) -> IndexArray:
        """Per finest cube (k,), where its points laid before ``visible`` (k,) end (they begin at ``start[cube]``)."""
        lo, hi = self.start[cube].copy(), self.start[cube + 1].copy()
        done = (lo == hi) | (self.time[np.maximum(hi - 1, 0)] < visible)
        lo[done] = hi[done]
        todo = np.flatnonzero(~done)
        l, h, v = lo[todo], hi[todo], visible[todo]
        while len(todo):
            mid = (l + h) // 2
            before = self.time[mid] < v
            l = np.where(before, mid + 1, l)
            h = np.where(before, h, mid)
            open_ = l < h
            lo[todo[~open_]] = l[~open_]
            todo, l, h, v = todo[open_], l[open_], h[open_], v[open_]
        return lo

    def top_before(self, visible: IndexArray) -> FloatArray:
        """Highest z (k,) of the material laid before ``visible`` (-inf when none)."""
        return self.top[np.clip(visible, 0, self.n_ranks)]


def _bead_ends(tp: Toolpaths, on: IndexArray, d: int) -> tuple[FloatArray, FloatArray]:
    """Coordinate ``d`` of the tops (the waypoints ``on``) and of the bottoms (``thickness`` below along the axis)."""
    tops = tp.xyz[on, d]
    return tops, tops - tp.thickness[on] * tp.axis[on, d]


def _grid(lo: FloatArray, hi: FloatArray, cell: float) -> tuple[float, FloatArray, np.ndarray]:
    """(cube edge, origin, finest dims) of the grid over points within [lo, hi]: at most MAX_CELLS cubes, the dims a
    multiple of the coarsest level's block."""
    span = np.maximum(hi - lo, 1e-9)
    cell = max(cell, float(np.cbrt(np.prod(span + cell) / MAX_CELLS)))
    origin = lo - 0.5 * cell
    block = 2 ** N_LEVELS                              # every level's cubes split exactly into the next one's
    return cell, origin, -(-(np.floor(span / cell).astype(np.int64) + 2) // block) * block


def _add_axis_key(flat: IndexArray, coord: FloatArray, origin: float, cell: float, dims0: np.ndarray, d: int) -> None:
    """Fold coordinate ``d`` of the points into their flat cube keys (row-major over ``dims0``), in place."""
    if d:
        flat *= dims0[d]
    flat += np.floor((coord - origin) / cell).astype(np.int64)


def _cube_keys(coords: list[FloatArray], origin: FloatArray, cell: float, dims0: np.ndarray) -> IndexArray:
    """Flat finest-cube keys (m,) of points given by their coordinate arrays."""
    flat = np.zeros(len(coords[0]), np.int64)
    for d in range(3):
        _add_axis_key(flat, coords[d], origin[d], cell, dims0, d)
    return flat


def _pooled(first: np.ndarray) -> tuple[np.ndarray, IndexArray]:
    """The next coarser level: per 2x2x2 block the smallest first key; (dims, flat keys)."""
    a, b, c = (s // 2 for s in first.shape)
    pooled = first.reshape(a, 2, b, 2, c, 2).min(axis=(1, 3, 5))
    return np.array(pooled.shape, np.int64), pooled.reshape(-1)


def _top_by_rank(points: FloatArray, time: IndexArray, n_ranks: int) -> FloatArray:
    """Highest z of the points (sorted by time) laid before each rank 0..n_ranks (-inf before any)."""
    zmax = np.full(n_ranks + 1, -np.inf)
    if len(points):
        first = np.flatnonzero(np.r_[True, time[1:] != time[:-1]])
        zmax[time[first] + 1] = np.maximum.reduceat(points[:, 2], first)
    return np.maximum.accumulate(zmax)


@lru_cache(maxsize=64)
def _stencil(radius_cells: float) -> IndexArray:
    """Offsets of the unit cubes whose box lies within ``radius_cells`` of the unit cube at the origin."""
    k = int(np.ceil(radius_cells)) + 1
    r = np.arange(-k, k + 1)
    o = np.stack(np.meshgrid(r, r, r, indexing="ij"), -1).reshape(-1, 3)
    gap = np.maximum(np.abs(o) - 1, 0).astype(np.float64)
    return o[np.einsum("ij,ij->i", gap, gap) <= radius_cells ** 2 * (1 + 1e-12) + 1e-12]
