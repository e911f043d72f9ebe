"""Cache keys: digests of a step's name, version and parameters, with inputs by their digest."""
from __future__ import annotations

import dataclasses
from typing import Any

from pydantic import BaseModel

from neuralslicer.fileio import json_sha256, to_json
from neuralslicer.storage.store import ArtifactRef


def canonical(value: Any) -> Any:
    """A JSON-able canonical form: artifacts by digest, pydantic models by their fields, other dataclasses as the
    list of their fields' values (as the tuple they stand for)."""
    if isinstance(value, ArtifactRef):
        return {"artifact": value.digest}
    if isinstance(value, BaseModel):
        return canonical(value.model_dump(mode="json"))
    if dataclasses.is_dataclass(value) and not isinstance(value, type):
        return [canonical(getattr(value, f.name)) for f in dataclasses.fields(value)]
    if isinstance(value, dict):
        return {str(k): canonical(v) for k, v in value.items()}
    if isinstance(value, (list, tuple)):
        return [canonical(v) for v in value]
    return to_json(value)


def digest(*parts: Any, length: int = 20) -> str:
    """Hex digest of canonical JSON of the parts."""
    return json_sha256(canonical(list(parts)))[:length]
