"""Toolpaths on curved layers (SPEC step 11): shells, infill, ordering, travels, thickness."""
from __future__ import annotations

from dataclasses import dataclass
from typing import Sequence

import numpy as np
import trimesh
from scipy.spatial import cKDTree

from neuralslicer.errors import InputError
from neuralslicer.toolpath.config import ToolpathConfig
from neuralslicer.toolpath.geometry import (Patch, TriangleSet, boundary_distance, layer_lpd,
                                            layer_thickness, refine_patch, split_patches)
from neuralslicer.toolpath.isolines import chain_segments, isoline_points, resample_polylines
from neuralslicer.toolpath.types import Toolpaths
from neuralslicer.types import FloatArray

SHELL, INFILL = 0, 1


@dataclass
class _Path:
    """One extrusion path before ordering."""

    xyz: FloatArray
    axis: FloatArray
    patch: int
    kind: int
    level: int
    closed: bool


def _normalise(v: FloatArray) -> FloatArray:
    n = np.linalg.norm(v, axis=-1, keepdims=True)
    return v / np.where(n > 0, n, 1.0)


def _polylines_from_points(xyz: FloatArray, axis: FloatArray, level: np.ndarray, segments: np.ndarray,
                           cfg: ToolpathConfig, patch_id: int, kind: int) -> list[_Path]:
    """Chain isoline segments, resample them, and wrap them as paths."""
    poly = chain_segments(segments, len(xyz))
    if len(poly) == 0:
        return []
    pts, off, ax = resample_polylines(xyz[poly.ids], poly.offsets, cfg.spacing,
                                      attributes=axis[poly.ids], corner_angle_deg=cfg.corner_angle_deg)
    ax = _normalise(ax)
    lev = level[poly.ids[poly.offsets[:-1]]]
    out = []
    for i in range(len(off) - 1):
        a, b = off[i], off[i + 1]
        if b - a < 2:
            continue
        out.append(_Path(pts[a:b], ax[a:b], patch_id, kind, int(lev[i]), bool(poly.closed[i])))
    return out


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
                 surface: TriangleSet | None = None) -> list[_Path]:
    """Shells and infill of one (refined) patch, unordered; ``surface``: its triangles before refinement."""
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
    # zig-zag infill: isolines of a projected coordinate, clipped to d >= d0
    if cfg.infill == "zigzag":
        d0 = cfg.n_shells * w + 0.5 * w if cfg.n_shells > 0 else 0.5 * w
        if not finite.all():
            d0 = -np.inf
            d = np.where(finite, d, 0.0)
        region = d >= d0
        if region.any():
            theta = np.radians(cfg.infill_angle_deg + layer_index * cfg.infill_angle_step_deg)
            u = np.array([np.cos(theta), np.sin(theta), 0.0])
            s = patch.vertices @ u
            s_lo, s_hi = s[region].min(), s[region].max()
            n_lines = int(np.floor((s_hi - s_lo) / spacing_in))
            # centre the lines in the region; a tiny offset keeps levels off vertex values
            offset = 0.5 * ((s_hi - s_lo) - n_lines * spacing_in) + 1e-7 * spacing_in
            lv = s_lo + offset + spacing_in * np.arange(n_lines + 1)
            lv = lv[(lv > s.min()) & (lv < s.max())]
            iso = isoline_points(patch.faces, s, lv)
            if len(iso.t):
                xyz = iso.interpolate(patch.vertices)
                ax = iso.interpolate(patch.lpd)
                dp = iso.interpolate(d)
                level = iso.level
                seg = iso.segments.copy()
                da, db = dp[seg[:, 0]], dp[seg[:, 1]]
                ina, inb = da >= d0, db >= d0
                keep = ina | inb
                cut = keep & (ina != inb)
                ci = np.flatnonzero(cut)
                if len(ci):
                    a, b = seg[ci, 0], seg[ci, 1]
                    tt = ((d0 - dp[a]) / (dp[b] - dp[a]))[:, None]
                    new_xyz = (1 - tt) * xyz[a] + tt * xyz[b]
                    new_ax = (1 - tt) * ax[a] + tt * ax[b]
                    new_id = len(xyz) + np.arange(len(ci))
                    xyz = np.concatenate([xyz, new_xyz])
                    ax = np.concatenate([ax, new_ax])
                    level = np.concatenate([level, level[a]])
                    seg[ci[~ina[ci]], 0] = new_id[~ina[ci]]
                    seg[ci[ina[ci]], 1] = new_id[ina[ci]]
                seg = seg[keep]
                paths += _polylines_from_points(xyz, _normalise(ax), level, seg, cfg, patch_id, INFILL)
    return paths


def _order_paths(paths: list[_Path], start: FloatArray, alternate_loops: bool = False,
                 loop_parity: int = 0) -> list[_Path]:
    """Greedy nearest-path ordering with reversal (open paths) or rotation (closed loops).

    With ``alternate_loops`` every second closed loop (counting from ``loop_parity``) is reversed.
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
    cur = np.asarray(start, np.float64)
    ordered = []
    k = min(32, len(cxyz))
    for _ in range(len(paths)):
        _, idx = tree.query(cur, k=k)
        idx = np.atleast_1d(idx)
        free = idx[~used[cpath[idx]]]
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
            p = _Path(p.xyz[order], p.axis[order], p.patch, p.kind, p.level, True)
        elif pos != 0:
            p = _Path(p.xyz[::-1], p.axis[::-1], p.patch, p.kind, p.level, False)
        ordered.append(p)
        cur = p.xyz[-1]
    return ordered


def _join_zigzag(ordered: list[_Path], patches: list[TriangleSet], cfg: ToolpathConfig) -> list[_Path]:
    """Join consecutive infill lines of adjacent levels by an extruding connector on the patch.

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
    join = ((kind[1:] == INFILL) & (kind[:-1] == INFILL) & (patch[1:] == patch[:-1])
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
    for i, p in enumerate(ordered):
        xyz.append(p.xyz)
        ax.append(p.axis)
        if i in conn:
            xyz.append(conn[i][0])
            ax.append(conn[i][1])
            continue
        if len(xyz) == 1:
            out.append(p)
        else:                                    # a joined group: one patch, the last line's level
            out.append(_Path(np.concatenate(xyz), np.concatenate(ax), p.patch, INFILL, p.level, False))
        xyz, ax = [], []
    return out


COLUMNS = ("layer", "path", "xyz", "axis", "thickness", "width", "extrude")


class _Columns:
    """The waypoint columns of :func:`toolpaths`, appended path by path."""

    def __init__(self) -> None:
        """Empty columns."""
        self.cols: dict[str, list] = {k: [] for k in COLUMNS}

    def emit(self, layer: int, path: int, xyz: FloatArray, axis: FloatArray, thick: FloatArray,
             width: float, extrude: np.ndarray) -> None:
        """Append waypoints."""
        for k, v in zip(COLUMNS, (np.full(len(xyz), layer, np.int64), np.full(len(xyz), path, np.int64), xyz, axis,
                                  thick, np.full(len(xyz), width), extrude)):
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
        norm = np.linalg.norm(c["axis"], axis=1)
        c["axis"] /= np.where(norm > 0, norm, 1.0)[:, None]
        return Toolpaths(layer=c["layer"], path=c["path"], xyz=c["xyz"], axis=c["axis"],
                         thickness=c["thickness"], width=c["width"], extrude=c["extrude"])


def _layer_paths(layer: trimesh.Trimesh, li: int, cfg: ToolpathConfig, start: FloatArray | None, n_loops: int
                 ) -> tuple[list[_Path], int, int, int]:
    """One layer's paths in print order from ``start`` (patches split, refined, filled, zigzags joined),
    the patches filled and skipped, and the closed loops among the paths."""
    verts, faces = np.asarray(layer.vertices, np.float64), np.asarray(layer.faces, np.int64)
    lpd = layer_lpd(layer)
    if lpd.shape != verts.shape:
        raise InputError(f"layers[{li}]", "vertex_attributes['lpd'] must be (n_vertices, 3)")
    all_paths: list[_Path] = []
    filled: list[TriangleSet] = []
    skipped = 0
    for patch in split_patches(verts, faces, lpd):
        if patch.area < cfg.min_patch_area:
            skipped += 1
            continue
        filled.append(TriangleSet(patch.vertices, patch.faces))
        fine = refine_patch(patch, cfg.max_edge or cfg.line_width, band=distance_band(cfg))
        all_paths += _patch_paths(fine, len(filled) - 1, li, cfg, filled[-1])
    if not all_paths:
        return [], 0, skipped, 0
    start = start if start is not None else all_paths[0].xyz[0]
    ordered = _join_zigzag(_order_paths(all_paths, start, cfg.alternate_loops, n_loops), filled, cfg)
    return ordered, len(filled), skipped, sum(p.closed for p in all_paths)


def _emit_layer(cols: _Columns, li: int, ordered: list[_Path], thick: FloatArray, cur: FloatArray | None,
                path_id: int, cfg: ToolpathConfig) -> tuple[FloatArray | None, int]:
    """Emit one layer's paths, each after a lifted travel from the previous one when it changes patch or
    jumps further than ``lift_min_travel``; returns the cursor and the next path id."""
    prev_patch, prev_ax = None, None
    for p, th in zip(ordered, np.split(thick, np.cumsum([len(p.xyz) for p in ordered])[:-1])):
        if cur is not None:
            gap = float(np.linalg.norm(p.xyz[0] - cur))
            if cfg.travel_lift > 0 and (prev_patch is None or prev_patch != p.patch or gap > cfg.lift_min_travel):
                a0 = prev_ax if prev_ax is not None else p.axis[0]
                lift_pts = np.stack([cur + cfg.travel_lift * a0, p.xyz[0] + cfg.travel_lift * p.axis[0]])
                cols.emit(li, -1, lift_pts, np.stack([a0, p.axis[0]]), np.zeros(2), 0.0, np.zeros(2, bool))
        ext = np.ones(len(p.xyz), bool)
        ext[0] = False
        cols.emit(li, path_id, p.xyz, p.axis, th, cfg.line_width, ext)
        path_id += 1
        cur, prev_ax, prev_patch = p.xyz[-1], p.axis[-1], p.patch
    return cur, path_id


def toolpaths(layers: Sequence[trimesh.Trimesh], platform_z: float,
              config: ToolpathConfig | None = None, t_max: float = 1.0) -> Toolpaths:
    """Toolpaths for curved layers in print order (SPEC step 11).

    layers : trimesh layers in the build frame, faces oriented along the LPD, optional
    ``vertex_attributes['lpd']`` (n, 3); platform_z : height of the platform plane; t_max : the
    layers' largest acceptable thickness (``LayerConfig.t_max``), which caps the measured thickness.
    Returns waypoints with tool axis (LPD), local thickness, width and extrude flags; travel
    waypoints lifted by ``config.travel_lift`` along the tool axis have ``path = -1``.
    """
    cfg = config or ToolpathConfig()
    if len(layers) == 0:
        raise InputError("layers", "no curved layers to fill with toolpaths")
    cols = _Columns()
    below: TriangleSet | None = None
    cur = None
    path_id = n_patches = n_skipped = n_loops = 0
    for li, layer in enumerate(layers):
        if len(layer.faces) == 0:
            continue
        ordered, filled, skipped, loops = _layer_paths(layer, li, cfg, cur, n_loops)
        n_patches, n_skipped, n_loops = n_patches + filled, n_skipped + skipped, n_loops + loops
        if ordered:
            xyz, ax = np.concatenate([p.xyz for p in ordered]), np.concatenate([p.axis for p in ordered])
            thick = layer_thickness(xyz, ax, below, platform_z, cfg.thickness_cap_factor * t_max, t_max)
            start = len(cols.cols["xyz"])
            cur, path_id = _emit_layer(cols, li, ordered, thick, cur, path_id, cfg)
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
                "n_paths": int(path_id), "n_patches": n_patches, "n_patches_skipped": n_skipped}
    return tp
