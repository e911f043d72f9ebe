"""Re-plan a stored slice's layers with the current toolpath and motion code (collision check, travel lift, tilt).

Usage: ``python benchmarks/replan_store.py OUT/store.zarr [--tilt DEG] [--machine NAME]``. Reads the model and
the layers of the (first) stored run, plans the print again and prints the collision figures and the stage
timings as JSON: how the lattice and topopt figures of docs/results.md ("Slices of real models") were made.
"""
from __future__ import annotations

import argparse
import json
import time
from pathlib import Path

from neuralslicer.motion import load_profile, plan_print
from neuralslicer.toolpath.config import ToolpathConfig
from neuralslicer.storage import ArtifactRef, ArtifactStore
from neuralslicer.tasks.codec import read_layers, read_solid


def first_ref(store: Path, step: str) -> ArtifactRef:
    """The first complete group of a step in a local store."""
    st = ArtifactStore(store)
    for model in sorted(p.name for p in store.iterdir() if p.is_dir() and not p.name.startswith("_")):
        for digest in st.children(f"{model}/{step}"):
            path = f"{model}/{step}/{digest}"
            if st.exists(path):
                return ArtifactRef(str(store), path, digest)
    raise SystemExit(f"{store}: no complete {step} artifact")


def main() -> None:
    """Parse the arguments, re-plan, print the figures."""
    ap = argparse.ArgumentParser(description=__doc__)
    ap.add_argument("store", type=Path)
    ap.add_argument("--tilt", type=float, default=ToolpathConfig().collision_tilt_deg, help="collision_tilt_deg")
    ap.add_argument("--machine", default="table_bc_linuxcnc")
    args = ap.parse_args()
    solid = read_solid(first_ref(args.store, "model"))
    layers = read_layers(first_ref(args.store, "layers"))
    start = time.perf_counter()
    tp, _, m, _ = plan_print(layers.meshes, platform_z=solid.platform_z, solid_H=solid.H,
                             profile=load_profile(args.machine), toolpath_cfg=ToolpathConfig(collision_tilt_deg=args.tilt))
    print(json.dumps({"layers": len(layers.meshes), "waypoints": len(tp), "collisions": m["n_collisions"],
                      "travel_lift": m["travel_lift"], "axis_tilt": m["axis_tilt"], "axis_reach": m["axis_reach"],
                      "timings_s": m["timings_s"], "total_s": time.perf_counter() - start}, indent=1))


if __name__ == "__main__":
    main()
