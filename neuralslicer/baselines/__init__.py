"""Baselines the Neural Slicer is compared with: S3-Slicer (Zhang et al. 2022), in `neuralslicer.baselines.s3`
(its settings in `neuralslicer.baselines.s3_config`, which needs no torch)."""
