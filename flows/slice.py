"""The slicing flow: model -> surface -> samples -> cage -> [fea -> stress_samples] -> field -> layers -> toolpaths -> motion
-> program -> export, every step a cached task (the chain is `neuralslicer.run.pipeline.run_chain`)."""
from __future__ import annotations

import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from prefect import flow, get_run_logger, tags
from prefect.states import State

from neuralslicer.allocator import release_freed_memory
from neuralslicer.config import SliceConfig
from neuralslicer.flows.settings import artifact_key
from neuralslicer.model.spec import ModelSpec, model_name
from neuralslicer.motion.output import print_hits
from neuralslicer.run.pipeline import Printed, run_chain
from neuralslicer.run.provenance import add_to_metrics, provenance
from neuralslicer.run.report_embed import embed_figures
from neuralslicer.run.step_table import step
from neuralslicer.storage import ArtifactRef, ArtifactStore, groups_used, write_json_atomic
from neuralslicer.tasks.codec import StoredMotion, store_user_field
from neuralslicer.tasks.common import run_step
from neuralslicer.tasks.export import export_task
from neuralslicer.tasks.provenance import record_provenance
from neuralslicer.tasks.release import check_room, forget_released, release_motion, release_toolpaths
from neuralslicer.tasks.steps import TASKS


@dataclass
class TaskRun:
    """One task run of a flow: the step, its final state's name (Completed / Cached / ...), its wall time (s, Prefect's
    round trips included) and the store group it wrote or read."""

    task: str
    state: str
    wall_s: float
    group: str

    def record(self) -> dict[str, Any]:
        """The task run as run.json lists it."""
        return {"task": self.task, "state": self.state, "wall_s": self.wall_s, "group": self.group}


@dataclass
class RunLog:
    """Every task run of one flow run, in order."""

    tasks: list[TaskRun] = field(default_factory=list)

    def run(self, task: Any, **params: Any) -> ArtifactRef:
        """Run a task, record it, return its result."""
        start = time.perf_counter()
        state: State = run_step(task, **params)
        ref = state.result()
        self.tasks.append(TaskRun(task.name, state.name, time.perf_counter() - start, ref.path))
        return ref

    @property
    def all_cached(self) -> bool:
        """Whether every task was served from the cache."""
        return all(t.state == "Cached" for t in self.tasks)


#: the task-run tag of a step that computes on a CUDA device: a Prefect tag concurrency limit of that name
#: (``prefect concurrency-limit create gpu 1``) lets that many such steps run at once; without one, it only labels
GPU_TAG = "gpu"


def device_tags(device: str | None) -> tuple[str, ...]:
    """The tags of a step that optimises on ``device`` (``auto``, ``cpu``, ``cuda``, ``cuda:1``; None: no
    optimisation): ``("gpu",)`` when it resolves to CUDA. ``auto`` imports torch only where it may have a GPU (not
    with a CPU build of torch: a cached rerun does not import it)."""
    from neuralslicer.neural.device import cuda_possible

    if device is None or device == "cpu" or (device == "auto" and not cuda_possible()):
        return ()
    if device.startswith("cuda"):
        return (GPU_TAG,)
    from neuralslicer.neural.device import resolve_device   # torch: only when a GPU may be there

    return (GPU_TAG,) if resolve_device(device).type == "cuda" else ()


@dataclass
class TaskSteps:
    """The table's steps as Prefect tasks on one store (``tasks/steps.py``): each call runs the step's task and
    returns its output ref."""

    log: RunLog
    store: str

    def run(self, name: str, **parameters: Any) -> ArtifactRef:
        """Run step ``name``'s task on this store (with the parameters that key it, and the GPU tag of a step that
        optimises on CUDA)."""
        s = step(name)
        if s.key_of is not None:
            parameters = {**parameters, **s.key_of(parameters)}
        with tags(*device_tags(s.device(parameters) if s.device is not None else None)):
            return self.log.run(TASKS[name], store=self.store, **parameters)

    def hits(self, motion: ArtifactRef) -> tuple[int, int, int]:
        """Collisions of a stored print: all, of the head at a waypoint, below the platform."""
        return print_hits(StoredMotion(motion))

    def note(self, message: str) -> None:
        """A warning in the flow run's log."""
        get_run_logger().warning(message)

    def release(self, printed: Printed[ArtifactRef]) -> None:
        """Drop a print's toolpaths and motion arrays from the store (``tasks/release.py``), keeping its metrics, its
        collisions and its collision map."""
        freed = release_toolpaths(printed.toolpaths) + release_motion(printed.motion)
        release_freed_memory()   # the waypoints read for its collision map go back to the kernel
        if freed:
            get_run_logger().info(f"released a print that will not be kept: {freed / 1e9:.2f} GB freed "
                                  f"({printed.motion.path})")

    def restore(self, printed: Printed[ArtifactRef]) -> bool:
        """Remove a released print's toolpaths and motion groups so that their steps make them again."""
        return forget_released([printed.toolpaths, printed.motion])

    def check_room(self, like: Printed[ArtifactRef]) -> None:
        """Raise when the store's disk has less room than a print like this one took."""
        check_room([like.layers, like.toolpaths, like.motion], unpacked=like.toolpaths)


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
    """One pass of the pipeline: the model name, every task run, each step's output ref, the provenance digest."""

    name: str
    log: RunLog
    refs: dict[str, ArtifactRef | None]
    provenance_digest: str


def slice_pipeline(spec: ModelSpec, out_dir: str, config: SliceConfig, store: str, user_field: str | None = None,
                   provenance_extra: dict[str, Any] | None = None) -> SliceRun:
    """Run every step of the slicing chain as a cached task (:func:`run_chain`), then write the outputs and
    provenance to out_dir."""
    log = RunLog()
    name = model_name(spec)
    user = store_user_field(store, name, user_field) if user_field else None
    c = run_chain(TaskSteps(log, store), spec, config, user)
    p = c.printed
    log.run(export_task, store=store, out_dir=out_dir, model=c.model, surface=c.surface, samples=c.samples, cage=c.cage,
            field=p.field, layers=p.layers, motion=p.motion, stress_samples=c.stress_samples, verify=c.verify,
            robot=config.robot, alpha_deg=config.alpha_deg, beta_deg=config.neural.loss.beta_deg, attempts=c.attempts,
            sr_rounds=c.rounds, toolpaths=p.toolpaths, program=c.program)
    record = provenance(spec, config, extra_files={"user_field": user_field} if user_field else None,
                        extra={**(provenance_extra or {}), "store": store,
                               "cage_sha256": ArtifactStore(store, create=False).attrs(c.cage.path).get("sha256")},
                        device_used=optimised_on(store, [a.field for a in c.attempts] + [p.field]))
    provenance_digest = record_provenance(out_dir, store, name, record)
    add_to_metrics(out_dir, record)
    refs = {"model": c.model, "surface": c.surface, "samples": c.samples, "cage": c.cage, "fea": c.fea,
            "stress_samples": c.stress_samples, "field": p.field, "layers": p.layers, "toolpaths": p.toolpaths,
            "motion": p.motion, "program": c.program, "verify": c.verify}
    return SliceRun(name, log, refs, provenance_digest)


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
    """The run's report.md as a Prefect markdown artifact (key ``slice-<model>``), its figures embedded (the UI
    cannot follow a relative link); the key, or None without a report."""
    from prefect.artifacts import create_markdown_artifact

    report = Path(out_dir) / "report.md"
    if not report.is_file():
        return None
    key = artifact_key(f"slice-{name}")
    create_markdown_artifact(key=key, markdown=embed_figures(report.read_text(), report.parent),
                             description=f"Neural Slicer report: {name} ({out_dir})")
    return key


@flow(name="neuralslicer-slice", flow_run_name=slice_run_name, persist_result=False)
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
        "flow_run_id": str(flow_run.id),
        "report_artifact": publish_report(run.name, out_dir),
        "provenance_digest": run.provenance_digest,
        "tasks": [t.record() for t in run.log.tasks],
        "all_cached": run.log.all_cached,
        "wall_s": time.perf_counter() - start,
        "store": store,
        "groups": groups_used(run.refs),   # the group each step of the kept print wrote or read (docs/store.md)
        "out_dir": out_dir,
    }
    write_json_atomic(Path(out_dir) / "run.json", summary)
    return summary


def ensure_store(store: str) -> str:
    """Create the store if needed and return its canonical location."""
    return ArtifactStore(store).root

