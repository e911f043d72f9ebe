"""The field optimisation task body: samples in, optimised field out, checkpoints in the store."""
from __future__ import annotations

import numpy as np
from prefect import get_run_logger

from neuralslicer.cage import Cage
from neuralslicer.fea.samples import StressSamples
from neuralslicer.model.solid import Solid
from neuralslicer.neural.config import NeuralConfig
from neuralslicer.neural.optimise import Refinement, optimise_for_solid
from neuralslicer.samples import SurfaceSamples
from neuralslicer.storage import ArtifactRef, ArtifactStore
from neuralslicer.tasks.progress import Progress, say

KEEP_CHECKPOINTS = 2
PROGRESS_TERMS = ("total", "sf", "po", "sr", "gc", "tb", "lr", "overhang", "overhang_target", "head_hits")


class StoreCheckpoints:
    """Checkpoints of one optimisation as groups `<root>/step_<n>`; the newest complete one resumes a run."""

    def __init__(self, store: ArtifactStore, root: str) -> None:
        """Checkpoints under `root` in `store`."""
        self.store, self.root = store, root
        self.resumed_from: int | None = None

    def save(self, blob: bytes, step: int) -> None:
        """Write a checkpoint atomically, then prune all but the newest few."""
        self.store.write_blob(f"{self.root}/step_{step:08d}", blob, {"step": step})
        for name in self.store.children(self.root)[:-KEEP_CHECKPOINTS]:
            self.store.remove(f"{self.root}/{name}")

    def load(self) -> bytes | None:
        """The newest complete checkpoint, if any."""
        names = self.store.children(self.root)
        if not names:
            return None
        self.resumed_from = int(self.store.attrs(f"{self.root}/{names[-1]}")["step"])
        say(f"resuming the optimisation from step {self.resumed_from}")
        return self.store.read_blob(f"{self.root}/{names[-1]}")


def run_optimisation(out: ArtifactRef, cage: Cage, samples: SurfaceSamples, stress: StressSamples | None,
                     objectives: list[str], config: NeuralConfig, solid: Solid, user_field: np.ndarray | None = None,
                     user_field_points: np.ndarray | None = None, refine: Refinement | None = None,
                     warm_start: dict[str, np.ndarray] | None = None) -> tuple[dict, dict]:
    """The field step with store checkpoints and a progress bar; arrays and attrs to store. ``refine``: the
    collisions of earlier prints to refine L_GC's pool around (and the weights to start from); ``warm_start``:
    weights to start from without a refinement (a strength round)."""
    checkpoints = StoreCheckpoints(ArtifactStore(out.store), f"{out.model}/checkpoints/{out.digest}")
    oc = config.optim
    if oc.target_overhang > 0 and "sr" not in objectives:
        say(f"optimise: stops once the overhang is at most {oc.target_overhang:g} of B (then {oc.target_overhang_late:g} "
            f"from step {oc.late_after}), no pool point's head hits earlier material and L_CA = 0, checked every "
            f"{oc.check_every} steps; else after {oc.max_steps} steps, when the loss stalls"
            + (f" or, from step {oc.late_after}, when neither the overhang nor the head hits improved over "
               f"{oc.progress_window} steps" if oc.progress_window else ""))
    shown = [k for k in PROGRESS_TERMS if k not in ("sf", "po", "sr", "gc") or k in objectives]
    if refine is not None:
        say(f"optimise: refining the collision term around {len(refine.hits)} colliding waypoints of the print"
            + (", from the field that printed them" if refine.weights else ""))
    budget = (oc.refine.steps if refine is not None and refine.weights else
              min(oc.refine.steps, oc.max_steps) if warm_start is not None else oc.max_steps)
    with Progress("optimise", total=budget) as bar:
        result = optimise_for_solid(
            solid, cage.vertices, cage.tets, samples, stress, objectives, config, refine=refine, warm_start=warm_start,
            user_field=user_field,
            user_field_points=user_field_points, save_checkpoint=checkpoints.save, load_checkpoint=checkpoints.load,
            progress=lambda step, info: bar.update(step, **{k: float(info[k]) for k in shown if k in info}),
        )
    get_run_logger().info("optimised in %d steps (%.1f s): %s", result.steps, result.wall_time_s, result.final)
    arrays, attrs = result.to_arrays()
    return arrays, {**attrs, "resumed_from_step": checkpoints.resumed_from}
