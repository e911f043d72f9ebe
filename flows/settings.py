"""Prefect settings of a run: quiet local defaults and task results (cache records) beside the store."""
from __future__ import annotations

import logging
import os
import re
from pathlib import Path
from collections.abc import Callable
from typing import Any, TypeVar

from neuralslicer.errors import NeuralSlicerError

T = TypeVar("T")


def prefect_environment() -> None:
    """Quiet, local Prefect defaults unless the user configured Prefect (PREFECT_API_URL / PREFECT_HOME)."""
    os.environ.setdefault("PREFECT_SERVER_ANALYTICS_ENABLED", "false")
    os.environ.setdefault("DO_NOT_TRACK", "1")
    os.environ.setdefault("PREFECT_LOGGING_LEVEL", "WARNING")
    os.environ.setdefault("PREFECT_SERVER_LOGGING_LEVEL", "WARNING")
    os.environ.setdefault("PREFECT_RESULTS_PERSIST_BY_DEFAULT", "true")
    # the local API server needs ~6 s on a quiet machine and far longer on a loaded one (20 s by default)
    os.environ.setdefault("PREFECT_SERVER_EPHEMERAL_STARTUP_TIMEOUT_SECONDS", str(API_STARTUP_TIMEOUT_S))
    quiet_interrupts()


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


def result_storage_dir(store: str) -> Path:
    """Where Prefect persists task results (cache records) for a store: beside it on local disk."""
    if "://" in store and not store.startswith("file://"):
        return Path.home() / ".cache" / "neuralslicer" / "prefect-results"
    store_path = Path(store.removeprefix("file://")).resolve()
    return store_path.parent / f".{store_path.name}.prefect-results"


def cache_settings(store: str) -> Any:
    """Prefect settings for a run on this store: task results (the cache records) persisted beside the store."""
    # imported here: prefect_environment() must run before Prefect is first imported (logging set-up)
    from prefect.settings import PREFECT_LOCAL_STORAGE_PATH, PREFECT_RESULTS_PERSIST_BY_DEFAULT, temporary_settings

    results = result_storage_dir(store)
    results.mkdir(parents=True, exist_ok=True)
    return temporary_settings(updates={PREFECT_LOCAL_STORAGE_PATH: results, PREFECT_RESULTS_PERSIST_BY_DEFAULT: True})


def artifact_key(text: str) -> str:
    """A Prefect artifact key or run name (lowercase letters, digits, dashes)."""
    return re.sub(r"[^a-z0-9-]+", "-", text.lower()).strip("-")[:100] or "run"
