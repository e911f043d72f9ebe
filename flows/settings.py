"""Prefect settings of a run: quiet local defaults (the store is the steps' cache: Prefect persists no results)."""
from __future__ import annotations

import logging
import os
import re
from collections.abc import Callable
from typing import TypeVar

from neuralslicer.errors import InputError, NeuralSlicerError

T = TypeVar("T")


def prefect_environment() -> None:
    """Quiet, local Prefect defaults unless the user configured Prefect (PREFECT_API_URL / PREFECT_HOME): the run's
    log in the Prefect UI at INFO (every step's started/done line and the progress lines), the terminal at WARNING
    (the command prints its own lines)."""
    os.environ.setdefault("PREFECT_SERVER_ANALYTICS_ENABLED", "false")
    os.environ.setdefault("DO_NOT_TRACK", "1")
    # Prefect's logging.yml, key by key: its console handler shows warnings only; the loggers stay at
    # PREFECT_LOGGING_LEVEL (INFO unless set), so the API handler sends the run's INFO lines to the server
    os.environ.setdefault(CONSOLE_LEVEL, "WARNING")
    os.environ.setdefault("PREFECT_SERVER_LOGGING_LEVEL", "WARNING")
    # the local API server needs ~6 s on a quiet machine and far longer on a loaded one (20 s by default)
    os.environ.setdefault("PREFECT_SERVER_EPHEMERAL_STARTUP_TIMEOUT_SECONDS", str(API_STARTUP_TIMEOUT_S))
    quiet_interrupts()


#: the level of the console handler of Prefect's logging.yml (``PREFECT_LOGGING_[PATH]_[TO]_[KEY]``)
CONSOLE_LEVEL = "PREFECT_LOGGING_HANDLERS_CONSOLE_LEVEL"


class _QuietInterrupts(logging.Filter):
    """Drops Prefect's log records of a run stopped by Ctrl-C or SIGTERM: the command says so in one line, and the
    run's state (Crashed, with the same words) still reaches the API."""

    WORDS = ("aborted by an interrupt signal", "aborted by a termination signal")

    def filter(self, record: logging.LogRecord) -> bool:
        """False for the records of an interrupted run."""
        message = record.getMessage()
        return not any(w in message for w in self.WORDS)


def quiet_interrupts() -> None:
    """Install ``_QuietInterrupts`` on Prefect's flow and task run loggers (once)."""
    for name in ("prefect.flow_runs", "prefect.task_runs"):
        logger = logging.getLogger(name)
        if not any(isinstance(f, _QuietInterrupts) for f in logger.filters):
            logger.addFilter(_QuietInterrupts())


class _OneLineInputErrors(logging.Filter):
    """Drops Prefect's records that carry the traceback of the user's bad input (an ``InputError``, a parameter that
    fails validation): the run's state says what is wrong in one line, and the run log has that line."""

    def filter(self, record: logging.LogRecord) -> bool:
        """False for a record whose exception is bad input."""
        from prefect.exceptions import ParameterTypeError

        exc = record.exc_info[1] if record.exc_info else None
        return not isinstance(exc, (InputError, ParameterTypeError))


def quiet_input_errors() -> None:
    """Install ``_OneLineInputErrors`` on the loggers of Prefect's flow engine (a flow run's and the engine's, once)."""
    for name in ("prefect.flow_runs", "prefect.engine"):
        logger = logging.getLogger(name)
        if not any(isinstance(f, _OneLineInputErrors) for f in logger.filters):
            logger.addFilter(_OneLineInputErrors())


API_STARTUP_TIMEOUT_S = 180
API_START_FAILED = "Timed out while attempting to connect to ephemeral Prefect API server"


def with_api_retry(job: Callable[[], T], attempts: int = 2) -> T:
    """Run a flow; when Prefect's local API server did not start in time (a loaded node), try again,
    then fail with one line that says what to do."""
    for attempt in range(attempts):
        try:
            return job()
        except RuntimeError as exc:
            if API_START_FAILED not in str(exc):
                raise
            failure = exc
    timeout = os.environ.get("PREFECT_SERVER_EPHEMERAL_STARTUP_TIMEOUT_SECONDS", API_STARTUP_TIMEOUT_S)
    raise NeuralSlicerError(
        f"Prefect's local API server did not start within {timeout} s, {attempts} times (a loaded machine?): "
        "raise PREFECT_SERVER_EPHEMERAL_STARTUP_TIMEOUT_SECONDS or point PREFECT_API_URL at a running server "
        "(prefect server start), then run the same command again") from failure


def artifact_key(text: str) -> str:
    """A Prefect artifact key or run name (lowercase letters, digits, dashes)."""
    return re.sub(r"[^a-z0-9-]+", "-", text.lower()).strip("-")[:100] or "run"
