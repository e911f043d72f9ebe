"""Sample models shipped with the package (licences beside them): the S3-Slicer dataset's ring.tet and
topopt_new4.tet (BSD-3-Clause, LICENSE-S3_DeformFDM.txt), y-up, in mm, and the compas_slicer test meshes
(MIT, LICENSE-compas_slicer.txt), z-up."""
from __future__ import annotations

from pathlib import Path

#: the folder of the sample models, inside the installed package
DATA_DIR = Path(__file__).resolve().parent


def sample(name: str) -> Path:
    """The path of a shipped sample model by file name (``ring.tet``); a clear error for an unknown one."""
    path = DATA_DIR / name
    if not path.is_file() or path.suffix == ".py":
        known = ", ".join(sorted(p.name for p in DATA_DIR.iterdir() if p.suffix in (".tet", ".stl")))
        raise FileNotFoundError(f"{name}: not a shipped sample model (these are: {known})")
    return path
