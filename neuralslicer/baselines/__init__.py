"""Baselines the Neural Slicer is compared with: S3-Slicer (Zhang et al. 2022)."""
from __future__ import annotations

from neuralslicer.baselines.s3 import S3Config, S3Result, optimise_s3

__all__ = ["S3Config", "S3Result", "optimise_s3"]
