"""The slicing flow: model -> solid -> samples -> cage -> field -> layers -> outputs, every step cached."""
from __future__ import annotations

import re
import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Callable

from prefect import flow, get_run_logger
from prefect.states import State

from neuralslicer.config import SliceConfig
from neuralslicer.layers import LayerConfig
from neuralslicer.neural.config import NeuralConfig
from neuralslicer.provenance import add_to_metrics, provenance
from neuralslicer.model.spec import ModelSpec, spec_digest
from neuralslicer.scalar_field import smallest_clean_blend
from neuralslicer.motion.profile import load_profile
from flows.settings import artifact_key
from storage import ArtifactRef, ArtifactStore, write_json_atomic
from tasks.codec import n_collisions, n_platform_collisions, read_part_collisions, store_user_field
from tasks.common import run_step
from tasks.export import export_task
from tasks.fea import fea_task, printed_fea_task, stress_samples_task, verify_task
from tasks.provenance import record_provenance
from tasks.steps import (cage_task, field_blend_task, field_task, layers_task, model_task, s3_field_task,
                         s3_oneshot_field_task, samples_task, solid_task, toolpaths_task)


@dataclass
class RunLog:
    """The state of every task of one flow run, in order."""

    states: list[tuple[str, str]] = field(default_factory=list)
    #: wall time of each task run (s), Prefect's round trips included, in the order of ``states``
    walls: list[float] = field(default_factory=list)

    def run(self, task: Any, **params: Any) -> ArtifactRef:
        """Run a task, record its final state name (Completed / Cached / ...) and wall time, return its result."""
        start = time.perf_counter()
        state: State = run_step(task, **params)
        self.states.append((task.name, state.name))
        self.walls.append(time.perf_counter() - start)
        return state.result()


def model_name(spec: ModelSpec) -> str:
    """A store-safe model name from the spec's source file."""
    source = Path(getattr(spec, "source", None) or spec.components[0].file)
    stem = source.parent.name if source.stem in ("model", "spec") and source.parent.name else source.stem
    return re.sub(r"[^A-Za-z0-9_.-]", "_", stem) or "model"


def smoother(config: NeuralConfig, factor: float) -> NeuralConfig:
    """The neural config with the harmonic (smoothness) weights multiplied."""
    loss = config.loss.model_copy(update={"w_hs": config.loss.w_hs * factor, "w_hq": config.loss.w_hq * factor})
    return config.model_copy(update={"loss": loss})


def firmer_floor(config: NeuralConfig, factor: float) -> NeuralConfig:
    """The neural config with L_GC's floor (platform) weight multiplied."""
    loss = config.loss.model_copy(update={"gc_floor_weight": config.loss.gc_floor_weight * factor})
    return config.model_copy(update={"loss": loss})


def blend_until_collision_free(
    log: RunLog, store: str, model: ArtifactRef, cage: ArtifactRef, field_ref: ArtifactRef, config: SliceConfig,
    print_layers: Callable[[ArtifactRef], ArtifactRef], attempts: list[tuple[str, ArtifactRef, ArtifactRef]],
) -> tuple[ArtifactRef, ArtifactRef, ArtifactRef]:
    """The smallest blend t of the field toward planar layers ((1-t) G + t z) whose print is collision-free
    (`smallest_clean_blend`, `collision_blend_steps` bisection steps; planar layers when no smaller t is).
    Every blend tried is appended to `attempts` as (label, field, print)."""
    logger = get_run_logger()
    prints: dict[float, tuple[ArtifactRef, ArtifactRef, ArtifactRef]] = {}

    def collisions(t: float) -> int:
        """Print the blend t and count its collisions."""
        prints[t] = _blended_print(log, store, model, cage, field_ref, config, print_layers, t)
        n = n_collisions(prints[t][2])
        label = "planar blend t = 1 (planar layers)" if t == 1.0 else f"planar blend t = {t:.4g}"
        attempts.append((label, prints[t][0], prints[t][2]))
        logger.warning("%s: %d nozzle collisions", label, n)
        return n

    t = smallest_clean_blend(collisions, config.collision_blend_steps)
    if t not in prints:
        collisions(t)
    return prints[t]


def _blended_print(log: RunLog, store: str, model: ArtifactRef, cage: ArtifactRef, field_ref: ArtifactRef,
                   config: SliceConfig, print_layers: Callable[[ArtifactRef], ArtifactRef], t: float
                   ) -> tuple[ArtifactRef, ArtifactRef, ArtifactRef]:
    """Blend, layers and print for one blend weight t."""
    blended = log.run(field_blend_task, store=store, cage=cage, field=field_ref, planar=t)
    layers = log.run(layers_task, store=store, model=model, cage=cage, field=blended, config=config.layers)
    return blended, layers, print_layers(layers)


def strength_rounds(
    log: RunLog, store: str, model: ArtifactRef, cage: ArtifactRef, samples: ArtifactRef, fea: ArtifactRef,
    objectives: list[str], neural: NeuralConfig, current: tuple[ArtifactRef, ArtifactRef, ArtifactRef], n_rounds: int,
    layer_config: LayerConfig, print_layers: Callable[[ArtifactRef, ArtifactRef | None], ArtifactRef],
) -> tuple[tuple[ArtifactRef, ArtifactRef, ArtifactRef], list[tuple[str, ArtifactRef, ArtifactRef, ArtifactRef]]]:
    """Strength rounds (``sr_rounds``, beyond the paper): the FEA of the part as printed (its filaments, its layers)
    gives the stress the print really carries; T and tau_max are sampled from it and the field re-optimised from
    its weights, then layered and printed with the infill following that stress, ``n_rounds`` - 1 times. A round
    whose print collides ends the rounds and the print before it is kept. Returns the final (field, layers,
    print) and every round as (label, field, print, the FEA of that print)."""
    field_ref, layers, printing = current
    rounds: list[tuple[str, ArtifactRef, ArtifactRef, ArtifactRef]] = []
    for r in range(1, n_rounds + 1):
        printed = log.run(printed_fea_task, store=store, model=model, fea=fea, cage=cage, field=field_ref,
                          printing=printing)
        rounds.append((f"round {r}" + (" (isotropic tau_max, the paper)" if r == 1 else ""), field_ref, printing, printed))
        if r == n_rounds:
            break
        stress = log.run(stress_samples_task, store=store, model=model, fea=printed)
        next_field = log.run(field_task, store=store, model=model, cage=cage, samples=samples, stress=stress,
                             objectives=objectives, config=neural, warm_start=field_ref)
        next_layers = log.run(layers_task, store=store, model=model, cage=cage, field=next_field, config=layer_config)
        next_print = print_layers(next_layers, printed)
        if n_collisions(next_print):
            get_run_logger().warning("strength round %d: its print has %d nozzle collisions; the print of round %d is "
                                     "kept", r + 1, n_collisions(next_print), r)
            break
        field_ref, layers, printing = next_field, next_layers, next_print
    return (field_ref, layers, printing), rounds


def optimised_on(store: str, fields: list[ArtifactRef]) -> dict[str, Any] | None:
    """The device record of the first of these fields that an optimisation wrote (None if none did)."""
    st = ArtifactStore(store, create=False)
    for ref in fields:
        attrs = st.attrs(ref.path)
        if attrs.get("device"):
            return attrs
    return None


@dataclass
class SliceRun:
    """One pass of the pipeline: the model name, every task's state, each step's output ref, the provenance digest,
    every task run's wall time."""

    name: str
    states: list[tuple[str, str]]
    refs: dict[str, ArtifactRef | None]
    provenance_digest: str
    walls: list[float] = field(default_factory=list)


def slice_pipeline(
    spec: ModelSpec,
    out_dir: str,
    config: SliceConfig,
    store: str,
    user_field: str | None = None,
    provenance_extra: dict[str, Any] | None = None,
) -> SliceRun:
    """Run every step of the slicing pipeline (cached tasks) and write the outputs and provenance to out_dir."""
    log = RunLog()
    objectives = config.objectives_for(spec)
    name = model_name(spec)
    model = log.run(model_task, store=store, name=name, spec=spec, content=spec_digest(spec))
    solid = log.run(solid_task, store=store, model=model)
    samples = log.run(samples_task, store=store, model=model, config=config.samples)
    cage = log.run(cage_task, store=store, model=model, samples=samples, config=config.cage)
    fea = stress = verify = None
    if config.needs_fea(spec):
        fea = log.run(fea_task, store=store, model=model)
    if "sr" in objectives:
        stress = log.run(stress_samples_task, store=store, model=model, fea=fea)
    user = store_user_field(store, name, user_field) if user_field else None
    machine = load_profile(config.machine)
    toolpath = config.toolpath_for(spec)

    def print_layers(layers: ArtifactRef, stress_of: ArtifactRef | None = None) -> ArtifactRef:
        """The toolpaths and program of these layers (the infill following the stress of the FEA ``stress_of``, by
        default the isotropic one, when asked)."""
        return log.run(toolpaths_task, store=store, model=model, layers=layers, config=toolpath, machine=machine,
                       t_max=config.layers.t_max, fea=(stress_of or fea) if toolpath.infill == "stress" else None)

    neural = config.neural.with_head(machine.nozzle, config.toolpath.line_width)
    # every field printed on the way to a collision-free program: (label, field, print)
    attempts: list[tuple[str, ArtifactRef, ArtifactRef]] = []
    # what the next field is refined against: every print so far (L_GC's pool grows around their collisions)
    refine: dict[str, Any] = {}
    label, smoothing, refinements = "optimised", 0, 0
    while True:
        if config.method == "s3":
            field_ref = log.run(s3_field_task, store=store, model=model, cage=cage, samples=samples, stress=stress,
                                objectives=objectives, config=config.s3)
        elif config.method == "s3_oneshot":
            field_ref = log.run(s3_oneshot_field_task, store=store, model=model, cage=cage, samples=samples,
                                stress=stress, objectives=objectives, config=config.s3_oneshot)
        else:
            field_ref = log.run(field_task, store=store, model=model, cage=cage, samples=samples, stress=stress,
                                objectives=objectives, config=neural, user_field=user, **refine)
        layers = log.run(layers_task, store=store, model=model, cage=cage, field=field_ref, config=config.layers)
        printing = print_layers(layers)
        attempts.append((label, field_ref, printing))
        collisions = n_collisions(printing)
        if collisions == 0 or not objectives or config.method != "neural":
            break  # S3's own answer to collisions is a smoother rotation field: the planar blend below serves it
        hits = len(read_part_collisions(printing)[0])
        if "gc" in objectives and hits and refinements < config.collision_refinements:
            # the exact check names where the head hits: L_GC's pool is refined there, from the field that printed it
            refinements += 1
            prints = [*refine.get("refine_prints", []), printing]
            refine = {"refine_prints": prints, "warm_start": field_ref}
            label = f"refined around the collisions of {len(prints)} print(s)"
            if n_platform_collisions(printing):
                # heads below the platform beyond what the planner's turn clears: the floor's quadratic penalty
                # settled short of the platform against SF, so it weighs more from here on
                neural = firmer_floor(neural, neural.optim.refine.floor_weight_factor)
                label += f", floor weight x{neural.loss.gc_floor_weight / config.neural.loss.gc_floor_weight:g}"
            get_run_logger().warning("%d nozzle collisions (%d of the head at a waypoint): refining the collision "
                                     "term there", collisions, hits)
            continue
        if smoothing == config.collision_retries:
            break
        # the paper's fallback: smoother fields (larger harmonic weights) and the local collision term, then again
        smoothing += 1
        neural = smoother(neural, config.collision_smoothness_factor)
        objectives = sorted(set(objectives) | {"ca"})
        label = f"re-optimised, harmonic x{config.collision_smoothness_factor ** smoothing:g} + CA"
        get_run_logger().warning("%d nozzle collisions: re-optimising with harmonic weights x%g", collisions,
                                 config.collision_smoothness_factor ** smoothing)
    if collisions and objectives and config.collision_fallback == "blend":
        field_ref, layers, printing = blend_until_collision_free(log, store, model, cage, field_ref, config,
                                                                 print_layers, attempts)
    rounds: list[tuple[str, ArtifactRef, ArtifactRef, ArtifactRef]] = []
    if config.sr_rounds > 1 and "sr" in objectives and config.method == "neural":
        (field_ref, layers, printing), rounds = strength_rounds(
            log, store, model, cage, samples, fea, objectives, neural, (field_ref, layers, printing), config.sr_rounds,
            config.layers, print_layers)
    if config.verify:
        printed = None if config.verify_tangents == "ideal" else printing
        verify = log.run(verify_task, store=store, model=model, fea=fea, cage=cage, field=field_ref, printing=printed,
                         layer_config=config.layers, toolpath_config=toolpath)
    log.run(
        export_task, store=store, out_dir=out_dir, model=model, solid=solid, samples=samples, cage=cage,
        field=field_ref, layers=layers, printing=printing, stress=stress, verify=verify, robot=config.robot,
        alpha_deg=config.alpha_deg,
        beta_deg=config.neural.loss.beta_deg,
        attempts=attempts if len(attempts) > 1 else [], sr_rounds=rounds,
    )
    record = provenance(spec, config, extra_files={"user_field": user_field} if user_field else None,
                        extra={**(provenance_extra or {}), "store": store,
                               "cage_sha256": ArtifactStore(store, create=False).attrs(cage.path).get("sha256")},
                        device_used=optimised_on(store, [f for _, f, _ in attempts] + [field_ref]))
    provenance_digest = record_provenance(out_dir, store, name, record)
    add_to_metrics(out_dir, record)
    refs = {"model": model, "solid": solid, "samples": samples, "cage": cage, "fea": fea, "stress_samples": stress,
            "field": field_ref, "layers": layers, "toolpaths": printing, "verify": verify}
    return SliceRun(name, log.states, refs, provenance_digest, log.walls)


def slice_run_name() -> str:
    """Flow-run name: ``slice-<model>-<output folder>`` (Prefect's random names say nothing in the UI)."""
    from prefect.runtime import flow_run

    params = flow_run.parameters
    spec = params.get("spec")
    try:
        model = model_name(spec if isinstance(spec, ModelSpec) else ModelSpec.model_validate(spec))
    except Exception:  # noqa: BLE001 - a name must never fail a run
        model = "model"
    return artifact_key(f"slice-{model}-{Path(str(params.get('out_dir', 'out'))).name}")


def publish_report(name: str, out_dir: str) -> str | None:
    """The run's report.md as a Prefect markdown artifact (key ``slice-<model>``); the key, or None without a report."""
    from prefect.artifacts import create_markdown_artifact

    report = Path(out_dir) / "report.md"
    if not report.is_file():
        return None
    key = artifact_key(f"slice-{name}")
    create_markdown_artifact(key=key, markdown=report.read_text(), description=f"Neural Slicer report: {name} ({out_dir})")
    return key


@flow(name="neuralslicer-slice", flow_run_name=slice_run_name)
def slice_flow(
    spec: ModelSpec, out_dir: str, config: SliceConfig, store: str, user_field: str | None = None
) -> dict[str, Any]:
    """Slice one model: every step a cached task whose artifacts live in the store; outputs in out_dir.

    `user_field`: an .npz (points (p,3) in the build frame, values (p,)) for the `user` initial guess.
    """
    from prefect.runtime import flow_run

    start = time.perf_counter()
    run = slice_pipeline(spec, out_dir, config, store, user_field)
    summary = {
        "flow_run_name": flow_run.name,
        "report_artifact": publish_report(run.name, out_dir),
        "provenance_digest": run.provenance_digest,
        "tasks": [{"task": t, "state": s, "wall_s": w} for (t, s), w in zip(run.states, run.walls)],
        "all_cached": all(s == "Cached" for _, s in run.states),
        "wall_s": time.perf_counter() - start,
        "store": store,
        "out_dir": out_dir,
    }
    write_json_atomic(Path(out_dir) / "run.json", summary)
    return summary


def ensure_store(store: str) -> str:
    """Create the store if needed and return its canonical location."""
    return ArtifactStore(store).root
