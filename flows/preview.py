"""``neuralslicer preview RUN_DIR``: (re)write a finished slice's ``preview.html`` from the program in its store."""
from __future__ import annotations

from pathlib import Path

from neuralslicer.errors import InputError
from neuralslicer.flows.run_record import open_run_store, read_run_record
from neuralslicer.motion.planning import ProgramMoves
from neuralslicer.preview import DEFAULT_DRAW_BUDGET, DEFAULT_MAX_POINTS, PREVIEW_FILE
from neuralslicer.preview.data import PreviewData
from neuralslicer.preview.page import write_preview
from neuralslicer.storage import ArtifactRef
from neuralslicer.tasks.codec import read_collided, read_motion


def motion_ref(run_dir: Path) -> ArtifactRef:
    """The motion step's group of the print a slice wrote to ``run_dir``, as its run.json names it."""
    run, record = read_run_record(run_dir)
    group = (run.get("groups") or {}).get("motion")
    if not group or not run.get("store"):
        raise InputError(record, "names no store and motion group (written by an older neuralslicer: slice again)")
    store = open_run_store(run, record)
    if not store.exists(group):
        raise InputError(run["store"], f"has no group {group} (the motion step {record} names): slice again")
    return store.ref(group, group.rsplit("/", 1)[-1])


def preview_run(run_dir: str | Path, out: str | Path | None = None, max_points: int = DEFAULT_MAX_POINTS,
                draw_budget: int = DEFAULT_DRAW_BUDGET) -> tuple[Path, PreviewData]:
    """Write the preview of a finished slice (default ``RUN_DIR/preview.html``) from its stored program, toolpaths
    and collisions; the file and the moves it draws."""
    run_dir = Path(run_dir)
    ref = motion_ref(run_dir)
    tp, program, metrics = read_motion(ref, ProgramMoves)
    path = Path(out) if out is not None else run_dir / PREVIEW_FILE
    data = write_preview(path, program, tp.width, read_collided(ref), ref.model, metrics, max_points, draw_budget)
    return path, data
