"""Neural Slicer: curved layers for multi-axis 3D printing.

The core library is this package's own folder. The pipeline's outer layers live beside it in the repository
(``cli/``, ``flows/``, ``tasks/``, ``storage/``, ``deployments/``) and are installed as its subpackages
(``neuralslicer.cli``, ``.flows``, ``.tasks``, ``.storage``, ``.deployments``): pyproject.toml's package-dir maps them,
for ``pip install .`` and for the editable install ``make install`` makes. Another checkout runs with this interpreter
through ``benchmarks/checkout_env.py`` (what the benchmarks' ``--against`` use).
"""
