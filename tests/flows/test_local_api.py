"""The local Prefect API server the command line starts in the background (flows/local_api.py)."""
from __future__ import annotations

import subprocess
import sys

import httpx
import pytest
from prefect import flow
from prefect.settings import PREFECT_API_URL, temporary_settings

from neuralslicer.flows.local_api import LocalApi, start_local_api
from neuralslicer.flows.settings import API_START_FAILED

pytestmark = pytest.mark.slow   # end to end (a Prefect server, the CLI or a cluster): not in `make test-fast`


@flow
def answer() -> int:
    """A flow that needs the API (it records its run there)."""
    return 42


def test_no_server_is_started_when_an_api_is_configured() -> None:
    """With PREFECT_API_URL set (a Prefect server, the test harness) the command uses it and starts nothing."""
    with temporary_settings(updates={PREFECT_API_URL: "http://127.0.0.1:9/api"}):
        assert start_local_api() is None


def test_a_flow_runs_against_the_local_api_and_a_failed_start_boots_afresh() -> None:
    """A start that times out stops its process and says so in Prefect's words (the CLI retries on them); the
    next wait boots a fresh server, a flow runs against it, and stop() ends the process."""
    api = LocalApi(idle_s=0.0)
    first = api.process
    with pytest.raises(RuntimeError, match=API_START_FAILED):
        api.wait(0.0)
    assert api.process is None and first is not None and first.poll() is not None
    with api.serving():
        assert httpx.get(f"{api.url}/health", timeout=5.0).status_code == 200
        assert answer() == 42
    process = api.process
    assert process is not None and process.poll() is None
    api.stop()
    assert api.process is None and process.poll() is not None


class CrashingApi(LocalApi):
    """A server process that exits at once with an error."""

    def _launch(self) -> None:
        """Start a process that writes an error and exits with status 1."""
        self.process = subprocess.Popen([sys.executable, "-c", "import sys; sys.exit('no database')"],
                                        stdout=subprocess.DEVNULL, stderr=self._log)


def test_a_server_that_exits_fails_in_prefects_words_with_its_error() -> None:
    """A crashed server is reported like a start-up failure (so the command retries, then prints one line), with
    the server's own last words."""
    api = CrashingApi()
    with pytest.raises(RuntimeError, match=API_START_FAILED) as failure:
        api.wait(60.0)
    assert "exited with code 1" in str(failure.value) and "no database" in str(failure.value)
    assert api.process is None


def test_a_server_left_up_serves_the_next_command_then_goes_when_idle(tmp_path) -> None:
    """With an idle time the server that served a command stays up after it (recorded in PREFECT_HOME); the next
    command of the same interpreter uses it instead of booting one, a record of another interpreter is not used,
    and the server stops by itself once nothing has asked it anything for the idle time."""
    import json
    import time

    from prefect.settings import PREFECT_HOME

    with temporary_settings(updates={PREFECT_HOME: tmp_path}):
        first = LocalApi(idle_s=3.0)
        with first.serving():
            assert answer() == 42
        first._at_exit()                                        # what the command does when it ends
        server = first.process
        assert server is not None and server.poll() is None
        record = json.loads((tmp_path / "neuralslicer-api.json").read_text())
        assert record["pid"] == server.pid and record["port"] == first.port
        again = LocalApi(idle_s=3.0)
        assert again.reused and again.process is None and again.port == first.port
        with again.serving():
            assert answer() == 42
        (tmp_path / "neuralslicer-api.json").write_text(json.dumps({**record, "python": "/elsewhere/python"}))
        other = LocalApi(idle_s=0.0)
        assert not other.reused and other.process is not None
        other.stop()
        deadline = time.monotonic() + 30.0
        while server.poll() is None and time.monotonic() < deadline:
            time.sleep(0.2)
        assert server.poll() is not None, "the idle server did not stop"
