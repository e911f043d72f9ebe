"""The export task: the output contract in DIR (meshes, field, metrics, report), written atomically."""
from __future__ import annotations

from pathlib import Path
from typing import Any

from neuralslicer.fileio import write_text_atomic
from neuralslicer.run.pipeline import RoundPrint, TriedPrint
from neuralslicer.run.step_table import STRESS_SAMPLES_KEY
from neuralslicer.storage import ArtifactRef
from neuralslicer.tasks.codec import read_run
from neuralslicer.tasks.common import pipeline_task
from neuralslicer.tasks.isolate import large_print

STAMP = ".neuralslicer-export"


def _export_current(out: ArtifactRef, params: dict[str, Any]) -> bool:
    """The export is current when DIR still holds the files of this very export."""
    stamp = Path(params["out_dir"], STAMP)
    return stamp.is_file() and stamp.read_text().strip() == out.digest and Path(params["out_dir"], "metrics.json").is_file()


@pipeline_task("export", version="8", exclude=(), valid=_export_current,
               isolate=large_print("motion", "toolpaths/xyz"), key_names=STRESS_SAMPLES_KEY)
def export_task(out: ArtifactRef, store: str, out_dir: str, model: ArtifactRef, surface: ArtifactRef,
                samples: ArtifactRef, cage: ArtifactRef, field: ArtifactRef, layers: ArtifactRef,
                motion: ArtifactRef, stress_samples: ArtifactRef | None, verify: ArtifactRef | None, robot: bool,
                alpha_deg: float, beta_deg: float, attempts: list[TriedPrint[ArtifactRef]] | None = None,
                sr_rounds: list[RoundPrint[ArtifactRef]] | None = None,
                toolpaths: ArtifactRef | None = None, program: ArtifactRef | None = None) -> tuple[dict, dict]:
    """Write model.ply, layers/, field.vtu, samples_B.ply, the print (``motion``: the motion step's output; the
    G-code of ``program``), metrics.json, report.md and figures to out_dir."""
    from neuralslicer.run.outputs import write_outputs   # the report's plotting libraries: only when exporting

    run = read_run(model, surface, samples, cage, field, layers, motion, stress_samples, verify, attempts or [],
                   sr_rounds or [], toolpaths, program)
    metrics = write_outputs(out_dir, run, alpha_deg, beta_deg, robot)
    write_text_atomic(Path(out_dir) / STAMP, out.digest)
    return {}, {"out_dir": str(out_dir), "metrics": metrics}
