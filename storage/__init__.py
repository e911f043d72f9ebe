"""Artifact store: zarr groups written atomically, mesh files, checkpoints and cache keys."""
from neuralslicer.fileio import atomic_path, write_json_atomic, write_text_atomic
from neuralslicer.storage.keys import canonical, digest
from neuralslicer.storage.store import ArrayStream, ArtifactRef, ArtifactStore, default_store, groups_used

__all__ = [
    "ArrayStream",
    "ArtifactRef",
    "ArtifactStore",
    "atomic_path",
    "canonical",
    "default_store",
    "digest",
    "groups_used",
    "write_json_atomic",
    "write_text_atomic",
]
