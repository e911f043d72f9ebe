"""A finished slice's ``run.json`` and the store it names: what ``neuralslicer preview`` and ``explain`` read."""
from __future__ import annotations

import json
from pathlib import Path
from typing import Any

from neuralslicer.errors import InputError
from neuralslicer.storage import ArtifactStore


def read_run_record(run_dir: Path) -> tuple[dict[str, Any], Path]:
    """The run.json of a slice's output folder and its path, or an InputError naming the folder or the file."""
    if not run_dir.is_dir():
        raise InputError(run_dir, "no such folder (give the output folder of `neuralslicer slice`)")
    record = run_dir / "run.json"
    try:
        run = json.loads(record.read_text())
    except FileNotFoundError:
        raise InputError(record, "no such file: not the output folder of a finished `neuralslicer slice`") from None
    except (OSError, json.JSONDecodeError) as exc:
        raise InputError(record, f"cannot read: {exc}") from None
    if not isinstance(run, dict):
        raise InputError(record, "not a JSON object")
    return run, record


def open_run_store(run: dict[str, Any], record: Path) -> ArtifactStore:
    """The artifact store a run.json names, or an InputError naming it."""
    if not run.get("store"):
        raise InputError(record, "names no store (written by an older neuralslicer: slice again)")
    try:
        return ArtifactStore(run["store"], create=False)
    except FileNotFoundError:
        raise InputError(run["store"], f"no artifact store there (the store {record} names)") from None
    except (OSError, ValueError) as exc:
        raise InputError(run["store"], f"cannot open the store {record} names: {exc}") from None
