"""Prefect settings of a run: quiet local defaults and task results (cache records) beside the store."""
from __future__ import annotations

import os
from pathlib import Path
from typing import Any


def prefect_environment() -> None:
    """Quiet, local Prefect defaults unless the user configured Prefect (PREFECT_API_URL / PREFECT_HOME)."""
    os.environ.setdefault("PREFECT_SERVER_ANALYTICS_ENABLED", "false")
    os.environ.setdefault("DO_NOT_TRACK", "1")
    os.environ.setdefault("PREFECT_LOGGING_LEVEL", "WARNING")
    os.environ.setdefault("PREFECT_SERVER_LOGGING_LEVEL", "WARNING")
    os.environ.setdefault("PREFECT_RESULTS_PERSIST_BY_DEFAULT", "true")


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
