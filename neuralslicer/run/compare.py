"""`neuralslicer compare RUN_A RUN_B`: differences in parameters and metrics of two output folders."""
from __future__ import annotations

import fnmatch
import json
import math
from pathlib import Path
from typing import Any

from pydantic import BaseModel, Field

from neuralslicer.errors import InputError
from neuralslicer.run.provenance import flatten
from neuralslicer.run.run_metrics import KEYS, RunMetrics

# entries that differ between any two runs and say nothing about the result
VOLATILE = ("recorded_at", "command", "digest", "provenance.device.torch_threads")


#: the format of ``neuralslicer compare --json`` (``comparison_doc``)
COMPARE_SCHEMA = "neuralslicer.compare/1"
#: the tolerances the command line uses by default (``compare_runs`` itself compares exactly)
DEFAULT_RTOL = 1e-6
DEFAULT_ATOL = 1e-9


class Difference(BaseModel):
    """One entry of a comparison."""

    section: str = Field(description="'parameters', 'metrics' or 'figures' (the headline figures, RunMetrics)")
    key: str
    a: Any = None
    b: Any = None
    equal: bool
    delta: float | None = Field(None, description="b - a for numbers")
    only_in: str | None = Field(None, description="'a' or 'b' when the entry is in one run only")


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


def _is_number(v: Any) -> bool:
    """An int or float that is not a bool."""
    return isinstance(v, (int, float)) and not isinstance(v, bool)


def values_equal(a: Any, b: Any, rtol: float = 0.0, atol: float = 0.0) -> bool:
    """Equality, numbers within ``|a - b| <= max(rtol * max(|a|, |b|), atol)`` (NaN equals NaN), lists element by
    element, anything else exactly (a bool equals only a bool)."""
    if isinstance(a, bool) or isinstance(b, bool):
        return type(a) is type(b) and a == b
    if _is_number(a) and _is_number(b):
        if math.isnan(a) or math.isnan(b):
            return math.isnan(a) and math.isnan(b)
        return a == b or math.isclose(a, b, rel_tol=rtol, abs_tol=atol)
    if isinstance(a, list) and isinstance(b, list):
        return len(a) == len(b) and all(values_equal(x, y, rtol, atol) for x, y in zip(a, b))
    return a == b


def ignored(key: str, patterns: tuple[str, ...]) -> bool:
    """Whether a key is left out: it matches a glob pattern, or starts with one followed by '.'."""
    return any(fnmatch.fnmatchcase(key, p) or key.startswith(p + ".") for p in patterns)


def compare_runs(run_a: str | Path, run_b: str | Path, rtol: float = 0.0, include_all: bool = False,
                 atol: float = 0.0, ignore: tuple[str, ...] = ()) -> list[Difference]:
    """The entries of two runs' parameters and metrics that differ beyond the tolerances (``values_equal``; all
    entries with include_all), sorted by key; keys matching ``ignore`` (``ignored``) and the volatile ones left out."""
    return compare_entries(run_entries(run_a), run_entries(run_b), rtol, include_all, atol, ignore)


def compare_entries(entries_a: tuple[dict[str, Any], dict[str, Any]], entries_b: tuple[dict[str, Any], dict[str, Any]],
                    rtol: float = 0.0, include_all: bool = False, atol: float = 0.0, ignore: tuple[str, ...] = ()
                    ) -> list[Difference]:
    """:func:`compare_runs` of two runs' (parameters, metrics) as :func:`run_entries` reads them."""
    out = []
    for section, a, b in (("parameters", entries_a[0], entries_b[0]), ("metrics", entries_a[1], entries_b[1])):
        for key in sorted(set(a) | set(b)):
            if any(key == v or key.endswith("." + v) for v in VOLATILE) or ignored(key, ignore):
                continue
            d = _difference(section, key, a, b, rtol, atol)
            if include_all or not d.equal:
                out.append(d)
    return out


def _difference(section: str, key: str, a: dict[str, Any], b: dict[str, Any], rtol: float, atol: float) -> Difference:
    """The entry ``key`` of two runs' mappings, compared."""
    va, vb = a.get(key), b.get(key)
    equal = key in a and key in b and values_equal(va, vb, rtol, atol)
    delta = float(vb) - float(va) if _is_number(va) and _is_number(vb) else None
    only_in = None if key in a and key in b else ("a" if key in a else "b")
    return Difference(section=section, key=key, a=va, b=vb, equal=equal, delta=delta, only_in=only_in)


def headline_figures(metrics_a: dict[str, Any], metrics_b: dict[str, Any], rtol: float = 0.0, atol: float = 0.0
                     ) -> list[Difference]:
    """The headline figures (:class:`RunMetrics`) that either run's metrics have, equal or not, in the schema's order:
    what a comparison shows first. They are metrics too, and count there."""
    fa, fb = ({KEYS[k]: v for k, v in RunMetrics.of(m).present().items()} for m in (metrics_a, metrics_b))
    return [_difference("figures", key, fa, fb, rtol, atol) for key in KEYS.values() if key in fa or key in fb]


def comparison_doc(diffs: list[Difference], run_a: str | Path, run_b: str | Path, rtol: float, atol: float,
                   ignore: tuple[str, ...] = (), figures: list[Difference] | None = None) -> dict[str, Any]:
    """The JSON document of ``neuralslicer compare --json`` (schema ``COMPARE_SCHEMA``, docs/outputs.md)."""
    n = {s: sum(not d.equal and d.section == s for d in diffs) for s in ("parameters", "metrics")}
    return {"schema": COMPARE_SCHEMA, "run_a": str(run_a), "run_b": str(run_b),
            "rtol": rtol, "atol": atol, "ignore": list(ignore),
            "differ": any(n.values()), "n_differences": sum(n.values()), "n_by_section": n,
            "figures": [{**d.model_dump(), "label": _label(d.key)} for d in figures or []],
            "differences": [d.model_dump() for d in diffs]}


def _label(key: str) -> str:
    """The table label of a headline figure's metrics key."""
    return RunMetrics.label(next(name for name, k in KEYS.items() if k == key))


def _cell(value: Any) -> str:
    """A compact table cell."""
    if value is None:
        return "[dim]-[/dim]"
    if isinstance(value, float):
        return f"{value:.6g}"
    text = json.dumps(value) if isinstance(value, (list, dict)) else str(value)
    return text if len(text) <= 60 else text[:57] + "..."


def print_comparison(diffs: list[Difference], run_a: str | Path, run_b: str | Path,
                     figures: list[Difference] | None = None) -> None:
    """Print the comparison as a rich table per section, the headline figures first (both values, equal or not)."""
    from rich.table import Table

    from neuralslicer.console import table_console

    console = table_console()
    for section, rows in (("figures", figures or []), *((s, [d for d in diffs if d.section == s])
                                                        for s in ("parameters", "metrics"))):
        if section == "figures" and not rows:
            continue
        table = Table(title=f"{section}: {run_a} vs {run_b}")
        table.add_column("figure" if section == "figures" else "key")
        table.add_column("A")
        table.add_column("B")
        table.add_column("B - A")
        for d in rows:
            name = f"{_label(d.key)} ({d.key})" if section == "figures" else d.key
            table.add_row(name if d.equal else f"[yellow]{name}[/yellow]", _cell(d.a), _cell(d.b),
                          "" if d.delta is None else f"{d.delta:+.4g}")
        console.print(table)
    n = sum(not d.equal for d in diffs)
    console.print(f"{n} difference(s)")
