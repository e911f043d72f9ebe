"""A study on a Dask cluster: what every worker must reach before a branch starts (the store, the study folder and the
Prefect API; GPU workers for the branches that compute on CUDA), and the Dask resources a branch asks for."""
from __future__ import annotations

import contextlib
import socket
import uuid
from collections.abc import Iterator, Mapping
from typing import Any

from neuralslicer.config import SliceConfig
from neuralslicer.errors import InputError

#: the Dask resource a GPU worker offers (``dask worker ... --resources GPU=1``) and a CUDA branch takes one of
GPU_RESOURCE = "GPU"
#: seconds to reach the scheduler, and to wait for its first worker (workers of a batch queue still starting)
CONNECT_TIMEOUT_S = 20.0
WAIT_FOR_WORKERS_S = 60.0
#: the name of a probe's marker file in a store or the study folder (removed after the check)
PROBE = ".neuralslicer-probe-"
SHARED = ("give a path on a file system that every worker mounts at the same place, or an fsspec URL "
          "(s3://bucket/store.zarr)")


def needs_gpu(config: SliceConfig) -> bool:
    """True when a branch's field step computes on the CUDA device its configuration names (``cuda``, ``cuda:1``):
    the steps ``flows/slice.py`` tags ``gpu``. ``auto`` asks for none (a worker's GPU serves it where there is one)."""
    if config.method == "s3_oneshot":
        device = config.s3_oneshot.device
    elif config.method == "neural" and config.objectives != []:
        device = config.neural.device
    else:
        return False
    return device.startswith("cuda")


def branch_resources(config: SliceConfig) -> dict[str, float]:
    """The Dask resources a branch holds while it runs: one GPU when its field step computes on CUDA, else none."""
    return {GPU_RESOURCE: 1.0} if needs_gpu(config) else {}


@contextlib.contextmanager
def annotated(resources: Mapping[str, float]) -> Iterator[None]:
    """Tasks submitted in the block ask Dask for ``resources`` (``dask.annotate``, which prefect-dask's client passes
    on to the scheduler); no resources: nothing is imported or changed."""
    if not resources:
        yield
        return
    import dask

    with dask.annotate(resources=dict(resources)):
        yield


def _fs(location: str) -> tuple[Any, str]:
    """The fsspec file system of a store or folder (path or URL) and the path on it."""
    from fsspec.core import url_to_fs

    fs, path = url_to_fs(location)
    return fs, str(path).rstrip("/")


def write_marker(location: str, token: str) -> None:
    """Create the location when missing and write this machine's probe marker in it."""
    fs, root = _fs(location)
    fs.makedirs(root, exist_ok=True)
    fs.pipe_file(f"{root}/{PROBE}{token}", token.encode())


def remove_marker(location: str, token: str) -> None:
    """Remove this machine's probe marker (gone already: nothing to do)."""
    fs, root = _fs(location)
    with contextlib.suppress(FileNotFoundError):
        fs.rm_file(f"{root}/{PROBE}{token}")


def probe_worker(locations: Mapping[str, str], token: str, api_url: str | None) -> dict[str, str]:
    """On a Dask worker: {where: what is wrong} for each location whose marker it does not read (not the same
    storage) or where it cannot write, and for the Prefect API when it does not answer; empty when all is well."""
    problems: dict[str, str] = {}
    host = socket.gethostname()
    for where, location in locations.items():
        try:
            fs, root = _fs(location)
            seen = fs.cat_file(f"{root}/{PROBE}{token}") == token.encode()
        except Exception:  # noqa: BLE001 - any failure to read it (no such file, no driver, no access) is the answer
            seen = False
        if not seen:
            problems[where] = f"{location} is not shared with host {host} (it does not see what this machine wrote)"
            continue
        mine = f"{root}/{PROBE}{token}-{uuid.uuid4().hex}"
        try:
            fs.pipe_file(mine, b"ok")
            fs.rm_file(mine)
        except Exception as exc:  # noqa: BLE001 - any failure to write is the answer
            problems[where] = f"host {host} cannot write to {location} ({type(exc).__name__}: {exc})"
    if api_url:
        import httpx

        try:
            httpx.get(f"{api_url.rstrip('/')}/health", timeout=5.0).raise_for_status()
        except httpx.HTTPError as exc:
            problems["PREFECT_API_URL"] = f"host {host} cannot reach the Prefect API at {api_url} ({exc})"
    return problems


def _connect(address: str) -> Any:
    """A client of the scheduler at ``address`` with at least one worker; InputError when there is none."""
    from distributed import Client

    try:
        client = Client(address, timeout=CONNECT_TIMEOUT_S, set_as_default=False)
    except (OSError, TimeoutError) as exc:
        raise InputError("--dask", f"{address}: no Dask scheduler answers there ({exc})") from None
    try:
        client.wait_for_workers(1, timeout=WAIT_FOR_WORKERS_S)
    except TimeoutError:
        client.close()
        raise InputError("--dask", f"{address}: no worker joined the scheduler within {WAIT_FOR_WORKERS_S:g} s; "
                         f"start workers with `dask worker {address}`") from None
    return client


def check_cluster(address: str, locations: Mapping[str, str], api_url: str | None, gpu: bool = False
                  ) -> dict[str, str]:
    """Before a study starts on the scheduler at ``address``: every worker reads this machine's marker in each of
    ``locations`` ({flag: store or folder}) and writes there, and reaches ``api_url``; with ``gpu``, a worker offers
    the GPU resource. InputError (one line naming the worker and the problem) otherwise. Returns {worker: host}."""
    token = uuid.uuid4().hex
    for location in locations.values():
        write_marker(location, token)
    try:
        with _connect(address) as client:
            found = client.run(probe_worker, dict(locations), token, api_url, on_error="return")
            workers = client.scheduler_info(n_workers=-1)["workers"]
    finally:
        for location in locations.values():
            remove_marker(location, token)
    for worker, problems in sorted(found.items()):
        if isinstance(problems, BaseException):
            raise InputError("--dask", f"Dask worker {worker} failed the study's checks: {problems}")
        for where, problem in problems.items():
            hint = (SHARED if where != "PREFECT_API_URL" else "serve the API on an address the workers reach "
                    "(prefect server start --host 0.0.0.0) and set PREFECT_API_URL to it")
            raise InputError(where, f"{problem}, Dask worker {worker}: {hint}")
    if gpu and not any(w.get("resources", {}).get(GPU_RESOURCE) for w in workers.values()):
        raise InputError("--device", f"cuda: no worker of {address} offers the Dask resource {GPU_RESOURCE}; start the "
                         f"GPU workers with `dask worker {address} --resources {GPU_RESOURCE}=1`")
    return {worker: str(info.get("host", "")) for worker, info in workers.items()}
