"""The Prefect API of a study on a Dask cluster: the configured one (``PREFECT_API_URL``) or the study's own server.

Without ``PREFECT_API_URL`` Prefect runs a flow against an ephemeral API server inside the calling process, and
Prefect 3.8 hands its address to no Dask worker: a worker would start an ephemeral server of its own that knows
nothing of the study (on another host, with another database). So a study on Dask with no API configured runs
against ``prefect server start`` (Prefect's public command, no UI, no scheduler), started for the study's lifetime on
the address of this machine that the scheduler's network reaches, and stopped when the study ends. The flow runs
with ``PREFECT_API_URL`` set to it; Prefect's task runner serialises the run's settings with every task it submits,
so each branch on a worker reports to that server (``flows/cluster.py`` checks that every worker reaches it).
"""
from __future__ import annotations

import contextlib
import ipaddress
import os
import signal
import subprocess
import sys
import tempfile
import time
from collections.abc import Iterator
from urllib.parse import urlsplit

from neuralslicer.errors import NeuralSlicerError
from neuralslicer.flows.local_api import free_port
from neuralslicer.flows.settings import API_STARTUP_TIMEOUT_S

#: the exit status of ``prefect server start`` when its port is taken meanwhile: pick another one
_PORT_TAKEN = 1


def configured_api_url() -> str | None:
    """The Prefect API the settings name (environment, profile or this process), None for the ephemeral one."""
    from prefect.settings import get_current_settings

    return get_current_settings().api.url or None


def server_host(dask: str) -> str:
    """The address of this machine that the Dask scheduler's network reaches (127.0.0.1 for ``local`` or a scheduler
    on this machine's loopback)."""
    if dask == "local":
        return "127.0.0.1"
    host = urlsplit(dask if "://" in dask else f"tcp://{dask}").hostname or "127.0.0.1"
    with contextlib.suppress(ValueError):
        if ipaddress.ip_address(host).is_loopback:
            return "127.0.0.1"
    if host == "localhost":
        return "127.0.0.1"
    from distributed.utils import get_ip

    return get_ip(host)   # the local address of a route to the scheduler's host


def _die_with_parent() -> None:
    """In the server's process before it starts: SIGTERM to it when the study's process dies, however (Linux)."""
    with contextlib.suppress(OSError, AttributeError):
        import ctypes

        ctypes.CDLL("libc.so.6").prctl(1, signal.SIGTERM)   # PR_SET_PDEATHSIG


class StudyServer:
    """``prefect server start`` on ``host`` and a free port, for one study: started, awaited, stopped."""

    def __init__(self, host: str) -> None:
        """A server to start on ``host``."""
        self.host = host
        self.port = 0
        self.process: subprocess.Popen[bytes] | None = None
        self._log = tempfile.TemporaryFile()   # its output: a file, so that it never blocks on a full pipe

    @property
    def url(self) -> str:
        """The API's base URL."""
        return f"http://{self.host}:{self.port}/api"

    def command(self) -> list[str]:
        """The server's command line: the API and its services, no UI, no deployment scheduler, no analytics."""
        return [sys.executable, "-m", "prefect", "server", "start", "--host", self.host, "--port", str(self.port),
                "--no-ui", "--no-scheduler", "--no-late-runs", "--analytics-off", "--log-level", "WARNING"]

    def start(self) -> None:
        """Launch the server process (returns at once)."""
        self.port = free_port(self.host)
        self._log.seek(0)
        self._log.truncate()
        env = {k: v for k, v in os.environ.items() if k != "PREFECT_API_URL"}
        self.process = subprocess.Popen(self.command(), env=env, stdin=subprocess.DEVNULL, stdout=self._log,
                                        stderr=subprocess.STDOUT, preexec_fn=_die_with_parent, start_new_session=True)

    def wait(self, timeout_s: float) -> None:
        """Block until the API answers its health check (a taken port: another port); NeuralSlicerError after
        ``timeout_s`` or when the server exits, with the end of its output."""
        import httpx

        deadline = time.monotonic() + timeout_s
        while time.monotonic() < deadline:
            assert self.process is not None
            status = self.process.poll()
            if status == _PORT_TAKEN and "already in use" in self._output():
                self.start()
                continue
            if status is not None:
                break
            with contextlib.suppress(httpx.HTTPError):
                if httpx.get(f"{self.url}/health", timeout=2.0).status_code == 200:
                    return
            time.sleep(0.2)
        output = self._output()[-600:].strip().replace("\n", " | ")
        self.stop()
        raise NeuralSlicerError(
            f"the study's Prefect server ({' '.join(self.command()[1:])}) did not answer within {timeout_s:.0f} s"
            f"{': ' + output if output else ''}; start one yourself and set PREFECT_API_URL to it")

    def _output(self) -> str:
        """What the server printed so far."""
        self._log.seek(0)
        return self._log.read().decode(errors="replace")

    def stop(self) -> None:
        """Stop the server (SIGTERM to its process group, SIGKILL after 10 s)."""
        process, self.process = self.process, None
        if process is None or process.poll() is not None:
            return
        with contextlib.suppress(ProcessLookupError):
            os.killpg(process.pid, signal.SIGTERM)
        try:
            process.wait(timeout=10)
        except subprocess.TimeoutExpired:
            with contextlib.suppress(ProcessLookupError):
                os.killpg(process.pid, signal.SIGKILL)
            process.wait()


@contextlib.contextmanager
def study_api(dask: str | None, timeout_s: float = API_STARTUP_TIMEOUT_S) -> Iterator[str | None]:
    """The block runs against a Prefect API every Dask worker can reach: the configured one, or (``dask`` given, no
    ``PREFECT_API_URL``) a server of the study's own, its URL yielded; None without Dask or with a configured API."""
    if not dask or configured_api_url():
        yield None
        return
    from prefect.settings import PREFECT_API_URL, temporary_settings

    server = StudyServer(server_host(dask))
    server.start()
    try:
        server.wait(timeout_s)
        with temporary_settings(updates={PREFECT_API_URL: server.url}):
            yield server.url
    finally:
        server.stop()
