"""Collision-driven refinement of L_GC's pool on a stored run: colliding waypoints before and after.

Usage: ``python benchmarks/bench_refine.py STORE.zarr [--model NAME] [--work DIR] [--steps N] [--lr LR]``.

Reads the model, samples, cage and optimised field of a stored slice; slices the field again and plans the
print with the current code (the exact collision check gives the colliding waypoints and the material each
hit); refines the pool around them and optimises again, warm-started from the network weights (the field
group's ``weights/*`` when it has them, else the last checkpoint of that field, else from scratch on the
refined pool); slices and plans the refined field; prints a JSON summary. Intermediate results are kept under
``--work`` so that a second call resumes.
"""
from __future__ import annotations

import argparse
import io
import json
import time
from pathlib import Path

import numpy as np
import torch

from neuralslicer.layers import LayerConfig, slice_layers
from neuralslicer.motion import load_profile, plan_print
from neuralslicer.neural.config import NeuralConfig
from neuralslicer.neural.optimise import FieldResult, Refinement, optimise_for_solid
from neuralslicer.scalar_field import ScalarField
from neuralslicer.toolpath.config import ToolpathConfig
from neuralslicer.storage import ArtifactRef, ArtifactStore
from neuralslicer.tasks.codec import read_cage, read_samples, read_solid


def ref(store: ArtifactStore, root: str, model: str, step: str) -> ArtifactRef:
    """The first complete group of a step."""
    digest = store.children(f"{model}/{step}")[0]
    return ArtifactRef(root, f"{model}/{step}/{digest}", digest)


def stored_weights(store: ArtifactStore, field: ArtifactRef) -> tuple[dict[str, np.ndarray] | None, str]:
    """The field's network weights: its weights/* arrays, else its last checkpoint's, else None."""
    arrays, _ = store.read(field.path)
    weights = FieldResult.weights_of(arrays)
    if weights is not None:
        return weights, "field weights/*"
    root = f"{field.model}/checkpoints/{field.digest}"
    names = store.children(root)
    if not names:
        return None, "none (from scratch)"
    state = torch.load(io.BytesIO(store.read_blob(f"{root}/{names[-1]}")), map_location="cpu", weights_only=True)
    return {k: v.numpy() for k, v in state["fields"].items()}, f"checkpoint {names[-1]}"


def print_and_check(solid, cage, G: np.ndarray, tp_cfg: ToolpathConfig, machine: str, t_max: float) -> dict:
    """Slice G, plan the print, and the colliding waypoints (positions, witnesses, kinds) with timings."""
    t0 = time.perf_counter()
    layers = slice_layers(solid, ScalarField(cage.vertices, cage.tets, G), LayerConfig())
    t1 = time.perf_counter()
    tp, _, metrics, report = plan_print(layers.meshes, platform_z=solid.platform_z, solid_H=solid.H,
                                        toolpath_cfg=tp_cfg, profile=load_profile(machine), t_max=t_max)
    return {"hits": tp.xyz[report.indices], "witnesses": report.locations, "kind": report.kind,
            "layers": len(layers.meshes), "waypoints": len(tp), "collisions": report.count,
            "summary": report.summary(), "slice_s": t1 - t0, "plan_s": time.perf_counter() - t1}


def cached(path: Path, make) -> dict:
    """make() once, its arrays and JSON-able values kept in path (npz)."""
    if path.exists():
        with np.load(path, allow_pickle=False) as z:
            out = {k: z[k] for k in z.files}
        return {k: (v.item() if v.ndim == 0 else v) for k, v in out.items()} | json.loads(str(out["_json"]))
    out = make()
    arrays = {k: np.asarray(v) for k, v in out.items() if isinstance(v, np.ndarray)}
    rest = {k: v for k, v in out.items() if not isinstance(v, np.ndarray)}
    np.savez(path, _json=json.dumps(rest, default=float), **arrays)
    return out


def main() -> None:
    """Parse the arguments, run before / refine / after, print the figures."""
    ap = argparse.ArgumentParser(description=__doc__)
    ap.add_argument("store", type=Path)
    ap.add_argument("--model", default=None)
    ap.add_argument("--work", type=Path, default=Path("runs/bench_refine"))
    ap.add_argument("--steps", type=int, default=None, help="optim.refine.steps (default: the config's)")
    ap.add_argument("--lr", type=float, default=None, help="optim.refine.lr (default: the config's)")
    ap.add_argument("--machine", default="table_bc_linuxcnc")
    args = ap.parse_args()
    root = str(args.store)
    store = ArtifactStore(root, create=False)
    model = args.model or next(p.name for p in args.store.iterdir() if p.is_dir() and not p.name.startswith("_"))
    work = args.work / model
    work.mkdir(parents=True, exist_ok=True)
    solid = read_solid(ref(store, root, model, "model"))
    cage = read_cage(ref(store, root, model, "cage"))
    samples = read_samples(ref(store, root, model, "samples"))
    field = ref(store, root, model, "field")
    field_attrs = store.attrs(field.path)
    G0 = store.read(field.path, ["G"])[0]["G"]
    tp_attrs = store.attrs(ref(store, root, model, "toolpaths").path) if store.children(
        f"{model}/toolpaths") else {"config": {}, "t_max": 1.0}
    tp_cfg, t_max = ToolpathConfig(**tp_attrs["config"]), float(tp_attrs.get("t_max", 1.0))
    config = NeuralConfig.model_validate(field_attrs["config"])
    update = {k: v for k, v in (("steps", args.steps), ("lr", args.lr)) if v is not None}
    if update:
        refine = config.optim.refine.model_copy(update=update)
        config = config.model_copy(update={"optim": config.optim.model_copy(update={"refine": refine})})
    objectives = list(field_attrs.get("objectives", ["sf", "po", "gc", "ca"]))
    before = cached(work / "before.npz", lambda: print_and_check(solid, cage, G0, tp_cfg, args.machine, t_max))
    weights, source = stored_weights(store, field)

    def refined() -> dict:
        t0 = time.perf_counter()
        result = optimise_for_solid(solid, cage.vertices, cage.tets, samples, None, objectives, config,
                                    refine=Refinement(before["hits"], before["witnesses"], weights))
        return {"G": result.G, "optimise_s": time.perf_counter() - t0, "steps": result.steps,
                "converged": result.converged, "refinement": result.attrs["refinement"],
                "head_collision": result.attrs["head_collision"], "satisfaction": result.satisfaction}

    run = cached(work / "refined.npz", refined)
    after = cached(work / "after.npz", lambda: print_and_check(solid, cage, run["G"], tp_cfg, args.machine, t_max))
    print(json.dumps({
        "model": model, "warm_start": source, "stored_field": {k: field_attrs.get(k) for k in ("steps", "converged")},
        "stored_overhang": field_attrs["satisfaction"]["overhang_area_fraction"],
        "before": {k: before[k] for k in ("layers", "waypoints", "collisions", "summary", "slice_s", "plan_s")},
        "refined": {k: run[k] for k in ("optimise_s", "steps", "converged", "refinement", "head_collision",
                                        "satisfaction")},
        "after": {k: after[k] for k in ("layers", "waypoints", "collisions", "summary", "slice_s", "plan_s")},
    }, indent=1, default=float))


if __name__ == "__main__":
    main()
