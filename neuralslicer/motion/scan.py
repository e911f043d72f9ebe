"""Exact queries of one part of the print head (the cone or the holder) against the printed material.

For every pose the cubes of the material pyramid (``PrintedMaterial``) that can meet the part's enclosing ball
are fetched from a coarse level by a fixed stencil; a cube whose first point is not yet laid at that pose is
empty and dropped, one whose bounding ball lies in the part (the part's exact signed distance at its centre
below minus its half diagonal) is a hit with that first point as witness, one whose ball lies outside is dropped,
and the others are split into their eight children one level finer. On the finest level the points of the cubes
left, those laid before the pose (a prefix of each cube's list), are tested one by one with the part's exact
membership rule. With a ``margin`` the scan also returns a lower bound on the distance from the part to the
material, capped at the margin (cubes within the margin are split until their bound is tight enough).

Poses are processed in chunks, in parallel threads: each pose's walk is compiled (``motion/scan_kernel.py``) and
releases the GIL.
"""
from __future__ import annotations

import os
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass

import numpy as np

from neuralslicer.motion.head import Rule, cone_ball, cone_bottom, cone_rule, holder_ball, holder_rule, in_rule
from neuralslicer.motion.material import PrintedMaterial
from neuralslicer.motion.profile import Nozzle
from neuralslicer.types import BoolArray, FloatArray, IndexArray

#: poses per chunk of work (one call of the compiled scan)
CHUNK = 2048
#: worker threads (None: the cores this process may use)
WORKERS: int | None = None


@dataclass(frozen=True)
class HeadPart:
    """A part of the head as a scan sees it: its enclosing ball on the axis, the half-planes that bound it in the
    (h, radial) half-plane (``bound``: the largest of their signed distances, the exact signed distance inside
    and a lower bound on the distance outside) and its exact membership rule."""

    centre: float
    radius: float
    #: per half-plane (a, b, c): signed distance a h + b radial + c
    planes: tuple[tuple[float, float, float], ...]
    #: its exact membership rule (``head.Rule``: ``cone_rule``, ``holder_rule``)
    rule: Rule
    #: level of the pyramid the scan starts on
    top_level: int

    def inside(self, h: FloatArray, radial: FloatArray) -> BoolArray:
        """The exact membership rule (k,) at heights ``h`` along the axis and distances ``radial`` from it."""
        return in_rule(h, radial, self.rule)

    def bound(self, h: FloatArray, radial: FloatArray) -> FloatArray:
        """Largest signed half-plane distance (k,): < 0 exactly inside, a lower bound on the distance outside."""
        out = None
        for a, b, c in self.planes:
            v = a * h + c if b == 0 else (b * radial + c if a == 0 else a * h + b * radial + c)
            out = v if out is None else np.maximum(out, v)
        return out

    @classmethod
    def cone(cls, nozzle: Nozzle, min_height: float, material: PrintedMaterial) -> "HeadPart":
        """The cone above ``min_height``: above its bottom, below its top, inside its side."""
        c, r = cone_ball(nozzle, min_height)
        m, L = cone_bottom(nozzle, min_height), nozzle.cone_length
        al = np.radians(nozzle.cone_half_angle_deg)
        planes = ((-1.0, 0.0, m), (1.0, 0.0, -L), (-float(np.sin(al)), float(np.cos(al)), 0.0))
        return cls(c, r, planes, cone_rule(nozzle, min_height), _level_for(material, r, 1.7))

    @classmethod
    def holder(cls, nozzle: Nozzle, material: PrintedMaterial) -> "HeadPart":
        """The holder cylinder: above the cone, below its top, within its radius."""
        c, r = holder_ball(nozzle)
        L = nozzle.cone_length
        planes = ((-1.0, 0.0, L), (1.0, 0.0, -(L + nozzle.holder_length)), (0.0, 1.0, -nozzle.holder_radius))
        return cls(c, r, planes, holder_rule(nozzle), _level_for(material, r, 0.9))


def _level_for(material: PrintedMaterial, radius: float, cubes: float) -> int:
    """The level whose cube edge is closest to ``radius / cubes`` (measured best: 1.7 for the cone, a stencil of
    117 cubes, and 0.9 for the wide holder, a stencil of 27 to 57 cubes)."""
    return int(np.clip(np.round(np.log2(max(radius, 1e-9) / (cubes * material.cell))), 0, len(material.dims) - 1))


def workers() -> int:
    """Threads for the scans: ``WORKERS`` or the cores this process may use."""
    if WORKERS:
        return WORKERS
    try:
        return max(1, len(os.sched_getaffinity(0)))
    except AttributeError:  # pragma: no cover - not Linux
        return max(1, os.cpu_count() or 1)


def scan(material: PrintedMaterial, part: HeadPart, tips: FloatArray, axes: FloatArray, visible: IndexArray,
         margin: float = 0.0) -> tuple[BoolArray, IndexArray, FloatArray]:
    """Per pose (tips (n, 3), unit axes (n, 3), seeing the material laid before ``visible`` (n,)): whether the
    part holds material, a witness (index into ``material.points``, -1 if none) and, with ``margin`` > 0, a lower
    bound on the distance from the part to the material, at most ``margin`` (-inf where hit)."""
    n = len(tips)
    hit, witness, clear = np.zeros(n, bool), np.full(n, -1, np.int64), np.full(n, float(margin))
    if n == 0:
        return hit, witness, clear
    from neuralslicer.motion.scan_kernel import scan_poses    # numba (~70 MB) only in the processes that scan

    tips, axes = np.ascontiguousarray(tips, np.float64), np.ascontiguousarray(axes, np.float64)
    visible = np.ascontiguousarray(visible)
    grid = _Pyramid.of(material, part, margin)
    chunks = [slice(i, min(i + CHUNK, n)) for i in range(0, n, CHUNK)]

    def run(sl: slice) -> None:
        """Scan one chunk into its rows of the results."""
        centre = material.cube_of(tips[sl] + part.centre * axes[sl], part.top_level)
        scan_poses(grid.first, grid.dims, grid.cell_sizes, grid.radii, material.origin, material.stride,
                   material.start, material.time, material.columns, centre, grid.offsets, part.top_level, tips[sl],
                   axes[sl], visible[sl], grid.planes, grid.rule, float(margin), hit[sl], witness[sl], clear[sl])

    if len(chunks) == 1 or workers() == 1:
        for sl in chunks:
            run(sl)
    else:
        with ThreadPoolExecutor(workers()) as pool:
            list(pool.map(run, chunks))
    return hit, witness, clear


@dataclass(frozen=True)
class _Pyramid:
    """What the compiled scan reads besides the material's arrays: the levels' first keys and dims, the cubes' edges
    and half diagonals (with the margin of the classification's rounding), the top level's stencil and the part."""

    first: tuple[IndexArray, ...]
    dims: IndexArray
    cell_sizes: FloatArray
    radii: FloatArray
    offsets: IndexArray
    planes: FloatArray
    rule: FloatArray

    @classmethod
    def of(cls, material: PrintedMaterial, part: HeadPart, margin: float) -> "_Pyramid":
        """The scan's view of ``material`` for ``part`` within ``margin``."""
        sizes = np.array([material.cell_size(level) for level in range(len(material.dims))])
        radii = np.array([0.5 * np.sqrt(3.0) * s * (1 + 1e-9) + 1e-9 for s in sizes])
        return cls(tuple(np.ascontiguousarray(f, np.int64) for f in material.first),
                   np.array(material.dims, np.int64), sizes, radii,
                   np.ascontiguousarray(material.stencil(part.radius + margin, part.top_level), np.int64),
                   np.array(part.planes, np.float64).reshape(-1, 3), np.array(part.rule, np.float64))
