"""The options every slicing subcommand shares, declared once, and the configuration they build."""
from __future__ import annotations

import argparse
import shutil
from collections.abc import Callable
from pathlib import Path
from typing import TYPE_CHECKING, NoReturn

from neuralslicer.errors import InputError
from neuralslicer.frames import UP_AXES
from neuralslicer.neural.config import NETWORK_PRESETS

if TYPE_CHECKING:   # the configuration imports the whole pipeline's settings: only once a command runs
    from neuralslicer.config import SliceConfig

OBJECTIVES = ("sf", "sr", "po", "gc", "ca")


class ArgumentParser(argparse.ArgumentParser):
    """argparse with one-line errors and exit code 2."""

    def error(self, message: str) -> NoReturn:
        """Print `neuralslicer: error: ...` and exit 2."""
        self.exit(2, f"neuralslicer: error: {message} (see '{self.prog} --help')\n")


def parse_objectives(text: str) -> list[str]:
    """`sf,po` -> ['sf', 'po']; `none` -> [] (the height field, planar layers)."""
    if text.strip().lower() in ("none", ""):
        return []
    items = [t.strip().lower() for t in text.split(",") if t.strip()]
    bad = [t for t in items if t not in OBJECTIVES]
    if bad:
        raise InputError("--objectives", f"unknown objective(s) {', '.join(bad)}; use a comma list of "
                         f"{', '.join(OBJECTIVES)} or 'none'")
    return items


def add_slicing_options(p: argparse.ArgumentParser, out_help: str = "output folder") -> None:
    """The options of a slice that `slice` and every study share (the configuration and where it goes)."""
    p.add_argument("--out", required=True, help=out_help)
    p.add_argument("--up", choices=UP_AXES, default=None, help="the model's up axis (default z, or the spec's)")
    p.add_argument("--config", default=None, help="YAML configuration (sections: samples, cage, neural, layers, ...)")
    p.add_argument("--layer-height", type=float, default=None, help="target layer thickness in mm (default 0.8)")
    p.add_argument("--objectives", default=None,
                   help="comma list of sf, sr, po, gc (global head collision), ca (local collision constraint), "
                        "or none (default sf,po,gc,ca[,sr])")
    p.add_argument("--method", choices=("neural", "s3", "s3_oneshot"), default=None,
                   help="the field: the Neural Slicer (neural, default), the S3-Slicer baseline (s3: its iterative "
                        "deformation, docs/baselines.md) or its one-shot variant (s3_oneshot)")
    p.add_argument("--max-steps", type=int, default=None, help="optimisation step budget")
    p.add_argument("--network", choices=tuple(NETWORK_PRESETS), default=None, help="network size preset")
    p.add_argument("--device", choices=("auto", "cpu", "cuda"), default=None, help="torch device (default auto)")
    p.add_argument("--seed", type=int, default=None, help="random seed of the optimisation")
    p.add_argument("--store", default=None, help="artifact store (zarr path or fsspec URL; default OUT/store.zarr)")
    p.add_argument("--machine", default=None, help="machine profile: a shipped name (`neuralslicer machines` lists them; default table_bc_linuxcnc) or a YAML")
    p.add_argument("--robot", action="store_true",
                   help="also write robot_waypoints.csv/.json and compas_slicer's printpoints.json")
    p.add_argument("--collision-refinements", type=int, default=None,
                   help="refine the print head term around the collisions of the print and re-optimise from that "
                        "field, at most this many times (default 3)")
    p.add_argument("--collision-retries", type=int, default=None,
                   help="then re-optimise with smoother fields while the nozzle collides (default 2)")
    p.add_argument("--collision-fallback", choices=("blend", "none"), default=None,
                   help="still colliding: blend the field toward planar layers until collision-free (default blend) "
                        "or keep the colliding program")
    p.add_argument("--keep-attempts", action="store_true",
                   help="keep every print of the collision resolution whole in the store (by default the prints "
                        "not kept drop their toolpaths and motion arrays once a later one replaces them)")
    p.add_argument("--verify", action="store_true",
                   help="anisotropic FEA of the printed part beside planar layers with zig-zag and with stress-following "
                        "infill (spec needs fea)")
    p.add_argument("--infill", choices=("auto", "zigzag", "contour", "stress", "none"), default=None,
                   help="infill inside the shells (default auto: stress-following with a load case and sr, else zigzag)")
    p.add_argument("--sr-rounds", type=int, default=None,
                   help="with sr: re-run the FEA with the material of the print, re-sample T and tau_max and "
                        "re-optimise from the current field, until this many rounds (default 1, the paper)")


# option -> its key in the configuration
CONFIG_KEYS = {
    "method": ("method",),
    "layer_height": ("layers", "layer_height"),
    "max_steps": ("neural", "optim", "max_steps"),
    "network": ("neural", "network"),
    "device": ("neural", "device"),
    "seed": ("neural", "optim", "seed"),
    "collision_refinements": ("collision_refinements",),
    "collision_retries": ("collision_retries",),
    "collision_fallback": ("collision_fallback",),
    "infill": ("toolpath", "infill"),
    "sr_rounds": ("sr_rounds",),
    "machine": ("machine",),
    "cage_elements": ("cage", "n_elements"),
}


def _set_key(data: dict, keys: tuple[str, ...], value: object) -> None:
    """``data[k0][k1]... = value``, making the sections that are missing (a section that is not a mapping is left
    for the validation to name)."""
    node = data
    for k in keys[:-1]:
        if node.get(k) is None:
            node[k] = {}
        if not isinstance(node[k], dict):
            return
        node = node[k]
    node[keys[-1]] = value


def build_config(options: argparse.Namespace) -> SliceConfig:
    """SliceConfig from --config, overridden by the explicit command-line options, validated."""
    from neuralslicer.config import SliceConfig

    # the options go into the file's mapping before it is validated: what neither sets comes from the defaults and
    # the machine profile's nozzle (a --machine with a smaller nozzle brings its layer thickness and line width)
    data = SliceConfig.read_yaml(options.config) if options.config else {}
    sets = [(keys, getattr(options, name, None)) for name, keys in CONFIG_KEYS.items()]
    if options.objectives is not None:
        sets.append((("objectives",), parse_objectives(options.objectives)))
    sets += [((flag,), True) for flag in ("verify", "robot", "keep_attempts") if getattr(options, flag, False)]
    init = getattr(options, "init", None)
    if init is not None:
        sets.append((("neural", "init", "kind"), init if init in ("height", "heat") else "user"))
    for keys, value in sets:
        if value is not None:
            _set_key(data, keys, value)
    try:
        return SliceConfig.checked(data, "options")
    except InputError as exc:  # name the option that set the key, else the key in the --config file
        key = exc.where.removeprefix("options: ")
        named = [name for name, keys in CONFIG_KEYS.items() if ".".join(keys) == key and getattr(options, name, None) is not None]
        where = f"--{named[0].replace('_', '-')}" if named else f"{options.config or 'configuration'}: {key}"
        raise InputError(where, exc.message) from None


def cli_names():  # noqa: ANN201 - neuralslicer.run.preflight.Names, imported when a command runs (not for --help)
    """How the preflight's messages name the settings on the command line: by their flags."""
    from neuralslicer.run.preflight import Names

    return Names(out="--out", store="--store", units="--units", layer_height="--layer-height", machine="--machine",
                 force="--force", config="--config")


def run_in_out_dir(out_dir: Path, job: Callable[[], int]) -> int:
    """Run a job that writes into out_dir; on bad input remove out_dir again if this run created it."""
    existed = out_dir.exists()
    try:
        return job()
    except InputError:
        if not existed:
            shutil.rmtree(out_dir, ignore_errors=True)
        raise
