"""Checks of everything a user can get wrong, run before any work starts: one InputError each."""
from __future__ import annotations

import math
import os
import tempfile
from dataclasses import dataclass
from pathlib import Path
from typing import TYPE_CHECKING

from neuralslicer.config import SliceConfig
from neuralslicer.errors import InputError
from neuralslicer.fea.spec import FEASpec
from neuralslicer.model.solid import Solid
from neuralslicer.model.spec import ModelSpec, load_model
from neuralslicer.motion.profile import MachineProfile, load_profile, profile_names

if TYPE_CHECKING:
    from neuralslicer.fea.grid import SolidLike


@dataclass(frozen=True)
class Names:
    """How the checks' messages name what the user set: the pipeline's parameters by default (a deployed flow's);
    the command line passes its flags (``neuralslicer.cli.options.cli_names``)."""

    out: str = "out_dir"
    store: str = "store"
    units: str = "units"
    layer_height: str = "layers.layer_height"
    machine: str = "machine"
    force: str = "force"
    config: str = "the configuration"


#: a model whose bounding-box diagonal is outside this range (mm) was most likely read in the wrong unit
PLAUSIBLE_SIZE_MM = (1.0, 5000.0)
#: more layers than this are refused unless forced (a wrong unit or layer height, not a real print)
MAX_LAYERS = 5000


def check_output_dir(out_dir: Path, inputs: list[Path], option: str = Names.out) -> None:
    """The output folder can be created and written, is not a file, and holds none of the inputs."""
    out_dir = Path(out_dir).resolve()
    if out_dir.exists() and not out_dir.is_dir():
        raise InputError(option, f"{out_dir} is a file, not a folder")
    for f in inputs:
        f = Path(f).resolve()
        if f == out_dir or out_dir in f.parents:
            raise InputError(option, f"{out_dir} holds the input {f}; the outputs would overwrite or remove it: "
                             "choose another folder")
    _check_writable(out_dir, option)


def check_store_location(store: str, option: str = Names.store) -> None:
    """A local store is a folder (or does not exist yet) in a writable place; remote URLs are not checked."""
    if "://" in store and not store.startswith("file://"):
        return
    path = Path(store.removeprefix("file://")).resolve()
    if path.exists() and not path.is_dir():
        raise InputError(option, f"{path} is a file, not a store folder")
    _check_writable(path, option)


def _check_writable(path: Path, option: str) -> None:
    """The folder or its nearest existing ancestor accepts new files."""
    probe = path
    while not probe.exists():
        probe = probe.parent
    if not probe.is_dir():
        raise InputError(option, f"{probe} is a file, so {path} cannot be created")
    if not os.access(probe, os.W_OK | os.X_OK):
        raise InputError(option, f"{probe} is not writable")
    try:  # permissions say yes to root everywhere; a read-only file system (or /proc) says no only when tried
        os.rmdir(tempfile.mkdtemp(prefix=".neuralslicer-probe-", dir=probe))
    except OSError as exc:
        raise InputError(option, f"{probe} is not writable ({exc.strerror.lower() if exc.strerror else exc})") from None


def check_scale(solid: Solid, spec: ModelSpec, names: Names = Names()) -> float:
    """The model's bounding-box diagonal in mm; an implausible size suggests the unit to use."""
    lo, hi = solid.bounds
    diag = float(math.dist(lo, hi))
    small, large = PLAUSIBLE_SIZE_MM
    if diag < small or diag > large:
        factors = {"m": 1000.0, "cm": 10.0, "in": 25.4, "mm": 1.0}
        raw = diag / factors[spec.units]
        hint = [u for u, f in factors.items() if small <= raw * f <= large and u != spec.units]
        files = spec.files()
        where = spec.source or (files[0] if files else "model")
        raise InputError(where, f"the model is {diag:.4g} mm across (bounding-box diagonal), implausible for a "
                         f"print in {spec.units}: its coordinates are probably in another unit; give "
                         + (" or ".join(f"{names.units} {u}" for u in hint) if hint else f"the right {names.units}")
                         + " (or 'units:' in a spec)")
    return diag


def check_layer_count(solid: Solid, config: SliceConfig, limit: int = MAX_LAYERS, names: Names = Names()) -> int:
    """Estimated layer count (model height / layer height); refused above ``limit`` or below 2."""
    height = float(solid.bounds[1][2] - solid.platform_z)
    h = config.layers.layer_height
    n = math.ceil(height / h)
    if n > limit:
        raise InputError(names.layer_height, f"{h:g} mm on a model {height:.4g} mm tall makes about {n:,} layers "
                         f"(limit {limit:,}); check the units or the layer height, or pass {names.force}")
    if n < 2:
        raise InputError(names.layer_height, f"{h:g} mm is at least the model's height ({height:.4g} mm): "
                         "no curved layers to print; use a smaller layer height")
    if not config.layers.t_min <= h <= config.layers.t_max:
        raise InputError(names.layer_height, f"{h:g} mm is outside the layers' thickness range "
                         f"[{config.layers.t_min:g}, {config.layers.t_max:g}] mm (layers.t_min/t_max: {_nozzle_of(config)}"
                         f"); use a machine profile with a nozzle that prints it ({names.machine}: "
                         f"{_nozzles_for(h)}), or set layers.t_min/t_max and toolpath.line_width together in "
                         f"{names.config}")
    return n


def _nozzle_of(config: SliceConfig) -> str:
    """Where the configuration's thickness range comes from, in words: the machine's nozzle (or the profile's name)."""
    try:
        nozzle = load_profile(config.machine).nozzle
    except InputError:
        return f"machine {config.machine}"
    return f"{config.machine}'s {nozzle.diameter_mm:g} mm nozzle, nozzle.layer_thickness_mm, unless set"


def _nozzles_for(height: float) -> str:
    """The shipped profiles whose nozzle's thickness range holds a layer height, or what to change."""
    fit = [n for n in profile_names() if (r := load_profile(n).nozzle.layer_thickness_mm)[0] <= height <= r[1]]
    return ", ".join(fit) if fit else "none shipped; set nozzle.diameter_mm in your profile"


def check_machine(name: str, option: str = Names.machine) -> MachineProfile:
    """The machine profile, loaded (an error names the option)."""
    try:
        return load_profile(name)
    except InputError as exc:
        raise InputError(f"{option} {exc.where}", exc.message) from None


def check_fea_regions(solid: SolidLike, spec: FEASpec) -> None:
    """Supports and loads select something of the voxel model the FEA will build."""
    from neuralslicer.fea.grid import voxelize   # the FEA's scipy.sparse: only for a model with a load case
    from neuralslicer.fea.solver import check_spec, fixed_dofs, load_vector

    check_spec(spec)
    grid = voxelize(solid, spec.voxels)
    fixed_dofs(grid, spec.supports, float(solid.platform_z))
    load_vector(grid, spec.loads, float(solid.platform_z))


def preflight(spec: ModelSpec, solid: Solid, config: SliceConfig, out_dir: Path, store: str, force: bool = False,
              needs_fea: bool = False, names: Names = Names()) -> None:
    """Every check of a slice before any work starts (outputs, store, scale, layers, machine and its nozzle, FEA);
    ``names``: how the messages name the settings (the command line's flags, or the flow's parameters)."""
    check_output_dir(out_dir, spec.files() + ([spec.source] if spec.source is not None else []), names.out)
    check_store_location(store, names.store)
    check_scale(solid, spec, names)
    check_layer_count(solid, config, limit=10**9 if force else MAX_LAYERS, names=names)
    machine = check_machine(config.machine, names.machine)
    lo, hi = machine.nozzle.bead_width_mm
    if not lo <= config.toolpath.line_width <= hi:
        raise InputError("toolpath.line_width", f"{config.toolpath.line_width:g} mm is outside the bead widths the "
                         f"{machine.nozzle.diameter_mm:g} mm nozzle of {machine.name} lays ({lo:g}..{hi:g} mm, "
                         "nozzle.bead_width_mm in the profile)")
    thickest = machine.nozzle.bead_thickness_mm[1]
    if config.layers.t_max > thickest:
        raise InputError("layers.t_max", f"{config.layers.t_max:g} mm is more than the thickest bead the "
                         f"{machine.nozzle.diameter_mm:g} mm nozzle of {machine.name} lays ({thickest:g} mm, "
                         "nozzle.bead_thickness_mm in the profile)")
    if needs_fea:
        if spec.fea is None:
            raise InputError(spec.source or "model", "strength (sr), the verification and toolpath.infill: stress need the "
                             "spec's 'fea' block (supports and loads)")
        check_fea_regions(solid, spec.fea)


def check_slice(model: str | Path, out_dir: Path, store: str, config: SliceConfig, up: str | None = None,
                units: str | None = None, force: bool = False, names: Names = Names()) -> ModelSpec:
    """The spec of a model file or spec YAML (its own ``up`` and ``units`` unless given) after every check of
    :func:`preflight`: what the command line and a deployed flow run before any work."""
    from neuralslicer.model.solid import implicit_solid

    path = Path(model)
    if not path.exists():
        raise InputError(model, "no such file")
    spec = load_model(path, up, units)
    solid = implicit_solid(spec)  # reads every file of the spec: bad input fails here with one line
    preflight(spec, solid, config, Path(out_dir), store, force=force, needs_fea=config.needs_fea(spec), names=names)
    return spec
