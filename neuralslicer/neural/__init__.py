"""Neural field optimisation: SIREN q/s fields, differentiable ARAP cage deformation, losses."""
from __future__ import annotations

from neuralslicer.neural.config import NETWORK_PRESETS, NeuralConfig
from neuralslicer.neural.optimise import FieldResult, optimise_field

__all__ = ["NETWORK_PRESETS", "NeuralConfig", "FieldResult", "optimise_field"]
