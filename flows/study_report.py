"""Study outputs: DIR/study.json, DIR/study.md with figures, and the same as Prefect table/markdown artifacts."""
from __future__ import annotations

from pathlib import Path
from typing import Any

import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt  # noqa: E402
import numpy as np  # noqa: E402
import trimesh  # noqa: E402

from neuralslicer.flows.branch import Branch  # noqa: E402
from neuralslicer.flows.settings import artifact_key  # noqa: E402
from neuralslicer.metrics import field_agreement  # noqa: E402
from neuralslicer.run.report import plot_learning_curves  # noqa: E402
from neuralslicer.run.run_metrics import RunMetrics  # noqa: E402
from neuralslicer.storage import ArtifactRef, ArtifactStore, atomic_path, write_json_atomic, write_text_atomic  # noqa: E402
from neuralslicer.tasks.codec import read_cage, read_field  # noqa: E402

LOSS_TERMS = ("total", "sf", "po", "sr", "hs", "hq", "ca")


def _fmt(value: Any) -> str:
    """A table cell."""
    if value is None:
        return "-"
    if isinstance(value, float):
        return f"{value:.4g}"
    return str(value)


def table_rows(study: dict[str, Any]) -> list[dict[str, Any]]:
    """One row per branch: parameters, cage, final losses, SF/SR satisfaction, key metrics, wall time, worker."""
    rows = []
    for b in study["branches"]:
        row: dict[str, Any] = {"branch": b["name"], "status": b.get("status")}
        row.update({k: v for k, v in b.get("parameters", {}).items() if k != "user_field"})
        if b.get("status") != "completed":
            row["error"] = b.get("error", "")
            rows.append(row)
            continue
        cage, field, m = b["cage"], b["field"], b["metrics"]
        row.update({"cage tets": cage.get("n_elements"), "cage genus": cage.get("genus"),
                    "steps": field.get("steps"), "s/step": field.get("s_per_step")})
        for term in LOSS_TERMS:
            if term in b["final_loss"] and (term == "total" or b["final_loss"][term]):
                row[f"L_{term}"] = b["final_loss"][term]
        sat, figures = b.get("satisfaction", {}), RunMetrics.of(m)
        row["SF supported"] = sat.get("sf_supported_fraction")
        if "sr_satisfied_fraction" in sat or figures.sr_satisfied is not None:
            row[RunMetrics.label("sr_satisfied")] = sat.get("sr_satisfied_fraction", figures.sr_satisfied)
        shown = ["overhang", "overhang_planar"]
        if study.get("kind") in ("methods", "ablation"):
            shown += ["overhang_held_out", "overhang_layers", "n_collisions"]
            if figures.max_strain is not None:
                shown += ["max_strain", "strain_p99", "max_strain_planar_zigzag", "aligned_fraction"]
        row.update({RunMetrics.label(name): getattr(figures, name) for name in shown})
        if study.get("kind") in ("methods", "ablation"):
            row["field s"] = field.get("optimise_wall_s")
        row[RunMetrics.label("n_layers")] = figures.n_layers
        row["wall s"] = b.get("wall_s")
        row["worker"] = b["worker"].get("dask_worker") or f"pid {b['worker']['pid']}"
        rows.append(row)
    return rows


def markdown_table(rows: list[dict[str, Any]]) -> str:
    """Rows as a Markdown table (union of the columns, in first-seen order)."""
    cols: list[str] = []
    for r in rows:
        cols += [c for c in r if c not in cols]
    lines = ["| " + " | ".join(cols) + " |", "|" + " --- |" * len(cols)]
    lines += ["| " + " | ".join(_fmt(r.get(c)) for c in cols) + " |" for r in rows]
    return "\n".join(lines)


def learning_curves(branches: list[Branch], study: dict[str, Any]) -> dict[str, dict[str, np.ndarray]]:
    """The total-loss history of each completed branch's optimisation, read from the store."""
    curves = {}
    for b, r in zip(branches, study["branches"]):
        if r.get("status") != "completed" or not r["field"].get("steps"):
            continue
        arrays, _ = ArtifactStore(b.store, create=False).read(r["field"]["path"])
        history = {k.split("/", 1)[1]: v for k, v in arrays.items() if k.startswith("history/")}
        if "total" in history and len(history["total"]):
            curves[r["name"]] = {"total": history["total"]}
    return curves


def fields_agreement(branches: list[Branch], study: dict[str, Any]) -> list[dict[str, Any]]:
    """How alike the completed branches' fields are (LPD angles and print-order correlation at the first branch's
    surface samples B, ``neuralslicer.metrics.field_agreement``): the headline of the initial-guess study, where
    every start stops at the same loss target whether or not the fields agree."""
    fields, points = {}, None
    for b, r in zip(branches, study["branches"]):
        if r.get("status") != "completed":
            continue
        ref = lambda path: ArtifactRef(b.store, path, path.rsplit("/", 1)[-1])  # noqa: E731
        fields[r["name"]] = read_field(read_cage(ref(r["cage"]["path"])), ref(r["field"]["path"]))
        if points is None and (Path(r["out_dir"]) / "samples_B.ply").is_file():
            points = np.asarray(trimesh.load(Path(r["out_dir"]) / "samples_B.ply", process=False).vertices)
    if len(fields) < 2 or points is None:
        return []
    return field_agreement(fields, points)


def agreement_table(rows: list[dict[str, Any]]) -> str:
    """The pairs as a Markdown table."""
    lines = ["| fields | LPD angle, median | LPD angle, 90th pct | print order (Spearman) | points |",
             "| --- | --- | --- | --- | --- |"]
    lines += [f"| {r['a']} vs {r['b']} | {r['lpd_angle_median_deg']:.1f}° | {r['lpd_angle_p90_deg']:.1f}° | "
              f"{r['print_order_spearman']:.3f} | {r['n_points']:,} |" for r in rows]
    return "\n".join(lines)


def plot_cage_study(path: Path, study: dict[str, Any]) -> None:
    """Cage study: step time and final total loss against the cage element count (genus annotated)."""
    done = [b for b in study["branches"] if b.get("status") == "completed"]
    n = np.array([b["cage"]["n_elements"] for b in done], dtype=float)
    order = np.argsort(n)
    fig, (a1, a2) = plt.subplots(1, 2, figsize=(10, 4))
    step = np.array([b["field"].get("s_per_step") or np.nan for b in done], dtype=float)
    loss = np.array([b["final_loss"].get("total", np.nan) for b in done], dtype=float)
    wall = np.array([b.get("wall_s", np.nan) for b in done], dtype=float)
    if np.isfinite(step).any():
        a1.plot(n[order], step[order], "o-", label="optimisation s/step")
    a1.plot(n[order], wall[order], "s--", label="branch wall s")
    a1.set_xlabel("cage elements (tets)")
    a1.set_ylabel("seconds")
    a1.set_yscale("log")
    a1.legend()
    for x, y, b in zip(n, wall, done):
        a1.annotate(f"genus {b['cage'].get('genus')}", (x, y), textcoords="offset points", xytext=(4, 4), fontsize=8)
    if np.isfinite(loss).any():
        a2.plot(n[order], loss[order], "o-", label="final total loss")
    ovh = np.array([b["metrics"].get("sf.overhang_area_fraction", np.nan) for b in done], dtype=float)
    a2.plot(n[order], ovh[order], "s--", label="overhang area fraction")
    a2.set_xlabel("cage elements (tets)")
    a2.legend()
    fig.suptitle(study["title"])
    with atomic_path(path) as tmp:
        fig.savefig(tmp, dpi=110, bbox_inches="tight", format="png")
    plt.close(fig)


def study_figures(study: dict[str, Any], out_dir: Path, branches: list[Branch]) -> dict[str, str]:
    """Draw the study's figures into out_dir/figures (learning curves; the cage plot of a cage study): caption ->
    path relative to out_dir; the curves' names go into the study record."""
    figures: dict[str, str] = {}
    curves = learning_curves(branches, study)
    if curves:
        plot_learning_curves(out_dir / "figures" / "learning_curves.png", curves)
        figures["Learning curves (total loss)"] = "figures/learning_curves.png"
        study["curves"] = sorted(curves)
    if study["kind"] == "cages" and any(b.get("status") == "completed" for b in study["branches"]):
        plot_cage_study(out_dir / "figures" / "cages.png", study)
        figures["Cage resolution"] = "figures/cages.png"
    return figures


def study_markdown(study: dict[str, Any], rows: list[dict[str, Any]], agreement: list[dict[str, Any]],
                   figures: dict[str, str]) -> str:
    """study.md: the title, how alike the fields are (initial-guess study), the branch table with its legend, links to
    each branch's report, the figures."""
    lines = [f"# {study['title']}", "", f"{len(study['branches'])} branches, wall time {study['wall_s']:.1f} s.", ""]
    if agreement:
        lines += ["## How alike the fields are", "",
                  "Every start stops at the same targets, so equal losses say little; this is what the starts change: "
                  "the angle between the print directions at the surface samples B, and the rank correlation of "
                  "the fields' values there (1: the same print order).", "", agreement_table(agreement), "",
                  "## Branches", ""]
    lines += [markdown_table(rows), "",
             "`s/step`: the optimisation's wall time (set-up and pre-training included) over its steps; "
             "`SF supported`: area fraction of the surface samples B within the self-supporting angle; "
             "`overhang`: area fraction beyond it (`overhang planar`: the same for planar layers); "
             "`worker`: the Dask worker (or process) the branch ran in.", ""]
    if study["kind"] in ("methods", "ablation"):
        lines[-1:-1] = ["", "Every branch prints its field as computed (collisions counted, not repaired). `overhang held out`: "
                        "the overhang area fraction at points of the surface mesh apart from the samples B, with the "
                        "field's LPD; `overhang of the layers`: the same points judged by the exported layers' own "
                        "normals; `max strain`: the transversely isotropic FEA of the printed part, filaments along the "
                        "printed toolpaths (with --verify); `field s`: the field's computation time.", ""]
    for b in study["branches"]:
        if b.get("status") == "completed":
            lines.append(f"- `{b['name']}`: [{b['name']}/report.md]({b['name']}/report.md)")
    for caption, rel in figures.items():
        lines += ["", f"## {caption}", "", f"![{caption}]({rel})"]
    return "\n".join(lines) + "\n"


def write_study_outputs(study: dict[str, Any], out_dir: Path, branches: list[Branch]) -> None:
    """study.json, study.md and figures in out_dir; the table and report as Prefect artifacts."""
    from prefect.artifacts import create_markdown_artifact, create_table_artifact

    study["figures"] = figures = study_figures(study, out_dir, branches)
    agreement = fields_agreement(branches, study) if study["kind"] == "initial-guess" else []
    if agreement:
        study["agreement"] = agreement
    rows = table_rows(study)
    write_json_atomic(out_dir / "study.json", study)
    text = study_markdown(study, rows, agreement, figures)
    write_text_atomic(out_dir / "study.md", text)
    key = artifact_key(f"{study['kind']}-{out_dir.name}")
    create_table_artifact(key=f"{key}-table", table=[{k: _fmt(v) for k, v in r.items()} for r in rows],
                          description=study["title"])
    create_markdown_artifact(key=f"{key}-report", markdown=text, description=f"{study['title']} ({out_dir})")
