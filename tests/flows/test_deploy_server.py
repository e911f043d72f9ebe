"""Integration: a real `prefect server start` (SQLite, loopback) and the deployments as a user makes them: `prefect deploy`
of deployments/prefect.yaml and a process worker, deployments/deploy.py, `neuralslicer serve`; a default command-line
slice's run log read back from the API."""
from __future__ import annotations

import contextlib
import json
import os
import re
import signal
import socket
import subprocess
import sys
import time
import urllib.request
from collections.abc import Iterator
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import pytest
import yaml

from conftest import fast_config
from neuralslicer.storage import ArtifactStore

pytestmark = pytest.mark.slow   # end to end (a Prefect server, the CLI or a cluster): not in `make test-fast`

REPO = Path(__file__).resolve().parents[2]
PREFECT = str(Path(sys.executable).with_name("prefect"))
SLICE = "neuralslicer-slice-model/slice"
#: Prefect's console format of a log record: what a quiet terminal does not show at INFO
CONSOLE_INFO = re.compile(r"\| (INFO|DEBUG)\s+\|")


def free_port() -> int:
    """A free TCP port on the loopback interface."""
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def server_env(home: Path, port: int) -> dict[str, str]:
    """Environment of every process of the test: private PREFECT_HOME and SQLite database, the server's API URL."""
    return {
        **os.environ,
        "PREFECT_HOME": str(home),
        "PREFECT_API_URL": f"http://127.0.0.1:{port}/api",
        "PREFECT_API_DATABASE_CONNECTION_URL": f"sqlite+aiosqlite:///{home / 'prefect.db'}",
        "PREFECT_SERVER_ANALYTICS_ENABLED": "false",
        "DO_NOT_TRACK": "1",
        "PREFECT_LOGGING_LEVEL": "INFO",
        "PYTHONUNBUFFERED": "1",
    }


@contextlib.contextmanager
def background(cmd: list[str], env: dict[str, str], log: Path) -> Iterator[subprocess.Popen]:
    """A process in its own session, killed with its children on exit (even on failure)."""
    fh = open(log, "w")
    proc = subprocess.Popen(cmd, cwd=REPO, env=env, stdout=fh, stderr=subprocess.STDOUT, start_new_session=True)
    try:
        yield proc
    finally:
        with contextlib.suppress(ProcessLookupError):
            os.killpg(proc.pid, signal.SIGTERM)
        try:
            proc.wait(timeout=20)
        except subprocess.TimeoutExpired:
            with contextlib.suppress(ProcessLookupError):
                os.killpg(proc.pid, signal.SIGKILL)
            proc.wait(timeout=20)
        fh.close()


def wait_healthy(port: int, proc: subprocess.Popen, log: Path, timeout_s: float = 180) -> None:
    """Poll the server's health endpoint until it answers (bounded)."""
    deadline = time.monotonic() + timeout_s
    while time.monotonic() < deadline:
        assert proc.poll() is None, f"prefect server exited:\n{log.read_text()[-3000:]}"
        with contextlib.suppress(OSError):
            with urllib.request.urlopen(f"http://127.0.0.1:{port}/api/health", timeout=2) as r:
                if r.status == 200:
                    return
        time.sleep(0.5)
    pytest.fail(f"prefect server not healthy after {timeout_s} s:\n{log.read_text()[-3000:]}")


@dataclass
class Server:
    """The module's Prefect server: the environment that points at it, a scratch folder, one store for every run."""

    env: dict[str, str]
    root: Path
    store: Path

    @property
    def url(self) -> str:
        """The API URL."""
        return self.env["PREFECT_API_URL"]

    def run(self, *args: str, timeout: float = 300) -> subprocess.CompletedProcess:
        """A command against this server, from the repository root; it must succeed."""
        done = subprocess.run(list(args), cwd=REPO, env=self.env, capture_output=True, text=True, timeout=timeout)
        assert done.returncode == 0, done.stdout[-3000:] + done.stderr[-3000:]
        return done

    @contextlib.contextmanager
    def client(self) -> Iterator[Any]:
        """A synchronous Prefect client of this server (in the test's process)."""
        from prefect.client.orchestration import get_client
        from prefect.settings import PREFECT_API_URL, temporary_settings

        with temporary_settings(updates={PREFECT_API_URL: self.url}):
            with get_client(sync_client=True) as client:
                yield client


@pytest.fixture(scope="module")
def server(tmp_path_factory: pytest.TempPathFactory) -> Iterator[Server]:
    """A `prefect server start` of its own (SQLite in a private PREFECT_HOME) for the module's tests."""
    root = tmp_path_factory.mktemp("deploy-server")
    home = root / "prefect-home"
    home.mkdir()
    port = free_port()
    env = server_env(home, port)
    cmd = [PREFECT, "server", "start", "--host", "127.0.0.1", "--port", str(port), "--no-ui", "--analytics-off"]
    with background(cmd, env, root / "server.log") as proc:
        wait_healthy(port, proc, root / "server.log")
        yield Server(env, root, root / "store.zarr")


def planar_config(folder: Path, **overrides: object) -> dict:
    """The tests' quick configuration (planar layers), also as folder/config.yaml."""
    config = fast_config(objectives=[], **overrides)
    (folder / "config.yaml").write_text(yaml.safe_dump(config))
    return config


def run_logs(client: Any, flow_run_id: Any) -> list[str]:
    """Every log message of a flow run and its task runs, from the API, in order."""
    from prefect.client.schemas.filters import LogFilter, LogFilterFlowRunId

    messages: list[str] = []
    while True:
        page = client.read_logs(LogFilter(flow_run_id=LogFilterFlowRunId(any_=[flow_run_id])), limit=200,
                                offset=len(messages))
        messages += [log.message for log in page]
        if len(page) < 200:
            return messages


def report_markdown(client: Any, flow_run_id: Any) -> str:
    """The markdown of the report artifact a deployed run's slicing flow (its subflow) published."""
    from prefect.client.schemas.filters import (ArtifactFilter, ArtifactFilterFlowRunId, ArtifactFilterType,
                                                FlowRunFilter, FlowRunFilterParentFlowRunId)

    children = client.read_flow_runs(flow_run_filter=FlowRunFilter(
        parent_flow_run_id=FlowRunFilterParentFlowRunId(any_=[flow_run_id])))
    assert children, "the deployed run has no slicing subflow"
    found = client.read_artifacts(artifact_filter=ArtifactFilter(
        flow_run_id=ArtifactFilterFlowRunId(any_=[flow_run_id, *(c.id for c in children)]),
        type=ArtifactFilterType(any_=["markdown"])))
    assert len(found) == 1, [a.key for a in found]
    assert found[0].key.startswith("slice-")
    return str(found[0].data)


def test_a_default_command_line_slice_logs_its_steps_and_progress_to_the_run_log(server: Server, small_part: Path
                                                                                ) -> None:
    """`neuralslicer slice` with Prefect's logging as the command sets it (no PREFECT_LOGGING_LEVEL): the terminal shows
    the command's own lines and no Prefect INFO record; the run's log in the API has every step's started/done line
    and the progress lines."""
    from neuralslicer.flows.settings import CONSOLE_LEVEL

    folder = server.root / "cli"
    folder.mkdir()
    planar_config(folder)
    env = {k: v for k, v in server.env.items() if k not in ("PREFECT_LOGGING_LEVEL", CONSOLE_LEVEL)}
    out = folder / "run"
    done = subprocess.run([sys.executable, "-m", "neuralslicer.cli", "slice", str(small_part), "--out", str(out),
                           "--store", str(server.store), "--config", str(folder / "config.yaml")],
                          cwd=REPO, env=env, capture_output=True, text=True, timeout=300)
    assert done.returncode == 0, done.stderr[-3000:]
    assert "model: started" in done.stderr and not CONSOLE_INFO.search(done.stderr), done.stderr[-3000:]
    name = json.loads((out / "run.json").read_text())["flow_run_name"]
    from prefect.client.schemas.filters import FlowRunFilter, FlowRunFilterName

    with server.client() as client:
        (run,) = client.read_flow_runs(flow_run_filter=FlowRunFilter(name=FlowRunFilterName(any_=[name])))
        logs = run_logs(client, run.id)
    for step in ("model", "surface", "samples", "cage", "field", "layers", "toolpaths", "motion", "program", "export"):
        assert f"{step}: started" in logs and any(m.startswith(f"{step}: done in ") for m in logs), (step, logs)
    assert any(re.match(r"layers: \d+/\d+ \(", m) for m in logs), "\n".join(logs)   # a Progress line


def test_prefect_yaml_deploys_and_a_process_worker_runs_the_slice_or_fails_it_in_one_line(
        server: Server, small_part: Path) -> None:
    """`prefect deploy --all` of deployments/prefect.yaml: the slice listed with its nightly schedule (inactive) and no
    up axis, a run asking for an unknown one refused by its parameter schema. `prefect worker start --run-once` runs a
    slice of the tiny part (paths as run parameters) to its output folder and report artifact (figures embedded),
    and a run with bad input to Failed with the preflight's one line (the parameter it names), no traceback in the
    worker's output or the run's log."""
    from prefect.deployments import run_deployment
    from prefect.settings import PREFECT_API_URL, temporary_settings

    folder = server.root / "prefect-yaml"
    folder.mkdir()
    config = planar_config(folder)
    server.run(PREFECT, "work-pool", "create", "neuralslicer", "--type", "process")
    server.run(PREFECT, "deploy", "--prefect-file", "deployments/prefect.yaml", "--all")
    with server.client() as client:
        names = {f"{client.read_flow(d.flow_id).name}/{d.name}" for d in client.read_deployments()}
        deployment = client.read_deployment_by_name(SLICE)
    assert names >= {SLICE, "neuralslicer-study-initial-guess/initial-guess", "neuralslicer-study-cages/cages",
                     "neuralslicer-study-batch/batch"}
    assert [(s.schedule.cron, s.active) for s in deployment.schedules] == [("0 3 * * *", False)]
    assert "up" not in deployment.parameters and deployment.parameters["model"] == "neuralslicer/data/ring.yaml"
    with temporary_settings(updates={PREFECT_API_URL: server.url}):
        good = run_deployment(SLICE, timeout=0, parameters={
            "model": str(small_part), "out_dir": str(folder / "run"), "store": str(server.store), "config": config})
        bad = run_deployment(SLICE, timeout=0, parameters={
            "model": str(small_part), "out_dir": str(folder / "bad"), "store": str(server.store),
            "config": {**config, "layers": {**config["layers"], "layer_height": 100.0}}})
        with pytest.raises(Exception, match="Validation failed for field 'up'"):   # the deployment's schema
            run_deployment(SLICE, timeout=0, parameters={"model": str(small_part), "out_dir": str(folder), "up": "q"})
    start = time.monotonic()
    worker = server.run(PREFECT, "worker", "start", "--pool", "neuralslicer", "--type", "process", "--run-once",
                        "--limit", "2", timeout=600)
    wall = time.monotonic() - start
    worker_log = worker.stdout + worker.stderr
    with server.client() as client:
        good, bad = client.read_flow_run(good.id), client.read_flow_run(bad.id)
        assert good.state.is_completed(), f"{good.state}\n{worker_log[-4000:]}"
        markdown = report_markdown(client, good.id)
        bad_logs = run_logs(client, bad.id)
    assert bad.state.is_failed() and bad.state.message.startswith(
        "layers.layer_height: 100 mm is at least the model's height"), bad.state
    assert "Traceback" not in worker_log, worker_log[-4000:]
    assert [m for m in bad_logs if m == bad.state.message] == [bad.state.message], bad_logs
    assert not any("Traceback" in m for m in bad_logs), bad_logs
    assert not (folder / "bad").exists()
    run_dir = folder / "run"
    for name in ("report.md", "metrics.json", "run.json", "provenance.json", "model.ply", "field.vtu"):
        assert (run_dir / name).is_file(), name
    assert json.loads((run_dir / "metrics.json").read_text())["n_layers"] > 0
    assert "![" in (run_dir / "report.md").read_text()
    assert "data:image/png;base64," in markdown and not re.search(r"!\[[^\]]*\]\((?!data:)", markdown)
    print(f"worker --run-once, one slice and one bad input: {wall:.1f} s")


def test_deploy_py_deploys_the_slice_with_a_schedule_and_a_worker_runs_it(server: Server, small_part: Path) -> None:
    """deployments/deploy.py: the slice on a process pool of its own, its defaults (no up axis), a cron schedule on
    it (--schedule slice), the gpu tag limit; a worker runs it into the store, every step's artifact complete."""
    from prefect.deployments import run_deployment
    from prefect.settings import PREFECT_API_URL, temporary_settings

    folder = server.root / "deploy-py"
    folder.mkdir()
    planar_config(folder)
    out = folder / "runs"
    deployed = server.run(sys.executable, "deployments/deploy.py", "--pool", "test-pool", "--only", "slice",
                          "--model", str(small_part), "--out", str(out), "--store", str(server.store),
                          "--config", str(folder / "config.yaml"), "--cron", "0 4 * * *", "--schedule", "slice",
                          "--paused", "--gpu-limit", "1")
    assert SLICE in deployed.stdout
    with server.client() as client:
        deployment = client.read_deployment_by_name(SLICE)
        assert client.read_concurrency_limit_by_tag("gpu").concurrency_limit == 1
    assert [s.schedule.cron for s in deployment.schedules] == ["0 4 * * *"] and deployment.paused
    assert "up" not in deployment.parameters and deployment.work_pool_name == "test-pool"
    with temporary_settings(updates={PREFECT_API_URL: server.url}):
        run = run_deployment(SLICE, timeout=0)
    worker = server.run(PREFECT, "worker", "start", "--pool", "test-pool", "--type", "process", "--run-once",
                        "--limit", "1", timeout=600)
    with server.client() as client:
        state = client.read_flow_run(run.id).state
    assert state.is_completed(), f"{state}\n{(worker.stdout + worker.stderr)[-4000:]}"
    run_dir = out / "slice"
    summary = json.loads((run_dir / "run.json").read_text())
    assert [t["task"] for t in summary["tasks"]][:4] == ["model", "surface", "samples", "cage"]
    metrics = json.loads((run_dir / "metrics.json").read_text())
    assert metrics["model"] == "lpart" and metrics["n_layers"] > 0 and metrics["field.steps"] == 0
    prov = json.loads((run_dir / "provenance.json").read_text())
    assert metrics["provenance.inputs.spec_sha256"] == prov["inputs"]["spec_sha256"]
    st = ArtifactStore(server.store)
    assert st.exists(f"lpart/provenance/{prov['digest']}")
    for step in ("model", "surface", "samples", "cage", "field", "layers", "toolpaths", "motion", "program", "export"):
        assert st.children(f"lpart/{step}"), f"no complete {step} artifact in the store"
    assert str(run_dir) in [st.attrs(f"lpart/export/{d}")["out_dir"] for d in st.children("lpart/export")]


def test_neuralslicer_serve_serves_the_scheduled_slice_and_runs_it(server: Server, small_part: Path) -> None:
    """`neuralslicer serve` (Prefect's serve): the slice deployment appears with its defaults and cron schedule, and a
    triggered run runs in the serving process's subprocess to Completed."""
    from prefect.deployments import run_deployment
    from prefect.settings import PREFECT_API_URL, temporary_settings

    folder = server.root / "serve"
    folder.mkdir()
    planar_config(folder)
    cmd = [sys.executable, "-m", "neuralslicer.cli", "serve", "--only", "slice", "--model", str(small_part),
           "--out", str(folder / "runs"), "--store", str(server.store), "--config", str(folder / "config.yaml"),
           "--cron", "0 5 * * *", "--limit", "1"]
    with background(cmd, server.env, folder / "serve.log") as proc:
        deadline = time.monotonic() + 180
        deployment = None
        while deployment is None or not deployment.schedules or deployment.schedules[0].schedule.cron != "0 5 * * *":
            assert proc.poll() is None and time.monotonic() < deadline, (folder / "serve.log").read_text()[-3000:]
            time.sleep(1)
            with server.client() as client, contextlib.suppress(Exception):
                deployment = client.read_deployment_by_name(SLICE)
        assert deployment.parameters["model"] == str(small_part) and "up" not in deployment.parameters
        with temporary_settings(updates={PREFECT_API_URL: server.url}):
            run = run_deployment(SLICE, timeout=300, poll_interval=1)
        assert run.state.is_completed(), f"{run.state}\n{(folder / 'serve.log').read_text()[-4000:]}"
    assert json.loads((folder / "runs" / "slice" / "metrics.json").read_text())["n_layers"] > 0
