"""Device selection for the neural optimisation."""
from __future__ import annotations

import torch


def resolve_device(device: str = "auto") -> torch.device:
    """'auto' -> CUDA when available, else CPU; any other string is passed to torch.device."""
    if device == "auto":
        return torch.device("cuda" if torch.cuda.is_available() else "cpu")
    return torch.device(device)


def resolve_dtype(name: str) -> torch.dtype:
    """'float32' | 'float64' -> torch dtype."""
    return {"float32": torch.float32, "float64": torch.float64}[name]
