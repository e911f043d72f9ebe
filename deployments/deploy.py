"""Deploy the slicing flow and the studies to a Prefect server's process work pool (from this source tree).

    python deployments/deploy.py --pool neuralslicer --model /data/ring.yaml --out /data/runs

creates the pool if needed and the deployments `neuralslicer-slice-model/slice`,
`neuralslicer-study-initial-guess/initial-guess`, `neuralslicer-study-cages/cages` and
`neuralslicer-study-batch/batch`; `--cron "0 2 * * *"` (or `--interval 86400`) puts a schedule on the deployments
`--schedule` names (default: the slice; `--schedule slice,cages` adds the cage study); `--gpu-limit N` sets the `gpu`
tag concurrency limit (at most N field steps on a CUDA device at once). Parameters given here are defaults: override
them per run (`prefect deployment run NAME --param out_dir=...` or the UI's "Custom run"). The same deployments are
served without a work pool by `neuralslicer serve`.
"""
from __future__ import annotations

import argparse
import asyncio
import sys
from pathlib import Path
from typing import Any

from pydantic import Field

from neuralslicer.errors import InputError
from neuralslicer.flows.serve import (DEPLOYMENTS, DeploymentDefaults, check_names, default_parameters, schedule_of,
                                      set_gpu_limit)

REPO = Path(__file__).resolve().parents[1]


class DeployOptions(DeploymentDefaults):
    """What to deploy and where: the deployments' defaults, the work pool and the source tree."""

    pool: str = Field("neuralslicer", description="process work pool (created when missing)")
    source: str = Field(str(REPO), description="source tree (path or git URL) the worker loads the flows from")
    gpu_limit: int | None = Field(None, ge=0, description="slots of the 'gpu' tag concurrency limit (None: unchanged)")


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


def deploy(options: DeployOptions) -> dict[str, str]:
    """Create the work pool and the deployments; return {deployment name: deployment id}."""
    from prefect import flow

    asyncio.run(ensure_process_pool(options.pool))
    if options.gpu_limit is not None:
        asyncio.run(set_gpu_limit(options.gpu_limit))
    ids = {}
    for name in options.only:
        entry = DEPLOYMENTS[name]
        remote = flow.from_source(source=options.source, entrypoint=entry)
        deployment_id = remote.deploy(
            name=name, work_pool_name=options.pool, parameters=default_parameters(name, options),
            tags=["neuralslicer"], description=f"neuralslicer {name} ({entry})", print_next_steps=False,
            **schedule_of(name, options),
        )
        ids[f"{remote.name}/{name}"] = str(deployment_id)
    return ids


def names(text: str, where: str) -> list[str]:
    """A comma list of deployment names, checked."""
    return check_names([s for s in text.split(",") if s], where)


def main(argv: list[str] | None = None) -> int:
    """Command line of the deploy script."""
    p = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    p.add_argument("--pool", default="neuralslicer")
    p.add_argument("--source", default=str(REPO), help="source tree (path or git URL) the worker loads flows from")
    p.add_argument("--only", default=",".join(DEPLOYMENTS), help=f"comma list of {', '.join(DEPLOYMENTS)}")
    p.add_argument("--model", default=None)
    p.add_argument("--up", default=None, help="default up axis (default: none, a spec keeps its own)")
    p.add_argument("--out", default=None)
    p.add_argument("--store", default=None)
    p.add_argument("--config", default=None, help="YAML slicing configuration used as the default 'config'")
    p.add_argument("--cage-elements", default="4000,8000,16000")
    p.add_argument("--cron", default=None)
    p.add_argument("--interval", type=float, default=None)
    p.add_argument("--schedule", default="slice", help="comma list of the deployments that get --cron/--interval")
    p.add_argument("--paused", action="store_true")
    p.add_argument("--gpu-limit", type=int, default=None, help="slots of the 'gpu' tag concurrency limit")
    a = p.parse_args(argv)
    config: dict[str, Any] | None = None
    if a.config:
        import yaml

        config = yaml.safe_load(Path(a.config).read_text()) or {}
    try:
        only, scheduled = names(a.only, "--only"), names(a.schedule, "--schedule")
    except InputError as exc:
        p.error(str(exc))
    options = DeployOptions(
        pool=a.pool, source=a.source, only=only, model=a.model, up=a.up, out=a.out, store=a.store, config=config,
        cage_elements=[int(n) for n in a.cage_elements.split(",")], cron=a.cron, interval=a.interval,
        scheduled=scheduled, paused=a.paused, gpu_limit=a.gpu_limit,
    )
    for name, deployment_id in deploy(options).items():
        print(f"{name}\t{deployment_id}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
