"""Neural Slicer: curved layers for multi-axis 3D printing.

Installed, the pipeline's outer layers are subpackages of this one (``neuralslicer.cli``, ``.flows``, ``.tasks``,
``.storage``, ``.deployments``; pyproject.toml maps the repository's top-level folders there). In a source checkout
run without installing it (``PYTHONPATH=.``, a git worktree), those folders sit beside this package: its path then
takes in the checkout, so the same names reach the checkout's own code.
"""
from pathlib import Path as _Path

_checkout = _Path(__file__).resolve().parent.parent
if (_checkout / "pyproject.toml").is_file() and (_checkout / "flows" / "slice.py").is_file() \
        and str(_checkout) not in __path__:
    __path__.append(str(_checkout))
del _Path, _checkout
