"""``neuralslicer preview RUN_DIR``: (re)write a finished slice's ``preview.html`` from the program in its store."""
from __future__ import annotations

import json
from pathlib import Path
from typing import Any

from neuralslicer.errors import InputError
from neuralslicer.motion.planning import ProgramMoves
from neuralslicer.preview import DEFAULT_DRAW_BUDGET, DEFAULT_MAX_POINTS, PREVIEW_FILE
from neuralslicer.preview.data import PreviewData
from neuralslicer.preview.page import write_preview
from neuralslicer.storage import ArtifactRef, ArtifactStore
from neuralslicer.tasks.codec import read_collided, read_motion


def motion_ref(run_dir: Path) -> ArtifactRef:
    """The motion step's group of the print a slice wrote to ``run_dir``, as its run.json names it."""
    if not run_dir.is_dir():
        raise InputError(run_dir, "no such folder (give the output folder of `neuralslicer slice`)")
    record = run_dir / "run.json"
    try:
        run: dict[str, Any] = json.loads(record.read_text())
    except FileNotFoundError:
        raise InputError(record, "no such file: not the output folder of a finished `neuralslicer slice`") from None
    except (OSError, json.JSONDecodeError) as exc:
        raise InputError(record, f"cannot read: {exc}") from None
    group = (run.get("groups") or {}).get("motion") if isinstance(run, dict) else None
    if not group or not run.get("store"):
        raise InputError(record, "names no store and motion group (written by an older neuralslicer: slice again)")
    try:
        store = ArtifactStore(run["store"], create=False)
    except FileNotFoundError:
        raise InputError(run["store"], f"no artifact store there (the store {record} names)") from None
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
