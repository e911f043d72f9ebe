"""Time the exact collision check on a window of layers of a stored print.

Usage: ``python benchmarks/bench_collision.py OUT/store.zarr LO HI [--machine NAME] [--platform-z Z]``.
Reads the first stored print (``toolpaths`` step), keeps its layers below HI as material and checks the waypoints
of layers LO..HI-1 against it, as the print's check does for those layers; prints the wall time, the number of colliding
waypoints and a checksum of their indices as JSON (the same checksum means the same hits). How the window figures
in docs/toolpaths.md ("Collision checks") were made: the 200 mm bunny's first print, layers 140-146.
"""
from __future__ import annotations

import argparse
import json
import time
from pathlib import Path

import numpy as np

from neuralslicer.motion import load_profile
from neuralslicer.motion.collision import check_collisions
from neuralslicer.toolpath.types import Toolpaths
from replan_store import first_ref
from tasks.codec import attrs_of, read_print, read_solid


def main() -> None:
    """Check the window and print the figures."""
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("store", type=Path)
    ap.add_argument("lo", type=int)
    ap.add_argument("hi", type=int)
    ap.add_argument("--machine", default="table_bc_linuxcnc")
    ap.add_argument("--platform-z", type=float, default=None, help="default: the stored solid's")
    args = ap.parse_args()
    ref = first_ref(args.store, "toolpaths")
    tp, _, _ = read_print(ref)
    platform_z = args.platform_z
    if platform_z is None:
        platform_z = float(read_solid(first_ref(args.store, "model")).platform_z)
    keep = tp.layer < args.hi
    sub = Toolpaths(**{k: getattr(tp, k)[keep] for k in ("layer", "path", "xyz", "axis", "thickness", "width",
                                                          "extrude")})
    only = np.flatnonzero(sub.layer >= args.lo)
    t0 = time.perf_counter()
    report = check_collisions(sub, load_profile(args.machine).nozzle, platform_z, only=only)
    wall = time.perf_counter() - t0
    print(json.dumps({"print": ref.path, "layers": [args.lo, args.hi], "poses": int(len(only)),
                      "material_waypoints": int(len(sub)), "wall_s": round(wall, 2),
                      "n_collisions": report.summary()["n_collisions"],
                      "checksum": int(np.sum(report.indices.astype(np.int64) * 7 % 1_000_003)),
                      "stored_wall_s": attrs_of(ref).get("wall_s")}))


if __name__ == "__main__":
    main()
