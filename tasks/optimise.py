"""The field optimisation task body: samples in, optimised field out, checkpoints in the store."""
from __future__ import annotations

import numpy as np
from prefect import get_run_logger

from neuralslicer.cage import Cage
from neuralslicer.fea.samples import StressSamples
from neuralslicer.model.solid import Solid
from neuralslicer.neural.config import NeuralConfig
from neuralslicer.neural.head_collision import collision_pool
from neuralslicer.neural.optimise import optimise_field
from neuralslicer.samples import SurfaceSamples
from storage import ArtifactRef, ArtifactStore
from tasks.progress import Progress

KEEP_CHECKPOINTS = 2


def objective_config(config: NeuralConfig, objectives: list[str]) -> NeuralConfig:
    """The config with the loss weights of objectives that were not asked for set to zero."""
    loss = config.loss.model_copy(
        update={
            "w_sf": config.loss.w_sf if "sf" in objectives else 0.0,
            "w_po": config.loss.w_po if "po" in objectives else 0.0,
            "w_sr": (config.loss.w_sr or 1.0) if "sr" in objectives else 0.0,
            "w_gc": (config.loss.w_gc or 1.0) if "gc" in objectives else 0.0,
            "collision": "ca" in objectives,
        }
    )
    return config.model_copy(update={"loss": loss})


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
        get_run_logger().info("resuming the optimisation from step %d", self.resumed_from)
        return self.store.read_blob(f"{self.root}/{names[-1]}")


def run_optimisation(
    out: ArtifactRef,
    cage: Cage,
    samples: SurfaceSamples,
    stress: StressSamples | None,
    objectives: list[str],
    config: NeuralConfig,
    solid: Solid,
    user_field: np.ndarray | None = None,
    user_field_points: np.ndarray | None = None,
) -> tuple[dict, dict]:
    """Run the neural optimisation with store checkpoints and a progress bar; return arrays and attrs to store."""
    checkpoints = StoreCheckpoints(ArtifactStore(out.store), f"{out.model}/checkpoints/{out.digest}")
    cfg = objective_config(config, objectives)
    pool = None
    if cfg.loss.w_gc > 0:
        pool = collision_pool(solid.H, solid.bounds, solid.volume(), samples.points, cfg.loss.gc_points,
                              cfg.loss.gc_spacing, seed=cfg.optim.seed)
    with Progress("optimise", total=cfg.optim.max_steps) as bar:
        result = optimise_field(
            cage.vertices, cage.tets, samples, stress, config=cfg, platform_z=solid.platform_z,
            user_field=user_field, user_field_points=user_field_points,
            progress=lambda step, info: bar.update(
                step, **{k: float(info[k]) for k in ("total", "sf", "po", "sr", "gc", "lr") if k in info}
            ),
            save_checkpoint=checkpoints.save, load_checkpoint=checkpoints.load, collision_pool=pool,
        )
    arrays, attrs = result.to_arrays()
    get_run_logger().info("optimised in %d steps (%.1f s): %s", result.steps, result.wall_time_s, result.final)
    return arrays, {**attrs, "objectives": list(objectives), "kind": "neural", "resumed_from_step": checkpoints.resumed_from}
