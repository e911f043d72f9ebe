"""The scan's traversal of the material pyramid, pose by pose, compiled with numba (``motion/scan.py`` says what it
computes).

Each pose walks its own cubes level by level, in the order the level-by-level numpy scan this replaced kept them
(the top level's stencil order, then each split cube's eight children with their offsets in (i, j, k) order), so
its answer is that scan's: the first cube wholly inside the part at the coarsest level that has one, else the
first point inside the part in that order, as the witness. Every float is computed with the same operations in the
same order as that scan did (numba neither fuses nor reorders them without ``fastmath``), so the bounds and
clearances are the same bits. A pose stops at its first hit; the clearance of a hit pose is -inf either way.

Why numba: the numpy scan built some thirty temporary arrays per level for every (pose, cube) pair; the compiled
walk keeps one pose's cubes in three small buffers, releases the GIL (the scan's threads run it in parallel), and
checks the 200 mm bunny's first 10M waypoints in 14 s where the numpy scan took 49 s (docs/performance.md).
"""
from __future__ import annotations

import numba
import numpy as np


@numba.njit(nogil=True, cache=True, error_model="numpy")
def _bound(h: float, rho: float, planes: np.ndarray) -> float:
    """The part's half-plane bound at (h, rho): as ``HeadPart.bound`` computes it."""
    out = 0.0
    for q in range(planes.shape[0]):
        a, b, c = planes[q, 0], planes[q, 1], planes[q, 2]
        if b == 0:
            v = a * h + c
        elif a == 0:
            v = b * rho + c
        else:
            v = a * h + b * rho + c
        out = v if q == 0 else max(out, v)
    return out


@numba.njit(nogil=True, cache=True, error_model="numpy")
def _within_heights(h: float, rule: np.ndarray) -> bool:
    """The height part of a part's membership rule (``head.Rule``, as ``head.in_rule`` reads it)."""
    return (h > rule[0] if rule[1] != 0.0 else h >= rule[0]) and h <= rule[2]


@numba.njit(nogil=True, cache=True, error_model="numpy")
def _inside(h: float, rho: float, rule: np.ndarray) -> bool:
    """The part's membership rule: within its heights (``_within_heights``) and rho at most slope * h + radius."""
    return _within_heights(h, rule) and rho <= h * rule[3] + rule[4]


@numba.njit(nogil=True, cache=True, error_model="numpy")
def _prefix_end(time: np.ndarray, lo: int, hi: int, visible: int) -> int:
    """Where the points of a cube (``lo:hi``, sorted by time) laid before ``visible`` end."""
    if lo == hi or time[hi - 1] < visible:
        return hi
    while lo < hi:
        mid = (lo + hi) // 2
        if time[mid] < visible:
            lo = mid + 1
        else:
            hi = mid
    return lo


@numba.njit(nogil=True, cache=True, error_model="numpy")
def scan_poses(first: tuple, dims: np.ndarray, cell_sizes: np.ndarray, radii: np.ndarray, origin: np.ndarray,
               stride: int, start: np.ndarray, time: np.ndarray, columns: np.ndarray, centre: np.ndarray,
               offsets: np.ndarray, top_level: int, tips: np.ndarray, axes: np.ndarray, visible: np.ndarray,
               planes: np.ndarray, rule: np.ndarray, margin: float, hit: np.ndarray, witness: np.ndarray,
               clear: np.ndarray) -> None:
    """Scan the poses (tips, axes (n, 3), ``visible`` (n,)) whose part's enclosing ball has its centre in the
    top-level cubes ``centre`` (n, 3): ``hit``, ``witness`` and ``clear`` (n,) are written. The cubes are carried
    as integer coordinates (a flat index is two multiply-adds away; decoding one took four integer divisions)."""
    # the buffers grow between levels, never inside a loop over cubes (a reallocation there slowed it twentyfold)
    cap = max(1024, 8 * offsets.shape[0])
    cubes, nxt, finest = np.empty((cap, 3), np.int64), np.empty((cap, 3), np.int64), np.empty(cap, np.int64)
    for p in range(tips.shape[0]):
        seen = np.int64(visible[p]) * stride
        shift0, shift1, shift2 = origin[0] - tips[p, 0], origin[1] - tips[p, 1], origin[2] - tips[p, 2]
        a0, a1, a2 = axes[p, 0], axes[p, 1], axes[p, 2]
        best = margin
        found = -1
        level = top_level
        n = 0
        for o in range(offsets.shape[0]):
            i, j, k = centre[p, 0] + offsets[o, 0], centre[p, 1] + offsets[o, 1], centre[p, 2] + offsets[o, 2]
            if 0 <= i < dims[level, 0] and 0 <= j < dims[level, 1] and 0 <= k < dims[level, 2]:
                cubes[n, 0], cubes[n, 1], cubes[n, 2] = i, j, k
                n += 1
        while n > 0:
            f = first[level]
            s, r = cell_sizes[level], radii[level]
            d1, d2 = dims[level, 1], dims[level, 2]
            if 8 * n > cap:                          # room for every cube's children
                cap = 8 * n
                cubes, nxt, finest = _grown(cubes, cap), np.empty((cap, 3), np.int64), np.empty(cap, np.int64)
            m = 0
            for q in range(n):
                i, j, k = cubes[q, 0], cubes[q, 1], cubes[q, 2]
                flat = (i * d1 + j) * d2 + k
                key = f[flat]
                if not key < seen:
                    continue
                x = (i + 0.5) * s + shift0
                y = (j + 0.5) * s + shift1
                z = (k + 0.5) * s + shift2
                h = x * a0 + y * a1 + z * a2
                rho = np.sqrt(max(x * x + y * y + z * z - h * h, 0.0))
                sd = _bound(h, rho, planes)
                if sd < -r:
                    found = key % stride
                    break
                outside = sd > r
                if margin > 0:
                    near = outside and sd - r < margin
                    if level > 0:
                        outside = outside and (not near or sd - r > 0.5 * margin)
                        near = near and outside
                    if near:
                        best = min(best, sd - r)
                if outside:
                    continue
                if level == 0:
                    finest[m] = flat
                    m += 1
                    continue
                for ci in range(2):
                    for cj in range(2):
                        for ck in range(2):
                            nxt[m, 0], nxt[m, 1], nxt[m, 2] = 2 * i + ci, 2 * j + cj, 2 * k + ck
                            m += 1
            if found >= 0:
                break
            if level == 0:
                found, best = _test_points(start, time, columns, finest, m, visible[p], tips[p], a0, a1, a2, planes,
                                           rule, margin, best)
                break
            cubes, nxt = nxt, cubes
            n = m
            level -= 1
        if found >= 0:
            hit[p], witness[p], clear[p] = True, found, -np.inf
        else:
            clear[p] = best


@numba.njit(nogil=True, cache=True, error_model="numpy")
def _test_points(start: np.ndarray, time: np.ndarray, columns: np.ndarray, cubes: np.ndarray, n: int, visible: int,
                 tip: np.ndarray, a0: float, a1: float, a2: float, planes: np.ndarray, rule: np.ndarray, margin: float,
                 best: float) -> tuple:
    """(witness or -1, clearance) of one pose over the points laid before ``visible`` in its finest cubes left."""
    for q in range(n):
        lo = start[cubes[q]]
        end = _prefix_end(time, lo, start[cubes[q] + 1], visible)
        for pt in range(lo, end):
            x = columns[0, pt] - tip[0]
            y = columns[1, pt] - tip[1]
            z = columns[2, pt] - tip[2]
            h = x * a0 + y * a1 + z * a2
            if margin <= 0 and not _within_heights(h, rule):
                continue                      # most points near the tip lie below the part: no radial distance
            rho = np.sqrt(max(x * x + y * y + z * z - h * h, 0.0))
            if _inside(h, rho, rule):
                return pt, best
            if margin > 0:
                best = min(best, _bound(h, rho, planes))
    return -1, best


@numba.njit(nogil=True, cache=True, error_model="numpy")
def _grown(a: np.ndarray, cap: int) -> np.ndarray:
    """A copy of ``a`` (rows) with room for ``cap`` rows."""
    out = np.empty((cap,) + a.shape[1:], a.dtype)
    out[:len(a)] = a
    return out


@numba.njit(nogil=True, cache=True, error_model="numpy")
def anchor_cleared(tips: np.ndarray, axes: np.ndarray, todo: np.ndarray, clear: np.ndarray, every: int,
                   reach: float, tol: float) -> np.ndarray:
    """Per pose ``todo[r]`` (poses in time order), whether the anchor ``todo[k * every]`` of its group (k = r //
    every) or of the next one clears it: the anchor's clearance ``clear[k]`` exceeds ``delta + gamma * reach +
    tol`` (``delta``: the distance between the tips, ``gamma``: the angle between the axes)."""
    cleared = np.zeros(len(todo), np.bool_)
    last = len(clear) - 1
    for r in range(len(todo)):
        j = todo[r]
        k = r // every
        for kk in range(k, min(k + 1, last) + 1):
            a = todo[kk * every]
            dx, dy, dz = tips[j, 0] - tips[a, 0], tips[j, 1] - tips[a, 1], tips[j, 2] - tips[a, 2]
            cos = axes[j, 0] * axes[a, 0] + axes[j, 1] * axes[a, 1] + axes[j, 2] * axes[a, 2]
            gamma = np.arccos(min(max(cos, -1.0), 1.0))
            if clear[kk] > np.sqrt(dx * dx + dy * dy + dz * dz) + gamma * reach + tol:
                cleared[r] = True
                break
    return cleared
