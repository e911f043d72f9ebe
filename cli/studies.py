"""Command line of studies and comparisons: `neuralslicer study initial-guess|cages|batch|methods|ablation` and `neuralslicer compare`."""
from __future__ import annotations

import argparse
from pathlib import Path
from typing import Any

from neuralslicer.cli.options import ArgumentParser, add_slicing_options, build_config, cli_names, run_in_out_dir
from neuralslicer.flows.settings import prefect_environment, with_api_retry
from neuralslicer.errors import InputError


def parse_counts(text: str) -> list[int]:
    """`4000,8000,16000` -> [4000, 8000, 16000] (each at least 200)."""
    try:
        counts = [int(t) for t in text.split(",") if t.strip()]
    except ValueError:
        raise InputError("--cage-elements", f"{text!r} is not a comma list of integers") from None
    if not counts or min(counts) < 200:
        raise InputError("--cage-elements", "give element counts of at least 200, e.g. 4000,8000,16000")
    return counts


def check_model(model: Path, args: argparse.Namespace, config: Any, out_dir: Path, store: str) -> None:
    """The slice command's checks before any work (outputs, store, scale, layer count, machine, FEA) for one model."""
    from neuralslicer.model.solid import implicit_solid
    from neuralslicer.model.spec import load_model
    from neuralslicer.run.preflight import preflight

    spec = load_model(model, args.up, getattr(args, "units", None))
    solid = implicit_solid(spec)
    preflight(spec, solid, config, out_dir, store, force=getattr(args, "force", False), names=cli_names(),
              needs_fea=config.needs_fea(spec))


def cmd_study(args: argparse.Namespace) -> int:
    """Run a study and print its table."""
    out_dir = Path(args.out).resolve()
    config = build_config(args)
    models = args.models if args.study == "batch" else [args.model]
    for m in models:
        if not Path(m).exists():
            raise InputError(m, "no such file")
    if args.dask is not None and args.dask != "local" and "://" not in args.dask and ":" not in args.dask:
        raise InputError("--dask", f"{args.dask!r}: give a scheduler address (tcp://host:8786) or 'local'")
    counts = parse_counts(args.cage_counts) if args.study == "cages" else None
    if args.study == "initial-guess" and config.objectives is not None and not config.objectives:
        raise InputError("--objectives", "the initial-guess study optimises: give objectives (e.g. sf,po), not none")
    if args.study == "initial-guess" and args.user_field is not None and not Path(args.user_field).is_file():
        raise InputError(args.user_field, "no such file (--user-field takes an .npz with points and values)")

    from neuralslicer.storage import default_store

    store_path = args.store or default_store(out_dir)
    for m in models:
        check_model(Path(m), args, config, out_dir, store_path)

    def job() -> int:
        prefect_environment()
        from neuralslicer.flows.cluster import check_cluster
        from neuralslicer.flows.study_server import study_api
        from neuralslicer.flows.studies import ablation_study, batch_study, cage_study, initial_guess_study, methods_study
        from neuralslicer.storage import ArtifactStore

        store = ArtifactStore(store_path).root
        common = dict(out_dir=str(out_dir), up=args.up, store=store, config=config, dask=args.dask,
                      dask_workers=args.dask_workers, max_workers=args.workers)
        if args.study == "initial-guess":
            kinds = [k.strip() for k in args.kinds.split(",") if k.strip()]
            run = lambda: initial_guess_study(model=args.model, kinds=kinds, user_field=args.user_field, **common)  # noqa: E731
        elif args.study == "cages":
            run = lambda: cage_study(model=args.model, cage_elements=counts, **common)  # noqa: E731
        elif args.study == "methods":
            run = lambda: methods_study(model=args.model, **common)  # noqa: E731
        elif args.study == "ablation":
            run = lambda: ablation_study(model=args.model, **common)  # noqa: E731
        else:
            run = lambda: batch_study(models=list(args.models), **common)  # noqa: E731
        if args.dask not in (None, "local"):   # before a server starts: every worker shares the store and the folder
            check_cluster(args.dask, {"--store": store, "--out": str(out_dir)}, api_url=None)
        with study_api(args.dask) as api_url:
            if api_url is not None:
                print(f"Prefect API of this study (handed to its Dask workers): {api_url}", flush=True)
            study = with_api_retry(run)
        print_study(study)
        return 0 if all(b.get("status") == "completed" for b in study["branches"]) else 1

    return run_in_out_dir(out_dir, job)


# columns of study.md left out of the terminal table (kept narrow)
TERMINAL_SKIP = ("L_sf", "L_po", "L_sr", "L_hs", "L_hq", "L_ca", "overhang planar", "steps", "status", "cage genus",
                 "SF supported", "overhang of the layers", "max strain planar", "worker", "method")


def print_study(study: dict[str, Any]) -> None:
    """The study table on the terminal."""
    from rich.table import Table

    from neuralslicer.flows.study_report import _fmt, table_rows
    from neuralslicer.console import table_console

    rows = table_rows(study)
    cols: list[str] = []
    for r in rows:
        cols += [c for c in r if c not in cols and c not in TERMINAL_SKIP]
    table = Table(title=study["title"])
    for c in cols:
        table.add_column(c)
    for r in rows:
        table.add_row(*(_fmt(r.get(c)) for c in cols))
    console = table_console()
    console.print(table)
    console.print(f"study: {study['out_dir']}/study.md, study.json ({study['wall_s']:.1f} s)")


def _study_options(p: argparse.ArgumentParser) -> None:
    """The slicing options a study shares across its branches, and the engine options."""
    add_slicing_options(p, "study folder (study.md, study.json, one folder per branch)")
    p.add_argument("--dask", default=None, metavar="ADDRESS|local",
                   help="run the branches on a Dask cluster: a scheduler address or 'local' (a LocalCluster)")
    p.add_argument("--dask-workers", type=int, default=2, help="workers of a --dask local cluster (default 2)")
    p.add_argument("--workers", type=int, default=None, help="concurrent branches without Dask (default: all)")


def add_study_parser(sub: Any) -> None:
    """Options of `neuralslicer study initial-guess|cages|batch|methods|ablation`."""
    p = sub.add_parser("study", help="studies fanned out over initial guesses, cage resolutions or models")
    studies = p.add_subparsers(dest="study", required=True, parser_class=ArgumentParser)
    ig = studies.add_parser("initial-guess", help="one model with the height, heat and a user-field initial guess")
    ig.add_argument("model", help="mesh, volume mesh (.tet) or model spec (.yaml)")
    ig.add_argument("--kinds", default="height,heat,user", help="initial guesses to compare (default height,heat,user)")
    ig.add_argument("--user-field", default=None,
                    help=".npz with points (p,3, build frame) and values (p,); default: a generated smooth field")
    _study_options(ig)
    cg = studies.add_parser("cages", help="one model at several cage element counts")
    cg.add_argument("model", help="mesh, volume mesh (.tet) or model spec (.yaml)")
    cg.add_argument("--cage-elements", dest="cage_counts", required=True, help="comma list of element counts, e.g. 4000,8000,16000")
    _study_options(cg)
    bt = studies.add_parser("batch", help="several models or specs with one configuration")
    bt.add_argument("models", nargs="+", help="meshes, volume meshes or model specs")
    bt.add_argument("--cage-elements", type=int, default=None,
                    help="target number of cage tets for every model")
    _study_options(bt)
    mt = studies.add_parser("methods", help="one model sliced by the Neural Slicer, the S3-Slicer baseline and planar "
                            "layers (fields printed as computed: collisions counted, not repaired)")
    mt.add_argument("model", help="mesh, volume mesh (.tet) or model spec (.yaml)")
    _study_options(mt)
    ab = studies.add_parser("ablation", help="the Neural Slicer with and without PO, with per-element q and s "
                            "instead of networks, and without SR when SR is on")
    ab.add_argument("model", help="mesh, volume mesh (.tet) or model spec (.yaml)")
    _study_options(ab)
    for q in (ig, cg, bt, mt, ab):
        q.set_defaults(func=cmd_study)


def cmd_compare(args: argparse.Namespace) -> int:
    """Print the differences in parameters and metrics of two output folders (a table, or JSON with --json);
    exit 1 when they differ beyond the tolerances, 0 when not."""
    import json

    from neuralslicer.fileio import to_json
    from neuralslicer.run.compare import comparison_doc, compare_entries, headline_figures, print_comparison, run_entries

    ignore = tuple(args.ignore or ())
    a, b = run_entries(args.run_a), run_entries(args.run_b)     # each folder's files read once
    diffs = compare_entries(a, b, rtol=args.rtol, atol=args.atol, include_all=args.all, ignore=ignore)
    figures = headline_figures(a[1], b[1], rtol=args.rtol, atol=args.atol)
    doc = comparison_doc(diffs, args.run_a, args.run_b, args.rtol, args.atol, ignore, figures)
    if args.json:
        print(json.dumps(to_json(doc), indent=2, allow_nan=False))
    else:
        print_comparison(diffs, args.run_a, args.run_b, figures)
    return 1 if doc["differ"] else 0


def add_compare_parser(sub: Any) -> None:
    """Options of `neuralslicer compare RUN_A RUN_B`."""
    from neuralslicer.run.compare import DEFAULT_ATOL, DEFAULT_RTOL

    p = sub.add_parser(
        "compare", help="differences in parameters and metrics of two output folders",
        description="Compare two output folders: their parameters (provenance.json: inputs by hash, spec, config, "
                    "seeds, package versions, device, git commit; and the provenance.* entries of metrics.json) and "
                    "their metrics (metrics.json). Every entry counts, parameters too; only the time of the run, the "
                    "command line, the record's digest and torch_threads are left out, and what --ignore names. "
                    "Exit status: 0 when every entry is equal within the tolerances, 1 when any differs (or is in "
                    "one run only), 2 when a folder cannot be read.")
    p.add_argument("run_a", help="output folder of a slice (or a branch of a study)")
    p.add_argument("run_b", help="another output folder")
    p.add_argument("--rtol", type=float, default=DEFAULT_RTOL,
                   help="numbers a, b are equal when |a - b| <= max(rtol * max(|a|, |b|), atol) "
                        f"(default {DEFAULT_RTOL:g})")
    p.add_argument("--atol", type=float, default=DEFAULT_ATOL, help=f"absolute tolerance (default {DEFAULT_ATOL:g})")
    p.add_argument("--ignore", action="append", metavar="KEY", default=[],
                   help="leave out the key KEY, the keys under it (KEY.*) and the keys matching it as a glob "
                        "pattern (repeatable); e.g. --ignore device --ignore provenance.device for runs on "
                        "different machines")
    p.add_argument("--json", action="store_true", help="print the comparison as JSON (schema in docs/outputs.md)")
    p.add_argument("--all", action="store_true", help="also list the entries that are equal")
    p.set_defaults(func=cmd_compare)


def cmd_explain(args: argparse.Namespace) -> int:
    """Print, for each step of a run, whether it reused a result or computed one and why (a table, or JSON)."""
    import json

    from neuralslicer.flows.explain import explain_run, print_explanation

    reasons = explain_run(args.run)
    if args.json:
        print(json.dumps({"run": str(args.run), "steps": [r.record() for r in reasons]}, indent=2))
    else:
        print_explanation(reasons, args.run)
    return 0


def add_explain_parser(sub: Any) -> None:
    """Options of `neuralslicer explain RUN`."""
    p = sub.add_parser(
        "explain", help="for each step of a run, whether it reused a result and why it computed one",
        description="For each step of a slice (its run.json and its store): 'reused' when another run made the "
                    "step's result, 'computed' when this run made it, with the reason: what differs from the "
                    "step's latest earlier result for the same model in the store (the step's code version, an "
                    "input computed anew, a parameter with both values), or that there was none.")
    p.add_argument("run", help="output folder of a slice")
    p.add_argument("--json", action="store_true", help="print the steps as JSON")
    p.set_defaults(func=cmd_explain)
