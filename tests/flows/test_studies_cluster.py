"""A study on a real multi-process Dask cluster (`dask scheduler`, two `dask worker` processes): one worker is killed
in the middle of an optimisation and the study still finishes every branch; and the checks before a study starts."""
from __future__ import annotations

import contextlib
import json
import os
import re
import signal
import subprocess
import sys
import time
from collections.abc import Iterator
from dataclasses import dataclass, field
from pathlib import Path

import httpx
import pytest
import yaml

from neuralslicer.errors import InputError
from neuralslicer.storage import ArtifactStore
from studies_common import tiny_config, torus_file

pytest.importorskip("distributed")

REPO = Path(__file__).resolve().parents[2]
DASK = Path(sys.executable).with_name("dask")


def _free_port() -> int:
    """A free TCP port on 127.0.0.1."""
    from neuralslicer.flows.local_api import free_port

    return free_port("127.0.0.1")


def _env(**extra: str) -> dict[str, str]:
    """The test's environment without a Prefect API: a study's processes must be handed the study's own."""
    env = {k: v for k, v in os.environ.items() if k != "PREFECT_API_URL"}
    return {**env, "PYTHONUNBUFFERED": "1", "DO_NOT_TRACK": "1", "PREFECT_SERVER_ANALYTICS_ENABLED": "false", **extra}


@dataclass
class Cluster:
    """A scheduler and its workers, each a process of its own, with their logs."""

    address: str
    folder: Path
    processes: dict[str, subprocess.Popen] = field(default_factory=dict)

    def start(self, name: str, command: list[str], env: dict[str, str]) -> subprocess.Popen:
        """Start one process of the cluster, its output in FOLDER/NAME.log."""
        log = open(self.folder / f"{name}.log", "wb")
        self.processes[name] = subprocess.Popen(command, env=env, stdout=log, stderr=subprocess.STDOUT,
                                                stdin=subprocess.DEVNULL, start_new_session=True)
        log.close()
        return self.processes[name]

    def logs(self) -> str:
        """The end of every process's log (for a failure's message)."""
        return "\n".join(f"--- {p.name}\n{p.read_text(errors='replace')[-2500:]}"
                         for p in sorted(self.folder.glob("*.log")))

    def stop(self) -> None:
        """SIGKILL every process still running (its process group) and reap it."""
        for proc in self.processes.values():
            if proc.poll() is None:
                os.killpg(proc.pid, signal.SIGKILL)
            proc.wait(timeout=30)


@contextlib.contextmanager
def dask_cluster(folder: Path, workers: dict[str, list[str]]) -> Iterator[Cluster]:
    """`dask scheduler` and one `dask worker` process per name (one thread, no nanny: a killed worker stays dead,
    the extra options of its entry) on free ports of 127.0.0.1, all killed at the end. The workers get no
    PREFECT_API_URL and may not start an ephemeral Prefect server."""
    from distributed import Client

    port = _free_port()
    folder.mkdir()
    c = Cluster(f"tcp://127.0.0.1:{port}", folder)
    try:
        c.start("scheduler", [str(DASK), "scheduler", "--host", "127.0.0.1", "--port", str(port), "--no-dashboard"],
                _env())
        for name, extra in workers.items():
            c.start(name, [str(DASK), "worker", c.address, "--name", name, "--host", "127.0.0.1", "--nthreads", "1",
                           "--nworkers", "1", "--no-nanny", "--memory-limit", "0", "--no-dashboard",
                           "--local-directory", str(folder / name), *extra],
                    _env(PREFECT_HOME=str(folder / f"{name}-prefect-home"),
                         PREFECT_SERVER_ALLOW_EPHEMERAL_MODE="false"))
        with Client(c.address, timeout=60, set_as_default=False) as client:
            client.wait_for_workers(len(workers), timeout=120)
        yield c
    finally:
        c.stop()


@pytest.fixture
def cluster(tmp_path: Path) -> Iterator[Cluster]:
    """A scheduler and two workers, w1 and w2 (``dask_cluster``)."""
    with dask_cluster(tmp_path / "cluster", {"w1": [], "w2": []}) as c:
        yield c


def _checkpoints(store: Path, model: str) -> dict[str, list[int]]:
    """The steps of the checkpoints of every optimisation in the store (field digest -> steps), read from the disk."""
    root = store / model / "checkpoints"
    if not root.is_dir():
        return {}
    return {d.name: sorted(int(p.name.removeprefix("step_")) for p in d.iterdir()
                           if p.name.startswith("step_") and (p / "zarr.json").is_file())
            for d in root.iterdir() if d.is_dir()}


def _holder(store: Path, model: str, digest: str) -> int | None:
    """The PID that holds the lock of a field being optimised (the store's lock file names it), None if none."""
    lock = store / "_staging" / "locks" / f"{model}__field__{digest}.lock"
    try:
        return int(json.loads(lock.read_text())["pid"])
    except (OSError, ValueError, KeyError):
        return None


@pytest.mark.slow
def test_cage_study_on_a_cluster_survives_a_killed_worker(cluster: Cluster, tmp_path: Path,
                                                          tmp_path_factory: pytest.TempPathFactory) -> None:
    """`neuralslicer study cages --dask tcp://...` with no PREFECT_API_URL: the command starts a Prefect server and
    hands its URL to the workers; one worker is SIGKILLed while its branch optimises; Dask reruns that branch on the
    other worker, which resumes the optimisation from its checkpoint, and every branch completes."""
    model = torus_file(tmp_path_factory.getbasetemp())
    store, out = tmp_path / "store.zarr", tmp_path / "study"
    max_steps = 30
    config = tmp_path / "config.yaml"
    settings = tiny_config(max_steps=max_steps, checkpoint_every=3).model_dump(mode="json")
    settings["layers"].update(layer_height=1.0, t_min=0.5, t_max=1.2)   # beads the default machine's nozzle lays
    config.write_text(yaml.safe_dump(settings))
    cmd = [sys.executable, "-m", "neuralslicer.cli", "study", "cages", str(model), "--cage-elements", "600,1000",
           "--out", str(out), "--store", str(store), "--config", str(config), "--dask", cluster.address]
    workers = {name: cluster.processes[name] for name in ("w1", "w2")}
    study = cluster.start("study", cmd, _env(PREFECT_HOME=str(tmp_path / "study-prefect-home"),
                                             NEURALSLICER_CACHE_DIR=str(tmp_path / "cage-cache")))
    killed: tuple[str, str, int] | None = None   # (worker, field digest, newest checkpoint step seen)
    start = time.monotonic()
    while time.monotonic() - start < 400 and study.poll() is None and killed is None:
        for digest, steps in _checkpoints(store, "torus").items():
            pid = _holder(store, "torus", digest)
            victim = next((n for n, p in workers.items() if p.pid == pid), None)
            if steps and victim is not None and steps[-1] < max_steps:
                os.kill(pid, signal.SIGKILL)
                killed = (victim, digest, steps[-1])
                break
        time.sleep(0.1)
    assert killed is not None, f"no optimisation checkpointed on a worker before the study ended\n{cluster.logs()}"
    victim, digest, seen_step = killed
    workers[victim].wait(timeout=30)
    try:
        study.wait(timeout=max(30.0, 480 - (time.monotonic() - start)))
    except subprocess.TimeoutExpired:
        pytest.fail(f"the study did not finish after the kill\n{cluster.logs()}")
    logs = cluster.logs()
    assert study.returncode == 0, logs
    survivor = next(n for n in workers if n != victim)
    api = re.search(r"Prefect API of this study \(handed to its Dask workers\): (\S+)", logs)
    assert api is not None and api.group(1).startswith("http://127.0.0.1:"), logs

    record = json.loads((out / "study.json").read_text())
    branches = {b["name"]: b for b in record["branches"]}
    assert sorted(branches) == ["cage_1000", "cage_600"]
    assert all(b["status"] == "completed" for b in branches.values()), record["branches"]
    rerun = next(b for b in branches.values() if b["field"]["path"].endswith(digest))
    # the killed worker's branch finished on the other worker, its optimisation resumed from the checkpoint
    assert rerun["worker"]["dask_worker"] == survivor and rerun["worker"]["pid"] == workers[survivor].pid
    assert rerun["field"]["resumed_from_step"] >= seen_step > 0
    assert rerun["field"]["steps"] == max_steps
    history = ArtifactStore(store).read(rerun["field"]["path"], ["history/total"])[0]["history/total"]
    assert len(history) == max_steps
    # every branch ran in a worker process (none in the command's), reported to the study's server, not to one of
    # its own: the workers may not start an ephemeral server and none left a database in their Prefect home
    assert {b["worker"]["dask_worker"] for b in branches.values()} <= {"w1", "w2"}
    assert all(b["worker"]["prefect_api"] == api.group(1) for b in branches.values())
    assert not any(cluster.folder.glob("w*-prefect-home/*.db"))
    for name in branches:
        assert json.loads((out / name / "metrics.json").read_text())["field.steps"] == max_steps
    assert (out / "study.md").is_file()
    with pytest.raises(httpx.HTTPError):   # the study's server went with the study
        httpx.get(f"{api.group(1)}/health", timeout=2.0)
    print(f"\nkilled {victim} at checkpoint step {seen_step} of {Path(rerun['field']['path']).name[:12]} "
          f"({rerun['name']}); resumed on {survivor} from step {rerun['field']['resumed_from_step']}; "
          + ", ".join(f"{n}: {b['worker']['dask_worker']} {b['wall_s']:.0f} s" for n, b in sorted(branches.items()))
          + f"; {time.monotonic() - start:.0f} s in all")


def test_unshared_store_is_refused_naming_the_worker(tmp_path: Path) -> None:
    """A store a worker does not share (an in-memory file system is one process's own) is refused before any branch,
    in one line naming the flag, the worker and the store; a shared folder passes."""
    from distributed import LocalCluster

    from neuralslicer.flows.cluster import check_cluster

    with LocalCluster(n_workers=1, threads_per_worker=1, processes=True, host="127.0.0.1",
                      dashboard_address=None) as local:
        (worker,) = check_cluster(local.scheduler_address, {"--out": str(tmp_path / "study")}, api_url=None)
        assert (tmp_path / "study").is_dir() and not list((tmp_path / "study").iterdir())   # the markers are gone
        with pytest.raises(InputError) as err:
            check_cluster(local.scheduler_address, {"--store": "memory://study/store.zarr"}, api_url=None)
        with pytest.raises(InputError) as no_api:
            check_cluster(local.scheduler_address, {}, api_url=f"http://127.0.0.1:{_free_port()}/api")
        with pytest.raises(InputError) as no_gpu:
            check_cluster(local.scheduler_address, {}, api_url=None, gpu=True)
    line = str(err.value)
    assert line.startswith("--store: memory://study/store.zarr is not shared with host") and worker in line
    assert "\n" not in line and "fsspec URL" in line
    assert str(no_api.value).startswith("PREFECT_API_URL: host") and "cannot reach the Prefect API" in str(no_api.value)
    assert str(no_gpu.value).startswith("--device: cuda: no worker") and "--resources GPU=1" in str(no_gpu.value)


@pytest.mark.slow
def test_dask_study_without_an_api_server_is_refused(prefect_server: None, monkeypatch: pytest.MonkeyPatch,
                                                     tmp_path: Path, tmp_path_factory: pytest.TempPathFactory) -> None:
    """A study flow on Dask with Prefect's ephemeral API (no PREFECT_API_URL) would leave each worker to start a
    server of its own: the flow fails before any branch, its error the one line that says what to set."""
    from neuralslicer.flows import studies

    monkeypatch.setattr(studies, "configured_api_url", lambda: None)
    with pytest.raises(InputError, match=r"^--dask: a study on Dask needs a Prefect API server .*PREFECT_API_URL"):
        studies.batch_study(models=[str(torus_file(tmp_path_factory.getbasetemp()))], out_dir=str(tmp_path / "out"),
                            dask="tcp://127.0.0.1:1")
    assert not (tmp_path / "out" / "torus").exists()


@pytest.mark.slow
def test_cuda_branches_go_to_the_workers_with_the_gpu_resource(prefect_server: None, tmp_path: Path) -> None:
    """A branch whose field computes on CUDA asks Dask for the GPU resource, and prefect-dask passes the annotation
    on: every such task runs on the worker started with ``--resources GPU=1``, whatever the other worker is doing."""
    from prefect import flow, task
    from prefect_dask import DaskTaskRunner

    from neuralslicer.config import SliceConfig
    from neuralslicer.flows.branch import worker_identity
    from neuralslicer.flows.cluster import annotated, branch_resources

    cuda, cpu = SliceConfig.model_validate({"neural": {"device": "cuda"}}), SliceConfig()
    assert branch_resources(cuda) == {"GPU": 1.0} and branch_resources(cpu) == {}
    assert branch_resources(SliceConfig.model_validate({"neural": {"device": "cuda"}, "objectives": []})) == {}
    where = task(worker_identity, name="where")

    with dask_cluster(tmp_path / "cluster", {"cpu": [], "gpu": ["--resources", "GPU=1"]}) as c:
        @flow(task_runner=DaskTaskRunner(address=c.address))
        def fan_out() -> list[tuple[str, str]]:
            futures = []
            for config in [cuda, cpu] * 4:
                with annotated(branch_resources(config)):
                    futures.append(("cuda" if branch_resources(config) else "cpu", where.submit()))
            return [(kind, f.result()["dask_worker"]) for kind, f in futures]

        placed = fan_out()
    assert {w for kind, w in placed if kind == "cuda"} == {"gpu"}
    assert len(placed) == 8
