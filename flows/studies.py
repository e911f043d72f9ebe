"""Study flows: batch over models, initial guesses, cage resolutions; branches fanned out on a Prefect task runner."""
from __future__ import annotations

import re
import time
from pathlib import Path
from typing import Any, Literal

from prefect import flow, get_run_logger
from prefect.states import Failed, State
from prefect.task_runners import ThreadPoolTaskRunner
from pydantic import BaseModel, ConfigDict, Field

from neuralslicer.flows.cluster import annotated, branch_resources, check_cluster, needs_gpu
from neuralslicer.flows.settings import quiet_input_errors
from neuralslicer.flows.study_server import configured_api_url
from neuralslicer.flows.branch import Branch, load_branch_spec, make_user_field, study_branch
from neuralslicer.flows.study_report import write_study_outputs
from neuralslicer.config import SliceConfig
from neuralslicer.errors import InputError
from neuralslicer.run.preflight import check_slice
from neuralslicer.storage import ArtifactStore, default_store

INIT_KINDS = ("height", "heat", "user")

# a deployment's flow run loads this module before Prefect validates the run's parameters: from here on, Prefect's
# records of bad input (an InputError, a parameter that fails validation) carry no traceback; the state says it
quiet_input_errors()


class StudyOptions(BaseModel):
    """How a study runs: where, on which engine, with which shared slicing configuration."""

    model_config = ConfigDict(extra="forbid")

    out_dir: str = Field(description="study folder: DIR/study.md, DIR/study.json, DIR/<branch>/")
    store: str | None = Field(None, description="artifact store (path or fsspec URL); default DIR/store.zarr")
    config: SliceConfig = Field(default_factory=SliceConfig, description="slicing configuration shared by the branches")
    up: str | None = Field(None, description="up axis override for every model")
    dask: str | None = Field(None, description="Dask scheduler address, 'local' for a LocalCluster, None: threads")
    dask_workers: int = Field(2, ge=1, description="workers of a '--dask local' cluster")
    max_workers: int | None = Field(None, ge=1, description="threads of the default runner (default: one per branch)")


def task_runner(dask: str | None, n_branches: int, dask_workers: int = 2, max_workers: int | None = None) -> Any:
    """The task runner of a study: threads on this machine, a Dask LocalCluster ('local') or an existing scheduler."""
    if not dask:
        return ThreadPoolTaskRunner(max_workers=max_workers or max(n_branches, 1))
    from prefect_dask import DaskTaskRunner

    if dask == "local":
        return DaskTaskRunner(cluster_class="distributed.LocalCluster",
                              cluster_kwargs={"n_workers": dask_workers, "threads_per_worker": 1, "processes": True,
                                              "host": "127.0.0.1", "dashboard_address": None})
    return DaskTaskRunner(address=dask)


def branch_name(text: str) -> str:
    """A folder-safe branch name."""
    return re.sub(r"[^A-Za-z0-9_.-]", "_", text).strip("._") or "branch"


@flow(name="neuralslicer-study-engine")
def study_engine(kind: str, title: str, branches: list[Branch], out_dir: str) -> dict[str, Any]:
    """Run every branch concurrently on this flow's task runner, then write study.json/study.md and Prefect artifacts."""
    logger = get_run_logger()
    start = time.perf_counter()
    futures = []
    for b in branches:
        with annotated(b.resources):   # a CUDA branch on a cluster: a worker with the GPU resource
            futures.append(study_branch.submit(b))
    results = []
    for b, fut in zip(branches, futures):
        fut.wait()
        state = fut.state
        if state.is_completed():
            results.append(state.result())
        else:
            try:
                state.result()
                message = state.message or state.name
            except Exception as exc:  # the branch's error, recorded in study.json
                message = f"{type(exc).__name__}: {exc}"
            logger.error("branch %s failed: %s", b.name, message)
            results.append({"name": b.name, "parameters": b.parameters, "out_dir": b.out_dir, "status": "failed",
                            "error": message})
    study = {"kind": kind, "title": title, "branches": results, "wall_s": time.perf_counter() - start,
             "out_dir": out_dir}
    write_study_outputs(study, Path(out_dir), branches)
    return study


def check_engine(options: StudyOptions, branches: list[Branch]) -> list[Branch]:
    """The branches, ready for the engine the options name. On Dask: a Prefect API the workers reach (never the
    ephemeral one, whose address no worker gets); on a scheduler's address, besides: every worker shares the
    store and the study folder and reaches the API, a CUDA branch asks for a GPU worker (``flows/cluster.py``)."""
    if not options.dask:
        return branches
    api_url = configured_api_url()
    if api_url is None:
        raise InputError("--dask", "a study on Dask needs a Prefect API server that its workers reach: set "
                         "PREFECT_API_URL (prefect server start), or run it with `neuralslicer study`, which "
                         "starts one")
    if options.dask == "local":
        return branches
    workers = check_cluster(options.dask, {"--store": branches[0].store, "--out": options.out_dir}, api_url,
                            gpu=any(needs_gpu(b.config) for b in branches))
    get_run_logger().info("Dask scheduler %s: %d worker(s) share the store and the study folder and reach the "
                          "Prefect API %s", options.dask, len(workers), api_url)
    return [b.model_copy(update={"resources": branch_resources(b.config)}) for b in branches]


def run_study(kind: str, title: str, branches: list[Branch], options: StudyOptions) -> dict[str, Any] | State:
    """Run the study engine as a subflow on the task runner the options ask for, once that engine is checked."""
    try:
        branches = check_engine(options, branches)
    except InputError as exc:
        return failed_on_input(exc)
    runner = task_runner(options.dask, len(branches), options.dask_workers, options.max_workers)
    engine = study_engine.with_options(task_runner=runner, flow_run_name=f"{kind}-{Path(options.out_dir).name}")
    return engine(kind=kind, title=title, branches=branches, out_dir=options.out_dir)


def _store(options: StudyOptions) -> str:
    """The study's store (created), default DIR/store.zarr."""
    return ArtifactStore(options.store or default_store(options.out_dir)).root


def initial_guess_branches(model: str, options: StudyOptions, kinds: list[str] | None = None,
                           user_field: str | None = None) -> list[Branch]:
    """Branches of the initial-guess study: one per initial field (height, heat, user) for one model."""
    kinds = list(kinds or INIT_KINDS)
    bad = [k for k in kinds if k not in INIT_KINDS]
    if bad:
        raise InputError("kinds", f"unknown initial guess(es) {', '.join(bad)}; use {', '.join(INIT_KINDS)}")
    out, store = Path(options.out_dir), _store(options)
    objectives = options.config.objectives
    if objectives is not None and not objectives:
        raise InputError("--objectives", "the initial-guess study optimises: give objectives (e.g. sf,po), not none")
    if "user" in kinds and user_field is None:
        user_field = str(default_user_field(model, options, out / "user_field.npz"))
    branches = []
    for kind in kinds:
        cfg = options.config.model_copy(deep=True)
        cfg.neural.init.kind = kind  # type: ignore[assignment]
        branches.append(Branch(name=kind, model=model, up=options.up, config=cfg, out_dir=str(out / kind), store=store,
                               user_field=user_field if kind == "user" else None,
                               parameters={"init": kind, **({"user_field": user_field} if kind == "user" else {})}))
    return branches


def default_user_field(model: str, options: StudyOptions, path: Path) -> Path:
    """A smooth user field over the model's build-frame bounds (tilted, gently curved height), saved to path."""
    from neuralslicer.model.solid import implicit_solid

    if path.is_file():
        return path
    solid = implicit_solid(load_branch_spec(model, options.up))
    return make_user_field(solid.bounds, path)


def _variant(config: SliceConfig, where: str, **changes: object) -> SliceConfig:
    """The configuration with keys changed, nested ones spelt with ``__`` (``neural__network``), validated (an
    error names ``where`` and the key)."""
    data = config.model_dump()
    for key, value in changes.items():
        node = data
        *path, last = key.split("__")
        for k in path:
            node = node[k]
        node[last] = value
    return SliceConfig.checked(data, where)


def with_cage_elements(config: SliceConfig, n: int) -> SliceConfig:
    """The configuration with another cage element count, validated (its limits apply)."""
    return _variant(config, "--cage-elements", cage__n_elements=int(n))


def cage_branches(model: str, options: StudyOptions, cage_elements: list[int]) -> list[Branch]:
    """Branches of the cage-resolution study: one per cage element count."""
    if not cage_elements:
        raise InputError("--cage-elements", "give at least one element count")
    out, store = Path(options.out_dir), _store(options)
    branches = []
    for n in cage_elements:
        cfg = with_cage_elements(options.config, n)
        branches.append(Branch(name=f"cage_{n}", model=model, up=options.up, config=cfg, out_dir=str(out / f"cage_{n}"),
                               store=store, parameters={"cage.n_elements": int(n)}))
    return branches


def batch_branches(models: list[str], options: StudyOptions) -> list[Branch]:
    """Branches of a batch: one per model file or spec, each with the shared configuration."""
    if not models:
        raise InputError("models", "give at least one model or spec")
    out, store = Path(options.out_dir), _store(options)
    names: dict[str, int] = {}
    branches = []
    for m in models:
        base = branch_name(Path(m).stem if Path(m).stem not in ("model", "spec") else Path(m).parent.name + "_" + Path(m).stem)
        names[base] = names.get(base, 0) + 1
        name = base if names[base] == 1 else f"{base}_{names[base]}"
        branches.append(Branch(name=name, model=str(Path(m).resolve()), up=options.up, config=options.config,
                               out_dir=str(out / name), store=store, parameters={"model": str(m)}))
    return branches



def _as_printed(config: SliceConfig) -> SliceConfig:
    """A comparison's configuration: every field printed as computed, its collisions counted, not repaired (no
    re-optimisation, no planar blend), so each branch shows its own method."""
    return _variant(config, "study", collision_refinements=0, collision_retries=0, collision_fallback="none")


def methods_branches(model: str, options: StudyOptions) -> list[Branch]:
    """Branches of the methods study: the Neural Slicer, the S3-Slicer baseline (iterative, and its one-shot variant)
    and planar layers, on one cage; with a
    load case all three print the same infill (stress-following unless the configuration names one), so that the
    strength figures compare the layers, not the infill."""
    out, store = Path(options.out_dir), _store(options)
    base = _as_printed(options.config)
    if load_branch_spec(model, options.up).fea is not None and base.toolpath.infill == "auto":
        base = _variant(base, "study", toolpath__infill="stress")
    variants = {"neural": _variant(base, "study", method="neural"), "s3": _variant(base, "study", method="s3"),
                "s3_oneshot": _variant(base, "study", method="s3_oneshot"),
                "planar": _variant(base, "study", objectives=[])}
    return [Branch(name=name, model=model, up=options.up, config=cfg, out_dir=str(out / name), store=store,
                   parameters={"method": "planar layers" if name == "planar" else name}) for name, cfg in variants.items()]


def ablation_branches(model: str, options: StudyOptions) -> list[Branch]:
    """Branches of the ablation study (Neural Slicer): the objectives asked for (default ones when none are), without
    the point-overhang term PO, with per-element q and s instead of the Q-S networks, and without SR when SR is on."""
    out, store = Path(options.out_dir), _store(options)
    base = _as_printed(options.config)
    objectives = base.objectives_for(load_branch_spec(model, options.up))
    if not objectives:
        raise InputError("--objectives", "the ablation study optimises: give objectives (e.g. sf,po), not none")
    variants: dict[str, tuple[SliceConfig, dict]] = {
        "full": (_variant(base, "study", objectives=objectives), {"objectives": ",".join(objectives)}),
    }
    if "po" in objectives:
        fewer = [o for o in objectives if o != "po"]
        variants["no_po"] = (_variant(base, "study", objectives=fewer), {"objectives": ",".join(fewer)})
    variants["per_element"] = (_variant(base, "study", objectives=objectives, neural__network="per_element"),
                               {"objectives": ",".join(objectives), "q, s": "per element"})
    if "sr" in objectives:
        fewer = [o for o in objectives if o != "sr"]
        variants["no_sr"] = (_variant(base, "study", objectives=fewer), {"objectives": ",".join(fewer)})
    return [Branch(name=name, model=model, up=options.up, config=cfg, out_dir=str(out / name), store=store,
                   parameters={"q, s": "networks", **params}) for name, (cfg, params) in variants.items()]


def _options(out_dir: str, store: str | None, config: SliceConfig | dict | None, up: str | None, dask: str | None,
             dask_workers: int, max_workers: int | None) -> StudyOptions:
    """StudyOptions from flow parameters (a config may come as a dict from a deployment)."""
    cfg = config if isinstance(config, SliceConfig) else SliceConfig.model_validate(config or {})
    return StudyOptions(out_dir=str(Path(out_dir).resolve()), store=store, config=cfg, up=up, dask=dask,
                        dask_workers=dask_workers, max_workers=max_workers)


#: the up axes and units a deployment's parameters offer (the UI's choices); None keeps the spec's own
UpAxis = Literal["x", "y", "z", "-x", "-y", "-z"]
Units = Literal["mm", "cm", "m", "in"]


def failed_on_input(exc: InputError) -> State:
    """The final state of a flow run stopped by bad input: Failed, its message the one line the command line would
    print (also the run log's one error line), no traceback anywhere (``quiet_input_errors``)."""
    get_run_logger().error("%s", exc)
    return Failed(message=str(exc), data=exc)


def check_deployed(models: list[str], options: StudyOptions) -> None:
    """A deployment's run of a study: the command line's checks of every model before any branch starts (the command
    line checks them itself, naming its flags, before it calls the flow)."""
    from prefect.runtime import deployment

    if deployment.id is None:
        return
    store = options.store or default_store(options.out_dir)
    for model in models:
        check_slice(model, Path(options.out_dir), store, options.config, up=options.up)


@flow(name="neuralslicer-study-initial-guess", persist_result=False)
def initial_guess_study(model: str, out_dir: str, up: UpAxis | None = None, store: str | None = None,
                        config: SliceConfig | None = None, kinds: list[str] | None = None,
                        user_field: str | None = None, dask: str | None = None, dask_workers: int = 2,
                        max_workers: int | None = None) -> dict[str, Any] | State:
    """Initial-guess study of one model: height, heat and a user field, learning curves overlaid."""
    options = _options(out_dir, store, config, up, dask, dask_workers, max_workers)
    try:
        check_deployed([model], options)
        branches = initial_guess_branches(str(Path(model).resolve()), options, kinds, user_field)
    except InputError as exc:
        return failed_on_input(exc)
    return run_study("initial-guess", f"Initial-guess study: {Path(model).name}", branches, options)


@flow(name="neuralslicer-study-cages", persist_result=False)
def cage_study(model: str, out_dir: str, cage_elements: list[int], up: UpAxis | None = None, store: str | None = None,
               config: SliceConfig | None = None, dask: str | None = None, dask_workers: int = 2,
               max_workers: int | None = None) -> dict[str, Any] | State:
    """Cage-resolution study of one model: genus, step time, final losses and metrics per cage element count."""
    options = _options(out_dir, store, config, up, dask, dask_workers, max_workers)
    try:
        check_deployed([model], options)
        branches = cage_branches(str(Path(model).resolve()), options, cage_elements)
    except InputError as exc:
        return failed_on_input(exc)
    return run_study("cages", f"Cage-resolution study: {Path(model).name}", branches, options)


@flow(name="neuralslicer-study-batch", persist_result=False)
def batch_study(models: list[str], out_dir: str, up: UpAxis | None = None, store: str | None = None,
                config: SliceConfig | None = None, dask: str | None = None, dask_workers: int = 2,
                max_workers: int | None = None) -> dict[str, Any] | State:
    """Batch: slice every model (file or spec) with the shared configuration, fanned out."""
    options = _options(out_dir, store, config, up, dask, dask_workers, max_workers)
    try:
        check_deployed(models, options)
        branches = batch_branches(models, options)
    except InputError as exc:
        return failed_on_input(exc)
    return run_study("batch", f"Batch of {len(models)} model(s)", branches, options)


@flow(name="neuralslicer-slice-model", persist_result=False)
def slice_model(model: str, out_dir: str, up: UpAxis | None = None, units: Units | None = None,
                store: str | None = None, config: SliceConfig | None = None, force: bool = False
                ) -> dict[str, Any] | State:
    """Slice one model file or spec (a deployment's flow): the command line's preflight, then the slicing flow.

    ``up`` / ``units`` override the model's only when given (a spec keeps its own); ``force``: slice past the layer
    count limit. Bad input fails the run with one line in its state (the parameter it names), no traceback."""
    from neuralslicer.flows.slice import slice_flow

    cfg = config if isinstance(config, SliceConfig) else SliceConfig.model_validate(config or {})
    out = Path(out_dir).resolve()
    try:
        spec = check_slice(model, out, store or default_store(out), cfg, up=up, units=units, force=force)
        store_root = ArtifactStore(store or default_store(out)).root
    except InputError as exc:
        return failed_on_input(exc)
    return slice_flow(spec=spec, out_dir=str(out), config=cfg, store=store_root)


@flow(name="neuralslicer-study-methods")
def methods_study(model: str, out_dir: str, up: str | None = None, store: str | None = None,
                  config: SliceConfig | None = None, dask: str | None = None, dask_workers: int = 2,
                  max_workers: int | None = None) -> dict[str, Any] | State:
    """Neural Slicer vs the S3-Slicer baseline vs planar layers on one model: the same cage, samples and
    downstream stages; overhang held out and from the exported layers, collisions, layers, time (and strain with
    --verify)."""
    options = _options(out_dir, store, config, up, dask, dask_workers, max_workers)
    branches = methods_branches(str(Path(model).resolve()), options)
    return run_study("methods", f"Methods: Neural Slicer vs S3-Slicer vs planar, {Path(model).name}", branches, options)


@flow(name="neuralslicer-study-ablation")
def ablation_study(model: str, out_dir: str, up: str | None = None, store: str | None = None,
                   config: SliceConfig | None = None, dask: str | None = None, dask_workers: int = 2,
                   max_workers: int | None = None) -> dict[str, Any] | State:
    """The Neural Slicer's ablations on one model: PO on and off, Q-S networks vs per-element q and s, SR on and
    off (with an FEA block); learning curves overlaid."""
    options = _options(out_dir, store, config, up, dask, dask_workers, max_workers)
    branches = ablation_branches(str(Path(model).resolve()), options)
    return run_study("ablation", f"Ablation: {Path(model).name}", branches, options)
