"""Pictures and the Markdown report of a slice: layer preview, angle histograms, learning curves."""
from __future__ import annotations

from collections.abc import Sequence
from pathlib import Path

import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt  # noqa: E402
import numpy as np  # noqa: E402
import trimesh  # noqa: E402
from mpl_toolkits.mplot3d.art3d import Poly3DCollection  # noqa: E402

from neuralslicer.fileio import atomic_path  # noqa: E402


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
        centre, half = (lo + hi) / 2, (hi - lo).max() / 2
        ax.set_xlim(centre[0] - half, centre[0] + half)
        ax.set_ylim(centre[1] - half, centre[1] + half)
        ax.set_zlim(centre[2] - half, centre[2] + half)
        ax.view_init(elev=elev, azim=azim)
        ax.set_xlabel("x (mm)")
        ax.set_ylabel("y (mm)")
        ax.set_zlabel("z (mm)")
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


def plot_collision_map(path: Path, prints: dict[str, tuple[np.ndarray, np.ndarray]], max_points: int = 40_000) -> None:
    """Where the head hits: waypoints (n,3) of each print, grey, with the colliding ones (bool (n,)) in red,
    one 3D view per print in the order given (the first field printed, then what resolved its collisions)."""
    n = max(len(prints), 1)
    fig = plt.figure(figsize=(5.5 * n, 5.5))
    for k, (label, (xyz, hit)) in enumerate(prints.items()):
        ax = fig.add_subplot(1, n, k + 1, projection="3d")
        ok = np.flatnonzero(~hit)
        ok = ok[:: max(1, len(ok) // max_points)]
        ax.scatter(*xyz[ok].T, s=0.6, c=xyz[ok, 2], cmap="Greys", vmin=xyz[:, 2].min() - 0.6 * np.ptp(xyz[:, 2]),
                   alpha=0.5, linewidths=0)
        bad = np.flatnonzero(hit)
        bad = bad[:: max(1, len(bad) // max_points)]
        ax.scatter(*xyz[bad].T, s=3, c="red", linewidths=0)
        lo, hi = xyz.min(axis=0), xyz.max(axis=0)
        centre, half = (lo + hi) / 2, max(float((hi - lo).max()) / 2, 1e-6)
        ax.set_xlim(centre[0] - half, centre[0] + half)
        ax.set_ylim(centre[1] - half, centre[1] + half)
        ax.set_zlim(centre[2] - half, centre[2] + half)
        ax.view_init(elev=20, azim=-60)
        ax.set_title(f"{label}\n{int(hit.sum()):,} colliding of {len(hit):,} waypoints", fontsize=9)
    fig.suptitle("print head collisions (red) against earlier layers and the platform")
    _save(fig, path)


def markdown_report(title: str, metrics: dict, figures: dict[str, str], sections: dict[str, str] | None = None) -> str:
    """A Markdown report: a metrics table, extra sections, and the figures."""
    lines = [f"# {title}", "", "| metric | value |", "| --- | --- |"]
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
