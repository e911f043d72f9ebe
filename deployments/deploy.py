"""Deploy the slicing flow and the studies to a Prefect server's process work pool (from this source tree).

    python deployments/deploy.py --pool neuralslicer --model /data/ring.tet --up y --out /data/runs

creates the pool if needed and the deployments `neuralslicer-slice-model/slice`,
`neuralslicer-study-initial-guess/initial-guess`, `neuralslicer-study-cages/cages` and
`neuralslicer-study-batch/batch`; `--cron "0 2 * * *"` (or `--interval 86400`) puts a schedule on the
cage study (the nightly-study example). Parameters given here are defaults: override them per run
(`prefect deployment run NAME --param out_dir=...` or the UI's "Custom run").
"""
from __future__ import annotations

import argparse
import asyncio
import sys
from pathlib import Path
from typing import Any

from pydantic import BaseModel, Field

REPO = Path(__file__).resolve().parents[1]

# deployment name -> (entrypoint in this repository, flow name)
DEPLOYMENTS: dict[str, str] = {
    "slice": "flows/studies.py:slice_model",
    "initial-guess": "flows/studies.py:initial_guess_study",
    "cages": "flows/studies.py:cage_study",
    "batch": "flows/studies.py:batch_study",
}


class DeployOptions(BaseModel):
    """What to deploy and where."""

    pool: str = Field("neuralslicer", description="process work pool (created when missing)")
    source: str = Field(str(REPO), description="source tree (path or git URL) the worker loads the flows from")
    only: list[str] = Field(default_factory=lambda: list(DEPLOYMENTS), description="deployment names to create")
    model: str | None = Field(None, description="default model for every deployment")
    up: str | None = Field(None, description="default up axis")
    out: str | None = Field(None, description="default output folder (each deployment gets out/<name>)")
    store: str | None = Field(None, description="default artifact store (shared by all deployments)")
    config: dict[str, Any] | None = Field(None, description="default slicing configuration (SliceConfig fields)")
    cage_elements: list[int] = Field(default_factory=lambda: [4000, 8000, 16000], description="cage study counts")
    cron: str | None = Field(None, description="cron schedule of the cage study, e.g. '0 2 * * *'")
    interval: float | None = Field(None, gt=0, description="interval schedule of the cage study, seconds")
    paused: bool = Field(False, description="create the schedule paused")


async def ensure_process_pool(name: str) -> None:
    """Create a process work pool unless it exists."""
    from prefect.client.orchestration import get_client
    from prefect.client.schemas.actions import WorkPoolCreate
    from prefect.exceptions import ObjectAlreadyExists

    async with get_client() as client:
        try:
            await client.create_work_pool(WorkPoolCreate(name=name, type="process"))
        except ObjectAlreadyExists:
            pass


def default_parameters(name: str, options: DeployOptions) -> dict[str, Any]:
    """The default parameters of one deployment."""
    params: dict[str, Any] = {}
    if options.model:
        params["models" if name == "batch" else "model"] = [options.model] if name == "batch" else options.model
    if options.out:
        params["out_dir"] = str(Path(options.out) / name)
    for key in ("up", "store", "config"):
        if getattr(options, key) is not None:
            params[key] = getattr(options, key)
    if name == "cages":
        params["cage_elements"] = options.cage_elements
    return params


def deploy(options: DeployOptions) -> dict[str, str]:
    """Create the work pool and the deployments; return {deployment name: deployment id}."""
    from prefect import flow

    asyncio.run(ensure_process_pool(options.pool))
    ids = {}
    for name in options.only:
        entry = DEPLOYMENTS[name]
        remote = flow.from_source(source=options.source, entrypoint=entry)
        schedule: dict[str, Any] = {}
        if name == "cages" and options.cron:
            schedule["cron"] = options.cron
        elif name == "cages" and options.interval:
            schedule["interval"] = options.interval
        deployment_id = remote.deploy(
            name=name, work_pool_name=options.pool, parameters=default_parameters(name, options),
            tags=["neuralslicer"], description=f"neuralslicer {name} ({entry})", print_next_steps=False,
            paused=options.paused if schedule else None, **schedule,
        )
        ids[f"{remote.name}/{name}"] = str(deployment_id)
    return ids


def main(argv: list[str] | None = None) -> int:
    """Command line of the deploy script."""
    p = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    p.add_argument("--pool", default="neuralslicer")
    p.add_argument("--source", default=str(REPO), help="source tree (path or git URL) the worker loads flows from")
    p.add_argument("--only", default=",".join(DEPLOYMENTS), help=f"comma list of {', '.join(DEPLOYMENTS)}")
    p.add_argument("--model", default=None)
    p.add_argument("--up", default=None)
    p.add_argument("--out", default=None)
    p.add_argument("--store", default=None)
    p.add_argument("--config", default=None, help="YAML slicing configuration used as the default 'config'")
    p.add_argument("--cage-elements", default="4000,8000,16000")
    p.add_argument("--cron", default=None)
    p.add_argument("--interval", type=float, default=None)
    p.add_argument("--paused", action="store_true")
    a = p.parse_args(argv)
    config = None
    if a.config:
        import yaml

        config = yaml.safe_load(Path(a.config).read_text()) or {}
    options = DeployOptions(
        pool=a.pool, source=a.source, only=[s for s in a.only.split(",") if s], model=a.model, up=a.up, out=a.out,
        store=a.store, config=config, cage_elements=[int(n) for n in a.cage_elements.split(",")], cron=a.cron,
        interval=a.interval, paused=a.paused,
    )
    for name, deployment_id in deploy(options).items():
        print(f"{name}\t{deployment_id}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
