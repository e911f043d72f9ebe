"""Artifact store: zarr groups written atomically, mesh files, checkpoints and cache keys."""
from storage.files import atomic_path, write_text_atomic
from storage.keys import canonical, digest
from storage.store import ArtifactRef, ArtifactStore, write_json_atomic

__all__ = [
    "ArtifactRef",
    "ArtifactStore",
    "atomic_path",
    "canonical",
    "digest",
    "write_json_atomic",
    "write_text_atomic",
]
