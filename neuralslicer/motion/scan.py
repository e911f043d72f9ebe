"""Exact queries of one part of the print head (the cone or the holder) against the printed material.

For every pose the cubes of the material pyramid (``PrintedMaterial``) that can meet the part's enclosing ball
are fetched from a coarse level by a fixed stencil; a cube whose first point is not yet laid at that pose is
empty and dropped, one whose bounding ball lies in the part (the part's exact signed distance at its centre
below minus its half diagonal) is a hit with that first point as witness, one whose ball lies outside is dropped,
and the others are split into their eight children one level finer. On the finest level the points of the cubes
left, those laid before the pose (a prefix of each cube's list), are tested one by one with the part's exact
membership rule. With a ``margin`` the scan also returns a lower bound on the distance from the part to the
material, capped at the margin (cubes within the margin are split until their bound is tight enough).

Poses are processed in chunks, in parallel threads (numpy releases the GIL in the work that counts).
"""
from __future__ import annotations

import os
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass
from typing import Callable

import numpy as np

from neuralslicer.motion.head import cone_ball, cone_bottom, holder_ball, in_cone, in_holder
from neuralslicer.motion.material import PrintedMaterial
from neuralslicer.motion.profile import Nozzle
from neuralslicer.types import BoolArray, FloatArray, IndexArray

#: poses per chunk of work (bounds the memory of the cube pairs)
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
    inside: Callable[[FloatArray, FloatArray], BoolArray]
    #: level of the pyramid the scan starts on
    top_level: int

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
        return cls(c, r, planes, lambda h, rho: in_cone(h, rho, nozzle, min_height), _level_for(material, r, 1.7))

    @classmethod
    def holder(cls, nozzle: Nozzle, material: PrintedMaterial) -> "HeadPart":
        """The holder cylinder: above the cone, below its top, within its radius."""
        c, r = holder_ball(nozzle)
        L = nozzle.cone_length
        planes = ((-1.0, 0.0, L), (1.0, 0.0, -(L + nozzle.holder_length)), (0.0, 1.0, -nozzle.holder_radius))
        return cls(c, r, planes, lambda h, rho: in_holder(h, rho, nozzle), _level_for(material, r, 0.9))


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
    chunks = [slice(i, min(i + CHUNK, n)) for i in range(0, n, CHUNK)]

    def run(sl: slice) -> None:
        """Scan one chunk into its rows of the results."""
        hit[sl], witness[sl], clear[sl] = _scan_chunk(material, part, tips[sl], axes[sl], visible[sl], margin)

    if len(chunks) == 1 or workers() == 1:
        for sl in chunks:
            run(sl)
    else:
        with ThreadPoolExecutor(workers()) as pool:
            list(pool.map(run, chunks))
    return hit, witness, clear


def _flat(material: PrintedMaterial, level: int, i: IndexArray, j: IndexArray, k: IndexArray) -> IndexArray:
    """Flat index of cube coordinates at a level."""
    d = material.dims[level]
    return (i * d[1] + j) * d[2] + k


def _coords(material: PrintedMaterial, level: int, flat: IndexArray) -> tuple[IndexArray, IndexArray, IndexArray]:
    """Cube coordinates of flat indices at a level."""
    d = material.dims[level]
    k = flat % d[2]
    rest = flat // d[2]
    return rest // d[1], rest % d[1], k


def _first_pairs(material: PrintedMaterial, part: HeadPart, tips: FloatArray, axes: FloatArray, margin: float
                 ) -> tuple[IndexArray, IndexArray]:
    """The (pose, flat cube) pairs of the part's top-level stencil that lie in the grid."""
    level = part.top_level
    offsets = material.stencil(part.radius + margin, level)
    centre = material.cube_of(tips + part.centre * axes, level)
    ext = np.abs(offsets).max(axis=0)
    dims = material.dims[level]
    inner = np.all((centre >= ext) & (centre < dims - ext), axis=1)
    far = np.any((centre < -ext) | (centre >= dims + ext), axis=1)
    pose_in = np.flatnonzero(inner)
    off = _flat(material, level, *offsets.T)
    pose = [np.repeat(pose_in, len(off))]
    flat = [(_flat(material, level, *centre[pose_in].T)[:, None] + off[None, :]).reshape(-1)]
    edge = np.flatnonzero(~inner & ~far)
    if len(edge):
        cube = (centre[edge][:, None, :] + offsets[None, :, :]).reshape(-1, 3)
        ok = np.all((cube >= 0) & (cube < dims), axis=1)
        pose.append(np.repeat(edge, len(offsets))[ok])
        flat.append(_flat(material, level, *cube[ok].T))
    return np.concatenate(pose), np.concatenate(flat)


def _scan_chunk(material: PrintedMaterial, part: HeadPart, tips: FloatArray, axes: FloatArray, visible: IndexArray,
                margin: float) -> tuple[BoolArray, IndexArray, FloatArray]:
    """``scan`` of one chunk of poses, level by level from the part's top level down to the points."""
    n = len(tips)
    hit, witness, clear = np.zeros(n, bool), np.full(n, -1, np.int64), np.full(n, float(margin))
    seen = visible.astype(np.int64) * material.stride
    shift = [material.origin[c] - tips[:, c] for c in range(3)]          # per pose: cube centre - tip = this + ...
    ax = [np.ascontiguousarray(axes[:, c]) for c in range(3)]
    level = part.top_level
    pose, flat = _first_pairs(material, part, tips, axes, margin)
    while len(pose):
        key = material.first[level][flat]
        laid = (key < seen[pose]) & ~hit[pose]
        pose, flat, key = pose[laid], flat[laid], key[laid]
        s = material.cell_size(level)
        i, j, k = _coords(material, level, flat)
        d = [(c + 0.5) * s + shift[q][pose] for q, c in enumerate((i, j, k))]
        h = d[0] * ax[0][pose] + d[1] * ax[1][pose] + d[2] * ax[2][pose]
        rho = np.sqrt(np.maximum(d[0] * d[0] + d[1] * d[1] + d[2] * d[2] - h * h, 0.0))
        split = _classify(material, part, level, pose, key, part.bound(h, rho), hit, witness, clear, margin)
        pose, i, j, k = pose[split], i[split], j[split], k[split]
        if level == 0:
            _test_points(material, part, pose, _flat(material, 0, i, j, k), tips, axes, visible, hit, witness,
                         clear, margin)
            break
        level -= 1
        base = _flat(material, level, 2 * i, 2 * j, 2 * k)
        pose = np.repeat(pose, 8)
        flat = (base[:, None] + _flat(material, level, *_CHILDREN.T)[None, :]).reshape(-1)
    clear[hit] = -np.inf
    return hit, witness, clear


#: the eight children of a cube, as offsets of twice its coordinates
_CHILDREN = np.stack(np.meshgrid([0, 1], [0, 1], [0, 1], indexing="ij"), -1).reshape(-1, 3)


def _classify(material: PrintedMaterial, part: HeadPart, level: int, pose: IndexArray, key: IndexArray,
              sd: FloatArray, hit: BoolArray, witness: IndexArray, clear: FloatArray, margin: float) -> BoolArray:
    """Mark the poses with a cube wholly inside the part (``sd``: the part's bound at the cube centres), lower their
    clearance by the cubes wholly outside it; the pairs to split (or, on the finest level, to test point by point)."""
    r = 0.5 * np.sqrt(3.0) * material.cell_size(level) * (1 + 1e-9) + 1e-9
    full = sd < -r
    if full.any():
        _mark(hit, witness, pose[full], key[full] % material.stride)
    outside = sd > r
    if margin > 0:
        near = outside & (sd - r < margin)
        if level > 0:                     # a cube within the margin gives a weak bound: split it instead
            outside &= ~near | (sd - r > 0.5 * margin)
            near &= outside
        np.minimum.at(clear, pose[near], sd[near] - r)
    return ~full & ~outside


def _mark(hit: BoolArray, witness: IndexArray, pose: IndexArray, point: IndexArray) -> None:
    """Mark the poses not hit yet among ``pose`` (k,), each with its first witness point."""
    first = np.unique(pose, return_index=True)[1]
    new = ~hit[pose[first]]
    hit[pose[first][new]] = True
    witness[pose[first][new]] = point[first][new]


def _test_points(material: PrintedMaterial, part: HeadPart, pose: IndexArray, flat: IndexArray, tips: FloatArray,
                 axes: FloatArray, visible: IndexArray, hit: BoolArray, witness: IndexArray, clear: FloatArray,
                 margin: float) -> None:
    """The exact test of the points laid before each pose in the finest cubes left (hits and clearances in place)."""
    keep = ~hit[pose]
    pose, flat = pose[keep], flat[keep]
    if not len(pose):
        return
    lo = material.start[flat]
    count = material.prefix_end(flat, visible[pose]) - lo
    total = int(count.sum())
    if not total:
        return
    point = np.repeat(lo - (np.cumsum(count) - count), count) + np.arange(total)
    p_pose = np.repeat(pose, count)
    d = [material.columns[c][point] - tips[:, c][p_pose] for c in range(3)]
    a = [axes[:, c][p_pose] for c in range(3)]
    h = d[0] * a[0] + d[1] * a[1] + d[2] * a[2]
    rho = np.sqrt(np.maximum(d[0] * d[0] + d[1] * d[1] + d[2] * d[2] - h * h, 0.0))
    inside = part.inside(h, rho)
    if inside.any():
        _mark(hit, witness, p_pose[inside], point[inside])
    if margin > 0:
        out = ~inside
        np.minimum.at(clear, p_pose[out], part.bound(h[out], rho[out]))
