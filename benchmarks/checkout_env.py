"""Run another checkout of the project (the code before a change) with this interpreter, in a subprocess.

The outer layers are subpackages of ``neuralslicer`` only once installed (pyproject.toml's package-dir), and the
editable install of this checkout would answer for them. ``checkout_environ(checkout)`` gives a subprocess a
``sitecustomize`` that drops the editable install's finders and maps ``neuralslicer.<layer>`` to the other checkout's
folders as its own pyproject.toml says, with the checkout first on ``PYTHONPATH``: that process and every process it
starts (a large print's steps, the cage's fTetWild, the API server) import the other checkout alone.

    env = checkout_environ(Path("../before"))
    subprocess.run([sys.executable, "-m", "neuralslicer.cli", "slice", ...], env=env, cwd="../before")

or from a shell: ``eval "$(python benchmarks/checkout_env.py ../before)"`` exports the same ``PYTHONPATH``.
"""
from __future__ import annotations

import argparse
import os
import shlex
import tempfile
import tomllib
from pathlib import Path

SITECUSTOMIZE = '''"""Written by benchmarks/checkout_env.py: import the checkout at {root!r}, not the installed
project."""
import importlib.util
import os
import sys

_ROOT = {root!r}
_LAYERS = {layers!r}    # neuralslicer.<layer> -> the checkout's folder, from its pyproject.toml
sys.meta_path[:] = [f for f in sys.meta_path if not getattr(f, "__module__", "").startswith("__editable__")]
sys.path_hooks[:] = [h for h in sys.path_hooks if not getattr(h, "__module__", "").startswith("__editable__")]
sys.path_importer_cache.clear()


class _CheckoutLayers:
    """Finds ``neuralslicer.<layer>`` in the checkout's folder of that layer."""

    @classmethod
    def find_spec(cls, name, path=None, target=None):
        folder = _LAYERS.get(name)
        if folder is None or not os.path.isfile(os.path.join(folder, "__init__.py")):
            return None
        return importlib.util.spec_from_file_location(name, os.path.join(folder, "__init__.py"),
                                                      submodule_search_locations=[folder])


sys.meta_path.append(_CheckoutLayers)
'''


def outer_layers(checkout: Path) -> dict[str, str]:
    """``neuralslicer.<layer>`` -> its folder in the checkout, from the checkout's pyproject.toml package-dir."""
    project = tomllib.loads((checkout / "pyproject.toml").read_text())
    dirs = project.get("tool", {}).get("setuptools", {}).get("package-dir", {})
    return {name: str((checkout / folder).resolve()) for name, folder in dirs.items()
            if name.startswith("neuralslicer.")}


def checkout_environ(checkout: Path, env: dict[str, str] | None = None) -> dict[str, str]:
    """``env`` (default: this process's) for a subprocess that imports ``checkout``'s code alone."""
    checkout = checkout.resolve()
    if not (checkout / "neuralslicer" / "__init__.py").is_file():
        raise SystemExit(f"{checkout}: not a checkout of the project (no neuralslicer/__init__.py)")
    boot = Path(tempfile.mkdtemp(prefix="neuralslicer-checkout-"))
    (boot / "sitecustomize.py").write_text(SITECUSTOMIZE.format(root=str(checkout), layers=outer_layers(checkout)))
    base = dict(os.environ if env is None else env)
    return {**base, "PYTHONPATH": os.pathsep.join([str(boot), str(checkout)])}


def main() -> None:
    """Print the ``export PYTHONPATH=...`` that runs a checkout with this interpreter."""
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("checkout", type=Path)
    env = checkout_environ(parser.parse_args().checkout)
    print(f"export PYTHONPATH={shlex.quote(env['PYTHONPATH'])}")


if __name__ == "__main__":
    main()
