"""The slicing chain in this process, without Prefect or a store: what a notebook, a benchmark or a test runs
(:func:`slice_model`); the Prefect flow runs the same chain (:func:`neuralslicer.pipeline.run_chain`) as tasks."""
from __future__ import annotations

import logging
import time
from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, TypeVar

import numpy as np
import trimesh

from neuralslicer.cage import Cage, CageConfig, make_cage
from neuralslicer.config import SampleConfig, SliceConfig
from neuralslicer.errors import InputError
from neuralslicer.fea import FEAResult, run_fea, stress_samples
from neuralslicer.fea.samples import StressSamples, stress_field
from neuralslicer.fea.spec import FEASpec
from neuralslicer.verify import printed_fea_record, verify_field, verify_print
from neuralslicer.field_step import (Progress, Record, blend_record, field_of, history_of, optimised_record,
                                     s3_oneshot_record, s3_record)
from neuralslicer.gcode.writers import gcode_bytes
from neuralslicer.layers import LayerConfig, Layers, slice_layers
from neuralslicer.model.solid import Solid, implicit_solid
from neuralslicer.model.spec import ModelSpec, model_name
from neuralslicer.motion.collision import CollisionMap, CollisionReport, part_collisions
from neuralslicer.motion.plan import plan_motion_of
from neuralslicer.motion.planning import MachineProgram
from neuralslicer.motion.profile import MachineProfile
from neuralslicer.pipeline import Chain, FieldCall, run_chain
from neuralslicer.samples import SurfaceSamples, surface_samples
from neuralslicer.toolpath.config import ToolpathConfig
from neuralslicer.toolpath.plan import plan_toolpaths
from neuralslicer.toolpath.types import Toolpaths

T = TypeVar("T")
LOG = "neuralslicer"


@dataclass(frozen=True)
class Model:
    """The model step's output in process: the spec and its implicit solid."""

    spec: ModelSpec
    solid: Solid

    @property
    def fea_spec(self) -> FEASpec:
        """The spec's FEA block (an error naming the spec when it has none)."""
        if self.spec.fea is None:
            raise InputError(getattr(self.spec, "source", None) or "model",
                             "the model spec has no 'fea' block (supports and loads)")
        return self.spec.fea


@dataclass(frozen=True)
class Motion:
    """The motion step's output in process: the toolpaths as moved, the machine program, metrics and collisions."""

    toolpaths: Toolpaths
    program: MachineProgram
    metrics: dict
    collisions: CollisionReport


@dataclass
class InProcessSteps:
    """The pipeline's steps as plain calls of the core; ``wall_s`` collects each step's wall time (s), summed over
    its calls; ``progress`` (step, info) is called after every step of a neural field's optimisation."""

    s3: Any = None
    s3_oneshot: Any = None
    wall_s: dict[str, float] = field(default_factory=dict)
    progress: Progress | None = None

    def _timed(self, step: str, make: Callable[[], T]) -> T:
        """Run one step and add its wall time."""
        start = time.perf_counter()
        out = make()
        self.wall_s[step] = self.wall_s.get(step, 0.0) + time.perf_counter() - start
        return out

    def model(self, spec: ModelSpec) -> Model:
        """The implicit solid of the spec."""
        return self._timed("model", lambda: Model(spec, implicit_solid(spec)))

    def surface(self, model: Model) -> tuple[trimesh.Trimesh, dict]:
        """The boundary surface and its record."""
        arrays, attrs = self._timed("surface", model.solid.surface_record)
        return trimesh.Trimesh(arrays["vertices"], arrays["faces"], process=False), attrs

    def samples(self, model: Model, config: SampleConfig) -> SurfaceSamples:
        """Surface samples B."""
        return self._timed("samples", lambda: surface_samples(model.solid, config.n_samples, k=config.k,
                                                              seed=config.seed))

    def cage(self, model: Model, samples: SurfaceSamples, config: CageConfig) -> Cage:
        """The cage."""
        return self._timed("cage", lambda: make_cage(model.solid, samples.points, config))

    def fea(self, model: Model) -> FEAResult:
        """The isotropic FEA."""
        return self._timed("fea", lambda: run_fea(model.solid, model.fea_spec))

    def stress_samples(self, model: Model, fea: FEAResult | Record) -> StressSamples:
        """T from an FEA (or from the record of a printed part's FEA)."""
        result = FEAResult.from_arrays(*fea) if isinstance(fea, tuple) else fea
        return self._timed("stress_samples", lambda: stress_samples(result, model.fea_spec.top_fraction))

    def field(self, call: FieldCall) -> Record:
        """The field of the call's method."""
        return self._timed("field", lambda: self._field(call))

    def _field(self, call: FieldCall) -> Record:
        """The field record: a blend, an S3 field or the neural one (refined, warm-started)."""
        inputs = call.inputs
        cage, solid, objectives = inputs.cage, inputs.model.solid, list(call.objectives)
        if call.method == "blend":
            return blend_record(cage, call.blended, call.planar)
        if call.method == "s3":
            return s3_record(cage, solid, inputs.samples, inputs.stress_samples, objectives, self.s3,
                             model_name(inputs.model.spec))
        if call.method == "s3_oneshot":
            return s3_oneshot_record(cage, solid, inputs.samples, inputs.stress_samples, objectives, self.s3_oneshot)
        return optimised_record(cage, inputs.samples, inputs.stress_samples, objectives, call.neural, solid,
                                progress=self.progress, **self._starts(call))

    @staticmethod
    def _starts(call: FieldCall) -> dict[str, Any]:
        """optimise_for_solid's refine / warm_start / user field options for a neural call."""
        if not call.objectives:
            return {}
        from neuralslicer.neural.optimise import FieldResult, Refinement

        weights = FieldResult.weights_of(call.warm_start[0]) if call.warm_start is not None else None
        options: dict[str, Any] = {}
        if call.inputs.user is not None:
            options.update(user_field=call.inputs.user[1], user_field_points=call.inputs.user[0])
        if call.refine_on:
            found = [part_collisions(m.toolpaths.xyz, m.collisions.indices, m.collisions.kind, m.collisions.locations)
                     for m in call.refine_on]
            options["refine"] = Refinement.of_prints(found, weights)
        elif weights is not None:
            options["warm_start"] = weights
        return options

    def layers(self, model: Model, cage: Cage, field_: Record, config: LayerConfig) -> Layers:
        """Curved layers."""
        return self._timed("layers", lambda: slice_layers(model.solid, field_of(cage, field_), config))

    def toolpaths(self, model: Model, layers: Layers, config: ToolpathConfig, machine: MachineProfile, t_max: float,
                  fea: FEAResult | Record | None) -> Toolpaths:
        """Toolpaths on every layer."""
        result = FEAResult.from_arrays(*fea) if isinstance(fea, tuple) else fea
        stress = stress_field(result, model.fea_spec.top_fraction) if result is not None else None
        return self._timed("toolpaths", lambda: plan_toolpaths(layers.meshes, platform_z=model.solid.platform_z,
                                                               toolpath_cfg=config, profile=machine, t_max=t_max,
                                                               stress=stress))

    def motion(self, model: Model, toolpaths: Toolpaths, config: ToolpathConfig, machine: MachineProfile) -> Motion:
        """The collision check, lifts, tilts and the machine program."""
        return self._timed("motion", lambda: Motion(*plan_motion_of(
            toolpaths, platform_z=model.solid.platform_z, solid_H=model.solid.H, toolpath_cfg=config, profile=machine)))

    def hits(self, motion: Motion) -> tuple[int, int, int]:
        """Collisions: all, of the head at a waypoint, below the platform."""
        m = motion.metrics
        head = part_collisions(motion.toolpaths.xyz, motion.collisions.indices, motion.collisions.kind)[0]
        return int(m.get("n_collisions", 0)), len(head), int(m.get("n_platform_collisions", 0))

    def program(self, motion: Motion) -> bytes:
        """The G-code."""
        return self._timed("program", lambda: gcode_bytes(motion.program))

    def printed_fea(self, model: Model, fea: FEAResult, cage: Cage, field_: Record, motion: Motion) -> Record:
        """The FEA of the printed part."""
        return self._timed("fea_printed", lambda: printed_fea_record(model.solid, model.fea_spec, field_of(cage, field_),
                                                                     motion.toolpaths, fea))

    def verify(self, model: Model, fea: FEAResult, cage: Cage, field_: Record, motion: Motion | None,
               layers: LayerConfig, toolpaths: ToolpathConfig) -> Record:
        """Strain of the printed part against planar layers."""
        computed = field_of(cage, field_)
        if motion is None:
            return self._timed("verify", lambda: verify_field(model.solid, model.fea_spec, computed, fea))
        return self._timed("verify", lambda: verify_print(model.solid, model.fea_spec, computed, motion.toolpaths,
                                                          layers, toolpaths, fea))

    def note(self, message: str) -> None:
        """A warning on the ``neuralslicer`` logger."""
        logging.getLogger(LOG).warning(message)


def run_results(chain: Chain, name: str, wall_s: dict[str, float]):  # noqa: ANN201 - RunResults, imported late
    """The output contract's view of an in-process chain."""
    from neuralslicer.outputs import Attempt, RunResults, StrengthRound

    cage, motion = chain.cage, chain.printed.motion
    maps = {"printed": _collision_map(motion)}
    if chain.attempts and chain.attempts[0].motion is not motion:
        first = chain.attempts[0]
        maps = {f"first print ({first.label})": _collision_map(first.motion), **maps}
    rounds = [StrengthRound(r.label, int(r.motion.metrics.get("n_collisions", 0)), r.printed_fea[1],
                            {k.split("/", 1)[1]: v for k, v in r.printed_fea[0].items() if k.startswith("turn/")})
              for r in chain.rounds]
    return RunResults(
        model=name, surface=chain.surface[0], surface_attrs=chain.surface[1], samples=chain.samples, cage=cage,
        cage_attrs={**cage.to_arrays()[1], **cage.summary()}, field=field_of(cage, chain.printed.field), field_history=history_of(chain.printed.field),
        layers=chain.printed.layers, toolpaths=motion.toolpaths, program=motion.program, print_metrics=motion.metrics,
        collision_maps=maps, collided=np.asarray(motion.collisions.indices, np.int64), wall_s=dict(wall_s),
        stress=chain.stress_samples, verify=chain.verify,
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
    steps = InProcessSteps(config.s3, config.s3_oneshot, progress=progress)
    chain = run_chain(steps, spec, config, user_field)
    if out_dir is None:
        return chain, None
    from neuralslicer.outputs import write_outputs

    metrics = write_outputs(out_dir, run_results(chain, model_name(spec), steps.wall_s), config.alpha_deg,
                            config.neural.loss.beta_deg, config.robot)
    return chain, metrics
