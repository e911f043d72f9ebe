"""The command line: `neuralslicer slice | fea | study | compare | serve` (outside the core: it starts the flows)."""
from __future__ import annotations

import argparse
import signal
import sys
from collections.abc import Sequence
from pathlib import Path
from typing import Any

from neuralslicer.cli.machines import add_machines_parser
from neuralslicer.cli.options import ArgumentParser, add_slicing_options, build_config, cli_names, run_in_out_dir
from neuralslicer.cli.preview import add_preview_parser
from neuralslicer.cli.studies import add_compare_parser, add_explain_parser, add_study_parser
from neuralslicer.flows.local_api import LocalApi, api_serving, start_local_api
from neuralslicer.flows.settings import with_api_retry
from neuralslicer.allocator import keep_freed_memory
from neuralslicer.errors import InputError, NeuralSlicerError
from neuralslicer.frames import UP_AXES
from neuralslicer.neural.device import limit_threads


def cmd_slice(args: argparse.Namespace) -> int:
    """Slice a model (mesh, .tet or spec YAML) into curved layers and write the output contract."""
    model = Path(args.model)
    if not model.exists():
        raise InputError(model, "no such file")
    api = start_local_api()  # boots in the background while the model is read and checked
    from neuralslicer.run.preflight import check_slice
    from neuralslicer.storage import default_store

    config = build_config(args)
    if args.init not in (None, "height", "heat") and not Path(args.init).is_file():
        raise InputError(args.init, "no such file (--init takes height, heat or a file of field values)")
    out_dir = Path(args.out).resolve()
    store = str(args.store or default_store(out_dir))
    spec = check_slice(model, out_dir, store, config, up=args.up, units=args.units, force=args.force,
                       names=cli_names())   # the deployed flow's checks, named by the flags here
    return run_in_out_dir(out_dir, lambda: _run_slice(spec, out_dir, config, store, args, api))


def _run_slice(spec: Any, out_dir: Path, config: Any, store: str, args: argparse.Namespace,
               api: LocalApi | None) -> int:
    """Run the slicing flow (against the local API once it is up) and print its summary."""
    from neuralslicer.flows.slice import ensure_store, slice_flow

    store = ensure_store(store)
    user_field = args.init if args.init not in (None, "height", "heat") else None
    if api is not None:
        api.meanwhile(lambda: warm_imports(config, spec))
    def job() -> dict[str, Any]:
        """The flow, run once the API answers."""
        with api_serving(api):
            return slice_flow(spec=spec, out_dir=str(out_dir), config=config, store=store, user_field=user_field)

    summary = with_api_retry(job)
    print_summary(summary)
    return 0


def warm_imports(config: Any, spec: Any) -> None:
    """Import what the steps of a slice that is not cached will need (torch for the field's optimisation, the
    plotting libraries of the export: 2-4 s), while the local API server boots: a fresh command waits for it
    anyway, and the run's tasks then find them imported."""
    import neuralslicer.gcode.writers  # noqa: F401 - the program step
    import neuralslicer.motion.plan  # noqa: F401 - the toolpaths and motion steps: the planner, scipy
    import neuralslicer.run.outputs  # noqa: F401 - the export: matplotlib, pyvista

    if config.objectives_for(spec):
        import neuralslicer.neural.optimise  # noqa: F401 - torch


def print_summary(summary: dict[str, Any]) -> None:
    """The tasks' states and where the results are."""
    from rich.table import Table

    from neuralslicer.console import table_console

    console = table_console()
    table = Table(title="neuralslicer slice")
    table.add_column("task")
    table.add_column("state")
    for row in summary["tasks"]:
        style = "green" if row["state"] == "Cached" else "cyan"
        table.add_row(row["task"], f"[{style}]{row['state']}[/{style}]")
    console.print(table)
    cached = sum(r["state"] == "Cached" for r in summary["tasks"])
    console.print(f"{cached}/{len(summary['tasks'])} tasks cached, {summary['wall_s']:.1f} s")
    console.print(f"results: {summary['out_dir']}  (metrics.json, layers/, field.vtu, model.ply)")
    for line in result_files(Path(summary["out_dir"])):
        console.print(line, soft_wrap=True, highlight=False)


#: the files a slice's last lines name, in the order a user opens them
RESULT_FILES = (("G-code", "print.gcode"), ("preview", "preview.html"), ("report", "report.md"))


def result_files(out_dir: Path) -> list[str]:
    """One line per result file in the output folder (``print.gcode``, ``preview.html`` where written,
    ``report.md``): what it is and its path."""
    return [f"{what + ':':<9}{out_dir / name}" for what, name in RESULT_FILES if (out_dir / name).is_file()]


def cmd_fea(args: argparse.Namespace) -> int:
    """Isotropic voxel FEA of a model spec alone: DIR/fea.vtu, DIR/metrics.json, a stress picture."""
    from neuralslicer.fea import run_fea, write_fea_outputs
    from neuralslicer.model.solid import implicit_solid
    from neuralslicer.model.spec import load_model

    path = Path(args.spec)
    if not path.exists():
        raise InputError(path, "no such file")
    spec = load_model(path, args.up)
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
    p.add_argument("model", help="mesh (STL/3MF/OBJ/PLY/OFF), volume mesh (.tet, meshio formats) or model spec (.yaml)")
    add_slicing_options(p)
    p.add_argument("--cage-elements", type=int, default=None, help="target number of cage tets (default 10000)")
    p.add_argument("--init", default=None, help="initial guess: height, heat or a file of values (default height)")
    p.add_argument("--units", choices=("mm", "cm", "m", "in"), default=None,
                   help="unit of the model file's coordinates (default mm, or the spec's)")
    p.add_argument("--force", action="store_true",
                   help="slice even when the layer count estimate exceeds the preflight's limit of 5,000 layers "
                        "(a wrong unit, usually)")
    p.set_defaults(func=cmd_slice)


def cmd_serve(args: argparse.Namespace) -> int:
    """Serve the slice and study deployments from this machine (Prefect's serve) until Ctrl-C."""
    import os

    from neuralslicer.flows.settings import CONSOLE_LEVEL, prefect_environment

    os.environ.setdefault(CONSOLE_LEVEL, "INFO")   # a server's terminal: the runs it picks up and their logs
    prefect_environment()
    from prefect.settings import get_current_settings

    if not get_current_settings().api.url:
        raise InputError("PREFECT_API_URL", "neuralslicer serve needs a Prefect server: start one (prefect server "
                         "start) and export PREFECT_API_URL=http://HOST:4200/api")
    from neuralslicer.flows.serve import DeploymentDefaults, check_names, serve_deployments

    if args.model and not Path(args.model).exists():
        raise InputError(args.model, "no such file")
    config = None
    if args.config:
        import yaml

        from neuralslicer.config import SliceConfig

        SliceConfig.from_yaml(args.config)   # checked here: an error names the file and the key
        config = yaml.safe_load(Path(args.config).read_text()) or {}
    defaults = DeploymentDefaults(
        only=check_names(_comma(args.only), "--only"), model=str(Path(args.model).resolve()) if args.model else None,
        up=args.up, out=str(Path(args.out).resolve()) if args.out else None, store=args.store, config=config,
        cron=args.cron, interval=args.interval, scheduled=check_names(_comma(args.schedule), "--schedule"),
        paused=args.paused)
    serve_deployments(defaults, limit=args.limit, gpu_slots=args.gpu_limit)
    return 0


def _comma(text: str) -> list[str]:
    """``a,b`` -> ['a', 'b']."""
    return [t.strip() for t in text.split(",") if t.strip()]


def add_serve_parser(sub: Any) -> None:
    """Options of `neuralslicer serve`."""
    p = sub.add_parser("serve", help="serve the slice and study deployments from this machine (a Prefect server's "
                                     "scheduled and triggered runs run here)")
    p.add_argument("--only", default="slice,initial-guess,cages,batch",
                   help="comma list of the deployments to serve (default: all)")
    p.add_argument("--model", default=None, help="default model (file or spec) of every deployment")
    p.add_argument("--up", choices=UP_AXES, default=None, help="default up axis (default: none, a spec keeps its own)")
    p.add_argument("--out", default=None, help="default output folder (each deployment gets OUT/<name>)")
    p.add_argument("--store", default=None, help="default artifact store of every deployment")
    p.add_argument("--config", default=None, help="YAML slicing configuration, the deployments' default 'config'")
    p.add_argument("--cron", default=None, help="cron schedule (UTC) of the deployments --schedule names, "
                                                "e.g. '0 2 * * *'")
    p.add_argument("--interval", type=float, default=None, help="interval schedule (s) instead of a cron one")
    p.add_argument("--schedule", default="slice", help="comma list of the deployments the schedule is for "
                                                        "(default slice)")
    p.add_argument("--paused", action="store_true", help="create the schedule paused")
    p.add_argument("--limit", type=int, default=None, help="at most this many runs at once (default: no limit)")
    p.add_argument("--gpu-limit", type=int, default=None,
                   help="set the 'gpu' tag concurrency limit: at most this many field steps on a CUDA device at once")
    p.set_defaults(func=cmd_serve)


def package_version() -> str:
    """The installed distribution's version (pyproject.toml), or 'unknown' when run from an uninstalled tree."""
    from importlib.metadata import PackageNotFoundError, version

    try:
        return version("neuralslicer")
    except PackageNotFoundError:
        return "unknown"


def make_parser() -> ArgumentParser:
    """The argument parser of every subcommand."""
    parser = ArgumentParser(prog="neuralslicer", description="Curved layers for multi-axis 3D printing (Neural Slicer).")
    parser.add_argument("--debug", action="store_true", help="show tracebacks")
    parser.add_argument("--version", action="version", version=f"neuralslicer {package_version()}")
    sub = parser.add_subparsers(dest="command", required=True, parser_class=ArgumentParser)
    add_slice_parser(sub)
    add_fea_parser(sub)
    add_study_parser(sub)
    add_compare_parser(sub)
    add_explain_parser(sub)
    add_preview_parser(sub)
    add_serve_parser(sub)
    add_machines_parser(sub)
    return parser


class Terminated(KeyboardInterrupt):
    """SIGTERM (a scheduler's time limit, an eviction, ``timeout``), handled as Ctrl-C is."""


def _raise_terminated(signum: int, frame: object) -> None:
    """SIGTERM handler: stop the run the way Ctrl-C does (checkpoints stay, the rerun resumes)."""
    raise Terminated()


def _on_sigterm() -> None:
    """Handle SIGTERM as Ctrl-C (in the main thread; Prefect's flow engine hands it back here when its run ends)."""
    try:
        signal.signal(signal.SIGTERM, _raise_terminated)
    except ValueError:  # pragma: no cover - not the main thread (an embedding application)
        pass


def _leave(code: int) -> int:
    """Leave a run stopped by Ctrl-C or SIGTERM now: the exit handlers run (the local server stops), the
    interpreter's teardown does not (native extensions would report the objects the interrupted frames still hold)."""
    import atexit
    import os

    atexit._run_exitfuncs()
    sys.stdout.flush()
    sys.stderr.flush()
    os._exit(code)


def main(argv: Sequence[str] | None = None) -> int:
    """Entry point of the `neuralslicer` command (``argv``: the arguments of an in-process call, which returns the
    exit status also when interrupted)."""
    parser = make_parser()
    args = parser.parse_args(argv)
    limit_threads()  # before anything imports torch (its OpenMP reads the thread and spin settings once); a run
    # pinned to fewer cores (taskset, a cgroup quota) uses only those
    keep_freed_memory()  # big arrays reused, not faulted in again for every step (neuralslicer/allocator.py)
    _on_sigterm()
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
    except KeyboardInterrupt as exc:
        if isinstance(exc, Terminated) or isinstance(exc.__context__, Terminated):
            print("neuralslicer: terminated (SIGTERM); run the same command again to resume", file=sys.stderr)
            code = 128 + signal.SIGTERM
        else:
            print("neuralslicer: interrupted; run the same command again to resume", file=sys.stderr)
            code = 130
        return code if argv is not None else _leave(code)


if __name__ == "__main__":
    sys.exit(main())
