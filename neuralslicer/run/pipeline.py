"""The slicing chain, written once (SPEC steps 1-12): model -> surface -> samples -> cage -> [FEA -> T] -> field ->
layers -> toolpaths -> motion -> program, with the collision policy's attempts and the strength rounds.

The chain runs on any :class:`Steps`: each call runs one step of the table (:mod:`neuralslicer.run.step_table`) by its
name. :class:`neuralslicer.run.in_process.InProcessSteps` calls the step's core function in this process (a notebook, a
benchmark, :func:`neuralslicer.run.in_process.slice_model`); the Prefect flow's steps run each as a task on a store and
hand store references along. Handles (``H``) are whatever the steps pass between them.
"""
from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass, field
from typing import Any, Generic, Protocol, TypeVar

from neuralslicer.config import SliceConfig
from neuralslicer.layers import LayerConfig
from neuralslicer.model.spec import ModelSpec
from neuralslicer.motion.profile import MachineProfile, load_profile
from neuralslicer.run.collision_policy import CollisionPolicy, FieldRequest, PrintAttempt, run_policy
from neuralslicer.toolpath.config import ToolpathConfig

H = TypeVar("H")


@dataclass(frozen=True)
class Printed(Generic[H]):
    """One field carried through to a planned print: the field, its layers, toolpaths and motion."""

    field: H
    layers: H
    toolpaths: H
    motion: H


@dataclass(frozen=True)
class FieldInputs(Generic[H]):
    """What every field of one slice is computed from: the model, cage, samples B, stress samples T (or None) and a
    user's initial guess (or None)."""

    model: H
    cage: H
    samples: H
    stress_samples: H | None = None
    user: H | None = None


@dataclass(frozen=True)
class FieldCall(Generic[H]):
    """How one field is computed, the request's indices resolved to the handles they name: the one choice both
    runners follow (:func:`field_call`).

    method : "blend" (the field ``blended`` toward planar layers by ``planar``), "s3", "s3_oneshot" or "neural" (the
    height field without objectives); config : the method's settings (NeuralConfig, S3DeformConfig or S3Config);
    refine_on : the motions of the prints whose collisions refine L_GC's pool; warm_start : the field whose weights
    start the optimisation.
    """

    method: str
    inputs: FieldInputs[H]
    objectives: tuple[str, ...]
    config: Any = None
    planar: float = 0.0
    blended: H | None = None
    refine_on: tuple[H, ...] = ()
    warm_start: H | None = None


def field_call(request: FieldRequest, inputs: FieldInputs[H], earlier: Sequence[Printed[H]],
               baselines: dict[str, Any] | None = None) -> FieldCall[H]:
    """The field a request asks for (``refine_on``, ``warm_start`` and ``blend`` index ``earlier``): a blend before
    any method, then the request's method (``baselines``: the settings of the S3 methods, by method)."""
    if request.blend is not None:
        planar, of = request.blend
        return FieldCall("blend", inputs, request.objectives, planar=planar, blended=earlier[of].field)
    if request.method in ("s3", "s3_oneshot"):
        return FieldCall(request.method, inputs, request.objectives, (baselines or {}).get(request.method))
    return FieldCall("neural", inputs, request.objectives, request.neural,
                     refine_on=tuple(earlier[i].motion for i in request.refine_on),
                     warm_start=earlier[request.warm_start].field if request.warm_start is not None else None)


def field_parameters(call: FieldCall[H]) -> tuple[str, dict[str, Any]]:
    """The step that computes a call's field and its parameters (the same for every runner: its cache key)."""
    i = call.inputs
    if call.method == "blend":
        return "field_blend", {"cage": i.cage, "field": call.blended, "planar": call.planar}
    common = {"model": i.model, "cage": i.cage, "samples": i.samples, "stress_samples": i.stress_samples,
              "objectives": list(call.objectives), "config": call.config}
    if call.method in ("s3", "s3_oneshot"):
        return f"field_{call.method}", common
    starts: dict[str, Any] = {"refine_prints": list(call.refine_on)} if call.refine_on else {}
    if call.warm_start is not None:
        starts["warm_start"] = call.warm_start
    return "field", {**common, "user_field": i.user, **starts}


class Steps(Protocol[H]):
    """Runs the steps of the table (:data:`neuralslicer.run.step_table.STEPS`); the chain decides the order and what to do
    after a colliding print."""

    def run(self, step: str, **parameters: Any) -> H:
        """The output of step ``step`` (its name in the table) for these parameters (its task's, by name)."""

    def hits(self, motion: H) -> tuple[int, int, int]:
        """(colliding waypoints, those whose head hits material or the platform, those below the platform)."""

    def note(self, message: str) -> None:
        """A warning for the run's log."""

    def release(self, printed: Printed[H]) -> None:
        """A print that will not be kept: drop what only a kept print needs (its per-waypoint arrays), keeping what
        later steps read of it (its metrics and where the head hit)."""

    def restore(self, printed: Printed[H]) -> bool:
        """Whether this print had been released (by an earlier run's collision resolution): if so, what is left of
        it is dropped so that printing its field again makes it whole."""

    def check_room(self, like: Printed[H]) -> None:
        """Raise when there is no room for another print like this one (its size where it is kept)."""


@dataclass(frozen=True)
class TriedPrint(Generic[H]):
    """One field the collision policy printed on the way to the kept print: its request's label, field and motion."""

    label: str
    field: H
    motion: H


@dataclass(frozen=True)
class RoundPrint(Generic[H]):
    """One strength round: its label, the field and motion it printed, and the FEA of that print."""

    label: str
    field: H
    motion: H
    printed_fea: H


@dataclass
class Chain(Generic[H]):
    """Every step's output of one slice: the print kept, every field tried (when there was more than one) and every
    strength round."""

    model: H
    surface: H
    samples: H
    cage: H
    fea: H | None
    stress_samples: H | None
    printed: Printed[H]
    program: H
    verify: H | None = None
    attempts: list[TriedPrint[H]] = field(default_factory=list)
    rounds: list[RoundPrint[H]] = field(default_factory=list)


@dataclass(frozen=True)
class Printer(Generic[H]):
    """Layers, toolpaths and motion of a field with one slice's settings."""

    steps: Steps[H]
    inputs: FieldInputs[H]
    layer_config: LayerConfig
    toolpath: ToolpathConfig
    machine: MachineProfile
    infill_fea: H | None = None
    baselines: dict[str, Any] = field(default_factory=dict)

    def field(self, call: FieldCall[H]) -> H:
        """The field of a call."""
        step, parameters = field_parameters(call)
        return self.steps.run(step, **parameters)

    def print_field(self, field_: H, stress_of: H | None = None) -> Printed[H]:
        """The field's layers, toolpaths (the infill following ``stress_of``'s stress, by default the isotropic FEA's,
        when the infill follows the stress) and motion."""
        s, model = self.steps, self.inputs.model
        layers = s.run("layers", model=model, cage=self.inputs.cage, field=field_, config=self.layer_config)
        fea = (stress_of or self.infill_fea) if self.infill_fea is not None else None
        toolpaths = s.run("toolpaths", model=model, layers=layers, config=self.toolpath, machine=self.machine,
                          t_max=self.layer_config.t_max, fea=fea)
        motion = s.run("motion", model=model, toolpaths=toolpaths, config=self.toolpath, machine=self.machine)
        return Printed(field_, layers, toolpaths, motion)

    def attempt(self, request: FieldRequest, earlier: Sequence[Printed[H]]) -> tuple[Printed[H], PrintAttempt]:
        """Compute and print the field a request asks for (after checking there is room for it); what its print
        hit."""
        if earlier:
            self.steps.check_room(earlier[-1])
        printed = self.print_field(self.field(field_call(request, self.inputs, earlier, self.baselines)))
        n, head, platform = self.steps.hits(printed.motion)
        if n:
            self.steps.note(f"{request.label}: {n} nozzle collisions ({head} of the head at a waypoint, {platform} "
                            "below the platform)")
        return printed, PrintAttempt(request, n, head, platform)


def run_chain(steps: Steps[H], spec: ModelSpec, config: SliceConfig, user: H | None = None) -> Chain[H]:
    """The whole slice on these steps: the fields the collision policy asks for until one prints clean (or the
    policy gives up), the strength rounds, the verification, and the kept print's program."""
    objectives = config.objectives_for(spec)
    model = steps.run("model", spec=spec)
    surface = steps.run("surface", model=model)
    samples = steps.run("samples", model=model, config=config.samples)
    cage = steps.run("cage", model=model, samples=samples, config=config.cage)
    fea = steps.run("fea", model=model) if config.needs_fea(spec) else None
    samples_t = steps.run("stress_samples", model=model, fea=fea) if "sr" in objectives else None
    machine, toolpath = load_profile(config.machine), config.toolpath_for(spec)
    neural = config.neural.with_head(machine.nozzle, config.toolpath.line_width, toolpath.collision_tilt_deg
                                     ).with_tilt_bound(machine.printing_direction_bound_deg())
    printer = Printer(steps, FieldInputs(model, cage, samples, samples_t, user), config.layers, toolpath, machine,
                      fea if toolpath.infill == "stress" else None, {"s3": config.s3, "s3_oneshot": config.s3_oneshot})
    outputs, attempts, kept = run_policy(CollisionPolicy.for_config(config, neural, objectives), printer.attempt,
                                         None if config.keep_attempts else steps.release)
    printed, request = outputs[kept], attempts[kept].request
    if steps.restore(printed):   # released by a run whose resolution went further: printed again, whole
        steps.note(f"{request.label}: its print was released by an earlier run; printing it again")
        printed = printer.print_field(printed.field)
    rounds: list[RoundPrint[H]] = []
    if config.sr_rounds > 1 and "sr" in request.objectives and config.method == "neural":
        printed, rounds = strength_rounds(printer, fea, printed, request, config.sr_rounds)
    verify = None
    if config.verify:
        verify = steps.run("verify", model=model, fea=fea, cage=cage, field=printed.field,
                           motion=None if config.verify_tangents == "ideal" else printed.motion,
                           layer_config=config.layers, toolpath_config=toolpath)
    listed = [TriedPrint(a.request.label, o.field, o.motion) for a, o in zip(attempts, outputs)]
    return Chain(model, surface, samples, cage, fea, samples_t, printed, steps.run("program", motion=printed.motion),
                 verify, listed if len(listed) > 1 else [], rounds)


def strength_rounds(printer: Printer[H], fea: H, current: Printed[H], request: FieldRequest, n_rounds: int
                    ) -> tuple[Printed[H], list[RoundPrint[H]]]:
    """Strength rounds (``sr_rounds``, beyond the paper): the FEA of the part as printed (its filaments, its layers)
    gives the stress the print really carries; T and tau_max are sampled from it and the field re-optimised from
    its weights, then layered and printed with the infill following that stress, ``n_rounds`` - 1 times. A round
    whose print collides ends the rounds and the print before it is kept. Returns the final print and every round."""
    s, inputs = printer.steps, printer.inputs
    rounds: list[RoundPrint[H]] = []
    for r in range(1, n_rounds + 1):
        printed = s.run("fea_printed", model=inputs.model, fea=fea, cage=inputs.cage, field=current.field,
                        motion=current.motion)
        rounds.append(RoundPrint(f"round {r}" + (" (isotropic tau_max, the paper)" if r == 1 else ""),
                                    current.field, current.motion, printed))
        if r == n_rounds:
            break
        samples_t = s.run("stress_samples", model=inputs.model, fea=printed)
        again = FieldRequest(f"strength round {r + 1}", "strength", request.method, request.neural, request.objectives,
                             warm_start=0)
        field_ = printer.field(field_call(again, FieldInputs(inputs.model, inputs.cage, inputs.samples, samples_t),
                                         [current]))
        candidate = printer.print_field(field_, printed)
        n = s.hits(candidate.motion)[0]
        if n:
            s.note(f"strength round {r + 1}: its print has {n} nozzle collisions; the print of round {r} is kept")
            break
        current = candidate
    return current, rounds
