"""Toolpaths on curved layers (SPEC step 11): shells, infill, ordering, travels, thickness."""
from __future__ import annotations

from dataclasses import dataclass, replace
from typing import TYPE_CHECKING, Sequence

import numpy as np
from scipy.spatial import cKDTree

from neuralslicer.allocator import release_freed_memory
from neuralslicer.errors import InputError
from neuralslicer.forked import shared_map
from neuralslicer.stress_field import StressLike
from neuralslicer.toolpath.config import ToolpathConfig
from neuralslicer.toolpath.geometry import (ElementSet, Patch, TriangleSet, boundary_distance, boundary_vertices,
                                            layer_lpd, layer_thickness, refine_patch, split_patches)
from neuralslicer.toolpath.isolines import chain_segments, isoline_points, resample_polylines
from neuralslicer.toolpath.stress_infill import (StressPotential, delaunay_flips, dyadic_levels, stress_potential,
                                                 stress_region)
from neuralslicer.toolpath.types import Toolpaths
from neuralslicer.types import FloatArray, IndexArray

if TYPE_CHECKING:  # trimesh (and scipy.spatial, networkx) only where a mesh is made: not on a cached rerun
    import trimesh


#: path kinds: contour-parallel shells, regular infill (zig-zag or contour), stress-following infill
SHELL, INFILL, STRESS = 0, 1, 2


@dataclass
class _Path:
    """One extrusion path before ordering."""

    xyz: FloatArray
    axis: FloatArray
    patch: int
    kind: int
    level: int
    closed: bool
    #: line width per waypoint (n,), or None for the configured line width
    width: FloatArray | None = None

    def reordered(self, order: IndexArray, closed: bool) -> _Path:
        """The same path with its waypoints in ``order``."""
        return _Path(self.xyz[order], self.axis[order], self.patch, self.kind, self.level, closed,
                     None if self.width is None else self.width[order])


def _normalise(v: FloatArray) -> FloatArray:
    n = np.linalg.norm(v, axis=-1, keepdims=True)
    return v / np.where(n > 0, n, 1.0)


def _polylines_from_points(xyz: FloatArray, axis: FloatArray, level: np.ndarray, segments: np.ndarray,
                           cfg: ToolpathConfig, patch_id: int, kind: int, width: FloatArray | None = None
                           ) -> list[_Path]:
    """Chain isoline segments, resample them, and wrap them as paths (``width``: per point, or None)."""
    poly = chain_segments(segments, len(xyz))
    if len(poly) == 0:
        return []
    attributes = axis if width is None else np.column_stack([axis, width])
    pts, off, at = resample_polylines(xyz[poly.ids], poly.offsets, cfg.spacing,
                                      attributes=attributes[poly.ids], corner_angle_deg=cfg.corner_angle_deg)
    ax = _normalise(at[:, :3])
    wd = None if width is None else at[:, 3]
    lev = level[poly.ids[poly.offsets[:-1]]]
    out = []
    for i in range(len(off) - 1):
        a, b = off[i], off[i + 1]
        if b - a < 2:
            continue
        out.append(_Path(pts[a:b], ax[a:b], patch_id, kind, int(lev[i]), bool(poly.closed[i]),
                         None if wd is None else wd[a:b]))
    return out


def clip_segments(segments: IndexArray, values: FloatArray, threshold: float, points: dict[str, np.ndarray]
                  ) -> tuple[IndexArray, dict[str, np.ndarray]]:
    """The parts of isoline segments (s, 2) where the per-point ``values`` (k,) are at least ``threshold``.

    A segment with one end below is cut where the (linear) values cross the threshold; every per-point
    array of ``points`` (k, ...) gets the cut points appended (floats interpolated, integers copied from the
    kept end's partner ``a``). Returns the kept segments and the extended point arrays.
    """
    seg = segments.copy()
    ina, inb = values[seg[:, 0]] >= threshold, values[seg[:, 1]] >= threshold
    keep = ina | inb
    ci = np.flatnonzero(keep & (ina != inb))
    if len(ci):
        a, b = seg[ci, 0], seg[ci, 1]
        tt = ((threshold - values[a]) / (values[b] - values[a]))[:, None]
        new_id = len(values) + np.arange(len(ci))
        out = {}
        for name, arr in points.items():
            if arr.dtype.kind == "f":
                t = tt if arr.ndim == 2 else tt[:, 0]
                out[name] = np.concatenate([arr, (1 - t) * arr[a] + t * arr[b]])
            else:
                out[name] = np.concatenate([arr, arr[a]])
        points = out
        seg[ci[~ina[ci]], 0] = new_id[~ina[ci]]
        seg[ci[ina[ci]], 1] = new_id[ina[ci]]
    return seg[keep], points


def distance_band(cfg: ToolpathConfig) -> float:
    """How far from a patch's boundary the paths need the boundary distance (mm; inf: everywhere).

    Shells are its isolines up to ``(n_shells - 1/2) w`` and zig-zag infill is clipped at
    ``(n_shells + 1/2) w``; one more line width keeps the clip inside the resolved band. Contour
    infill needs it across the whole patch.
    """
    if cfg.infill == "contour":
        return np.inf
    return (cfg.n_shells + 1.5) * cfg.line_width


def _patch_paths(patch: Patch, patch_id: int, layer_index: int, cfg: ToolpathConfig,
                 surface: TriangleSet | None = None, stress: _StressSetup | None = None) -> list[_Path]:
    """Shells and infill of one (refined) patch, unordered; ``surface``: its triangles before refinement;
    ``stress``: its stress scalar, for stress-following infill, with the regular zig-zag where ``patch.values`` (the
    stress region, :func:`_stress_setups`) is below 0."""
    w = cfg.line_width
    d = boundary_distance(patch, upper=distance_band(cfg), surface=surface)
    finite = np.isfinite(d)
    d_max = float(d[finite].max()) if finite.any() else 0.0
    paths: list[_Path] = []
    spacing_in = w / cfg.infill_density
    # contour-parallel shells (and contour infill continuing them)
    levels = [(k + 0.5) * w for k in range(cfg.n_shells)]
    if cfg.infill == "contour":
        base = cfg.n_shells * w
        k_max = int(np.floor((d_max - base) / spacing_in - 0.5)) + 1
        levels += [base + (k + 0.5) * spacing_in for k in range(max(k_max, 0))]
    levels = np.asarray([lv for lv in levels if lv < d_max], np.float64)
    if len(levels) and finite.all():
        iso = isoline_points(patch.faces, d, levels)
        if len(iso.t):
            xyz = iso.interpolate(patch.vertices)
            ax = _normalise(iso.interpolate(patch.lpd))
            paths += _polylines_from_points(xyz, ax, iso.level, iso.segments, cfg, patch_id, SHELL)
    if cfg.infill not in ("zigzag", "stress"):
        return paths
    # infill inside the shells: clipped to d >= d0
    d0 = cfg.n_shells * w + 0.5 * w if cfg.n_shells > 0 else 0.5 * w
    if not finite.all():
        d0 = -np.inf
        d = np.where(finite, d, 0.0)
    if stress is None:
        return paths + _zigzag_lines(patch, d, d0, cfg, patch_id, layer_index)
    paths += _stress_lines(stress, d0, cfg, patch_id, layer_index, surface)
    if patch.values is not None:
        # the regular pattern where the in-layer stress is negligible (the region refined with the patch)
        paths += _zigzag_lines(patch, d, d0, cfg, patch_id, layer_index, -patch.values)
    return paths


def _zigzag_lines(patch: Patch, d: FloatArray, d0: float, cfg: ToolpathConfig, patch_id: int, layer_index: int,
                  region: FloatArray | None = None) -> list[_Path]:
    """Zig-zag infill: isolines of a coordinate projected on the layer's direction, clipped to ``d >= d0`` (and to
    ``region >= 0`` per vertex, when given)."""
    inside = d >= d0
    if region is not None:
        inside &= region >= 0
    if not inside.any():
        return []
    spacing_in = cfg.line_width / cfg.infill_density
    theta = np.radians(cfg.infill_angle_deg + layer_index * cfg.infill_angle_step_deg)
    u = np.array([np.cos(theta), np.sin(theta), 0.0])
    s = patch.vertices @ u
    s_lo, s_hi = s[inside].min(), s[inside].max()
    n_lines = int(np.floor((s_hi - s_lo) / spacing_in))
    # centre the lines in the region; a tiny offset keeps levels off vertex values
    offset = 0.5 * ((s_hi - s_lo) - n_lines * spacing_in) + 1e-7 * spacing_in
    lv = s_lo + offset + spacing_in * np.arange(n_lines + 1)
    lv = lv[(lv > s.min()) & (lv < s.max())]
    iso = isoline_points(patch.faces, s, lv)
    if not len(iso.t):
        return []
    pts = {"xyz": iso.interpolate(patch.vertices), "axis": iso.interpolate(patch.lpd), "level": iso.level}
    if region is not None:
        pts["region"] = iso.interpolate(region)
    seg, pts = clip_segments(iso.segments, iso.interpolate(d), d0, pts)
    if region is not None:
        seg, pts = clip_segments(seg, pts["region"], 0.0, pts)
    return _polylines_from_points(pts["xyz"], _normalise(pts["axis"]), pts["level"], seg, cfg, patch_id, INFILL)


def _stress_lines(setup: _StressSetup, d0: float, cfg: ToolpathConfig, patch_id: int, layer_index: int,
                  surface: TriangleSet | None = None) -> list[_Path]:
    """Stress-following infill: isolines of the patch's stress scalar (on its triangulation, cut open) at dyadic
    levels, each kept where the local gradient asks for its order, densified to the refined patch's edge length and
    clipped to the significant stress region and to ``d >= d0`` (the straight-line distance to the patch boundary,
    which never exceeds the distance along the patch, so the lines stay off the shells); widths = the local line
    spacing (module ``stress_infill``). Odd layers are shifted by half a line (staggered). Where the triangulation
    leaves the layer by more than 0.01 mm (flipped edges of a curved patch) the isoline points are put back onto its
    own triangles ``surface`` before the densification."""
    mesh, pot = setup.mesh, setup.potential
    spacing_in = cfg.line_width / cfg.infill_density
    region = pot.region[pot.origin]
    edges = boundary_vertices(mesh.faces)[1]
    boundary = ElementSet(mesh.vertices, edges) if len(edges) and np.isfinite(d0) else None
    d_mesh = boundary.distance(mesh.vertices)[pot.origin] if boundary is not None else np.full(len(region), np.inf)
    keep = (region >= 0) & (d_mesh >= d0)
    if not keep.any():
        return []
    lv = dyadic_levels(pot, spacing_in, cfg.stress_levels, 0.5 * (layer_index % 2), keep)
    iso = isoline_points(pot.faces, pot.phi, lv.levels)
    if not len(iso.t):
        return []
    pts = {"xyz": iso.interpolate(mesh.vertices[pot.origin]), "axis": iso.interpolate(mesh.lpd[pot.origin]),
           "level": iso.level, "rho": iso.interpolate(pot.rho), "region": iso.interpolate(region),
           "d": iso.interpolate(np.minimum(d_mesh, 1e6))}
    order = lv.order[pts["level"]]
    coarsest = int(lv.order.max())
    # a line of order o stays where log2(|grad phi| / ref) <= o + 1/2 (the coarsest everywhere)
    seg, pts = clip_segments(iso.segments, np.where(order >= coarsest, np.inf, order + 0.5 - pts["rho"]), 0.0, pts)
    seg, pts = compact_points(*clip_segments(seg, pts["region"], 0.0, pts))
    if surface is not None and setup.offset > 0.01:
        pts["xyz"] = surface.closest(pts["xyz"])[0]
    seg, pts = densify_segments(seg, pts, cfg.max_edge or cfg.line_width)
    if boundary is not None:
        # the exact distance where the interpolated one (1-Lipschitz, on edges of stress_resolution) may be near d0
        d = pts["d"].copy()
        near = d < d0 + cfg.stress_resolution
        d[near] = boundary.distance(pts["xyz"][near])
        seg, pts = clip_segments(seg, d, d0, pts)
    if not len(seg):
        return []
    present = np.clip(np.ceil(pts["rho"] - 0.5), int(lv.order.min()), coarsest)
    factor = np.clip(2.0 ** (present - pts["rho"]), 2.0 ** -0.5, 2.0 ** 0.5) if cfg.stress_adapt_width else 1.0
    width = cfg.line_width * np.broadcast_to(factor, pts["rho"].shape).astype(np.float64)
    _, rank = np.unique(pts["level"][seg.ravel()], return_inverse=True)
    level = np.zeros(len(pts["level"]), np.int64)
    level[seg.ravel()] = rank
    return _polylines_from_points(pts["xyz"], _normalise(pts["axis"]), level, seg, cfg, patch_id, STRESS, width)


def compact_points(segments: IndexArray, points: dict[str, np.ndarray]) -> tuple[IndexArray, dict[str, np.ndarray]]:
    """Only the points (and per-point arrays) the segments (s, 2) use, renumbered."""
    used, inv = np.unique(segments, return_inverse=True)
    return inv.reshape(-1, 2).astype(np.int64), {k: v[used] for k, v in points.items()}


def densify_segments(segments: IndexArray, points: dict[str, np.ndarray], max_length: float
                     ) -> tuple[IndexArray, dict[str, np.ndarray]]:
    """Segments (s, 2) split into equal pieces no longer than ``max_length``: the per-point arrays of ``points``
    get the new points appended (floats interpolated, integers copied from the segment's first point)."""
    a, b = segments[:, 0], segments[:, 1]
    length = np.linalg.norm(points["xyz"][b] - points["xyz"][a], axis=1)
    n = np.maximum(np.ceil(length / max_length - 1e-9).astype(np.int64), 1)
    if (n == 1).all():
        return segments, points
    rep = np.repeat(np.arange(len(segments)), n - 1)
    j = np.arange(len(rep)) - np.repeat(np.cumsum(n - 1) - (n - 1), n - 1) + 1
    t = j / n[rep]
    base = len(points["xyz"])
    out = {}
    for name, arr in points.items():
        if arr.dtype.kind == "f":
            tt = t.reshape((-1,) + (1,) * (arr.ndim - 1))
            out[name] = np.concatenate([arr, (1 - tt) * arr[a[rep]] + tt * arr[b[rep]]])
        else:
            out[name] = np.concatenate([arr, arr[a[rep]]])
    # chain: a -> the segment's new points in order -> b
    new_id = base + np.arange(len(rep))
    prev = np.where(j == 1, a[rep], new_id - 1)
    split = np.flatnonzero(n > 1)
    last = base + np.cumsum(n - 1)[split] - 1
    pieces = np.concatenate([segments[n == 1], np.stack([prev, new_id], axis=1), np.stack([last, b[split]], axis=1)])
    return pieces, out


def _order_paths(paths: list[_Path], start: FloatArray, alternate_loops: bool = False,
                 loop_parity: int = 0, continue_within: float = 0.0) -> list[_Path]:
    """Greedy nearest-path ordering with reversal (open paths) or rotation (closed loops).

    With ``alternate_loops`` every second closed loop (counting from ``loop_parity``) is reversed. After a stress
    line, the nearest unused stress line of the same patch starting within ``continue_within`` goes next, even
    where another path starts nearer (the zig-zag of the region beside it): so the stress lines join up.
    """
    if not paths:
        return []
    cand_xyz, cand_path, cand_pos = [], [], []
    for i, p in enumerate(paths):
        if p.closed:
            k = len(p.xyz) - 1
            cand_xyz.append(p.xyz[:k])
            cand_pos.append(np.arange(k))
        else:
            cand_xyz.append(p.xyz[[0, -1]])
            cand_pos.append(np.array([0, len(p.xyz) - 1]))
        cand_path.append(np.full(len(cand_pos[-1]), i))
    cxyz = np.concatenate(cand_xyz)
    cpath = np.concatenate(cand_path)
    cpos = np.concatenate(cand_pos)
    tree = cKDTree(cxyz)
    used = np.zeros(len(paths), bool)
    kind = np.array([p.kind for p in paths])
    patch = np.array([p.patch for p in paths])
    cur = np.asarray(start, np.float64)
    ordered = []
    k = min(32, len(cxyz))
    for _ in range(len(paths)):
        dist, idx = tree.query(cur, k=k)
        dist, idx = np.atleast_1d(dist), np.atleast_1d(idx)
        unused = ~used[cpath[idx]]
        free = idx[unused]
        if ordered and ordered[-1].kind == STRESS and continue_within > 0:
            near = free[(kind[cpath[free]] == STRESS) & (patch[cpath[free]] == ordered[-1].patch)
                        & (dist[unused] <= continue_within)]
            free = near[:1] if len(near) else free
        if len(free):
            c = int(free[0])
        else:
            m = np.flatnonzero(~used[cpath])
            c = int(m[np.argmin(np.linalg.norm(cxyz[m] - cur, axis=1))])
        i, pos = int(cpath[c]), int(cpos[c])
        used[i] = True
        p = paths[i]
        if p.closed:
            k_ = len(p.xyz) - 1
            order = np.concatenate([np.arange(pos, k_), np.arange(0, pos), [pos]])
            if alternate_loops and loop_parity % 2 == 1:
                order = order[::-1]
            loop_parity += 1
            p = p.reordered(order, True)
        elif pos != 0:
            p = p.reordered(np.arange(len(p.xyz))[::-1], False)
        ordered.append(p)
        cur = p.xyz[-1]
    return ordered


def _join_zigzag(ordered: list[_Path], patches: list[TriangleSet], cfg: ToolpathConfig) -> list[_Path]:
    """Join consecutive infill lines of one kind and adjacent levels by an extruding connector on the patch.

    Connector points are spaced by at most ``cfg.spacing`` and projected onto the patch (closest
    point on the layer's own triangles, which the refined patch subdivides), so they lie on the
    layer too.
    """
    if len(ordered) < 2:
        return ordered
    gap_max = cfg.join_factor * cfg.line_width / cfg.infill_density
    first = np.array([p.xyz[0] for p in ordered])
    last = np.array([p.xyz[-1] for p in ordered])
    kind = np.array([p.kind for p in ordered])
    patch = np.array([p.patch for p in ordered])
    level = np.array([p.level for p in ordered])
    gap = np.linalg.norm(first[1:] - last[:-1], axis=1)
    join = ((kind[1:] != SHELL) & (kind[1:] == kind[:-1]) & (patch[1:] == patch[:-1])
            & (np.abs(np.diff(level)) == 1) & (gap > 0) & (gap <= gap_max))
    if not join.any():
        return ordered
    # connectors of all joins (j: path j joined to path j + 1) at once, projected per patch
    j = np.flatnonzero(join)
    n = np.maximum(np.ceil(gap[j] / cfg.spacing - 1e-9).astype(np.int64), 1)
    rep = np.repeat(np.arange(len(j)), n - 1)
    t = ((np.arange(len(rep)) - np.repeat(np.cumsum(n - 1) - (n - 1), n - 1) + 1) / n[rep])[:, None]
    a0 = np.array([ordered[i].axis[-1] for i in j])
    a1 = np.array([ordered[i + 1].axis[0] for i in j])
    pts = (1 - t) * last[j][rep] + t * first[j + 1][rep]
    axs = _normalise((1 - t) * a0[rep] + t * a1[rep])
    for pid in np.unique(patch[j]):
        sel = patch[j][rep] == pid
        if sel.any():
            pts[sel] = patches[pid].closest(pts[sel])[0]
    cut = np.cumsum(n - 1)[:-1]
    conn = dict(zip(j.tolist(), zip(np.split(pts, cut), np.split(axs, cut))))
    out: list[_Path] = []
    xyz: list[FloatArray] = []
    ax: list[FloatArray] = []
    wd: list[FloatArray] = []
    for i, p in enumerate(ordered):
        xyz.append(p.xyz)
        ax.append(p.axis)
        if p.width is not None:
            wd.append(p.width)
        if i in conn:
            xyz.append(conn[i][0])
            ax.append(conn[i][1])
            if p.width is not None:                # the connector's width runs from one line's end to the next's start
                t_i = np.linspace(0.0, 1.0, len(conn[i][0]) + 2)[1:-1]
                wd.append((1 - t_i) * p.width[-1] + t_i * ordered[i + 1].width[0])
            continue
        if len(xyz) == 1:
            out.append(p)
        else:                                    # a joined group: one patch and kind, the last line's level
            out.append(_Path(np.concatenate(xyz), np.concatenate(ax), p.patch, p.kind, p.level, False,
                             np.concatenate(wd) if wd else None))
        xyz, ax, wd = [], [], []
    return out


COLUMNS = ("layer", "path", "xyz", "axis", "thickness", "width", "extrude")


class _Columns:
    """The waypoint columns of :func:`toolpaths`, appended path by path."""

    def __init__(self) -> None:
        """Empty columns."""
        self.cols: dict[str, list] = {k: [] for k in COLUMNS}

    def emit(self, layer: int, path: int, xyz: FloatArray, axis: FloatArray, thick: FloatArray,
             width: float | FloatArray, extrude: np.ndarray) -> None:
        """Append waypoints (``width``: one for all, or one per waypoint)."""
        widths = np.full(len(xyz), width) if np.ndim(width) == 0 else np.asarray(width, np.float64)
        for k, v in zip(COLUMNS, (np.full(len(xyz), layer, np.int64), np.full(len(xyz), path, np.int64), xyz, axis,
                                  thick, widths, extrude)):
            self.cols[k].append(v)

    def end_layer(self, start: int) -> None:
        """Merge the pieces appended since piece ``start`` (one layer's) into one array per column."""
        for v in self.cols.values():
            if len(v) - start > 1:
                v[start:] = [np.concatenate(v[start:])]

    def toolpaths(self) -> Toolpaths:
        """The columns concatenated (unit tool axes); each column's pieces are freed once merged."""
        c = {}
        for k in COLUMNS:
            c[k] = np.concatenate(self.cols[k])
            self.cols[k] = []
            release_freed_memory()   # the pieces' pages go back to the kernel, not into the next column's peak
        norm = np.linalg.norm(c["axis"], axis=1)
        c["axis"] /= np.where(norm > 0, norm, 1.0)[:, None]
        return Toolpaths(layer=c["layer"], path=c["path"], xyz=c["xyz"], axis=c["axis"],
                         thickness=c["thickness"], width=c["width"], extrude=c["extrude"])


@dataclass
class _StressSetup:
    """What a patch's stress-following infill needs: the triangulation its scalar is solved on (the layer's triangles
    made Delaunay and split to ``stress_resolution``), the scalar and how far that triangulation leaves the layer."""

    mesh: Patch
    potential: StressPotential
    offset: float


#: patches whose stress scalars are solved together, at most this many vertices at a time
_BATCH_VERTICES = 200_000


def _stress_setups(patches: list[Patch], stress: StressLike, cfg: ToolpathConfig
                   ) -> tuple[list[_StressSetup | None], list[FloatArray | None]]:
    """The stress scalars of patches (of all layers), solved together a batch at a time (one triangulation, one
    sparse solve: the work per patch is numpy's, not Python's), and each patch's stress region per vertex (how much
    its in-layer stress prefers a direction over the significance threshold, minus 1: >= 0 where the infill follows
    it); None for a patch where the in-layer stress is nowhere significant."""
    setups: list[_StressSetup | None] = [None] * len(patches)
    reference = float(stress.reference_mpa)
    if not reference > 0 or not patches:
        return setups, [None] * len(patches)
    cuts = np.cumsum([len(p.vertices) for p in patches])[:-1]
    tensors = np.split(stress.tensor_at(np.concatenate([p.vertices for p in patches])), cuts)
    regions = [r if (r >= 0).any() else None for r in np.split(
        stress_region(np.concatenate(tensors), np.concatenate([p.lpd for p in patches]), cfg.stress_threshold,
                      reference), cuts)]
    todo = [i for i, r in enumerate(regions) if r is not None]
    while todo:
        n = max(1, int(np.searchsorted(np.cumsum([len(patches[i].vertices) for i in todo]), _BATCH_VERTICES)))
        batch, todo = todo[:n], todo[n:]
        offsets = np.cumsum([0] + [len(patches[i].vertices) for i in batch])
        group = np.repeat(np.arange(len(batch), dtype=np.float64), np.diff(offsets))
        union = Patch(np.concatenate([patches[i].vertices for i in batch]),
                      np.concatenate([patches[i].faces + o for i, o in zip(batch, offsets)]),
                      np.concatenate([patches[i].lpd for i in batch]),
                      values=np.column_stack([group, np.concatenate([tensors[i] for i in batch]).reshape(-1, 9)]))
        faces, offset = delaunay_flips(union.vertices, union.faces)
        # the stress tensors are carried through the refinement, linear along the layer's edges
        mesh = refine_patch(replace(union, faces=faces), cfg.stress_resolution)
        pot = stress_potential(mesh.vertices, mesh.faces, mesh.lpd, mesh.values[:, 1:].reshape(-1, 3, 3), reference,
                               cfg.stress_threshold, cfg.line_width / cfg.infill_density,
                               np.rint(mesh.values[:, 0]).astype(np.int64))
        if pot is None:
            continue
        for i, (used, piece) in zip(batch, pot.pieces()):
            if len(piece.faces) and (piece.region >= 0).any():
                setups[i] = _StressSetup(Patch(mesh.vertices[used], piece.origin[piece.faces], mesh.lpd[used]), piece,
                                         offset)
    return setups, regions


def _layer_patches(layer: trimesh.Trimesh, li: int, cfg: ToolpathConfig) -> tuple[list[Patch], int]:
    """A layer's patches (connected components, cleaned) big enough to fill, and how many were too small."""
    verts, faces = np.asarray(layer.vertices, np.float64), np.asarray(layer.faces, np.int64)
    lpd = layer_lpd(layer)
    if lpd.shape != verts.shape:
        raise InputError(f"layers[{li}]", "vertex_attributes['lpd'] must be (n_vertices, 3)")
    patches = split_patches(verts, faces, lpd)
    kept = [p for p in patches if p.area >= cfg.min_patch_area]
    return kept, len(patches) - len(kept)


def _layer_patch_paths(patches: list[Patch], li: int, cfg: ToolpathConfig,
                       stress: list[tuple[_StressSetup | None, FloatArray | None]] | None = None) -> list[_Path]:
    """One layer's paths, unordered: every patch refined and filled (shells, infill); ``stress``: per patch its
    stress scalar and region (stress-following infill). Independent of the other layers."""
    all_paths: list[_Path] = []
    for k, patch in enumerate(patches):
        surface = TriangleSet(patch.vertices, patch.faces)
        lines, region = stress[k] if stress is not None else (None, None)
        if lines is not None and (lines.potential.region < 0).any():
            # part of the patch is left to the zig-zag: its region, carried through the refinement (linear on the
            # layer's triangles), tells _patch_paths where
            patch = replace(patch, values=region)
        fine = refine_patch(patch, cfg.max_edge or cfg.line_width, band=distance_band(cfg))
        all_paths += _patch_paths(fine, k, li, cfg, surface, lines)
    return all_paths


def _layer_paths(patches: list[Patch], li: int, cfg: ToolpathConfig, start: FloatArray | None, n_loops: int,
                 stress: list[tuple[_StressSetup | None, FloatArray | None]] | None = None,
                 all_paths: list[_Path] | None = None) -> tuple[list[_Path], int]:
    """One layer's paths in print order from ``start`` (patches refined, filled, zigzags joined) and the closed
    loops among them; ``stress``: per patch its stress scalar and region (stress-following infill); ``all_paths``:
    the layer's :func:`_layer_patch_paths`, when computed already."""
    if all_paths is None:
        all_paths = _layer_patch_paths(patches, li, cfg, stress)
    if not all_paths:
        return [], 0
    filled = [TriangleSet(patch.vertices, patch.faces) for patch in patches]
    start = start if start is not None else all_paths[0].xyz[0]
    gap_max = cfg.join_factor * cfg.line_width / cfg.infill_density
    ordered = _join_zigzag(_order_paths(all_paths, start, cfg.alternate_loops, n_loops, gap_max), filled, cfg)
    return ordered, sum(p.closed for p in all_paths)


def _emit_layer(cols: _Columns, li: int, ordered: list[_Path], thick: FloatArray, cur: FloatArray | None,
                cur_axis: FloatArray | None, path_id: int, cfg: ToolpathConfig
                ) -> tuple[FloatArray | None, FloatArray | None, int]:
    """Emit one layer's paths, each after a lifted travel from the previous one when it changes patch or
    jumps further than ``lift_min_travel`` (the first path of a layer always): the head lifts along the axis it
    printed the last waypoint with (``cur_axis`` for the previous layer's), and turns to the next path's axis on the
    way; returns the cursor, its axis and the next path id."""
    prev_patch, prev_ax = None, cur_axis
    for p, th in zip(ordered, np.split(thick, np.cumsum([len(p.xyz) for p in ordered])[:-1])):
        if cur is not None:
            gap = float(np.linalg.norm(p.xyz[0] - cur))
            if cfg.travel_lift > 0 and (prev_patch is None or prev_patch != p.patch or gap > cfg.lift_min_travel):
                a0 = prev_ax if prev_ax is not None else p.axis[0]
                lift_pts = np.stack([cur + cfg.travel_lift * a0, p.xyz[0] + cfg.travel_lift * p.axis[0]])
                cols.emit(li, -1, lift_pts, np.stack([a0, p.axis[0]]), np.zeros(2), 0.0, np.zeros(2, bool))
        ext = np.ones(len(p.xyz), bool)
        ext[0] = False
        cols.emit(li, path_id, p.xyz, p.axis, th, cfg.line_width if p.width is None else p.width, ext)
        path_id += 1
        cur, prev_ax, prev_patch = p.xyz[-1], p.axis[-1], p.patch
    return cur, prev_ax, path_id


def toolpaths(layers: Sequence[trimesh.Trimesh], platform_z: float,
              config: ToolpathConfig | None = None, t_max: float = 1.0, stress: StressLike | None = None) -> Toolpaths:
    """Toolpaths for curved layers in print order (SPEC step 11).

    layers : trimesh layers in the build frame, faces oriented along the LPD, optional
    ``vertex_attributes['lpd']`` (n, 3); platform_z : height of the platform plane; t_max : the
    layers' largest acceptable thickness (``LayerConfig.t_max``), which caps the measured thickness;
    stress : the load case's stress field, which ``infill: stress`` (and ``auto``) follows.
    Returns waypoints with tool axis (LPD), local thickness, width and extrude flags; travel
    waypoints lifted by ``config.travel_lift`` along the tool axis have ``path = -1``.
    """
    cfg = (config or ToolpathConfig()).resolved(stress is not None)
    if len(layers) == 0:
        raise InputError("layers", "no curved layers to fill with toolpaths")
    if cfg.infill == "stress" and stress is None:
        raise InputError("toolpath.infill", "stress-following infill needs the stress of a load case: an 'fea' block "
                         "(supports and loads) in the model spec")
    cols = _Columns()
    below: TriangleSet | None = None
    cur = cur_axis = None
    path_id = n_loops = 0
    path_kinds: list[str] = []                     # one digit per path id: SHELL, INFILL or STRESS
    layer_patches = [_layer_patches(layer, li, cfg) if len(layer.faces) else ([], 0) for li, layer in enumerate(layers)]
    n_patches = sum(len(p) for p, _ in layer_patches)
    n_skipped = sum(k for _, k in layer_patches)
    per_patch = None
    if cfg.infill == "stress" and stress is not None:
        setups, regions = _stress_setups([p for patches, _ in layer_patches for p in patches], stress, cfg)
        cuts = np.cumsum([0] + [len(p) for p, _ in layer_patches])
        per_patch = [list(zip(setups[a:b], regions[a:b])) for a, b in zip(cuts[:-1], cuts[1:])]
    infill_mm = {INFILL: 0.0, STRESS: 0.0}
    # every layer's patches filled (independent of each other: shared with a forked helper process), then ordered,
    # layer after layer, from where the previous one ended
    filled = shared_map([lambda li=li: _layer_patch_paths(layer_patches[li][0], li, cfg,
                                                          None if per_patch is None else per_patch[li])
                         for li in range(len(layers))], [float(len(layer.faces)) for layer in layers])
    for li, layer in enumerate(layers):
        if len(layer.faces) == 0:
            continue
        ordered, loops = _layer_paths(layer_patches[li][0], li, cfg, cur, n_loops,
                                      None if per_patch is None else per_patch[li], filled[li])
        n_loops += loops
        for p in ordered:
            if p.kind in infill_mm:
                infill_mm[p.kind] += float(np.linalg.norm(np.diff(p.xyz, axis=0), axis=1).sum())
        if ordered:
            xyz, ax = np.concatenate([p.xyz for p in ordered]), np.concatenate([p.axis for p in ordered])
            thick = layer_thickness(xyz, ax, below, platform_z, cfg.thickness_cap_factor * t_max, t_max)
            start = len(cols.cols["xyz"])
            cur, cur_axis, path_id = _emit_layer(cols, li, ordered, thick, cur, cur_axis, path_id, cfg)
            path_kinds.extend(str(p.kind) for p in ordered)
            cols.end_layer(start)
        below = TriangleSet(np.asarray(layer.vertices, np.float64), np.asarray(layer.faces, np.int64))
    if not cols.cols["xyz"]:
        raise InputError("layers", "the layers are too small for any toolpath "
                         f"(line width {cfg.line_width} mm); check units or reduce toolpath.line_width")
    tp = cols.toolpaths()
    isovalues = [layer.metadata.get("isovalue") if hasattr(layer, "metadata") else None for layer in layers]
    tp.attrs = {"config": cfg.model_dump(), "t_max": float(t_max), "platform_z": float(platform_z),
                "n_input_layers": len(layers),
                "isovalues": [None if v is None else float(v) for v in isovalues],
                "n_paths": int(path_id), "n_patches": n_patches, "n_patches_skipped": n_skipped,
                "path_kinds": "".join(path_kinds)}
    if cfg.infill == "stress":
        total = infill_mm[INFILL] + infill_mm[STRESS]
        tp.attrs["stress_infill_fraction"] = infill_mm[STRESS] / total if total > 0 else 0.0
    return tp
