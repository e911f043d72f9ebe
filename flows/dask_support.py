"""Dask support: a DaskTaskRunner whose workers import this project's top-level `storage` package.

A Dask worker puts its local directory on `sys.path`, and that directory holds a `storage/` folder
(the worker's spill space). Python then imports it as an empty namespace package `storage`, ahead of
this project's editable-installed `storage` package. The plugin below puts the source tree first on
each worker's path and drops the wrong module.
"""
from __future__ import annotations

import importlib
import sys
from pathlib import Path
from typing import Any

from distributed.diagnostics.plugin import WorkerPlugin
from prefect_dask import DaskTaskRunner


def source_root() -> Path:
    """The source tree that holds the `neuralslicer`, `storage`, `tasks` and `flows` packages."""
    import neuralslicer

    return Path(neuralslicer.__file__).resolve().parents[1]


def fix_import_path() -> str:
    """Put the source tree first on sys.path and forget a namespace-package `storage`; return the root."""
    root = source_root()
    if (root / "storage" / "__init__.py").is_file() and str(root) not in sys.path[:1]:
        sys.path.insert(0, str(root))
    module = sys.modules.get("storage")
    if module is not None and getattr(module, "__file__", None) is None:
        del sys.modules["storage"]
    importlib.invalidate_caches()
    return str(root)


class SourcePathPlugin(WorkerPlugin):
    """Worker plugin: run fix_import_path on every worker (present and future)."""

    name = "neuralslicer-source-path"

    def setup(self, worker: Any) -> None:
        """Fix the worker's import path."""
        fix_import_path()


class StudyDaskTaskRunner(DaskTaskRunner):
    """prefect-dask's DaskTaskRunner that registers SourcePathPlugin on its cluster's workers."""

    def __enter__(self) -> StudyDaskTaskRunner:
        """Start (or connect to) the cluster and prepare its workers."""
        super().__enter__()
        self.client.register_plugin(SourcePathPlugin(), name=SourcePathPlugin.name)
        return self
