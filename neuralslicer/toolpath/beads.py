"""Beads the nozzle can lay: per-waypoint thickness held to the nozzle's range, thin beads carried upwards.

The thickness of a waypoint is the gap to the layer below along the tool axis. Where that gap is thinner
than the nozzle lays with controlled flow, the waypoint does not extrude and its gap is carried to the
bead printed above it in the next layer (found at the point below that bead, within a line width), so the
material lands there instead; a gap thicker than the nozzle lays is printed at its largest bead (reported,
the layer spacing is the field's business).
"""
from __future__ import annotations

from dataclasses import replace

import numpy as np
from scipy.spatial import cKDTree

from neuralslicer.toolpath.types import Toolpaths


def hold_beads(tp: Toolpaths, bead_range: tuple[float, float], radius: float | None = None
               ) -> tuple[Toolpaths, dict]:
    """Toolpaths with beads inside ``bead_range`` (mm) and a summary.

    Layer by layer in print order: gap = measured thickness + the gap carried from the previous layer's
    skipped waypoint nearest below (within ``radius``, default the line width); a printing waypoint whose gap
    is below the range stops extruding and carries the gap on; above the range the bead is capped. Summary:
    ``fraction_outside_range`` (extruding waypoints whose gap lies outside the range, as the layers leave
    it), ``fraction_thin``/``fraction_thick`` (its two parts), ``n_skipped``, ``n_carried`` (beads made
    thicker by a carried gap), ``n_capped``, the gap histogram (``hist_edges_mm``, ``hist_counts``).
    """
    lo, hi = (float(v) for v in bead_range)
    on = tp.path >= 0
    if radius is None:
        radius = float(np.median(tp.width[on])) if on.any() else 0.5     # the line width (travels have width 0)
    printing = on & tp.extrude
    gap = tp.thickness.copy()
    extrude = tp.extrude.copy()
    carried_in = np.zeros(len(tp))
    prev: tuple[cKDTree, np.ndarray] | None = None
    cuts = np.r_[0, np.flatnonzero(np.diff(tp.layer)) + 1, len(tp)]     # a layer's waypoints are contiguous
    for a, b in zip(cuts[:-1], cuts[1:]):
        idx = a + np.flatnonzero(on[a:b])
        if not len(idx):
            continue
        if prev is not None:
            below = tp.xyz[idx] - tp.axis[idx] * tp.thickness[idx, None]
            dist, j = prev[0].query(below, distance_upper_bound=radius)
            found = np.isfinite(dist)
            carried_in[idx[found]] = prev[1][j[found]]
        gap[idx] = tp.thickness[idx] + carried_in[idx]
        thin = gap[idx] < lo
        extrude[idx[thin & printing[idx]]] = False
        deficit = np.where(thin, gap[idx], 0.0)
        prev = (cKDTree(tp.xyz[idx]), deficit) if deficit.any() else None
    summary = _summary(gap, printing, extrude, carried_in, lo, hi)
    if summary["fraction_outside_range"] == 0.0 and not carried_in.any():
        return tp, summary
    thickness = np.where(on, np.minimum(gap, hi), tp.thickness)
    return replace(tp, thickness=thickness, extrude=extrude, attrs=dict(tp.attrs)), summary


def bead_summary(tp: Toolpaths, bead_range: tuple[float, float]) -> dict:
    """The summary of :func:`hold_beads` for toolpaths printed as they are (every gap extruded)."""
    printing = (tp.path >= 0) & tp.extrude
    return _summary(tp.thickness, printing, tp.extrude, np.zeros(len(tp)), *bead_range)


def _summary(gap: np.ndarray, printing: np.ndarray, extrude: np.ndarray, carried_in: np.ndarray,
             lo: float, hi: float) -> dict:
    """Fractions of the printing waypoints (n,) whose gap lies outside [lo, hi], counts, the gap histogram."""
    n_print = int(printing.sum())
    thin, thick = printing & (gap < lo), printing & (gap > hi)
    counts, edges = np.histogram(np.clip(gap[printing], 0.0, None), bins=80,
                                 range=(0.0, max(1.5 * hi, float(gap[printing].max(initial=0.0)))))
    return {
        "thickness_range_mm": [float(lo), float(hi)], "n_extruding": n_print,
        "fraction_outside_range": float((thin | thick).sum() / max(n_print, 1)),
        "fraction_thin": float(thin.sum() / max(n_print, 1)),
        "fraction_thick": float(thick.sum() / max(n_print, 1)),
        "n_skipped": int((thin & ~extrude).sum()), "n_carried": int((printing & extrude & (carried_in > 0)).sum()),
        "n_capped": int(thick.sum()),
        "hist_edges_mm": [float(v) for v in edges], "hist_counts": [int(v) for v in counts],
    }
