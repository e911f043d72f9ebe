"""`neuralslicer compare RUN_A RUN_B`: differences in parameters and metrics of two output folders."""
from __future__ import annotations

import json
import math
from pathlib import Path
from typing import Any

from pydantic import BaseModel, Field

from neuralslicer.errors import InputError
from neuralslicer.provenance import flatten

# entries that differ between any two runs and say nothing about the result
VOLATILE = ("recorded_at", "command", "digest", "provenance.device.torch_threads")


class Difference(BaseModel):
    """One entry of a comparison."""

    section: str = Field(description="'parameters' or 'metrics'")
    key: str
    a: Any = None
    b: Any = None
    equal: bool
    delta: float | None = Field(None, description="b - a for numbers")


def _load_json(path: Path) -> dict[str, Any]:
    """A JSON object from a file, or an InputError naming it."""
    try:
        data = json.loads(path.read_text())
    except (OSError, json.JSONDecodeError) as exc:
        raise InputError(path, f"cannot read: {exc}") from None
    if not isinstance(data, dict):
        raise InputError(path, "not a JSON object")
    return data


def run_entries(run: str | Path) -> tuple[dict[str, Any], dict[str, Any]]:
    """(parameters, metrics) of an output folder: provenance.json (spec, config, seeds, versions, inputs) and metrics.json."""
    d = Path(run)
    if not (d / "metrics.json").is_file():
        raise InputError(run, "not an output folder (no metrics.json)")
    metrics = _load_json(d / "metrics.json")
    params: dict[str, Any] = {}
    if (d / "provenance.json").is_file():
        prov = _load_json(d / "provenance.json")
        params.update(flatten({k: v for k, v in prov.items() if k not in VOLATILE}))
    params.update({k: v for k, v in metrics.items() if k.startswith("provenance.")})
    metrics = {k: v for k, v in metrics.items() if not k.startswith("provenance.")}
    return params, metrics


def _equal(a: Any, b: Any, rtol: float) -> bool:
    """Equality with a relative tolerance for numbers."""
    if isinstance(a, bool) or isinstance(b, bool):
        return a == b
    if isinstance(a, (int, float)) and isinstance(b, (int, float)):
        return a == b or math.isclose(a, b, rel_tol=rtol, abs_tol=0.0)
    return a == b


def compare_runs(run_a: str | Path, run_b: str | Path, rtol: float = 0.0, include_all: bool = False) -> list[Difference]:
    """The entries of two runs' parameters and metrics that differ (all entries with include_all), sorted by key."""
    pa, ma = run_entries(run_a)
    pb, mb = run_entries(run_b)
    out = []
    for section, a, b in (("parameters", pa, pb), ("metrics", ma, mb)):
        for key in sorted(set(a) | set(b)):
            if any(key == v or key.endswith("." + v) for v in VOLATILE):
                continue
            va, vb = a.get(key), b.get(key)
            equal = key in a and key in b and _equal(va, vb, rtol)
            if equal and not include_all:
                continue
            delta = None
            if isinstance(va, (int, float)) and isinstance(vb, (int, float)) and not isinstance(va, bool):
                delta = float(vb) - float(va)
            out.append(Difference(section=section, key=key, a=va, b=vb, equal=equal, delta=delta))
    return out


def _cell(value: Any) -> str:
    """A compact table cell."""
    if value is None:
        return "[dim]-[/dim]"
    if isinstance(value, float):
        return f"{value:.6g}"
    text = json.dumps(value) if isinstance(value, (list, dict)) else str(value)
    return text if len(text) <= 60 else text[:57] + "..."


def print_comparison(diffs: list[Difference], run_a: str | Path, run_b: str | Path) -> None:
    """Print the comparison as a rich table per section."""
    from rich.table import Table

    from neuralslicer.console import table_console

    console = table_console()
    for section in ("parameters", "metrics"):
        rows = [d for d in diffs if d.section == section]
        table = Table(title=f"{section}: {run_a} vs {run_b}")
        table.add_column("key")
        table.add_column("A")
        table.add_column("B")
        table.add_column("B - A")
        for d in rows:
            style = "" if d.equal else "yellow"
            table.add_row(f"[{style}]{d.key}[/{style}]" if style else d.key, _cell(d.a), _cell(d.b),
                          "" if d.delta is None else f"{d.delta:+.4g}")
        console.print(table)
    n = sum(not d.equal for d in diffs)
    console.print(f"{n} difference(s)")
