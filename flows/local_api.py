"""Prefect's local API server, started the moment a command knows it needs one.

With no API configured, Prefect's client starts a local ("ephemeral") API server the first time a flow runs:
it first imports the whole server package into the calling process (about 2.5 s) and then waits for the
server's own process to boot (about 3.3 s), while the command does nothing else. ``LocalApi`` launches the
same server process (the same uvicorn app and settings as Prefect's ``SubprocessASGIServer``) as soon as the
command starts, without that import, so that its boot overlaps reading the model, the checks and the
imports; the flow then runs against it through ``PREFECT_API_URL``. A cached rerun of the ring takes about
4 s less. With ``PREFECT_API_URL`` set (a Prefect server, the test harness) nothing is started.
"""
from __future__ import annotations

import atexit
import contextlib
import os
import socket
import subprocess
import sys
import tempfile
import time
from collections.abc import Iterator
from pathlib import Path

from flows.settings import API_START_FAILED, prefect_environment

#: exit status of uvicorn when its port is taken (another process got it first): pick another one
_PORT_TAKEN = 3


def free_port() -> int:
    """A TCP port on 127.0.0.1 that nothing listens on now."""
    with contextlib.closing(socket.socket(socket.AF_INET, socket.SOCK_STREAM)) as sock:
        sock.bind(("127.0.0.1", 0))
        return int(sock.getsockname()[1])


#: the server process: on Linux it asks for SIGTERM when the command that started it dies, however it dies
#: (PR_SET_PDEATHSIG), leaves at once if that happened already, then runs uvicorn with the remaining arguments
_LAUNCHER = """
import ctypes, os, runpy, signal, sys
parent = int(sys.argv[1])
try:
    ctypes.CDLL("libc.so.6").prctl(1, signal.SIGTERM)
except (OSError, AttributeError):
    pass
if os.getppid() != parent:
    sys.exit(0)
sys.argv = ["uvicorn", *sys.argv[2:]]
runpy.run_module("uvicorn", run_name="__main__", alter_sys=True)
"""


class LocalApi:
    """A local Prefect API server process, booting in the background from construction on."""

    def __init__(self) -> None:
        """Launch the server process (returns at once)."""
        self.process: subprocess.Popen[bytes] | None = None
        self.port = 0
        self._log = tempfile.TemporaryFile()   # the server's stderr: a file, so that it can never block on a full pipe
        self._launch()
        atexit.register(self.stop)

    @property
    def url(self) -> str:
        """The API's base URL."""
        return f"http://127.0.0.1:{self.port}/api"

    def _launch(self) -> None:
        """Start the uvicorn process of Prefect's server app (the ephemeral server's command and settings)."""
        import prefect
        from prefect.settings import get_current_settings

        self.port = free_port()
        env = {**os.environ, "PREFECT_UI_ENABLED": "0", "PREFECT__SERVER_EPHEMERAL": "1", "PREFECT__SERVER_FINAL": "1",
               **get_current_settings().to_environment_variables(exclude_unset=True)}
        # a session of its own: a SIGTERM or Ctrl-C sent to the command's process group stops the flow, which then
        # reports its end to this server; the server goes when the command does (``stop``, or with it)
        self.process = subprocess.Popen(
            [sys.executable, "-c", _LAUNCHER, str(os.getpid()), "--app-dir", str(Path(prefect.__module_path__).parent),
             "--factory", "prefect.server.api.server:create_app", "--host", "127.0.0.1", "--port", str(self.port),
             "--log-level", "error", "--lifespan", "on"],
            env=env, stdout=subprocess.DEVNULL, stderr=self._log, start_new_session=True)

    def wait(self, timeout_s: float) -> None:
        """Block until the API answers its health check; RuntimeError (Prefect's words) after ``timeout_s``."""
        import httpx

        if self.process is None:          # stopped after a failed start: boot a fresh one
            self._launch()
        deadline = time.monotonic() + timeout_s
        with httpx.Client() as client:
            while time.monotonic() < deadline:
                assert self.process is not None
                status = self.process.poll()
                if status == _PORT_TAKEN:
                    self._launch()
                    continue
                if status is not None:
                    self._log.seek(0)
                    err = self._log.read().decode(errors="replace")[-2000:]
                    self.stop()
                    # Prefect's words, as its own server's failure: the command retries once, then says what to do
                    raise RuntimeError(f"{API_START_FAILED}: the server process exited with code {status}: {err}")
                try:
                    if client.get(f"{self.url}/health", timeout=5.0).status_code == 200:
                        return
                except httpx.HTTPError:
                    pass
                time.sleep(0.05)
        self.stop()
        raise RuntimeError(f"{API_START_FAILED} (waited {timeout_s:.0f} s)")

    @contextlib.contextmanager
    def serving(self) -> Iterator[None]:
        """Wait for the server, then point Prefect's client at it for the duration of the block."""
        from prefect.settings import PREFECT_API_URL, PREFECT_SERVER_EPHEMERAL_STARTUP_TIMEOUT_SECONDS, temporary_settings

        self.wait(float(PREFECT_SERVER_EPHEMERAL_STARTUP_TIMEOUT_SECONDS.value()))
        with temporary_settings(updates={PREFECT_API_URL: self.url}):
            yield

    def stop(self) -> None:
        """Terminate the server process (at exit, or after a failed start)."""
        process, self.process = self.process, None
        if process is None or process.poll() is not None:
            return
        process.terminate()
        try:
            process.wait(timeout=5)
        except subprocess.TimeoutExpired:
            process.kill()
            process.wait()


def start_local_api() -> LocalApi | None:
    """Start a local API server in the background unless an API is configured (PREFECT_API_URL)."""
    prefect_environment()
    from prefect.settings import get_current_settings  # after prefect_environment(): Prefect's logging set-up

    return None if get_current_settings().api.url else LocalApi()


@contextlib.contextmanager
def api_serving(api: LocalApi | None) -> Iterator[None]:
    """The block runs against ``api`` once it is up, or against the configured API when ``api`` is None."""
    if api is None:
        yield
    else:
        with api.serving():
            yield
