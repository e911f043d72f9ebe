"""One study branch: the slicing pipeline of one model and configuration, run as a Prefect task on any task runner."""
from __future__ import annotations

import os
import socket
import threading
import time
from pathlib import Path
from typing import Any

import numpy as np
from prefect import task
from prefect.cache_policies import NONE
from neuralslicer.config import SliceConfig
from neuralslicer.errors import InputError, NeuralSlicerError
from neuralslicer.model.spec import ModelSpec, load_model
from pydantic import BaseModel, ConfigDict, Field

from neuralslicer.storage import ArtifactRef, ArtifactStore, write_json_atomic


class Branch(BaseModel):
    """One branch of a study: which model, with which configuration, into which folder."""

    model_config = ConfigDict(extra="forbid")

    name: str = Field(description="branch name; also the folder DIR/<name>")
    model: str = Field(description="model file or spec (.yaml)")
    up: str | None = Field(None, description="up axis override (default: the spec's, or z)")
    config: SliceConfig = Field(default_factory=SliceConfig)
    out_dir: str = Field(description="the branch's output folder (slice contract)")
    store: str = Field(description="artifact store path or fsspec URL")
    user_field: str | None = Field(None, description=".npz with 'points' (p,3, build frame) and 'values' (p,)")
    parameters: dict[str, Any] = Field(default_factory=dict, description="what this branch varies (for reports)")
    resources: dict[str, float] = Field(default_factory=dict,
                                        description="Dask resources it holds while it runs (GPU: 1 for a CUDA field)")


def load_branch_spec(model: str, up: str | None) -> ModelSpec:
    """The model spec of a branch (file or spec YAML) with the up override."""
    path = Path(model)
    if not path.exists():
        raise InputError(model, "no such file")
    return load_model(path, up)


def make_user_field(bounds: np.ndarray, path: str | Path, n: int = 9, tilt: float = 0.5) -> Path:
    """A smooth user field over a box (build frame): a tilted, gently curved height, saved as .npz."""
    lo, hi = np.asarray(bounds[0], float), np.asarray(bounds[1], float)
    pad = 0.25 * (hi - lo) + 1.0
    axes = [np.linspace(lo[i] - pad[i], hi[i] + pad[i], n) for i in range(3)]
    X, Y, Z = np.meshgrid(*axes, indexing="ij")
    centre, size = (lo + hi) / 2, float(np.max(hi - lo))
    values = Z + tilt * (X - centre[0]) + 0.25 * size * np.sin(np.pi * (Y - centre[1]) / (2 * size))
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    np.savez(path, points=np.stack([X.ravel(), Y.ravel(), Z.ravel()], axis=1), values=values.ravel())
    return path


def worker_identity() -> dict[str, Any]:
    """Where this code runs: pid, host, thread, the Prefect API its task runs report to, and the Dask worker's
    name/address when on one."""
    from prefect.settings import get_current_settings

    info: dict[str, Any] = {"pid": os.getpid(), "host": socket.gethostname(), "thread": threading.current_thread().name,
                            "prefect_api": get_current_settings().api.url}
    try:
        from distributed import get_worker

        w = get_worker()
        info["dask_worker"] = str(w.name)
        info["dask_address"] = str(w.address)
    except (ImportError, ValueError):
        pass
    return info


def run_pipeline(branch: Branch) -> dict[str, Any]:
    """The slicing pipeline for one branch (the slice flow's steps, with its user field); returns its record."""
    from neuralslicer.flows.slice import slice_pipeline

    start = time.perf_counter()
    started_at = time.strftime("%Y-%m-%dT%H:%M:%SZ", time.gmtime())
    spec = load_branch_spec(branch.model, branch.up)
    store = ArtifactStore(branch.store).root
    run = slice_pipeline(spec, branch.out_dir, branch.config, store, branch.user_field, {"branch": branch.name})
    st = ArtifactStore(store)
    field_attrs = st.attrs(run.refs["field"].path)
    result = {
        "name": branch.name,
        "parameters": branch.parameters,
        "model": run.name,
        "out_dir": branch.out_dir,
        "tasks": [{"task": t.task, "state": t.state} for t in run.log.tasks],
        "all_cached": run.log.all_cached,
        "final_loss": field_attrs.get("final") or {},
        "satisfaction": field_attrs.get("satisfaction") or {},
        "field": _field_record(run.refs["field"], field_attrs, {t.task: t.state for t in run.log.tasks}),
        "cage": _cage_record(run.refs["cage"], st.attrs(run.refs["cage"].path)),
        "metrics": _metrics(branch.out_dir),
        "provenance_digest": run.provenance_digest,
        "worker": worker_identity(),
        "started_at": started_at,
        "wall_s": time.perf_counter() - start,
        "status": "completed",
    }
    write_json_atomic(Path(branch.out_dir) / "branch.json", result)
    return result


def _field_record(ref: ArtifactRef, attrs: dict[str, Any], states: dict[str, str]) -> dict[str, Any]:
    """The branch record's field entry from the field group's attributes: its group, steps, convergence, optimisation
    time, and the checkpoint a field computed in this run resumed from."""
    steps = int(attrs.get("steps", 0) or 0)
    field_state = states.get("field", states.get("field_s3", states.get("field_s3_oneshot")))
    resumed_step = attrs.get("resumed_from_step") if field_state != "Cached" else None
    return {"path": ref.path, "steps": steps, "converged": attrs.get("converged"),
            "optimise_wall_s": attrs.get("wall_time_s"),
            "s_per_step": (attrs["wall_time_s"] / steps) if steps and attrs.get("wall_time_s") else None,
            "resumed_from_checkpoint": None if resumed_step is None else f"step_{resumed_step:08d}",
            "resumed_from_step": attrs.get("resumed_from_step")}


def _cage_record(ref: ArtifactRef, attrs: dict[str, Any]) -> dict[str, Any]:
    """The branch record's cage entry from the cage group's attributes: its group, size, genus and build time."""
    return {"path": ref.path, "n_elements": attrs.get("n_elements"), "genus": attrs.get("genus"),
            "n_vertices": attrs.get("n_vertices"), "wall_s": attrs.get("wall_s")}


def _metrics(out_dir: str) -> dict[str, Any]:
    """The branch's metrics.json without the provenance entries."""
    import json

    path = Path(out_dir) / "metrics.json"
    if not path.is_file():
        return {}
    return {k: v for k, v in json.loads(path.read_text()).items() if not k.startswith("provenance.")}


def _retry_transient(task_: Any, task_run: Any, state: Any) -> bool:
    """Retry a branch unless it failed on the user's input (a retry could not help)."""
    try:
        state.result()
    except (InputError, NeuralSlicerError):
        return False
    except Exception:
        return True
    return False


@task(name="study-branch", cache_policy=NONE, persist_result=False, retries=1, retry_delay_seconds=2,
      retry_condition_fn=_retry_transient, task_run_name="branch-{branch.name}")
def study_branch(branch: Branch) -> dict[str, Any]:
    """Run one branch's pipeline (its steps are cached tasks keyed by content; a retry resumes from checkpoints)."""
    return run_pipeline(branch)
