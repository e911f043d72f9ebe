"""The slicing chain's steps, each written once, as data: :data:`STEPS`.

A :class:`Step` names the paper's step, the store group it writes (its name), its code version (what its cache key
covers besides its parameters and inputs), its core call and how its output is stored. Both runners are made from this
table: :class:`neuralslicer.run.in_process.InProcessSteps` calls ``compute`` on the outputs of earlier steps as they are in
memory; the Prefect flow runs one task per step (``tasks/steps.py``), which reads each input from the store by the
kind of its group (``tasks/codec.py: decode``), calls the same ``compute`` and writes ``encode`` of its output.

A step's ``compute`` takes the outputs of earlier steps and its settings by the parameter names its task has (they
enter the cache key under those names), and a :class:`StepContext`: the run's log, a progress bar and, for a step
that can resume, its checkpoints. Adding a step is one entry here and one core function (docs/ARCHITECTURE.md).
"""
from __future__ import annotations

import contextlib
import logging
from collections.abc import Callable, Mapping
from dataclasses import dataclass, field
from pathlib import Path
from types import MappingProxyType
from typing import TYPE_CHECKING, Any, ContextManager, Protocol

import numpy as np

from neuralslicer.baselines.s3_config import S3Config, S3DeformConfig
from neuralslicer.cage import Cage, CageConfig, make_cage
from neuralslicer.config import SampleConfig
from neuralslicer.layers import LayerConfig, Layers, slice_layers
from neuralslicer.model.solid import Model, implicit_solid
from neuralslicer.model.spec import ModelSpec, model_name, spec_digest
from neuralslicer.motion.output import Motion
from neuralslicer.motion.profile import MachineProfile
from neuralslicer.neural.config import NeuralConfig
from neuralslicer.run.field_step import (FieldRecord, Record, blend_record, field_of, height_record,
                                         s3_oneshot_record, s3_record)
from neuralslicer.samples import SurfaceSamples, surface_samples
from neuralslicer.toolpath.config import ToolpathConfig
from neuralslicer.toolpath.types import Toolpaths

if TYPE_CHECKING:  # the FEA's scipy.sparse and the G-code writers only where a step runs
    import trimesh

    from neuralslicer.fea.samples import StressSamples
    from neuralslicer.fea.solver import FEAResult, PrintedFEA
    from neuralslicer.gcode.writers import GCode

#: terms of the optimisation's progress lines (those of objectives not optimised are left out)
PROGRESS_TERMS = ("total", "sf", "po", "sr", "gc", "tb", "lr", "overhang", "overhang_target", "head_hits")


class Update(Protocol):
    """Moves a progress bar: ``update(done, total=None, **fields)``."""

    def __call__(self, done: int, total: int | None = None, /, **fields: Any) -> None:
        """Advance to ``done`` (of ``total`` when given), showing ``fields``."""


class Checkpoints(Protocol):
    """Where a resumable step keeps its state: the newest complete blob resumes it."""

    resumed_from: int | None

    def save(self, blob: bytes, step: int) -> None:
        """Keep a checkpoint of ``step``."""

    def load(self) -> bytes | None:
        """The newest checkpoint, if any."""


def _no_bar(description: str, total: int) -> ContextManager[Update]:
    """A progress bar that shows nothing."""
    return contextlib.nullcontext(lambda done, total=None, /, **fields: None)


@dataclass(frozen=True)
class StepContext:
    """What a step's core call uses of the runner: ``log`` (the run's log), ``progress(description, total)`` (a
    context manager giving the bar's ``update``), ``say(line)`` (a line on the terminal and in the log),
    ``checkpoints`` (a resumable step's; None: it starts over), ``on_step(step, info)`` (called after every step of an
    optimisation with all its figures), ``owns_inputs`` (the inputs were read for this call alone: a step may take
    their arrays over) and ``scratch`` (a folder on the store's disk for temporary files; None: the system's)."""

    log: logging.Logger | logging.LoggerAdapter = field(default_factory=lambda: logging.getLogger("neuralslicer"))
    progress: Callable[[str, int], ContextManager[Update]] = _no_bar
    say: Callable[[str], None] | None = None
    checkpoints: Checkpoints | None = None
    on_step: Callable[[int, dict], None] | None = None
    owns_inputs: bool = False
    scratch: Path | None = None

    def line(self, message: str) -> None:
        """A line for whoever follows the run (``say``, else the log at INFO)."""
        (self.say or self.log.info)(message)


@dataclass(frozen=True)
class Step:
    """One step of the chain: ``name`` (its task and store group kind), what the paper calls it, its code
    ``version`` (bump it when its output for the same inputs changes), its core call ``compute(**parameters,
    ctx=StepContext)`` and ``encode`` (its output as the store's ``(arrays, attrs)``).

    key : the parameters that only name or key its output (the Prefect runner adds them, ``key_of`` of the others;
    ``compute`` does not take them); exclude : parameters left out of the cache key; large : (parameter, array) of
    the print whose waypoint count makes the step run in a process of its own; content_cached : the check of an
    entry of the machine's content cache, where the step's output is also kept, across stores (the cage: fTetWild's
    draw is not the same everywhere); resumable : gets checkpoints; device : the torch device it computes on, from
    its parameters (the Prefect runner tags GPU steps); retries : Prefect's retries of its task (its default when
    None); family : the role it fills in a chain (every method of the field is a "field"), its wall time's name;
    key_names : parameters keyed under an earlier name (a parameter renamed in the code keeps its stores' keys).
    """

    name: str
    paper: str
    version: str
    compute: Callable[..., Any]
    encode: Callable[[Any], Record]
    key: tuple[str, ...] = ()
    key_of: Callable[[dict[str, Any]], dict[str, Any]] | None = None
    exclude: tuple[str, ...] = ()
    large: tuple[str, str] | None = None
    content_cached: Callable[[Record], bool] | None = None
    resumable: bool = False
    device: Callable[[dict[str, Any]], str | None] | None = None
    retries: int | None = None
    family: str = ""
    key_names: Mapping[str, str] = field(default_factory=dict, hash=False)

    @property
    def role(self) -> str:
        """The role in a chain (``family``, else the name)."""
        return self.family or self.name


def identity(record: Record) -> Record:
    """A record stored as it is."""
    return record


# ---- steps 1-3: the solid, its surface, samples B, the cage ------------------------------------------------------

def model_step(spec: ModelSpec, *, ctx: StepContext) -> Model:
    """Step 1: the implicit solid H of the spec's files, in the build frame."""
    solid = implicit_solid(spec)
    name = model_name(spec)
    ctx.log.info("model %s: %s, bounds %s", name, solid, np.round(solid.bounds, 3).tolist())
    return Model(spec, solid, name)


def surface_step(model: Model, *, ctx: StepContext) -> tuple[trimesh.Trimesh, dict]:
    """The boundary surface H = 0 of the solid, its genus, volume and bounds."""
    import trimesh

    arrays, attrs = model.solid.surface_record()
    return trimesh.Trimesh(arrays["vertices"], arrays["faces"], process=False), attrs


def encode_surface(surface: tuple[trimesh.Trimesh, dict]) -> Record:
    """The surface's vertices and faces with its record."""
    mesh, attrs = surface
    return {"vertices": np.asarray(mesh.vertices), "faces": np.asarray(mesh.faces)}, attrs


def samples_step(model: Model, config: SampleConfig, *, ctx: StepContext) -> SurfaceSamples:
    """Step 2: surface samples B with normals, area weights, kNN lists and platform flags."""
    samples = surface_samples(model.solid, config.n_samples, k=config.k, seed=config.seed)
    ctx.log.info("B: %d samples, %d on the platform, residual %.2e", len(samples), samples.on_platform.sum(),
                 samples.residual)
    return samples


def cage_step(model: Model, samples: SurfaceSamples, config: CageConfig, *, ctx: StepContext) -> Cage:
    """Step 3: the tetrahedralized offset of the solid at the target element count, containing B."""
    cage = make_cage(model.solid, samples.points, config)
    ctx.log.info("cage: %d tets, %d vertices", len(cage.tets), len(cage.vertices))
    if not cage.seeded:
        ctx.log.warning("cage: fTetWild's random draw could not be seeded here (neuralslicer/tetwild_seed.py): "
                        "another machine builds another cage from these inputs")
    return cage


def encode_cage(cage: Cage) -> Record:
    """The cage's arrays, its summary and digest."""
    arrays, attrs = cage.to_arrays()
    return arrays, {**attrs, **cage.summary()}


def intact_cage(record: Record) -> bool:
    """True when a cached cage's content matches the digest recorded with it."""
    try:
        return Cage.from_arrays(*record).sha256() == record[1]["sha256"]
    except (KeyError, TypeError, ValueError):
        return False


# ---- the load case: FEA and stress samples T ---------------------------------------------------------------------

def fea_step(model: Model, *, ctx: StepContext) -> FEAResult:
    """Isotropic linear elasticity on the voxels of the solid: stresses, principal directions, tau_max."""
    from neuralslicer.fea import run_fea   # the solver (scipy.sparse): only when the step runs

    result = run_fea(model.solid, model.fea_spec)
    ctx.log.info("FEA: %d voxels, max von Mises %.3g MPa", len(result.centres), float(np.max(result.von_mises)))
    return result


def encode_to_arrays(value: Any) -> Record:
    """An output that stores itself (``to_arrays``)."""
    return value.to_arrays()


def stress_samples_step(model: Model, fea: FEAResult, *, ctx: StepContext) -> StressSamples:
    """T: voxel centres in the top fraction of max principal stress magnitude, with volume and tau_max (from the
    isotropic FEA, or from a printed part's in a strength round)."""
    from neuralslicer.fea import stress_samples

    return stress_samples(fea, model.fea_spec.top_fraction)


# ---- steps 4-9: the field, by each method ------------------------------------------------------------------------

def neural_field_step(model: Model, cage: Cage, samples: SurfaceSamples, stress_samples: StressSamples | None,
               objectives: list[str], config: NeuralConfig, user_field: tuple[np.ndarray, np.ndarray] | None = None,
               refine_prints: list[Motion] | None = None, warm_start: FieldRecord | None = None, *,
               ctx: StepContext) -> FieldRecord:
    """Steps 4-9, the printing field G: the height field without objectives, else the neural optimisation
    (checkpointed); with ``refine_prints``, L_GC's pool refined around those prints' collisions, started from
    ``warm_start``'s weights; with ``warm_start`` alone, started from its weights (a strength round)."""
    if not objectives:
        return height_record(cage)
    from neuralslicer.neural.optimise import FieldResult, Refinement, optimise_for_solid   # torch: only here

    weights = FieldResult.weights_of(warm_start.arrays) if warm_start is not None else None
    refine = Refinement.of_prints([m.part_collisions() for m in refine_prints], weights) if refine_prints else None
    start = weights if refine is None else None
    oc = config.optim
    if oc.target_overhang > 0 and "sr" not in objectives:
        ctx.line(f"optimise: stops once the overhang is at most {oc.target_overhang:g} of B (then "
                 f"{oc.target_overhang_late:g} from step {oc.late_after}), no pool point's head hits earlier material "
                 f"and L_CA = 0, checked every {oc.check_every} steps; else after {oc.max_steps} steps, when the loss "
                 "stalls" + (f" or, from step {oc.late_after}, when neither the overhang nor the head hits improved "
                             f"over {oc.progress_window} steps" if oc.progress_window else ""))
    shown = [k for k in PROGRESS_TERMS if k not in ("sf", "po", "sr", "gc") or k in objectives]
    if refine is not None:
        ctx.line(f"optimise: refining the collision term around {len(refine.hits)} colliding waypoints of the print"
                 + (", from the field that printed them" if refine.weights else ""))
    budget = (oc.refine.steps if refine is not None and refine.weights else
              min(oc.refine.steps, oc.max_steps) if start is not None else oc.max_steps)
    user = {} if user_field is None else {"user_field_points": user_field[0], "user_field": user_field[1]}
    saved = {} if ctx.checkpoints is None else {"save_checkpoint": ctx.checkpoints.save,
                                                 "load_checkpoint": ctx.checkpoints.load}
    with ctx.progress("optimise", budget) as update:
        def progress(step: int, info: dict) -> None:
            """The bar moved, and the runner's own observer told."""
            update(step, **{k: float(info[k]) for k in shown if k in info})
            if ctx.on_step is not None:
                ctx.on_step(step, info)

        result = optimise_for_solid(model.solid, cage.vertices, cage.tets, samples, stress_samples, objectives, config,
                                    refine=refine, warm_start=start, progress=progress, **user, **saved)
    ctx.log.info("optimised in %d steps (%.1f s): %s", result.steps, result.wall_time_s, result.final)
    arrays, attrs = result.to_arrays()
    resumed = ctx.checkpoints.resumed_from if ctx.checkpoints is not None else None
    return FieldRecord(arrays, {**attrs, "resumed_from_step": resumed})


def s3_field_step(model: Model, cage: Cage, samples: SurfaceSamples, stress_samples: StressSamples | None,
                  objectives: list[str], config: S3DeformConfig, *, ctx: StepContext) -> FieldRecord:
    """S3-Slicer's field G: its iterative deformation of the model's tet mesh (or the cage), carried to the cage."""
    name = model.label
    with ctx.progress("s3", config.resolve(name, objectives).outer_loops) as update:
        arrays, attrs = s3_record(cage, model.solid, samples, stress_samples, objectives, config, name,
                                  progress=lambda it, info: update(it, total=float(info["fabrication_sl"])))
    ctx.log.info("s3 on the %s mesh: %s", attrs.get("on"), attrs.get("satisfaction"))
    return FieldRecord(arrays, attrs)


def s3_oneshot_field_step(model: Model, cage: Cage, samples: SurfaceSamples, stress_samples: StressSamples | None,
                          objectives: list[str], config: S3Config, *, ctx: StepContext) -> FieldRecord:
    """The one-shot S3 variant's field G: per-element rotations optimised in the deformed space, one ARAP solve."""
    with ctx.progress("s3", config.steps) as update:
        arrays, attrs = s3_oneshot_record(cage, model.solid, samples, stress_samples, objectives, config,
                                          progress=lambda step, info: update(step, total=float(info["total"])))
    ctx.log.info("s3_oneshot: %s", attrs.get("satisfaction"))
    return FieldRecord(arrays, attrs)


def field_blend_step(cage: Cage, field: FieldRecord, planar: float, *, ctx: StepContext) -> FieldRecord:
    """The field blended toward planar layers, (1 - planar) G + planar z: the last resort against collisions."""
    ctx.log.info("field blended toward planar layers: %.3g", planar)
    return blend_record(cage, field, planar)


# ---- steps 10-12: layers, toolpaths, motion, and the program ------------------------------------------------------

def layers_step(model: Model, cage: Cage, field: FieldRecord, config: LayerConfig, *, ctx: StepContext) -> Layers:
    """Step 10: isosurfaces of G trimmed by H <= 0, isovalues chosen for the thickness range, in print order."""
    with ctx.progress("layers", 1) as update:
        layers = slice_layers(model.solid, field_of(cage, field), config, progress=update)
    ctx.log.info("layers: %d, thickness %s", len(layers.meshes),
                 {k: round(v, 3) for k, v in layers.report.items() if k.startswith("thickness")})
    return layers


def toolpaths_step(model: Model, layers: Layers, config: ToolpathConfig, machine: MachineProfile, t_max: float,
                   fea: FEAResult | None = None, *, ctx: StepContext) -> Toolpaths:
    """Step 11: toolpaths on every layer (shells, infill, order, bead widths and heights); with ``fea`` the infill
    can follow its stress."""
    from neuralslicer.fea.samples import stress_field
    from neuralslicer.toolpath.plan import plan_toolpaths   # the planner (scipy): only when the step runs

    stress = stress_field(fea, model.fea_spec.top_fraction) if fea is not None else None
    tp = plan_toolpaths(layers.meshes, platform_z=model.solid.platform_z, toolpath_cfg=config, profile=machine,
                        t_max=t_max, stress=stress)
    ctx.log.info("toolpaths: %d waypoints, %d paths", len(tp), int(tp.attrs.get("n_paths", 0)))
    return tp


def motion_step(model: Model, toolpaths: Toolpaths, config: ToolpathConfig, machine: MachineProfile, *,
                ctx: StepContext) -> Motion:
    """Step 12: the exact collision check of the head, travel lifts, tilts and reach, and the machine program (IK,
    extrusion) with the print's metrics. The toolpaths' arrays are taken over where they were read for this call
    alone; in process the chain's toolpaths stay as they are."""
    from neuralslicer.motion.plan import plan_motion_of

    motion = Motion(*plan_motion_of(toolpaths, platform_z=model.solid.platform_z, solid_H=model.solid.H,
                                    toolpath_cfg=config, profile=machine, consume=ctx.owns_inputs,
                                    scratch=ctx.scratch))
    ctx.log.info("motion: %d waypoints, %d collisions", motion.metrics["n_waypoints"], motion.metrics["n_collisions"])
    return motion


def program_step(motion: Motion, *, ctx: StepContext) -> GCode:
    """The machine program as G-code in the profile's dialect, made a layer at a time as it is read."""
    from neuralslicer.gcode.writers import GCode

    return GCode(motion.program, ctx.log)


def encode_program(gcode: GCode) -> Record:
    """The G-code as the store's ``gcode`` bytes (chunks: the store writes them as they are made)."""
    return {"gcode": gcode}, {"dialect": gcode.program.profile.gcode.dialect}


# ---- judging a print: the FEA of the printed part, the verification -----------------------------------------------

def printed_fea_step(model: Model, fea: FEAResult, cage: Cage, field: FieldRecord, motion: Motion, *,
                     ctx: StepContext) -> PrintedFEA:
    """The FEA of the printed part (transversely isotropic, filaments along the printed toolpaths, layers of the
    field), with the print's strain and how far tau_max turned; a strength round samples its T from it."""
    from neuralslicer.verify import printed_fea_of   # the anisotropic FEA (scipy): only when the step runs

    printed = printed_fea_of(model.solid, model.fea_spec, field_of(cage, field), motion.toolpaths, fea)
    ctx.log.info("printed part: max strain %.4g, tau_max turned %.1f° (median) by the printed material",
                 printed.figures["max_strain"], printed.figures["tau_turn_median_deg"])
    return printed


def verify_step(model: Model, fea: FEAResult, cage: Cage, field: FieldRecord, motion: Motion | None = None,
                layer_config: LayerConfig | None = None, toolpath_config: ToolpathConfig | None = None, *,
                ctx: StepContext) -> Record:
    """Max strain of the part printed with planar layers and with the computed layers (transversely isotropic).
    With ``motion`` (a print) the filaments lie along the printed toolpaths; without, along the ideal direction."""
    from neuralslicer.verify import verify_field, verify_print

    computed = field_of(cage, field)
    if motion is None:
        return verify_field(model.solid, model.fea_spec, computed, fea)
    return verify_print(model.solid, model.fea_spec, computed, motion.toolpaths, layer_config, toolpath_config, fea)


def _neural_device(p: dict[str, Any]) -> str | None:
    """The device of a neural field (None for the height field: nothing is optimised)."""
    return p["config"].device if p.get("objectives") else None


def _model_key(p: dict[str, Any]) -> dict[str, Any]:
    """The model step's output is named after the spec's file and keyed by its content (not by the spec's paths)."""
    return {"name": model_name(p["spec"]), "content": spec_digest(p["spec"])}


#: T was the field steps' (and the export's) parameter ``stress``: their keys still name it so
STRESS_SAMPLES_KEY: Mapping[str, str] = MappingProxyType({"stress_samples": "stress"})

#: every step of the chain, in the order a slice runs them (docs/ARCHITECTURE.md lists them with the paper's names)
STEPS: tuple[Step, ...] = (
    Step("model", "step 1: the implicit solid H", "1", model_step, encode_to_arrays, key=("name", "content"),
         key_of=_model_key, exclude=("spec",), retries=0),
    Step("surface", "the boundary surface H = 0", "1", surface_step, encode_surface),
    Step("samples", "step 2: surface samples B", "1", samples_step, encode_to_arrays),
    Step("cage", "step 3: the cage", "2", cage_step, encode_cage, content_cached=intact_cage),
    Step("fea", "the load case: isotropic voxel FEA", "1", fea_step, encode_to_arrays),
    Step("stress_samples", "stress samples T", "1", stress_samples_step, encode_to_arrays),
    Step("field", "steps 4-9: the neural field G", "4", neural_field_step, identity, resumable=True,
         device=_neural_device, family="field", key_names=STRESS_SAMPLES_KEY),
    Step("field_s3", "the S3-Slicer baseline's field", "3", s3_field_step, identity, family="field",
         key_names=STRESS_SAMPLES_KEY),
    Step("field_s3_oneshot", "the one-shot S3 variant's field", "1", s3_oneshot_field_step, identity,
         device=lambda p: p["config"].device if p.get("config") is not None else "auto", family="field",
         key_names=STRESS_SAMPLES_KEY),
    Step("field_blend", "the field blended toward planar layers", "1", field_blend_step, identity, family="field"),
    Step("layers", "step 10: curved layers", "5", layers_step, encode_to_arrays),
    Step("toolpaths", "step 11: toolpaths", "13", toolpaths_step, encode_to_arrays),
    Step("motion", "step 12: collision check and machine motion", "1", motion_step, encode_to_arrays,
         large=("toolpaths", "xyz")),
    Step("program", "the G-code", "1", program_step, encode_program, large=("motion", "toolpaths/xyz")),
    Step("fea_printed", "the FEA of the part as printed", "1", printed_fea_step, encode_to_arrays),
    Step("verify", "strain against planar layers", "3", verify_step, identity),
)

#: the steps by name
BY_NAME: dict[str, Step] = {s.name: s for s in STEPS}

#: the step of each field method (``pipeline.FieldCall.method``)
FIELD_STEPS = {"neural": "field", "s3": "field_s3", "s3_oneshot": "field_s3_oneshot", "blend": "field_blend"}


def step(name: str) -> Step:
    """The step of this name (a KeyError naming the known ones otherwise)."""
    try:
        return BY_NAME[name]
    except KeyError:
        raise KeyError(f"no step {name!r}; the steps: {', '.join(BY_NAME)}") from None
