"""Pictures and the Markdown report of a slice: layer preview, angle histograms, learning curves, and the
operator's pictures (overhang map, bead thickness, toolpaths of representative layers)."""
from __future__ import annotations

import ctypes
import os
import threading
import warnings
from collections.abc import Sequence
from pathlib import Path
from typing import TYPE_CHECKING, Any

import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt  # noqa: E402
import numpy as np  # noqa: E402
import trimesh  # noqa: E402
from matplotlib.collections import LineCollection  # noqa: E402
from matplotlib.colors import TwoSlopeNorm  # noqa: E402
from matplotlib.ticker import MaxNLocator  # noqa: E402
from mpl_toolkits.mplot3d.art3d import Poly3DCollection  # noqa: E402

from neuralslicer.fileio import atomic_path  # noqa: E402
from neuralslicer.metrics import overhang_area_fraction, support_angles  # noqa: E402
from neuralslicer.run.run_metrics import RunMetrics  # noqa: E402
from neuralslicer.toolpath.types import Toolpaths  # noqa: E402

if TYPE_CHECKING:
    from neuralslicer.motion.collision import CollisionMap


#: one off-screen VTK render at a time in this process
_RENDER_LOCK = threading.Lock()


def _save(fig: plt.Figure, path: Path) -> None:
    """Save a figure atomically and close it."""
    with atomic_path(path) as tmp:
        fig.savefig(tmp, dpi=110, bbox_inches="tight", format="png")
    plt.close(fig)


def plot_layers(path: Path, layers: Sequence[trimesh.Trimesh], surface: trimesh.Trimesh | None = None,
                max_faces: int = 60_000) -> None:
    """Layer preview: every few layers drawn as a surface coloured by print order, in two views."""
    fig = plt.figure(figsize=(11, 5.5))
    n = len(layers)
    stride = max(1, n // 40)
    chosen = list(range(0, n, stride))
    per = max(200, max_faces // max(len(chosen), 1))
    cmap = plt.get_cmap("viridis")
    lo = np.min([m.bounds[0] for m in layers], axis=0) if n else np.zeros(3)
    hi = np.max([m.bounds[1] for m in layers], axis=0) if n else np.ones(3)
    for k, (elev, azim) in enumerate([(20, -60), (20, 30)]):
        ax = fig.add_subplot(1, 2, k + 1, projection="3d")
        for i in chosen:
            m = layers[i]
            faces = m.faces if len(m.faces) <= per else m.faces[np.linspace(0, len(m.faces) - 1, per).astype(int)]
            poly = Poly3DCollection(m.vertices[faces], facecolor=cmap(i / max(n - 1, 1)), edgecolor="none", alpha=0.9)
            ax.add_collection3d(poly)
        _equal_3d(ax, np.vstack([lo, hi]))
        ax.view_init(elev=elev, azim=azim)
    fig.suptitle(f"{n} layers (every {stride}), colour = print order")
    _save(fig, path)


def plot_angle_histogram(path: Path, angles: dict[str, np.ndarray], weights: np.ndarray, threshold_deg: float,
                         xlabel: str, title: str) -> None:
    """Area/volume-weighted histograms of an angle for several fields, with the threshold."""
    fig, ax = plt.subplots(figsize=(7, 4))
    bins = np.linspace(min(-90.0, *(a.min() for a in angles.values())) if angles else -90, 90, 61)
    for label, a in angles.items():
        ax.hist(a, bins=bins, weights=weights / weights.sum() * 100, histtype="step", linewidth=1.8, label=label)
    ax.axvline(threshold_deg, color="red", linestyle="--", label=f"threshold {threshold_deg:g}°")
    ax.set_xlabel(xlabel)
    ax.set_ylabel("% of samples (weighted)")
    ax.set_title(title)
    ax.legend()
    _save(fig, path)


def plot_strain_histogram(path: Path, strains: dict[str, np.ndarray]) -> None:
    """Histograms of the per-voxel max principal strain for several layer sets."""
    fig, ax = plt.subplots(figsize=(7, 4))
    top = max(float(np.max(s)) for s in strains.values())
    bins = np.linspace(0, top, 61)
    for label, s in strains.items():
        ax.hist(s, bins=bins, histtype="step", linewidth=1.8, label=f"{label} (max {np.max(s):.3g})")
    ax.set_yscale("log")
    ax.set_xlabel("max |principal strain| per voxel")
    ax.set_ylabel("voxels")
    ax.legend()
    ax.set_title("strain of the printed part")
    _save(fig, path)


def plot_strain_maps(path: Path, centres: np.ndarray, strains: dict[str, np.ndarray], spacing: float) -> None:
    """One map per part of the per-voxel max |principal strain| (n,) at voxel centres (n, 3), on one colour scale:
    the largest strain along the horizontal axis of least extent (x or y), seen across it; + marks each maximum."""
    axis = 0 if np.ptp(centres[:, 0]) <= np.ptp(centres[:, 1]) else 1
    u = 1 - axis
    lo = centres.min(axis=0)
    iu = np.rint((centres[:, u] - lo[u]) / spacing).astype(np.int64)
    iz = np.rint((centres[:, 2] - lo[2]) / spacing).astype(np.int64)
    top = max(float(np.max(s)) for s in strains.values())
    n = len(strains)
    fig, axes = plt.subplots(1, n, figsize=(4.8 * n, 4.4), squeeze=False)
    extent = (lo[u] - spacing / 2, lo[u] + (iu.max() + 0.5) * spacing, lo[2] - spacing / 2, lo[2] + (iz.max() + 0.5) * spacing)
    for ax, (label, s) in zip(axes[0], strains.items()):
        img = np.full((iz.max() + 1, iu.max() + 1), np.nan)
        flat = np.full(img.size, -np.inf)
        np.maximum.at(flat, iz * img.shape[1] + iu, s)
        img = np.where(np.isfinite(flat), flat, np.nan).reshape(img.shape)
        im = ax.imshow(img, origin="lower", extent=extent, cmap="inferno", vmin=0.0, vmax=top, interpolation="nearest")
        k = int(np.argmax(s))
        ax.plot(centres[k, u], centres[k, 2], "+", color="cyan", markersize=12, markeredgewidth=2)
        ax.set_title(f"{label}\nmax {np.max(s):.3g}, p99 {np.percentile(s, 99):.3g}", fontsize=9)
        ax.set_xlabel(f"{'xy'[u]} (mm)")
        ax.set_ylabel("z (mm)")
    fig.colorbar(im, ax=axes[0].tolist(), shrink=0.85, label="max |principal strain| (largest across the part)")
    fig.suptitle(f"strain of the printed parts, seen along {'xy'[axis]} (one colour scale)")
    _save(fig, path)


def plot_filament_angles(path: Path, angles: dict[str, tuple[np.ndarray, np.ndarray]], band_deg: float = 20.0) -> None:
    """Per part, the histogram of the angle between the printed filaments and tau_max projected onto the layer in the
    most stressed region, weighted by filament length (angles (k,), lengths (k,)); the band of aligned filaments red."""
    n = max(len(angles), 1)
    fig, axes = plt.subplots(n, 1, figsize=(7, 2.2 * n + 0.6), sharex=True, squeeze=False)
    bins = np.linspace(0.0, 90.0, 19)
    for ax, (label, (a, w)) in zip(axes[:, 0], angles.items()):
        total = float(np.sum(w))
        ax.axvspan(0.0, band_deg, color="red", alpha=0.15)
        if total > 0:
            ax.hist(a, bins=bins, weights=w / total * 100, color="tab:blue")
        share = float(np.sum(w[a <= band_deg]) / total) if total > 0 else 0.0
        ax.set_title(f"{label}: {100 * share:.1f} % of the length within {band_deg:g}°", fontsize=9)
        ax.set_ylabel("% of length")
    axes[-1, 0].set_xlabel("angle between filament and tau_max projected onto the layer (°), top-stress region")
    _save(fig, path)


def plot_stress_turn(path: Path, rounds: dict[str, dict[str, np.ndarray]], beta_deg: float) -> None:
    """Per strength round, in the most stressed voxels: how far the printed material turned tau_max from the
    isotropic one (left), and the angle of the round's layers to the isotropic and to the printed tau_max (right, the
    paper's Fig. 19; the beta band in red)."""
    fig, (a, b) = plt.subplots(1, 2, figsize=(12, 4))
    bins = np.linspace(0.0, 90.0, 31)
    for label, t in rounds.items():
        a.hist(t["tau_turn_deg"], bins=bins, histtype="step", linewidth=1.8, density=True, label=label)
        b.hist(t["layer_tau_iso_deg"], bins=bins, histtype="step", linewidth=1.4, linestyle="--", density=True,
               label=f"{label}: isotropic tau_max")
        b.hist(t["layer_tau_printed_deg"], bins=bins, histtype="step", linewidth=1.8, density=True,
               label=f"{label}: printed tau_max")
    a.set_xlabel("angle between the isotropic and the printed part's tau_max (°)")
    a.set_ylabel("density")
    a.legend(fontsize=8)
    b.axvspan(0.0, beta_deg, color="red", alpha=0.15)
    b.set_xlabel("angle between the layer and tau_max (°)")
    b.legend(fontsize=7)
    fig.suptitle("strength rounds: the stress the print carries (top-stress voxels)")
    _save(fig, path)


def plot_learning_curves(path: Path, curves: dict[str, dict[str, np.ndarray]]) -> None:
    """Loss terms per step (log scale) for one or several runs."""
    fig, ax = plt.subplots(figsize=(7, 4))
    for run, history in curves.items():
        for term, values in history.items():
            if term in ("lr", "ca_after_correction") or np.all(np.asarray(values) == 0):
                continue
            label = f"{run}: {term}" if len(curves) > 1 else term
            ax.plot(np.arange(1, len(values) + 1), np.maximum(values, 1e-12), label=label)
    ax.set_yscale("log")
    ax.set_xlabel("step")
    ax.set_ylabel("loss")
    ax.legend(fontsize=8)
    ax.set_title("learning curves")
    _save(fig, path)


def plot_collision_map(path: Path, prints: dict[str, CollisionMap]) -> None:
    """Where the head hits: waypoints of each print, grey, with the colliding ones in red (each print's
    :class:`CollisionMap`), one 3D view per print in the order given (the first field printed, then what resolved
    its collisions)."""
    n = max(len(prints), 1)
    fig = plt.figure(figsize=(5.5 * n, 5.5))
    for k, (label, m) in enumerate(prints.items()):
        ax = fig.add_subplot(1, n, k + 1, projection="3d")
        z_lo, z_hi = (m.bounds[0, 2], m.bounds[1, 2]) if len(m.bounds) else (0.0, 0.0)
        ax.scatter(*m.clear.T, s=0.6, c=m.clear[:, 2], cmap="Greys", vmin=z_lo - 0.6 * (z_hi - z_lo),
                   alpha=0.5, linewidths=0)
        ax.scatter(*m.hit.T, s=3, c="red", linewidths=0)
        _equal_3d(ax, m.bounds)
        ax.view_init(elev=20, azim=-60)
        ax.set_title(f"{label}\n{m.n_hit:,} colliding of {m.n_waypoints:,} waypoints", fontsize=9)
    fig.suptitle("print head collisions (red) against earlier layers and the platform")
    _save(fig, path)


def summary_rows(metrics: dict) -> list[tuple[str, str]]:
    """What a user looks for first, from the metrics a run has (:class:`RunMetrics`): layers, time, material,
    collisions, overhang and strain against planar layers."""
    m, rows = RunMetrics.of(metrics), []

    def pct(x: float) -> str:
        return f"{100 * x:.2f} %"

    if m.n_layers is not None:
        rows.append(("layers", f"{m.n_layers}"))
    if m.estimated_print_time_s is not None:
        t = m.estimated_print_time_s
        rows.append(("estimated print time", f"{int(t // 3600)} h {int(t % 3600 // 60):02d} min"))
    if m.material_mm3 is not None:
        rows.append(("material", f"{m.material_mm3 / 1000:.1f} cm³"))
    if m.n_collisions is not None:
        rows.append(("nozzle collisions", f"{m.n_collisions}"))
    if m.overhang_layers is not None and m.overhang_layers_planar is not None:
        rows.append(("overhang, held out, exported layers (planar)",
                     f"{pct(m.overhang_layers)} ({pct(m.overhang_layers_planar)})"))
    if m.max_strain is not None and m.max_strain_planar_zigzag:
        rows.append(("max strain, printed (planar + zig-zag)",
                     f"{m.max_strain:.4g} ({m.max_strain_planar_zigzag:.4g}, "
                     f"{100 * (m.max_strain / m.max_strain_planar_zigzag - 1):+.1f} %)"))
    return rows


def markdown_report(title: str, metrics: dict, figures: dict[str, str], sections: dict[str, str] | None = None) -> str:
    """A Markdown report: a summary, every metric, extra sections, and the figures."""
    lines = [f"# {title}", ""]
    summary = summary_rows(metrics)
    if summary:
        lines += ["## Summary", "", "| | |", "| --- | --- |", *(f"| {k} | {v} |" for k, v in summary), ""]
    lines += ["## All metrics", "", "| metric | value |", "| --- | --- |"]
    for key in sorted(metrics):
        value = metrics[key]
        if isinstance(value, float):
            value = f"{value:.6g}"
        if isinstance(value, (dict, list)):
            continue
        lines.append(f"| `{key}` | {value} |")
    for heading, body in (sections or {}).items():
        lines += ["", f"## {heading}", "", body]
    for caption, rel in figures.items():
        lines += ["", f"## {caption}", "", f"![{caption}]({rel})"]
    return "\n".join(lines) + "\n"


def _subsample(n: int, max_points: int, seed: int = 0) -> np.ndarray:
    """At most ``max_points`` sorted indices into ``range(n)``, drawn without replacement (all when few)."""
    if n <= max_points:
        return np.arange(n)
    return np.sort(np.random.default_rng(seed).choice(n, max_points, replace=False))


def _equal_3d(ax: plt.Axes, xyz: np.ndarray) -> None:
    """Equal, cube-shaped limits around points (n, 3) on a 3D axis."""
    lo, hi = (xyz.min(axis=0), xyz.max(axis=0)) if len(xyz) else (np.zeros(3), np.ones(3))
    centre, half = (lo + hi) / 2, max(float((hi - lo).max()) / 2, 1e-6)
    ax.set_xlim(centre[0] - half, centre[0] + half)
    ax.set_ylim(centre[1] - half, centre[1] + half)
    ax.set_zlim(centre[2] - half, centre[2] + half)
    ax.set_xlabel("x (mm)")
    ax.set_ylabel("y (mm)")
    ax.set_zlabel("z (mm)")


def plot_overhang_map(path: Path, points: np.ndarray, normals: np.ndarray, lpd_by_label: dict[str, np.ndarray],
                      alpha_deg: float, areas: np.ndarray | None = None, on_platform: np.ndarray | None = None,
                      max_points: int = 25_000) -> dict[str, float]:
    """Surface samples coloured by overhang angle asin(-n·d), one column per field, seen from above and below.

    points, normals : (n, 3) float, the samples B and their outward unit normals
    lpd_by_label : {label: (n, 3) float unit print direction d at the samples}, e.g. planar and computed
    areas : (n,) float sample areas weighting the overhang fraction (equal weights when None)
    on_platform : (n,) bool samples on the platform, left out of the picture and of the fraction
    Returns {label: overhang area fraction}, as :func:`neuralslicer.metrics.overhang_area_fraction` counts it
    and as the titles show.
    """
    n = len(points)
    areas = np.ones(n) if areas is None else np.asarray(areas, float)
    on_platform = np.zeros(n, bool) if on_platform is None else np.asarray(on_platform, bool)
    fractions = {label: overhang_area_fraction(normals, areas, on_platform, d, alpha_deg)
                 for label, d in lpd_by_label.items()}
    shown = np.flatnonzero(~on_platform)
    shown = shown[_subsample(len(shown), max_points)]
    norm = TwoSlopeNorm(vcenter=alpha_deg, vmin=-90.0, vmax=90.0)
    cols = max(len(lpd_by_label), 1)
    fig = plt.figure(figsize=(5.0 * cols, 9.0))
    scatter = None
    for k, (label, d) in enumerate(lpd_by_label.items()):
        angle = support_angles(normals[shown], d[shown])
        ok = np.isfinite(angle)
        for row, (elev, azim, view) in enumerate([(25, -60, "from above"), (-30, -60, "from below")]):
            ax = fig.add_subplot(2, cols, row * cols + k + 1, projection="3d")
            scatter = ax.scatter(*points[shown[ok]].T, c=angle[ok], cmap="coolwarm", norm=norm, s=1.5,
                                 linewidths=0, depthshade=False)
            _equal_3d(ax, points[shown])
            ax.view_init(elev=elev, azim=azim)
            if row == 1:
                ax.set_axis_off()  # the same scale as above; ticks seen from below only clutter
            ax.set_title(f"{label}: {100 * fractions[label]:.2f} % overhang area\n({view})" if row == 0
                         else f"{label} ({view})", fontsize=10)
    if scatter is not None:
        bar = fig.colorbar(scatter, ax=fig.axes, shrink=0.5, extend="neither")
        bar.set_label(f"overhang angle asin(-n·d) (°), red beyond α = {alpha_deg:g}°")
    fig.suptitle("overhang map of the model surface (platform samples left out)")
    _save(fig, path)
    return fractions


def plot_thickness_map(path: Path, xyz: np.ndarray, thickness: np.ndarray, extrude: np.ndarray,
                       bead_range: tuple[float, float], max_points: int = 40_000, gaps: dict | None = None
                       ) -> dict[str, float]:
    """Extruding waypoints coloured by bead thickness (3D) beside a histogram with the nozzle's bead range.

    xyz : (n, 3) float waypoints; thickness : (n,) float local layer thickness (mm); extrude : (n,) bool
    bead_range : (min, max) bead thickness the nozzle can lay (mm); gaps : the bead summary of the print
    (``toolpath.beads``): the gaps to the layer below as the layers leave them, drawn as a second histogram
    and named in the title (the printed beads are inside the range once thin gaps are carried up).
    Returns the fractions of extruding waypoints below, above and outside the range, and their count.
    """
    lo, hi = float(bead_range[0]), float(bead_range[1])
    idx = np.flatnonzero(np.asarray(extrude, bool) & np.isfinite(thickness))
    t = thickness[idx]
    m = max(len(t), 1)
    stats = {"n": int(len(t)), "below": float(np.sum(t < lo) / m), "above": float(np.sum(t > hi) / m)}
    stats["outside"] = stats["below"] + stats["above"]
    fig = plt.figure(figsize=(13, 5.5))
    ax = fig.add_subplot(1, 2, 1, projection="3d", computed_zorder=False)
    shown = idx[_subsample(len(idx), max_points)]
    cmap = plt.get_cmap("viridis").with_extremes(under="magenta", over="red")
    out = (thickness[shown] < lo) | (thickness[shown] > hi)
    sc = None
    for part, size in ((shown[~out], 0.8), (shown[out], 3.0)):  # beads outside the range drawn on top
        sc = ax.scatter(*xyz[part].T, c=thickness[part], cmap=cmap, vmin=lo, vmax=hi, s=size, linewidths=0,
                        depthshade=False)
    _equal_3d(ax, xyz[shown])
    ax.view_init(elev=20, azim=-60)
    fig.colorbar(sc, ax=ax, shrink=0.6, pad=0.12, extend="both",
                 label="bead thickness (mm); magenta below, red above range")
    ax.set_title(f"{len(shown):,} of {len(idx):,} extruding waypoints", fontsize=10)
    hx = fig.add_subplot(1, 2, 2)
    if len(t):
        top = max(float(t.max()), hi) * 1.05
        hx.hist(t, bins=np.linspace(min(float(t.min()), lo, 0.0), top, 81), color="tab:gray")
    if gaps is not None and gaps.get("hist_counts"):
        hx.stairs(np.asarray(gaps["hist_counts"]), np.asarray(gaps["hist_edges_mm"]), color="tab:blue",
                  label="gap to the layer below (as sliced)")
    hx.axvline(lo, color="magenta", linestyle="--", label=f"bead min {lo:g} mm")
    hx.axvline(hi, color="red", linestyle="--", label=f"bead max {hi:g} mm")
    hx.set_xlabel("bead thickness (mm)")
    hx.set_yscale("log")
    hx.set_ylabel("extruding waypoints (log)")
    hx.legend()
    title = (f"printed beads: {100 * stats['outside']:.2f} % outside the bead range "
             f"({100 * stats['below']:.2f} % thinner, {100 * stats['above']:.2f} % thicker)")
    if gaps is not None:
        title = (f"gaps as sliced: {100 * gaps['fraction_outside_range']:.2f} % outside ({100 * gaps['fraction_thin']:.2f} % "
                 f"thinner, carried up; {100 * gaps['fraction_thick']:.2f} % thicker, capped)\n{title}")
    hx.set_title(title, fontsize=10)
    _save(fig, path)
    return stats


def representative_layers(layer: np.ndarray, path_id: np.ndarray, count: int = 4) -> list[int]:
    """Up to ``count`` layer indices with printing waypoints: the first, evenly spaced ones, the last."""
    printed = np.unique(layer[path_id >= 0])
    if len(printed) == 0:
        return []
    picks = np.round(np.linspace(0, len(printed) - 1, min(count, len(printed)))).astype(int)
    return [int(v) for v in printed[np.unique(picks)]]


def _layer_frame(axis: np.ndarray) -> np.ndarray:
    """Rows (u, v, a): an orthonormal frame whose third row is the mean of unit tool axes (n, 3)."""
    a = axis.mean(axis=0) if len(axis) else np.array([0.0, 0.0, 1.0])
    a = a / np.linalg.norm(a) if np.linalg.norm(a) > 1e-9 else np.array([0.0, 0.0, 1.0])
    e = np.array([1.0, 0.0, 0.0]) if abs(a[0]) < 0.9 else np.array([0.0, 1.0, 0.0])
    u = e - (e @ a) * a
    u /= np.linalg.norm(u)
    return np.stack([u, np.cross(a, u), a])


def _layer_segments(xyz2: np.ndarray, path_id: np.ndarray, extrude: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Printing and travel segments (k, 2, 2) of one layer's consecutive waypoints (projected (n, 2))."""
    if len(xyz2) < 2:
        return np.zeros((0, 2, 2)), np.zeros((0, 2, 2))
    segs = np.stack([xyz2[:-1], xyz2[1:]], axis=1)
    printing = extrude[1:] & (path_id[1:] == path_id[:-1]) & (path_id[1:] >= 0)
    return segs[printing], segs[~printing]


def plot_layer_toolpaths(path: Path, tp: Toolpaths, layers_to_show: list[int] | None = None,
                         max_segments: int = 40_000) -> list[int]:
    """Toolpaths of a few layers, each projected on the plane orthogonal to its mean tool axis.

    Printing moves are lines coloured by their order in the layer, travels dashed grey, the start a
    black dot; ``layers_to_show`` defaults to the first, 1/3, 2/3 and last printed layers. Returns the
    layers drawn.
    """
    shown = representative_layers(tp.layer, tp.path) if layers_to_show is None else list(layers_to_show)
    cols = max(len(shown), 1)
    fig, axes = plt.subplots(1, cols, figsize=(4.6 * cols, 4.9), squeeze=False)
    for ax, li in zip(axes[0], shown):
        idx = np.flatnonzero(tp.layer == li)
        idx = idx[:: int(np.ceil(len(idx) / max_segments))] if len(idx) > max_segments else idx
        frame = _layer_frame(tp.axis[idx[tp.path[idx] >= 0]])
        uv = tp.xyz[idx] @ frame[:2].T
        printing, travel = _layer_segments(uv, tp.path[idx], tp.extrude[idx])
        if len(travel):
            ax.add_collection(LineCollection(travel, colors="0.6", linestyles="--", linewidths=0.6))
        if len(printing):
            lines = LineCollection(printing, cmap="viridis", linewidths=0.8)
            lines.set_array(np.linspace(0.0, 1.0, len(printing)))
            ax.add_collection(lines)
        if len(uv):
            ax.plot(*uv[0], "ko", markersize=4)
        ax.set_aspect("equal", adjustable="datalim")
        ax.autoscale_view()
        a = frame[2]
        n_paths = len(np.unique(tp.path[idx][tp.path[idx] >= 0]))
        ax.set_title(f"layer {li}: {n_paths} paths, {len(idx):,} waypoints\n"
                     f"seen along tool axis ({a[0]:.2f}, {a[1]:.2f}, {a[2]:.2f})", fontsize=9)
        ax.set_xlabel("u (mm)")
        ax.set_ylabel("v (mm)")
        ax.xaxis.set_major_locator(MaxNLocator(5))
        ax.tick_params(labelsize=8)
    for ax in axes[0][len(shown):]:
        ax.set_axis_off()
    fig.suptitle("toolpaths of representative layers (colour = order in the layer, dashed = travel, dot = start)",
                 y=1.04)
    _save(fig, path)
    return shown


#: VTK render window classes by off-screen backend
_VTK_WINDOWS = {"egl": "vtkEGLRenderWindow", "osmesa": "vtkOSOpenGLRenderWindow"}


def offscreen_backend() -> str | None:
    """How VTK can render off-screen here: ``"x"`` (a display), ``"egl"``, ``"osmesa"``, or None.

    VTK falls back from X to EGL to OSMesa and crashes when none loads, so the libraries are checked
    (dlopen, no subprocess) before any window is made; ``NEURALSLICER_RENDERER=matplotlib`` turns pyvista off.
    """
    if os.environ.get("NEURALSLICER_RENDERER", "").lower() == "matplotlib":
        return None
    if os.environ.get("DISPLAY"):
        return "x"
    if _loadable("libEGL.so.1") and any(_loadable(v) for v in ("libEGL_mesa.so.0", "libEGL_nvidia.so.0")):
        return "egl"
    if any(_loadable(v) for v in ("libOSMesa.so.8", "libOSMesa.so.6", "libOSMesa.so")):
        return "osmesa"
    return None


def offscreen_rendering_available() -> bool:
    """Whether pyvista can render off-screen here (see :func:`offscreen_backend`)."""
    return offscreen_backend() is not None


def _loadable(name: str) -> bool:
    """Whether a shared library loads (dlopen, no subprocess)."""
    try:
        ctypes.CDLL(name)
    except OSError:
        return False
    return True


def _coarsened(vertices: np.ndarray, faces: np.ndarray, max_faces: int) -> tuple[np.ndarray, np.ndarray]:
    """A layer's vertices (v, 3) and faces (f, 3), vertex-clustered (VTK quadric clustering, linear time)
    to roughly ``max_faces`` faces when it has more."""
    if len(faces) <= max_faces:
        return vertices, faces
    import pyvista as pv
    from vtkmodules.vtkFiltersCore import vtkQuadricClustering

    clustering = vtkQuadricClustering()
    clustering.SetInputData(pv.PolyData.from_regular_faces(vertices, faces))
    divisions = int(np.clip(np.sqrt(max_faces), 8, 512))
    clustering.SetNumberOfDivisions(divisions, divisions, divisions)
    clustering.Update()
    out = pv.wrap(clustering.GetOutput())
    return (np.asarray(out.points, float), np.asarray(out.regular_faces, np.int64)) if out.n_cells else (vertices, faces)


def _merged_layers(layers: Sequence[trimesh.Trimesh], chosen: list[int], max_faces: int
                   ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Vertices (v, 3), faces (f, 3) and per-face layer index (f,) of the chosen layers as one mesh, each
    layer coarsened to its share of ``max_faces``."""
    share = max(max_faces // max(len(chosen), 1), 500)
    meshes = [_coarsened(np.asarray(layers[i].vertices, float), np.asarray(layers[i].faces, np.int64), share)
              for i in chosen]
    offsets = np.cumsum([0] + [len(v) for v, _ in meshes])[:-1]
    vertices = np.concatenate([v for v, _ in meshes])
    faces = np.concatenate([f + o for (_, f), o in zip(meshes, offsets)])
    order = np.concatenate([np.full(len(f), i) for i, (_, f) in zip(chosen, meshes)])
    return vertices, faces, order


def _plot_layers_pyvista(path: Path, layers: Sequence[trimesh.Trimesh], max_layers: int, max_faces: int) -> None:
    """Layer preview rendered off-screen with pyvista: every few layers coloured by print order, seen whole
    and cut in half through the centre (the cut shows the layers' curves inside the part)."""
    import pyvista as pv

    n = len(layers)
    faces_per_layer = np.array([len(m.faces) for m in layers])
    stride = max(1, int(np.ceil(n / max_layers)), min(int(np.ceil(faces_per_layer.sum() / max_faces)), n // 24))
    chosen = [i for i in range(0, n, stride) if faces_per_layer[i]]
    vertices, faces, order = _merged_layers(layers, chosen, max_faces)
    mesh = pv.PolyData.from_regular_faces(vertices, faces)
    mesh.cell_data["print order (layer)"] = order
    centre = 0.5 * (vertices.min(axis=0) + vertices.max(axis=0))
    views = [(mesh, f"{n} layers (every {stride}), colour = print order"),
             (mesh.clip(normal="y", origin=centre), "the half y < centre, seen from +y onto the cut")]
    with _RENDER_LOCK:  # VTK render windows are not safe to use from several threads at once
        _render_views(path, views, n)


def _render_views(path: Path, views: list[tuple[Any, str]], n_layers: int) -> None:
    """Render (pyvista mesh with cell data "print order (layer)", text) views side by side off-screen and save
    the screenshot atomically."""
    import pyvista as pv

    backend = offscreen_backend()
    if backend in _VTK_WINDOWS:  # straight to the backend found, without VTK's failing try of X first
        os.environ.setdefault("VTK_DEFAULT_OPENGL_WINDOW", _VTK_WINDOWS[backend])
    plotter = pv.Plotter(off_screen=True, window_size=(1400, 700), shape=(1, 2), border=False)
    try:
        for k, (shown, text) in enumerate(views):
            plotter.subplot(0, k)
            if shown.n_cells:
                plotter.add_mesh(shown, scalars="print order (layer)", cmap="viridis", clim=(0, max(n_layers - 1, 1)),
                                 show_scalar_bar=k == 1, ambient=0.3)
            plotter.add_text(text, font_size=10)
            if k == 0:
                plotter.view_isometric()
            else:
                plotter.view_vector((0.25, 1.0, 0.25), viewup=(0.0, 0.0, 1.0))
        with atomic_path(path) as tmp:
            img = plotter.screenshot(tmp, return_img=True)
            if img is None or float(np.std(img)) < 1.0:
                raise RuntimeError("pyvista rendered a blank image")
    finally:
        plotter.close()


def plot_layers_3d(path: Path, layers: Sequence[trimesh.Trimesh], max_layers: int = 120,
                   max_faces: int = 500_000) -> str:
    """Layer preview with pyvista off-screen when it renders here, else :func:`plot_layers` (matplotlib);
    returns the renderer used, ``"pyvista"`` or ``"matplotlib"``."""
    if len(layers) and sum(len(m.faces) for m in layers) and offscreen_rendering_available():
        try:
            _plot_layers_pyvista(path, layers, max_layers, max_faces)
            return "pyvista"
        except Exception as exc:  # noqa: BLE001 - any renderer failure falls back to matplotlib
            warnings.warn(f"pyvista layer preview failed ({exc}); drawing it with matplotlib", stacklevel=2)
    plot_layers(path, layers)
    return "matplotlib"
