"""The deployments of the slicing flow and the studies, in one table: served from this machine by `neuralslicer serve`
(Prefect's ``serve``: one process polls the server and runs every deployment's flow runs as subprocesses) or created
on a work pool by ``deployments/deploy.py``; and the ``gpu`` tag concurrency limit their field steps take."""
from __future__ import annotations

import asyncio
from pathlib import Path
from typing import Any

from pydantic import BaseModel, Field

from neuralslicer.flows.slice import GPU_TAG

#: deployment name -> the flow's entrypoint in the source tree (file path: prefect.yaml and deploy.py)
DEPLOYMENTS: dict[str, str] = {
    "slice": "flows/studies.py:slice_model",
    "initial-guess": "flows/studies.py:initial_guess_study",
    "cages": "flows/studies.py:cage_study",
    "batch": "flows/studies.py:batch_study",
}


class DeploymentDefaults(BaseModel):
    """The default parameters and schedule of the deployments (every one can be overridden per run)."""

    only: list[str] = Field(default_factory=lambda: list(DEPLOYMENTS), description="deployment names to create")
    model: str | None = Field(None, description="default model (file or spec) of every deployment")
    up: str | None = Field(None, description="default up axis; None keeps a spec's own (and z for a bare file)")
    out: str | None = Field(None, description="default output folder (each deployment gets out/<name>)")
    store: str | None = Field(None, description="default artifact store (shared by all deployments)")
    config: dict[str, Any] | None = Field(None, description="default slicing configuration (SliceConfig fields)")
    cage_elements: list[int] = Field(default_factory=lambda: [4000, 8000, 16000], description="cage study counts")
    cron: str | None = Field(None, description="cron schedule, e.g. '0 2 * * *' (UTC)")
    interval: float | None = Field(None, gt=0, description="interval schedule, seconds")
    scheduled: list[str] = Field(default_factory=lambda: ["slice"],
                                 description="the deployments that get the cron or interval schedule")
    paused: bool = Field(False, description="create the schedules paused")


def default_parameters(name: str, defaults: DeploymentDefaults) -> dict[str, Any]:
    """The default parameters of one deployment (``up`` only when given: a spec keeps its own)."""
    params: dict[str, Any] = {}
    if defaults.model:
        params["models" if name == "batch" else "model"] = [defaults.model] if name == "batch" else defaults.model
    if defaults.out:
        params["out_dir"] = str(Path(defaults.out) / name)
    for key in ("up", "store", "config"):
        if getattr(defaults, key) is not None:
            params[key] = getattr(defaults, key)
    if name == "cages":
        params["cage_elements"] = defaults.cage_elements
    return params


def schedule_of(name: str, defaults: DeploymentDefaults) -> dict[str, Any]:
    """The schedule keywords of ``to_deployment`` / ``deploy`` for one deployment (none unless it is scheduled)."""
    if name not in defaults.scheduled:
        return {}
    if defaults.cron:
        return {"cron": defaults.cron, "paused": defaults.paused}
    if defaults.interval:
        return {"interval": defaults.interval, "paused": defaults.paused}
    return {}


def check_names(names: list[str], where: str) -> list[str]:
    """The names, each a deployment of :data:`DEPLOYMENTS` (InputError naming ``where`` otherwise)."""
    from neuralslicer.errors import InputError

    bad = [n for n in names if n not in DEPLOYMENTS]
    if bad:
        raise InputError(where, f"unknown deployment(s) {', '.join(bad)}; use {', '.join(DEPLOYMENTS)}")
    return names


def flow_of(name: str) -> Any:
    """The flow object of a deployment."""
    from neuralslicer.flows import studies

    return getattr(studies, DEPLOYMENTS[name].split(":")[1])


def runner_deployments(defaults: DeploymentDefaults) -> list[Any]:
    """Prefect ``RunnerDeployment``s of the deployments asked for, loaded by module path (any working directory)."""
    from prefect.deployments.runner import EntrypointType

    return [flow_of(name).to_deployment(
        name=name, parameters=default_parameters(name, defaults), tags=["neuralslicer"],
        description=f"neuralslicer {name} ({DEPLOYMENTS[name]})", entrypoint_type=EntrypointType.MODULE_PATH,
        **schedule_of(name, defaults)) for name in defaults.only]


async def set_gpu_limit(slots: int) -> None:
    """Create or update the tag concurrency limit ``gpu``: at most ``slots`` steps on a CUDA device at once."""
    from prefect.client.orchestration import get_client

    async with get_client() as client:
        await client.create_concurrency_limit(tag=GPU_TAG, concurrency_limit=slots)


def serve_deployments(defaults: DeploymentDefaults, limit: int | None = None, gpu_slots: int | None = None) -> None:
    """Serve the deployments from this process until stopped (Ctrl-C): scheduled and triggered runs of each run here,
    at most ``limit`` at once; ``gpu_slots``: set the ``gpu`` limit first."""
    from prefect import serve

    if gpu_slots is not None:
        asyncio.run(set_gpu_limit(gpu_slots))
    serve(*runner_deployments(defaults), limit=limit)
