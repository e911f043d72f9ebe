"""Neural field optimisation: SIREN q/s fields, differentiable ARAP cage deformation, losses.

`NeuralConfig` and the presets need no torch; `optimise_field` and `FieldResult` import it on first use, so that
reading a configuration (the command line does before anything runs) stays light.
"""
from __future__ import annotations

from typing import Any

from neuralslicer.neural.config import NETWORK_PRESETS, NeuralConfig

__all__ = ["NETWORK_PRESETS", "NeuralConfig", "FieldResult", "optimise_field"]


def __getattr__(name: str) -> Any:
    """The optimiser's names, imported (with torch) on first use."""
    if name in ("FieldResult", "optimise_field"):
        from neuralslicer.neural import optimise

        return getattr(optimise, name)
    raise AttributeError(f"module 'neuralslicer.neural' has no attribute {name!r}")
