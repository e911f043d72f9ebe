"""Prefect's local API server, started the moment a command knows it needs one.

With no API configured, Prefect's client starts a local ("ephemeral") API server the first time a flow runs:
it first imports the whole server package into the calling process (about 2.5 s) and then waits for the
server's own process to boot (about 3.3 s), while the command does nothing else. ``LocalApi`` launches the
same server process (the same uvicorn app and settings as Prefect's ``SubprocessASGIServer``) as soon as the
command starts, without that import, so that its boot overlaps reading the model, the checks and the
imports; the flow then runs against it through ``PREFECT_API_URL``. With ``PREFECT_API_URL`` set (a Prefect
server, the test harness) nothing is started.

The server's boot (3-7 s, the import of Prefect's server package most of it) is the longest part of a cached
rerun, so a server stays up after the command for ``NEURALSLICER_API_IDLE_S`` seconds without a request (default
300; 0: it stops with the command), recorded in ``PREFECT_HOME/neuralslicer-api.json``; the next command of the
same interpreter and Prefect version uses it (a health check) instead of booting its own. The server runs in a
session of its own, so that a SIGTERM or Ctrl-C to the command's process group reaches the flow, which reports
its end to the server (``flows/api_server.py``).
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
from collections.abc import Callable, Iterator
from pathlib import Path

from neuralslicer.flows.settings import API_START_FAILED, prefect_environment

#: exit status of uvicorn when its port is taken (another process got it first): pick another one
_PORT_TAKEN = 3


def free_port(host: str = "127.0.0.1") -> int:
    """A TCP port on ``host`` that nothing listens on now."""
    with contextlib.closing(socket.socket(socket.AF_INET, socket.SOCK_STREAM)) as sock:
        sock.bind((host, 0))
        return int(sock.getsockname()[1])


#: seconds a local server stays up after its last request, for the next command to use (0: it stops with the
#: command that started it); ``NEURALSLICER_API_IDLE_S`` sets it
IDLE_S = 300.0
#: the record of a server left up for the next command, in PREFECT_HOME
RECORD = "neuralslicer-api.json"


def idle_seconds() -> float:
    """How long a server this command starts stays up after its last request (``NEURALSLICER_API_IDLE_S``)."""
    try:
        return max(0.0, float(os.environ.get("NEURALSLICER_API_IDLE_S", IDLE_S)))
    except ValueError:
        return IDLE_S


class LocalApi:
    """A local Prefect API server: one another command left up (``RECORD``), or a process of its own booting in the
    background from construction on."""

    def __init__(self, idle_s: float | None = None, home: Path | None = None) -> None:
        """Use the server of the record when it answers, else launch one (returns at once). ``home``: the Prefect
        home that keeps the record, when known before Prefect is imported (None: Prefect's settings say)."""
        self.process: subprocess.Popen[bytes] | None = None
        self.port = 0
        self.home = home
        self.idle_s = idle_seconds() if idle_s is None else idle_s
        self.reused = False
        self._served = False
        self._meanwhile: list[Callable[[], object]] = []
        self._log = tempfile.TemporaryFile()   # the server's stderr: a file, so that it can never block on a full pipe
        if not (self.idle_s > 0 and self._reuse()):
            self._launch()
        atexit.register(self._at_exit)

    @property
    def url(self) -> str:
        """The API's base URL."""
        return f"http://127.0.0.1:{self.port}/api"

    def _launch(self) -> None:
        """Start the process of Prefect's server app (the ephemeral server's app and settings, ``flows/api_server``)."""
        self.port = free_port()
        self.reused = False
        # no UI (a public setting); the ephemeral mode is create_app's own argument (flows/api_server.py)
        env = {**os.environ, "PREFECT_SERVER_UI_ENABLED": "false"}
        if "prefect" in sys.modules:  # settings made in this process (else the server reads the same environment)
            from prefect.settings import get_current_settings

            env.update(get_current_settings().to_environment_variables(exclude_unset=True))
        # a session of its own: a SIGTERM or Ctrl-C sent to the command's process group stops the flow, which then
        # reports its end to this server; the server stays for the next command or goes with this one
        self.process = subprocess.Popen(
            [sys.executable, "-m", "neuralslicer.flows.api_server", str(os.getpid()), str(self.idle_s), str(self.port)],
            env=env, stdout=subprocess.DEVNULL, stderr=self._log, start_new_session=True)

    def _record(self) -> Path:
        """Where a server left up for the next command is recorded (in PREFECT_HOME)."""
        if self.home is not None:
            return self.home / RECORD
        from prefect.settings import get_current_settings

        return Path(get_current_settings().home) / RECORD

    def _identity(self) -> dict[str, str]:
        """What a reused server must share with this command: the interpreter and Prefect's version."""
        return {"python": sys.executable, "prefect": prefect_version()}

    def _reuse(self) -> bool:
        """Take the recorded server when it is of this interpreter and Prefect, alive and answering."""
        import json

        try:
            record = json.loads(self._record().read_text())
            if {k: record.get(k) for k in ("python", "prefect")} != self._identity():
                return False
            os.kill(int(record["pid"]), 0)
            self.port = int(record["port"])
        except (OSError, ValueError, KeyError, TypeError):
            return False
        if not self._healthy(timeout_s=2.0):
            return False
        self.reused = self._served = True
        return True

    def _healthy(self, timeout_s: float) -> bool:
        """True when the API answers its health check within ``timeout_s``."""
        import httpx

        try:
            return httpx.get(f"{self.url}/health", timeout=timeout_s).status_code == 200
        except httpx.HTTPError:
            return False

    def _keep(self) -> None:
        """Record this server for the next command (a server that stays up after this one)."""
        from neuralslicer.fileio import write_json_atomic

        assert self.process is not None
        with contextlib.suppress(OSError):
            write_json_atomic(self._record(), {"port": self.port, "pid": self.process.pid, **self._identity()})

    def meanwhile(self, work: Callable[[], object]) -> None:
        """Work for the command to do while it would otherwise wait for a server that is still booting (imports
        its steps will need); done once, at the first wait, and only then: a server that answers at once (one left
        up by an earlier command) is not kept waiting for it. Errors in the work are ignored."""
        self._meanwhile.append(work)

    def _do_meanwhile(self) -> None:
        """The work registered with :meth:`meanwhile`, once, while the server boots."""
        work, self._meanwhile = self._meanwhile, []
        for job in work:
            try:
                job()
            except Exception:  # noqa: BLE001 - only a head start: whatever needs it does it again and says why
                pass

    def wait(self, timeout_s: float) -> None:
        """Block until the API answers its health check; RuntimeError (Prefect's words) after ``timeout_s``."""
        import httpx

        if self.reused:
            if self._healthy(timeout_s=5.0):
                self._meanwhile = []
                return
            self._launch()                # the recorded server went away: boot a fresh one
        if self.process is None:          # stopped after a failed start: boot a fresh one
            self._launch()
        deadline = time.monotonic() + timeout_s
        if self._meanwhile and not self._healthy(timeout_s=1.0):
            self._do_meanwhile()          # the server boots on another core meanwhile
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
                        self._served = True
                        if self.idle_s > 0:
                            self._keep()
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

    def _at_exit(self) -> None:
        """At the command's exit: leave a server that served it up for the next command, else stop it."""
        if not (self.idle_s > 0 and self._served):
            self.stop()

    def stop(self) -> None:
        """Terminate the server process this command started (after a failed start, at exit, or when asked)."""
        process, self.process = self.process, None
        if process is None or process.poll() is not None:
            return
        process.terminate()
        try:
            process.wait(timeout=5)
        except subprocess.TimeoutExpired:
            process.kill()
            process.wait()


def prefect_version() -> str:
    """The installed Prefect's version, without importing Prefect when it is not imported yet."""
    if "prefect" in sys.modules:
        return str(sys.modules["prefect"].__version__)
    from importlib.metadata import version

    return version("prefect")


def prefect_home() -> Path:
    """PREFECT_HOME as the environment gives it, before Prefect is imported (Prefect's default: ~/.prefect)."""
    return Path(os.environ.get("PREFECT_HOME") or Path.home() / ".prefect").expanduser()


def _configured_home() -> tuple[bool, Path]:
    """Whether Prefect's settings name an API (PREFECT_API_URL, in the environment, a profile or this process), and
    its home."""
    from prefect.settings import get_current_settings  # after prefect_environment(): Prefect's logging set-up

    settings = get_current_settings()
    return bool(settings.api.url), Path(settings.home)


def start_local_api() -> LocalApi | None:
    """Start a local API server in the background unless an API is configured (PREFECT_API_URL).

    A command that has not imported Prefect yet takes or launches the server first and imports Prefect (1-2 s)
    while it boots; should Prefect's settings then name an API after all (a profile's PREFECT_API_URL), that
    server is stopped."""
    prefect_environment()
    if os.environ.get("PREFECT_API_URL"):
        return None
    early = "prefect" not in sys.modules
    if not early and _configured_home()[0]:
        return None
    api = LocalApi(home=prefect_home() if early else None)
    if early:
        configured, home = _configured_home()
        if configured:
            api.stop()
            api.idle_s = 0.0
            return None
        api.home = home   # a profile may keep PREFECT_HOME elsewhere: the record goes there
    return api


@contextlib.contextmanager
def api_serving(api: LocalApi | None) -> Iterator[None]:
    """The block runs against ``api`` once it is up, or against the configured API when ``api`` is None."""
    if api is None:
        yield
    else:
        with api.serving():
            yield
