"""Command line of `neuralslicer preview RUN_DIR`: (re)write a finished slice's preview.html."""
from __future__ import annotations

import argparse
from typing import Any

from neuralslicer.errors import InputError


def positive(name: str, text: str) -> int:
    """A positive integer option, or an InputError naming the option."""
    try:
        value = int(text)
    except ValueError:
        raise InputError(name, f"{text!r} is not an integer") from None
    if value < 1:
        raise InputError(name, f"{value} must be at least 1")
    return value


def cmd_preview(args: argparse.Namespace) -> int:
    """Write RUN_DIR/preview.html (or --out) from the program in the run's store and say what it draws."""
    from neuralslicer.flows.preview import preview_run

    max_points = positive("--max-points", args.max_points)
    draw_budget = positive("--draw-budget", args.draw_budget)
    path, data = preview_run(args.run_dir, args.out, max_points, draw_budget)
    size = path.stat().st_size / 1e6
    print(f"preview: {path} ({size:.1f} MB; {len(data):,} of {data.n_drawable:,} moves kept, 1 in {data.factor:.1f}, "
          f"within {data.max_deviation_mm:.3g} mm; {len(data.collisions):,} colliding moves)")
    return 0


def add_preview_parser(sub: Any) -> None:
    """Options of `neuralslicer preview RUN_DIR`."""
    from neuralslicer.preview import DEFAULT_DRAW_BUDGET, DEFAULT_MAX_POINTS

    p = sub.add_parser(
        "preview", help="(re)write a slice's preview.html: the program back-plotted in the part frame",
        description="Write RUN_DIR/preview.html from the machine program in the run's store (run.json names it): one "
                    "self-contained page that opens offline in a browser and draws the program's moves through the "
                    "machine profile's forward kinematics (layer range, colour by layer, tool tilt, feed or bead "
                    "width, travels, the head at a chosen move, collisions), decimated for display.")
    p.add_argument("run_dir", help="output folder of `neuralslicer slice`")
    p.add_argument("--out", default=None, help="write the page here instead of RUN_DIR/preview.html")
    p.add_argument("--max-points", default=str(DEFAULT_MAX_POINTS),
                   help=f"most moves kept in the page (default {DEFAULT_MAX_POINTS:,}; more: a larger, slower page)")
    p.add_argument("--draw-budget", default=str(DEFAULT_DRAW_BUDGET),
                   help=f"most moves drawn at once; a wider layer range draws a coarser level (default "
                        f"{DEFAULT_DRAW_BUDGET:,})")
    p.set_defaults(func=cmd_preview)
