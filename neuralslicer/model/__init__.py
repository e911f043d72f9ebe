"""Model input: readers, the model spec, implicit components and the implicit solid H."""
from __future__ import annotations

from neuralslicer.model.io import read_segments, read_surface, read_tet, read_volume
from neuralslicer.model.solid import Solid, implicit_solid
from neuralslicer.model.spec import ModelSpec, load_spec, spec_digest, spec_for_file

__all__ = [
    "ModelSpec", "Solid", "implicit_solid", "load_spec", "read_segments", "read_surface",
    "read_tet", "read_volume", "spec_digest", "spec_for_file",
]
