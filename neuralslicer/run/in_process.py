"""The slicing chain in this process, without Prefect or a store: what a notebook, a benchmark or a test runs
(:func:`slice_model`); the Prefect flow runs the same chain (:func:`neuralslicer.run.pipeline.run_chain`) as tasks."""
from __future__ import annotations

import logging
import time
from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, TypeVar

import numpy as np

from neuralslicer.config import SliceConfig
from neuralslicer.model.solid import Model
from neuralslicer.model.spec import ModelSpec, model_name
from neuralslicer.motion.collision import CollisionMap
from neuralslicer.motion.output import Motion, print_hits
from neuralslicer.run.field_step import Progress, field_of, history_of
from neuralslicer.run.pipeline import Chain, Printed, run_chain
from neuralslicer.run.step_table import StepContext, encode_cage, step

T = TypeVar("T")
LOG = "neuralslicer"

__all__ = ["InProcessSteps", "Model", "Motion", "run_results", "slice_model"]


@dataclass
class InProcessSteps:
    """The table's steps as plain calls of their core functions on the outputs of earlier steps as they are in memory;
    ``wall_s`` collects each step's wall time (s) by its role, summed over its calls; ``progress`` (step, info) is
    called after every step of a neural field's optimisation."""

    wall_s: dict[str, float] = field(default_factory=dict)
    progress: Progress | None = None

    def _timed(self, step_: str, make: Callable[[], T]) -> T:
        """Run one step and add its wall time."""
        start = time.perf_counter()
        out = make()
        self.wall_s[step_] = self.wall_s.get(step_, 0.0) + time.perf_counter() - start
        return out

    def run(self, name: str, **parameters: Any) -> Any:
        """The step's core call on these parameters."""
        s = step(name)
        context = StepContext(log=logging.getLogger(LOG), on_step=self.progress)
        return self._timed(s.role, lambda: s.compute(**parameters, ctx=context))

    def hits(self, motion: Motion) -> tuple[int, int, int]:
        """Collisions: all, of the head at a waypoint, below the platform."""
        return print_hits(motion)

    def note(self, message: str) -> None:
        """A warning on the ``neuralslicer`` logger."""
        logging.getLogger(LOG).warning(message)

    def release(self, printed: Printed[Any]) -> None:
        """Nothing: a print in memory is dropped with the chain."""

    def restore(self, printed: Printed[Any]) -> bool:
        """False: nothing in memory is released."""
        return False

    def check_room(self, like: Printed[Any]) -> None:
        """Nothing: the prints are in memory, not on a disk."""


def run_results(chain: Chain, name: str, wall_s: dict[str, float]):  # noqa: ANN201 - RunResults, imported late
    """The output contract's view of an in-process chain."""
    from neuralslicer.run.outputs import Attempt, RunResults, StrengthRound

    cage, motion = chain.cage, chain.printed.motion
    maps = {"printed": _collision_map(motion)}
    if chain.attempts and chain.attempts[0].motion is not motion:
        first = chain.attempts[0]
        maps = {f"first print ({first.label})": _collision_map(first.motion), **maps}
    rounds = [StrengthRound(r.label, int(r.motion.metrics.get("n_collisions", 0)), r.printed_fea.to_arrays()[1],
                            dict(r.printed_fea.turn)) for r in chain.rounds]
    return RunResults(
        model=name, surface=chain.surface[0], surface_attrs=chain.surface[1], samples=chain.samples, cage=cage,
        cage_attrs=encode_cage(cage)[1], field=field_of(cage, chain.printed.field),
        field_history=history_of(chain.printed.field),
        layers=chain.printed.layers, toolpaths=motion.toolpaths, program=motion.program, print_metrics=motion.metrics,
        collision_maps=maps, collided=np.asarray(motion.collisions.indices, np.int64), wall_s=dict(wall_s),
        stress_samples=chain.stress_samples, verify=chain.verify,
        attempts=[Attempt(a.label, field_of(cage, a.field), a.motion.metrics) for a in chain.attempts],
        strength_rounds=rounds, gcode=chain.program)


def _collision_map(motion: Motion) -> CollisionMap:
    """Where the head of a print hits, as its figure draws it."""
    return CollisionMap.of_indices(motion.toolpaths.xyz, motion.collisions.indices)


def slice_model(spec: ModelSpec, config: SliceConfig, out_dir: str | Path | None = None,
                user_field: tuple[np.ndarray, np.ndarray] | None = None,
                progress: Progress | None = None) -> tuple[Chain, dict[str, Any] | None]:
    """Slice one model in this process: the chain's outputs and, with ``out_dir``, the output contract written there
    (its metrics returned). ``user_field``: (points (p,3), values (p,)) for the ``user`` initial guess; ``progress``:
    called with (step, info) after each step of a neural field's optimisation."""
    steps = InProcessSteps(progress=progress)
    chain = run_chain(steps, spec, config, user_field)
    if out_dir is None:
        return chain, None
    from neuralslicer.run.outputs import write_outputs

    metrics = write_outputs(out_dir, run_results(chain, model_name(spec), steps.wall_s), config.alpha_deg,
                            config.neural.loss.beta_deg, config.robot)
    return chain, metrics
