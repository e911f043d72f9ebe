"""``preview.html``: one self-contained page (plotly.js inlined from the plotly package, data and controls inline)
that draws a program's decimated moves (:mod:`neuralslicer.preview.data`) and opens offline."""
from __future__ import annotations

import base64
import json
from functools import lru_cache
from importlib import resources
from pathlib import Path
from typing import Any

import numpy as np

from neuralslicer.fileio import atomic_path
from neuralslicer.motion.planning import PRINT, ProgramMoves
from neuralslicer.motion.profile import Nozzle
from neuralslicer.preview import DEFAULT_DRAW_BUDGET, DEFAULT_MAX_POINTS
from neuralslicer.preview.data import PreviewData, preview_data
from neuralslicer.types import FloatArray, IndexArray

#: the page's format (the ``schema`` of its embedded data)
PREVIEW_SCHEMA = "neuralslicer.preview/1"
#: print metrics shown in the page's header
PREVIEW_STATS = ("estimated_print_time_s", "toolpath_length_mm", "n_collisions")
#: the colour modes of the page: key, label, unit
COLOUR_MODES = (("layer", "layer", ""), ("tilt", "tool tilt", "°"), ("feed", "feed", "mm/s"),
                ("width", "bead width", "mm"))


@lru_cache(maxsize=1)
def plotly_js() -> str:
    """plotly.js as the plotly package ships it (minified), to inline in the page."""
    from plotly.offline import get_plotlyjs

    return get_plotlyjs()


@lru_cache(maxsize=2)
def page_asset(name: str) -> str:
    """The page's own script or style sheet, shipped beside this module."""
    return resources.files("neuralslicer.preview").joinpath(name).read_text(encoding="utf-8")


def encode(values: np.ndarray, dtype: str) -> dict[str, Any]:
    """An array as base64 of its little-endian bytes, for a typed array in the page."""
    arr = np.ascontiguousarray(np.asarray(values).astype(np.dtype(dtype).newbyteorder("<")))
    return {"dtype": dtype, "b64": base64.b64encode(arr.tobytes()).decode("ascii")}


def quantised(values: FloatArray, lo: float, hi: float, bits: int = 16) -> dict[str, Any]:
    """Values in [lo, hi] as unsigned integers of ``bits`` bits with the ``offset`` and ``scale`` that restore them
    (to within half a step: (hi - lo) / (2^bits - 1) / 2)."""
    top = float(2 ** bits - 1)
    scale = (hi - lo) / top if hi > lo else 1.0
    q = np.clip(np.rint((np.asarray(values, np.float64) - lo) / scale), 0, top)
    return {**encode(q, f"uint{bits}"), "offset": float(lo), "scale": float(scale)}


def _range(values: FloatArray, mask: np.ndarray | None = None) -> list[float]:
    """[min, max] of the values (where ``mask``; all of them when it selects none), [0, 1] when empty."""
    v = values[mask] if mask is not None and mask.any() else values
    v = v[np.isfinite(v)]
    return [float(v.min()), float(v.max())] if len(v) else [0.0, 1.0]


def level_notes(data: PreviewData) -> list[dict[str, Any]]:
    """Per detail level: its moves and every how many layers it draws (1: all)."""
    n_layers = max(len(np.unique(data.layer)), 1)
    notes = []
    for v in range(int(data.level.max(initial=0)) + 1):
        at = data.level >= v
        shown = max(len(np.unique(data.layer[at])), 1)
        notes.append({"n": int(at.sum()), "layer_stride": int(round(n_layers / shown))})
    return notes


def page_data(data: PreviewData, title: str, nozzle: Nozzle, stats: dict[str, Any] | None = None) -> dict[str, Any]:
    """The JSON the page's script reads: the kept moves (quantised), colour ranges (of the printing moves), head
    geometry, figures."""
    tip = data.tip if len(data) else np.zeros((1, 3))
    lo, hi = tip.min(axis=0), tip.max(axis=0)
    span = float(np.max(hi - lo)) or 1.0
    printing = data.kind == PRINT
    layer_dtype = "uint16" if len(data) == 0 or data.layer.max() < 2 ** 16 else "uint32"
    ranges = {"layer": [float(data.layer.min()), float(data.layer.max())] if len(data) else [0.0, 1.0],
              "tilt": _range(data.tilt_deg, printing), "feed": _range(data.feed_mm_s, printing),
              "width": _range(data.width_mm, printing)}
    return {
        "schema": PREVIEW_SCHEMA, "title": title, "n": len(data),
        "decimation": data.summary(), "stats": stats or {},
        "x": quantised(data.tip[:, 0], lo[0], lo[0] + span), "y": quantised(data.tip[:, 1], lo[1], lo[1] + span),
        "z": quantised(data.tip[:, 2], lo[2], lo[2] + span),
        "axis": {**encode(np.rint(np.clip(data.axis, -1, 1) * 32767).ravel(), "int16"), "scale": 1 / 32767},
        "layer": encode(data.layer, layer_dtype), "kind": encode(data.kind, "uint8"),
        "level": encode(data.level, "uint8"), "draw_budget": int(data.draw_budget), "levels": level_notes(data),
        "move": encode(data.move, "uint32"),
        "tilt": quantised(data.tilt_deg, 0.0, 180.0), "feed": quantised(data.feed_mm_s, *_range(data.feed_mm_s)),
        "width": quantised(data.width_mm, *_range(data.width_mm)),
        "collisions": encode(data.collisions, "uint32"), "ranges": ranges,
        "modes": [{"key": k, "label": label, "unit": unit} for k, label, unit in COLOUR_MODES],
        "head": {"cone_half_angle_deg": nozzle.cone_half_angle_deg, "cone_length": nozzle.cone_length,
                 "holder_radius": nozzle.holder_radius, "holder_length": nozzle.holder_length},
    }


def _script_json(doc: dict[str, Any]) -> str:
    """JSON safe inside a <script> element (no ``</`` or ``<!--`` can close it)."""
    return json.dumps(doc, separators=(",", ":"), allow_nan=False).replace("<", "\\u003c")


def _escape(text: str) -> str:
    """Text for HTML."""
    return text.replace("&", "&amp;").replace("<", "&lt;").replace(">", "&gt;")


def preview_html(data: PreviewData, title: str, nozzle: Nozzle, stats: dict[str, Any] | None = None) -> str:
    """The whole page: plotly.js, the data and the controls' script, nothing fetched."""
    return (
        "<!DOCTYPE html>\n<html lang=\"en\"><head><meta charset=\"utf-8\">"
        f"<title>{_escape(title)}</title>\n<style>{page_asset('page.css')}</style>\n"
        f"<script>{plotly_js()}</script>\n</head>\n<body>\n{page_asset('page.html')}\n"
        f"<script type=\"application/json\" id=\"preview-data\">{_script_json(page_data(data, title, nozzle, stats))}"
        f"</script>\n<script>{page_asset('page.js')}</script>\n</body></html>\n")


def preview_stats(program: ProgramMoves, metrics: dict[str, Any] | None) -> dict[str, Any]:
    """The figures in the page's header: the program's layers and the print metrics of :data:`PREVIEW_STATS` (the
    finite numbers among them)."""
    n_layers = int(program.layer.max()) + 1 if len(program) else 0
    figures = {k: (metrics or {}).get(k) for k in PREVIEW_STATS}
    return {"n_layers": n_layers, **{k: float(v) for k, v in figures.items()
                                     if isinstance(v, (int, float)) and not isinstance(v, bool) and np.isfinite(v)}}


def write_preview(path: str | Path, program: ProgramMoves, widths: FloatArray, collided_waypoints: IndexArray,
                  model: str, metrics: dict[str, Any] | None = None, max_points: int = DEFAULT_MAX_POINTS,
                  draw_budget: int = DEFAULT_DRAW_BUDGET) -> PreviewData:
    """Write ``preview.html`` of a program atomically; the decimated moves it draws.

    widths : (w,) the toolpaths' bead width per waypoint; collided_waypoints : (c,) toolpath waypoint indices whose
    head collides (``CollisionReport.indices``); model : the model's name, in the title; metrics : the print metrics
    (print time, length, collisions in the header); max_points, draw_budget : the most moves kept in the page, and
    drawn at once (:func:`neuralslicer.preview.data.decimate`).
    """
    data = preview_data(program, widths, collided_waypoints, max_points, draw_budget)
    html = preview_html(data, f"{model}: preview of print.gcode", program.profile.nozzle,
                        preview_stats(program, metrics))
    with atomic_path(path) as tmp:
        tmp.write_text(html, encoding="utf-8")
    return data
