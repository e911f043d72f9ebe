"""``neuralslicer explain RUN``: for each step of a run, whether it reused a result and, where it computed one, why.

The store is the steps' one cache: a task whose group is there computes nothing (its state is ``Cached``). A step's
output group records what its digest covers (``key``: the step's code version, its parameters with inputs
by digest, its inputs' groups), which flow run made it (``made``; ``tasks/common.py``) and when (``written_at``). A
step of the run whose group another flow run made reused that result. A step whose group this run made computed it; the
reason is what differs from the step's latest earlier result for the same model in the same store: the code
version, an input computed anew, or a parameter (named, with both values).
"""
from __future__ import annotations

import json
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from neuralslicer.errors import InputError
from neuralslicer.flows.run_record import open_run_store, read_run_record
from neuralslicer.run.provenance import flatten
from neuralslicer.storage import ArtifactStore

#: parameter differences listed per step before "and N more"
MAX_LISTED = 6


@dataclass(frozen=True)
class StepReason:
    """One task of a run: its step, group, whether it computed its result, and why (or where it came from)."""

    task: str
    group: str
    state: str
    computed: bool
    reason: str

    def record(self) -> dict[str, Any]:
        """As ``explain --json`` lists it."""
        return {"task": self.task, "group": self.group, "state": self.state, "computed": self.computed,
                "reason": self.reason}


def explain_run(run_dir: str | Path) -> list[StepReason]:
    """Every task of the run in ``run_dir``, in order, with why it computed or reused its result."""
    run, record = read_run_record(Path(run_dir))
    if "flow_run_id" not in run or any("group" not in t for t in run.get("tasks", [])):
        raise InputError(record, "written by a version before `explain` (no flow run id or task groups): slice again")
    store = open_run_store(run, record)
    return [_reason(store, task, run["flow_run_id"]) for task in run["tasks"]]


def _reason(store: ArtifactStore, task: dict[str, Any], flow_run: str) -> StepReason:
    """Why one task computed or reused its group."""
    group, state = task["group"], task["state"]
    if not store.exists(group):
        return StepReason(task["task"], group, state, state != "Cached", "its result is no longer in the store")
    attrs = store.attrs(group)
    made = attrs.get("made") or {}
    if made.get("flow_run") != flow_run:
        when = f" at {attrs['written_at']}" if attrs.get("written_at") else ""
        source = f"flow run {made['flow_run']}{when}" if made.get("flow_run") else "an earlier run"
        return StepReason(task["task"], group, state, False, f"reused from the store: made by {source}")
    why = _why_computed(store, group, attrs)
    if attrs.get("from_cage_cache"):
        why = f"taken from the machine's cage cache, not built; {why}"
    return StepReason(task["task"], group, state, True, why)


def _why_computed(store: ArtifactStore, group: str, attrs: dict[str, Any]) -> str:
    """What differs between a computed group's key and the latest group of its step and model made before it."""
    key = attrs.get("key") or {}
    earlier = _latest_before(store, group, attrs.get("written_at") or "")
    if earlier is None:
        return "no earlier result of this step for this model in the store"
    before = earlier.get("key") or {}
    if not before:
        return "the earlier results of this step were written before their keys were recorded"
    reasons = []
    if before.get("version") != key.get("version"):
        reasons.append(f"the step's code version changed ({before.get('version')} -> {key.get('version')})")
    old_inputs, new_inputs = before.get("inputs", {}), key.get("inputs", {})
    changed_inputs = sorted(k for k in set(old_inputs) | set(new_inputs) if old_inputs.get(k) != new_inputs.get(k))
    reasons += [f"its input {k} is another result ({_step_of(new_inputs.get(k))})" for k in changed_inputs]
    old, new = (flatten({k: v for k, v in d.get("parameters", {}).items() if k not in changed_inputs})
                for d in (before, key))
    params = [k for k in sorted(set(old) | set(new)) if old.get(k) != new.get(k)]
    listed = [f"{k}: {_short(old.get(k))} -> {_short(new.get(k))}" for k in params[:MAX_LISTED]]
    if len(params) > MAX_LISTED:
        listed.append(f"and {len(params) - MAX_LISTED} more")
    if listed:
        reasons.append("parameters differ: " + "; ".join(listed))
    return "; ".join(reasons) or "the same key as an earlier result that is gone from the store"


def _latest_before(store: ArtifactStore, group: str, at: str) -> dict[str, Any] | None:
    """The attributes of the most recently made other group of ``group``'s step and model, made no later than ``at``
    (groups without a record of when count as the oldest); None if there is none."""
    folder = group.rsplit("/", 1)[0]
    others = [store.attrs(f"{folder}/{name}") for name in store.children(folder) if f"{folder}/{name}" != group]
    others = [a for a in others if (a.get("written_at") or "") <= at]
    return max(others, key=lambda a: a.get("written_at") or "", default=None)


def _step_of(path: str | None) -> str:
    """'<step> <first 8 characters of the digest>' of a group path."""
    if not path:
        return "none"
    parts = path.split("/")
    return f"{parts[-2]} {parts[-1][:8]}" if len(parts) >= 2 else path


def _short(value: Any) -> str:
    """A compact value for a reason."""
    text = "absent" if value is None else json.dumps(value) if isinstance(value, (list, dict)) else str(value)
    return text if len(text) <= 40 else text[:37] + "..."


def print_explanation(reasons: list[StepReason], run_dir: str | Path) -> None:
    """The reasons as a rich table."""
    from rich.table import Table

    from neuralslicer.console import table_console

    table = Table(title=f"steps of {run_dir}")
    for column in ("step", "result", "why"):
        table.add_column(column)
    for r in reasons:
        table.add_row(r.task, "[yellow]computed[/yellow]" if r.computed else "reused", r.reason)
    console = table_console()
    console.print(table)
    console.print(f"{sum(r.computed for r in reasons)} of {len(reasons)} steps computed")
