"""The run's reproducibility record, written beside the outputs and into the store."""
from __future__ import annotations

from pathlib import Path
from typing import Any

from neuralslicer.fileio import write_json_atomic
from neuralslicer.run.provenance import record_digest
from neuralslicer.storage import ArtifactStore


def record_provenance(out_dir: str | Path, store: str, model: str, record: dict[str, Any]) -> str:
    """Write `out_dir/provenance.json` and the record in the store as `<model>/provenance/<digest>`; return the digest."""
    key = record_digest(record)
    write_json_atomic(Path(out_dir) / "provenance.json", {**record, "digest": key})
    ArtifactStore(store).write_once(f"{model}/provenance/{key}", lambda: ({}, {"provenance": record}))
    return key
