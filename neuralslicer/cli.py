"""The command line: `neuralslicer slice | fea | study | compare`."""
from __future__ import annotations

import argparse
import os
import shutil
import sys
from collections.abc import Callable, Sequence
from pathlib import Path
from typing import Any, NoReturn

from neuralslicer.cli_studies import add_compare_parser, add_study_parser
from neuralslicer.errors import InputError, NeuralSlicerError
from neuralslicer.frames import UP_AXES


class ArgumentParser(argparse.ArgumentParser):
    """argparse with one-line errors and exit code 2."""

    def error(self, message: str) -> NoReturn:
        """Print `neuralslicer: error: ...` and exit 2."""
        self.exit(2, f"neuralslicer: error: {message} (see '{self.prog} --help')\n")


def prefect_environment(workspace: Path) -> None:
    """Quiet, local Prefect defaults unless the user configured Prefect (PREFECT_API_URL / PREFECT_HOME)."""
    os.environ.setdefault("PREFECT_SERVER_ANALYTICS_ENABLED", "false")
    os.environ.setdefault("DO_NOT_TRACK", "1")
    os.environ.setdefault("PREFECT_LOGGING_LEVEL", "WARNING")
    os.environ.setdefault("PREFECT_SERVER_LOGGING_LEVEL", "WARNING")
    os.environ.setdefault("PREFECT_RESULTS_PERSIST_BY_DEFAULT", "true")


def result_storage_dir(store: str) -> Path:
    """Where Prefect persists task results (cache records) for a store: beside it on local disk."""
    if "://" in store and not store.startswith("file://"):
        return Path.home() / ".cache" / "neuralslicer" / "prefect-results"
    store_path = Path(store.removeprefix("file://")).resolve()
    return store_path.parent / f".{store_path.name}.prefect-results"


def parse_objectives(text: str) -> list[str]:
    """`sf,po` -> ['sf', 'po']; `none` -> [] (the height field, planar layers)."""
    if text.strip().lower() in ("none", ""):
        return []
    items = [t.strip().lower() for t in text.split(",") if t.strip()]
    bad = [t for t in items if t not in ("sf", "sr", "po", "gc", "ca")]
    if bad:
        raise InputError("--objectives", f"unknown objective(s) {', '.join(bad)}; use a comma list of sf, sr, po, gc, ca "
                         "or 'none'")
    return items


def build_config(args: argparse.Namespace) -> Any:
    """SliceConfig from --config, overridden by the explicit command-line options."""
    from neuralslicer.config import SliceConfig

    cfg = SliceConfig.from_yaml(args.config) if args.config else SliceConfig()
    data = cfg.model_dump()
    if args.cage_elements is not None:
        data["cage"]["n_elements"] = args.cage_elements
    if args.layer_height is not None:
        data["layers"]["layer_height"] = args.layer_height
    if args.objectives is not None:
        data["objectives"] = parse_objectives(args.objectives)
    if args.max_steps is not None:
        data["neural"]["optim"]["max_steps"] = args.max_steps
    if args.network is not None:
        data["neural"]["network"] = args.network
    if args.device is not None:
        data["neural"]["device"] = args.device
    if args.seed is not None:
        data["neural"]["optim"]["seed"] = args.seed
    if args.verify:
        data["verify"] = True
    if args.robot:
        data["robot"] = True
    if args.collision_retries is not None:
        data["collision_retries"] = args.collision_retries
    if args.collision_fallback is not None:
        data["collision_fallback"] = args.collision_fallback
    if args.machine is not None:
        data["machine"] = args.machine
    if args.init is not None:
        data["neural"]["init"]["kind"] = args.init if args.init in ("height", "heat") else "user"
    try:
        return SliceConfig.model_validate(data)
    except Exception as exc:  # pydantic ValidationError: name the option
        raise InputError("options", str(exc).splitlines()[-2].strip() if len(str(exc).splitlines()) > 1 else str(exc)) from None


def validate_model(spec: Any) -> None:
    """Read every file of the spec before any output is made: bad input fails here with one line."""
    from neuralslicer.model.solid import implicit_solid

    implicit_solid(spec)


def cmd_slice(args: argparse.Namespace) -> int:
    """Slice a model (mesh, .tet or spec YAML) into curved layers and write the output contract."""
    from neuralslicer.model.spec import spec_for_file

    model = Path(args.model)
    if not model.exists():
        raise InputError(model, "no such file")
    spec = spec_for_file(model, args.up or "z")
    if args.up is not None and spec.up != args.up:
        spec = spec.model_copy(update={"up": args.up})
    config = build_config(args)
    validate_model(spec)
    if args.init not in (None, "height", "heat") and not Path(args.init).is_file():
        raise InputError(args.init, "no such file (--init takes height, heat or a file of field values)")
    out_dir = Path(args.out).resolve()
    store = str(args.store or out_dir / "store.zarr")
    return run_in_out_dir(out_dir, lambda: _run_slice(spec, out_dir, config, store, args))


def _run_slice(spec: Any, out_dir: Path, config: Any, store: str, args: argparse.Namespace) -> int:
    """Run the slicing flow and print its summary."""
    prefect_environment(out_dir)
    from flows.slice import ensure_store, slice_flow

    store = ensure_store(store)
    with cache_settings(store):
        user_field = args.init if args.init not in (None, "height", "heat") else None
        summary = slice_flow(spec=spec, out_dir=str(out_dir), config=config, store=store, user_field=user_field)
    print_summary(summary)
    return 0


def cache_settings(store: str) -> Any:
    """Prefect settings for a run on this store: task results (the cache records) persisted beside the store."""
    from prefect.settings import PREFECT_LOCAL_STORAGE_PATH, PREFECT_RESULTS_PERSIST_BY_DEFAULT, temporary_settings

    results = result_storage_dir(store)
    results.mkdir(parents=True, exist_ok=True)
    return temporary_settings(updates={PREFECT_LOCAL_STORAGE_PATH: results, PREFECT_RESULTS_PERSIST_BY_DEFAULT: True})


def print_summary(summary: dict[str, Any]) -> None:
    """The tasks' states and where the results are."""
    from rich.console import Console
    from rich.table import Table

    console = Console(stderr=False)
    table = Table(title="neuralslicer slice")
    table.add_column("task")
    table.add_column("state")
    for row in summary["tasks"]:
        style = "green" if row["state"] == "Cached" else "cyan"
        table.add_row(row["task"], f"[{style}]{row['state']}[/{style}]")
    console.print(table)
    cached = sum(r["state"] == "Cached" for r in summary["tasks"])
    console.print(f"{cached}/{len(summary['tasks'])} tasks cached, {summary['wall_s']:.1f} s")
    console.print(f"results: {summary['out_dir']}  (report.md, metrics.json, layers/, field.vtu, model.ply)")


def run_in_out_dir(out_dir: Path, job: Callable[[], int]) -> int:
    """Run a job that writes into out_dir; on bad input remove out_dir again if this run created it."""
    existed = out_dir.exists()
    try:
        return job()
    except InputError:
        if not existed:
            shutil.rmtree(out_dir, ignore_errors=True)
        raise


def cmd_fea(args: argparse.Namespace) -> int:
    """Isotropic voxel FEA of a model spec alone: DIR/fea.vtu, DIR/metrics.json, a stress picture."""
    from neuralslicer.fea import run_fea, write_fea_outputs
    from neuralslicer.model.solid import implicit_solid
    from neuralslicer.model.spec import spec_for_file

    path = Path(args.spec)
    if not path.exists():
        raise InputError(path, "no such file")
    spec = spec_for_file(path, args.up or "z")
    if args.up is not None:
        spec = spec.model_copy(update={"up": args.up})
    if spec.fea is None:
        raise InputError(path, "the spec has no 'fea' block (material, supports, loads)")
    fea = spec.fea if args.voxels is None else spec.fea.model_copy(update={"voxels": args.voxels})
    out_dir = Path(args.out).resolve()

    def job() -> int:
        try:
            result = run_fea(implicit_solid(spec), fea)
        except InputError as exc:
            if exc.where.startswith("fea"):
                raise InputError(f"{path}: {exc.where}", exc.message) from None
            raise
        metrics = write_fea_outputs(result, out_dir)
        for key in ("fea.max_displacement_mm", "fea.max_von_mises_mpa"):
            print(f"{key}: {metrics[key]:.6g}")
        print(f"results: {out_dir}  (fea.vtu, metrics.json, fea_von_mises.png)")
        return 0

    return run_in_out_dir(out_dir, job)


def add_fea_parser(sub: Any) -> None:
    """Options of `neuralslicer fea`."""
    p = sub.add_parser("fea", help="isotropic voxel FEA of a model spec (stresses, principal directions)")
    p.add_argument("spec", help="model spec (.yaml) with an fea block")
    p.add_argument("--out", required=True, help="output folder")
    p.add_argument("--up", choices=UP_AXES, default=None, help="override the spec's up axis")
    p.add_argument("--voxels", type=int, default=None, help="target voxel count (default from the spec, 100000)")
    p.set_defaults(func=cmd_fea)


def add_slice_parser(sub: Any) -> None:
    """Options of `neuralslicer slice`."""
    p = sub.add_parser("slice", help="slice a model into curved layers")
    p.add_argument("model", help="mesh (STL/OBJ/PLY/OFF), volume mesh (.tet, meshio formats) or model spec (.yaml)")
    p.add_argument("--out", required=True, help="output folder")
    p.add_argument("--up", choices=UP_AXES, default=None, help="the model's up axis (default z, or the spec's)")
    p.add_argument("--cage-elements", type=int, default=None, help="target number of cage tets (default 10000)")
    p.add_argument("--layer-height", type=float, default=None, help="target layer thickness in mm (default 0.8)")
    p.add_argument("--config", default=None, help="YAML configuration (sections: samples, cage, neural, layers)")
    p.add_argument("--objectives", default=None,
                   help="comma list of sf, sr, po, gc (global head collision), ca (local collision constraint), "
                        "or none (default sf,po,gc,ca[,sr])")
    p.add_argument("--init", default=None, help="initial guess: height, heat or a file of values (default height)")
    p.add_argument("--max-steps", type=int, default=None, help="optimisation step budget")
    p.add_argument("--network", choices=("default", "paper"), default=None, help="network size preset")
    p.add_argument("--device", choices=("auto", "cpu", "cuda"), default=None, help="torch device (default auto)")
    p.add_argument("--seed", type=int, default=None, help="random seed of the optimisation")
    p.add_argument("--store", default=None, help="artifact store (zarr path or fsspec URL; default OUT/store.zarr)")
    p.add_argument("--machine", default=None, help="machine profile: table_bc_linuxcnc (default), reprap_5axis or a YAML")
    p.add_argument("--robot", action="store_true", help="also write robot_waypoints.csv/.json")
    p.add_argument("--collision-retries", type=int, default=None,
                   help="re-optimise with smoother fields and the collision term while the nozzle collides (default 2)")
    p.add_argument("--collision-fallback", choices=("blend", "none"), default=None,
                   help="still colliding: blend the field toward planar layers until collision-free (default blend) "
                        "or keep the colliding program")
    p.add_argument("--verify", action="store_true", help="anisotropic FEA of planar vs computed layers (spec needs fea)")
    p.set_defaults(func=cmd_slice)


def make_parser() -> ArgumentParser:
    """The argument parser of every subcommand."""
    parser = ArgumentParser(prog="neuralslicer", description="Curved layers for multi-axis 3D printing (Neural Slicer).")
    parser.add_argument("--debug", action="store_true", help="show tracebacks")
    sub = parser.add_subparsers(dest="command", required=True, parser_class=ArgumentParser)
    add_slice_parser(sub)
    add_fea_parser(sub)
    add_study_parser(sub)
    add_compare_parser(sub)
    return parser


def main(argv: Sequence[str] | None = None) -> int:
    """Entry point of the `neuralslicer` command."""
    parser = make_parser()
    args = parser.parse_args(argv)
    try:
        return int(args.func(args) or 0)
    except InputError as exc:
        if args.debug:
            raise
        print(f"neuralslicer: error: {exc.where}: {exc.message}", file=sys.stderr)
        return 2
    except NeuralSlicerError as exc:
        if args.debug:
            raise
        print(f"neuralslicer: error: {exc}", file=sys.stderr)
        return 1
    except KeyboardInterrupt:
        print("neuralslicer: interrupted; run the same command again to resume", file=sys.stderr)
        return 130


if __name__ == "__main__":
    sys.exit(main())
