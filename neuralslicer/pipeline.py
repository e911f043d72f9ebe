"""The slicing chain, written once (SPEC steps 1-12): model -> surface -> samples -> cage -> [FEA -> T] -> field ->
layers -> toolpaths -> motion -> program, with the collision policy's attempts and the strength rounds.

The chain runs on any :class:`Steps`: :class:`neuralslicer.in_process.InProcessSteps` calls the core in this process
(a notebook, a benchmark, :func:`neuralslicer.in_process.slice_model`); the Prefect flow's steps run each as a
cached task and hand store references along. Handles (``H``) are whatever the steps pass between them.
"""
from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass, field
from typing import Generic, Protocol, TypeVar

from neuralslicer.cage import CageConfig
from neuralslicer.collision_policy import CollisionPolicy, FieldRequest, PrintAttempt, run_policy
from neuralslicer.config import SampleConfig, SliceConfig
from neuralslicer.layers import LayerConfig
from neuralslicer.model.spec import ModelSpec
from neuralslicer.motion.profile import MachineProfile, load_profile
from neuralslicer.neural.config import NeuralConfig
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
    height field without objectives); refine_on : the motions of the prints whose collisions refine L_GC's pool;
    warm_start : the field whose weights start the optimisation.
    """

    method: str
    inputs: FieldInputs[H]
    objectives: tuple[str, ...]
    neural: NeuralConfig | None = None
    planar: float = 0.0
    blended: H | None = None
    refine_on: tuple[H, ...] = ()
    warm_start: H | None = None


def field_call(request: FieldRequest, inputs: FieldInputs[H], earlier: Sequence[Printed[H]]) -> FieldCall[H]:
    """The field a request asks for (``refine_on``, ``warm_start`` and ``blend`` index ``earlier``): a blend before
    any method, then the request's method."""
    if request.blend is not None:
        planar, of = request.blend
        return FieldCall("blend", inputs, request.objectives, planar=planar, blended=earlier[of].field)
    if request.method in ("s3", "s3_oneshot"):
        return FieldCall(request.method, inputs, request.objectives)
    return FieldCall("neural", inputs, request.objectives, request.neural,
                     refine_on=tuple(earlier[i].motion for i in request.refine_on),
                     warm_start=earlier[request.warm_start].field if request.warm_start is not None else None)


class Steps(Protocol[H]):
    """The pipeline's steps, each one call; the chain decides the order and what to do after a colliding print."""

    def model(self, spec: ModelSpec) -> H:
        """Step 1: the implicit solid H of the spec's files."""

    def surface(self, model: H) -> H:
        """The boundary surface H = 0 of the solid, its genus, volume and bounds."""

    def samples(self, model: H, config: SampleConfig) -> H:
        """Step 2: surface samples B."""

    def cage(self, model: H, samples: H, config: CageConfig) -> H:
        """Step 3: the cage."""

    def fea(self, model: H) -> H:
        """The isotropic FEA of the spec's load case."""

    def stress_samples(self, model: H, fea: H) -> H:
        """Stress samples T from an FEA."""

    def field(self, call: FieldCall[H]) -> H:
        """Steps 4-9: the field of a call (:func:`field_call`)."""

    def layers(self, model: H, cage: H, field: H, config: LayerConfig) -> H:
        """Step 10: curved layers."""

    def toolpaths(self, model: H, layers: H, config: ToolpathConfig, machine: MachineProfile, t_max: float,
                  fea: H | None) -> H:
        """Step 11: toolpaths on every layer (the infill following ``fea``'s stress when given)."""

    def motion(self, model: H, toolpaths: H, config: ToolpathConfig, machine: MachineProfile) -> H:
        """Step 12: the exact collision check, travel lifts, tilts and the machine program."""

    def hits(self, motion: H) -> tuple[int, int, int]:
        """(colliding waypoints, those whose head hits material or the platform, those below the platform)."""

    def program(self, motion: H) -> H:
        """The machine program as G-code."""

    def printed_fea(self, model: H, fea: H, cage: H, field: H, motion: H) -> H:
        """The anisotropic FEA of the part as printed."""

    def verify(self, model: H, fea: H, cage: H, field: H, motion: H | None, layers: LayerConfig,
               toolpaths: ToolpathConfig) -> H:
        """Strain of the printed part against planar layers (``--verify``)."""

    def note(self, message: str) -> None:
        """A warning for the run's log."""


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

    def print_field(self, field_: H, stress_of: H | None = None) -> Printed[H]:
        """The field's layers, toolpaths (the infill following ``stress_of``'s stress, by default the isotropic FEA's,
        when the infill follows the stress) and motion."""
        s, model = self.steps, self.inputs.model
        layers = s.layers(model, self.inputs.cage, field_, self.layer_config)
        fea = (stress_of or self.infill_fea) if self.infill_fea is not None else None
        toolpaths = s.toolpaths(model, layers, self.toolpath, self.machine, self.layer_config.t_max, fea)
        return Printed(field_, layers, toolpaths, s.motion(model, toolpaths, self.toolpath, self.machine))

    def attempt(self, request: FieldRequest, earlier: Sequence[Printed[H]]) -> tuple[Printed[H], PrintAttempt]:
        """Compute and print the field a request asks for; what its print hit."""
        printed = self.print_field(self.steps.field(field_call(request, self.inputs, earlier)))
        n, head, platform = self.steps.hits(printed.motion)
        if n:
            self.steps.note(f"{request.label}: {n} nozzle collisions ({head} of the head at a waypoint, {platform} "
                            "below the platform)")
        return printed, PrintAttempt(request, n, head, platform)


def run_chain(steps: Steps[H], spec: ModelSpec, config: SliceConfig, user: H | None = None) -> Chain[H]:
    """The whole slice on these steps: the fields the collision policy asks for until one prints clean (or the
    policy gives up), the strength rounds, the verification, and the kept print's program."""
    objectives = config.objectives_for(spec)
    model = steps.model(spec)
    surface, samples = steps.surface(model), steps.samples(model, config.samples)
    cage = steps.cage(model, samples, config.cage)
    fea = steps.fea(model) if config.needs_fea(spec) else None
    samples_t = steps.stress_samples(model, fea) if "sr" in objectives else None
    machine, toolpath = load_profile(config.machine), config.toolpath_for(spec)
    neural = config.neural.with_head(machine.nozzle, config.toolpath.line_width, toolpath.collision_tilt_deg
                                     ).with_tilt_bound(machine.printing_direction_bound_deg())
    printer = Printer(steps, FieldInputs(model, cage, samples, samples_t, user), config.layers, toolpath, machine,
                      fea if toolpath.infill == "stress" else None)
    outputs, attempts, kept = run_policy(CollisionPolicy.for_config(config, neural, objectives), printer.attempt)
    printed, request = outputs[kept], attempts[kept].request
    rounds: list[RoundPrint[H]] = []
    if config.sr_rounds > 1 and "sr" in request.objectives and config.method == "neural":
        printed, rounds = strength_rounds(printer, fea, printed, request, config.sr_rounds)
    verify = None
    if config.verify:
        verify = steps.verify(model, fea, cage, printed.field,
                              None if config.verify_tangents == "ideal" else printed.motion, config.layers, toolpath)
    listed = [TriedPrint(a.request.label, o.field, o.motion) for a, o in zip(attempts, outputs)]
    return Chain(model, surface, samples, cage, fea, samples_t, printed, steps.program(printed.motion), verify,
                 listed if len(listed) > 1 else [], rounds)


def strength_rounds(printer: Printer[H], fea: H, current: Printed[H], request: FieldRequest, n_rounds: int
                    ) -> tuple[Printed[H], list[RoundPrint[H]]]:
    """Strength rounds (``sr_rounds``, beyond the paper): the FEA of the part as printed (its filaments, its layers)
    gives the stress the print really carries; T and tau_max are sampled from it and the field re-optimised from
    its weights, then layered and printed with the infill following that stress, ``n_rounds`` - 1 times. A round
    whose print collides ends the rounds and the print before it is kept. Returns the final print and every round."""
    s, inputs = printer.steps, printer.inputs
    rounds: list[RoundPrint[H]] = []
    for r in range(1, n_rounds + 1):
        printed = s.printed_fea(inputs.model, fea, inputs.cage, current.field, current.motion)
        rounds.append(RoundPrint(f"round {r}" + (" (isotropic tau_max, the paper)" if r == 1 else ""),
                                    current.field, current.motion, printed))
        if r == n_rounds:
            break
        samples_t = s.stress_samples(inputs.model, printed)
        again = FieldRequest(f"strength round {r + 1}", "strength", request.method, request.neural, request.objectives,
                             warm_start=0)
        field_ = s.field(field_call(again, FieldInputs(inputs.model, inputs.cage, inputs.samples, samples_t), [current]))
        candidate = printer.print_field(field_, printed)
        n = s.hits(candidate.motion)[0]
        if n:
            s.note(f"strength round {r + 1}: its print has {n} nozzle collisions; the print of round {r} is kept")
            break
        current = candidate
    return current, rounds
