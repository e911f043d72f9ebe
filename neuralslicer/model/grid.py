"""Implicit functions on grids: narrow-band sampling, marching cubes, projection onto ``H = 0``.

Sampling ``H`` on a fine grid is the cost of surface extraction (a mesh distance query is ~1 µs).
:func:`narrow_band_grid` evaluates ``H`` exactly only in blocks that can hold the surface: it samples a
coarse grid first, and a block whose corner value ``|H(c)|`` exceeds ``L`` times the block diagonal
(``L`` a Lipschitz bound of ``H``) provably has the sign of ``H(c)`` everywhere, so its nodes get that
sign without evaluation. Marching cubes only needs signs away from the surface, so the extracted
surface equals the one from the full grid.
"""
from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass

import numpy as np

from neuralslicer.types import FloatArray, IndexArray

ValueFn = Callable[[FloatArray], FloatArray]
ValueGradFn = Callable[[FloatArray], tuple[FloatArray, FloatArray]]


@dataclass
class GridSamples:
    """``H`` on a regular grid: node ``(i, j, k)`` is at ``origin + spacing * (i, j, k)``."""

    values: FloatArray          # (nx, ny, nz)
    origin: FloatArray          # (3,)
    spacing: float
    exact: np.ndarray           # (nx, ny, nz) bool: evaluated (True) or sign-certified (False)

    def points(self, index: IndexArray) -> FloatArray:
        """Positions (n, 3) of node indices (n, 3)."""
        return self.origin + self.spacing * np.asarray(index, dtype=np.float64)


def grid_shape(lo: FloatArray, hi: FloatArray, spacing: float, block: int = 1) -> tuple[int, int, int]:
    """Node counts per axis covering ``[lo, hi]``, with ``count - 1`` a multiple of ``block``."""
    cells = np.maximum(1, np.ceil((np.asarray(hi) - np.asarray(lo)) / spacing - 1e-9)).astype(int)
    cells = block * np.ceil(cells / block).astype(int)
    return tuple(int(c) + 1 for c in cells)


def narrow_band_grid(fn: ValueFn, lo: FloatArray, hi: FloatArray, spacing: float, lipschitz: float = 1.0,
                     block: int = 8) -> GridSamples:
    """Sample ``fn`` on a grid over ``[lo, hi]``, exactly wherever the zero set can pass.

    Parameters
    ----------
    fn : callable
        ``(n, 3) float64 -> (n,) float64``.
    lo, hi : (3,) float64
        The box to cover; the grid may extend past ``hi`` by up to one block.
    spacing : float
        Node spacing.
    lipschitz : float
        Upper bound of ``|∇fn|``; too small a value can drop thin parts, too large only costs time.
    block : int
        Coarse block size in cells.
    """
    lo = np.asarray(lo, dtype=np.float64)
    shape = np.array(grid_shape(lo, hi, spacing, block))
    nb = (shape - 1) // block
    coarse_idx = np.stack(np.meshgrid(*[np.arange(n + 1) for n in nb], indexing="ij"), -1).reshape(-1, 3)
    coarse = fn(lo + spacing * block * coarse_idx).reshape(tuple(nb + 1))
    # per block: the corner with the largest |H| certifies the block's sign when |H| > L * diagonal
    corners = np.stack([coarse[i:i + nb[0], j:j + nb[1], k:k + nb[2]]
                        for i in (0, 1) for j in (0, 1) for k in (0, 1)], -1)
    strongest = np.take_along_axis(corners, np.abs(corners).argmax(-1)[..., None], -1)[..., 0]
    diagonal = spacing * block * np.sqrt(3.0)
    far = np.abs(strongest) > lipschitz * diagonal
    # fine cells inherit their block's state; a node is exact if any cell around it is near
    near_cells = np.repeat(np.repeat(np.repeat(~far, block, 0), block, 1), block, 2)
    padded = np.pad(near_cells, 1)
    exact = np.zeros(tuple(shape), dtype=bool)
    for i in (0, 1):
        for j in (0, 1):
            for k in (0, 1):
                exact |= padded[i:i + shape[0], j:j + shape[1], k:k + shape[2]]
    fill = np.where(strongest > 0, 1.0, -1.0) * lipschitz * diagonal
    values = np.repeat(np.repeat(np.repeat(fill, block, 0), block, 1), block, 2)
    values = np.pad(values, ((0, 1), (0, 1), (0, 1)), mode="edge")
    idx = np.argwhere(exact)
    if len(idx):
        values[exact] = fn(lo + spacing * idx)
    return GridSamples(values=values, origin=lo, spacing=float(spacing), exact=exact)


def inside_bounds(fn: ValueFn, lo_hi: FloatArray, spacing: float, lipschitz: float = 1.0) -> FloatArray:
    """Tight box (2, 3) of ``{fn <= 0}`` inside the box ``lo_hi``, padded by one grid spacing."""
    lo, hi = np.asarray(lo_hi, dtype=np.float64)
    extent = float((hi - lo).max())
    spacing = max(spacing, extent / 512)
    grid = narrow_band_grid(fn, lo, hi, spacing, lipschitz)
    inside = np.argwhere(grid.values <= 0)
    if len(inside) == 0:
        raise ValueError("the implicit function is positive everywhere in its search box")
    return np.stack([grid.points(inside.min(0)) - spacing, grid.points(inside.max(0)) + spacing])


#: cubes of the bounding box :func:`values_above` bins the points in (their centres are evaluated exactly)
ABOVE_CUBES = 250_000
#: fewer points than this are all evaluated (the cubes would cost more than they save)
ABOVE_DIRECT = 100_000
#: points whose bounds are made at a time
ABOVE_BLOCK = 1 << 18


def values_above(fn: ValueFn, points: FloatArray, tol: float, lipschitz: float = 1.0) -> tuple[int, float]:
    """How many of the points (n, 3) have ``fn > tol``, and the largest value of ``fn`` at them (-inf for none),
    exactly, with ``fn`` evaluated only where a cube's centre cannot certify the answer.

    The points are binned in about ``ABOVE_CUBES`` cubes of their bounding box and ``fn`` is evaluated at the
    centre ``c`` of every cube that holds one; ``fn(x) <= fn(c) + L |x - c|`` (``L = lipschitz``, 1 for a signed
    distance, as in the layers' trim), so a point whose bound is at most ``tol`` is not counted, and only the
    others are evaluated. The largest value is the largest evaluated one once every point left has a bound below
    it (those that do not are evaluated too). On a 10.4M-waypoint print of the 200 mm bunny: 4.1 s against 23 s
    for ``fn`` at every point, 5 % of the points evaluated."""
    x = np.ascontiguousarray(points, dtype=np.float64).reshape(-1, 3)
    if len(x) < ABOVE_DIRECT:
        h = np.asarray(fn(x), np.float64)
        return int((h > tol).sum()), float(h.max(initial=-np.inf))
    lo, hi = x.min(axis=0), x.max(axis=0)
    span = np.maximum(hi - lo, 1e-9)
    size = float(np.cbrt(np.prod(span) / ABOVE_CUBES))
    dims = np.floor(span / size).astype(np.int64) + 1
    flat = np.zeros(len(x), np.int64)                           # the cube of each point, row-major over dims
    for axis in range(3):
        if axis:
            flat *= dims[axis]
        flat += np.floor((x[:, axis] - lo[axis]) / size).astype(np.int64)
    held = np.zeros(int(np.prod(dims)), bool)
    held[flat] = True
    cubes = np.flatnonzero(held)
    rank = np.cumsum(held) - 1                                  # the row of each held cube among ``cubes``
    centres = lo + (np.stack(np.unravel_index(cubes, dims), axis=1) + 0.5) * size
    at_centre = np.asarray(fn(centres), np.float64)
    upper = np.empty(len(x))
    for a in range(0, len(x), ABOVE_BLOCK):                     # in blocks: the (n, 3) offsets of a long print
        row = rank[flat[a:a + ABOVE_BLOCK]]
        d = x[a:a + ABOVE_BLOCK] - centres[row]
        upper[a:a + ABOVE_BLOCK] = at_centre[row] + lipschitz * np.sqrt(np.einsum("ij,ij->i", d, d))
    del flat
    near = np.flatnonzero(upper > tol)
    h = np.asarray(fn(x[near]), np.float64)
    best = float(h.max(initial=-np.inf))
    rest = np.flatnonzero((upper <= tol) & (upper > best))    # bounds above the largest value found: evaluate them
    if len(rest):
        best = max(best, float(np.asarray(fn(x[rest]), np.float64).max()))
    return int((h > tol).sum()), best


def level_set_mesh(values: np.ndarray, origin: FloatArray, spacing: float, level: float = 0.0,
                   allow_degenerate: bool = False) -> tuple[FloatArray, IndexArray]:
    """Marching cubes of ``values == level`` on a regular grid (node ``i, j, k`` at ``origin + spacing ·
    (i, j, k)``): vertices (n, 3) float64 and faces (m, 3) int64 wound so that normals point toward
    larger values (outward for H)."""
    from skimage.measure import marching_cubes

    verts, faces, _, _ = marching_cubes(values, level=level, spacing=(spacing,) * 3,
                                        allow_degenerate=allow_degenerate)
    verts = np.asarray(verts, dtype=np.float64) + origin
    faces = faces.astype(np.int64)
    a, b, c = (verts[faces[:, i]] for i in range(3))
    if np.einsum("ij,ij->i", a, np.cross(b, c)).sum() < 0:  # signed volume: outward winding
        faces = faces[:, ::-1].copy()
    return verts, faces


def zero_level_mesh(grid: GridSamples) -> tuple[FloatArray, IndexArray]:
    """Marching cubes of ``H = 0``: vertices (n, 3), faces (m, 3) wound so that normals point outward."""
    if not (grid.values.min() < 0 < grid.values.max()):
        raise ValueError("the grid does not cross H = 0")
    return level_set_mesh(grid.values, grid.origin, grid.spacing)


def project_to_zero(fn: ValueGradFn, points: FloatArray, max_step: float, tolerance: float,
                    iterations: int = 20) -> tuple[FloatArray, FloatArray, FloatArray]:
    """Newton steps ``x -= H ∇H / |∇H|²`` (each at most ``max_step`` long) until ``|H| <= tolerance``.

    Returns the projected points (n, 3), ``H`` (n,) and ``∇H`` (n, 3) there. Points that do not reach
    the tolerance keep their last position; the caller decides what to do with them.
    """
    x = np.array(points, dtype=np.float64, copy=True).reshape(-1, 3)
    h, g = fn(x)
    todo = np.flatnonzero(np.abs(h) > tolerance)
    for _ in range(iterations):
        if len(todo) == 0:
            break
        gg = np.einsum("ij,ij->i", g[todo], g[todo])
        step = -(h[todo] / np.maximum(gg, 1e-300))[:, None] * g[todo]
        length = np.linalg.norm(step, axis=1)
        step *= np.minimum(1.0, max_step / np.maximum(length, 1e-300))[:, None]
        x[todo] += step
        h[todo], g[todo] = fn(x[todo])
        todo = todo[np.abs(h[todo]) > tolerance]
    return x, h, g
