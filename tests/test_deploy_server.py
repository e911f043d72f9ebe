"""Integration: a real `prefect server start` (SQLite, loopback), a process work pool and worker, a deployed slicing run."""
from __future__ import annotations

import contextlib
import json
import os
import signal
import socket
import subprocess
import sys
import time
import urllib.request
from collections.abc import Iterator
from pathlib import Path

import pytest
import yaml

from neuralslicer.storage import ArtifactStore
from studies_common import shared_store, tiny_config, torus_file

pytestmark = pytest.mark.slow   # end to end (a Prefect server, the CLI or a cluster): not in `make test-fast`

REPO = Path(__file__).resolve().parents[1]
PREFECT = str(Path(sys.executable).with_name("prefect"))


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


@pytest.mark.slow
def test_deployed_slice_runs_on_process_worker(tmp_path: Path, tmp_path_factory: pytest.TempPathFactory) -> None:
    """Deploy the slicing flow from this source tree, run it through a process worker, find its outputs in the store."""
    home = tmp_path / "prefect-home"
    home.mkdir()
    port = free_port()
    env = server_env(home, port)
    model = torus_file(tmp_path_factory.getbasetemp())
    store = shared_store(tmp_path_factory)
    out = tmp_path / "runs"
    config = tmp_path / "config.yaml"
    config.write_text(yaml.safe_dump(tiny_config(objectives=[]).model_dump(mode="json")))
    server_cmd = [PREFECT, "server", "start", "--host", "127.0.0.1", "--port", str(port), "--no-ui", "--analytics-off"]
    with background(server_cmd, env, tmp_path / "server.log") as server:
        wait_healthy(port, server, tmp_path / "server.log")
        deployed = subprocess.run(
            [sys.executable, "deployments/deploy.py", "--pool", "test-pool", "--only", "slice", "--model", str(model),
             "--out", str(out), "--store", str(store), "--config", str(config)],
            cwd=REPO, env=env, capture_output=True, text=True, timeout=180,
        )
        assert deployed.returncode == 0, deployed.stdout + deployed.stderr
        assert "neuralslicer-slice-model/slice" in deployed.stdout
        worker_cmd = [PREFECT, "worker", "start", "--pool", "test-pool", "--type", "process", "--limit", "1"]
        with background(worker_cmd, env, tmp_path / "worker.log") as worker:
            trigger = (
                "from prefect.deployments import run_deployment\n"
                "fr = run_deployment('neuralslicer-slice-model/slice', timeout=420, poll_interval=2)\n"
                "print('STATE', fr.state.type.value, fr.id)\n"
            )
            ran = subprocess.run([sys.executable, "-c", trigger], cwd=REPO, env=env, capture_output=True, text=True,
                                 timeout=480)
            assert worker.poll() is None, (tmp_path / "worker.log").read_text()[-3000:]
        assert "STATE COMPLETED" in ran.stdout, (
            ran.stdout + ran.stderr + "\nworker log:\n" + (tmp_path / "worker.log").read_text()[-4000:]
        )
    # the run's outputs: the slice contract in out/slice, every step's artifact complete in the store
    run_dir = out / "slice"
    summary = json.loads((run_dir / "run.json").read_text())
    assert [t["task"] for t in summary["tasks"]][:4] == ["model", "surface", "samples", "cage"]
    metrics = json.loads((run_dir / "metrics.json").read_text())
    assert metrics["model"] == "torus" and metrics["n_layers"] > 0 and metrics["field.steps"] == 0
    # the run's provenance: in the folder, in metrics.json and in the store
    prov = json.loads((run_dir / "provenance.json").read_text())
    assert metrics["provenance.inputs.spec_sha256"] == prov["inputs"]["spec_sha256"]
    assert ArtifactStore(store).exists(f"torus/provenance/{prov['digest']}")
    st = ArtifactStore(store)
    for step in ("model", "surface", "samples", "cage", "field", "layers", "toolpaths", "motion", "program", "export"):
        assert st.children(f"torus/{step}"), f"no complete {step} artifact in the store"
    exports = [st.attrs(f"torus/export/{d}")["out_dir"] for d in st.children("torus/export")]
    assert str(run_dir) in exports
