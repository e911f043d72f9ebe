"""The headline figures' schema (``RunMetrics``): read from metrics.json keys, None where a run has no such figure."""
from __future__ import annotations

import numpy as np
import pytest

from neuralslicer.run.run_metrics import KEYS, RunMetrics


def test_figures_are_read_by_their_metrics_keys_and_missing_ones_are_none() -> None:
    figures = RunMetrics.of({"n_layers": 151, "sf.heldout.overhang_area_fraction_layers": 0.0016, "field.stop":
                             "constraints", "loss.total": 0.002, "fea.max_strain": None})
    assert figures.n_layers == 151 and figures.overhang_layers == 0.0016 and figures.field_stop == "constraints"
    assert figures.max_strain is None and figures.material_mm3 is None
    assert figures.present() == {"n_layers": 151, "overhang_layers": 0.0016, "field_stop": "constraints"}
    assert "loss.total" not in KEYS.values()
    # as the export makes them, before JSON: numpy scalars
    assert RunMetrics.of({"n_layers": np.int64(7), "material_mm3": np.float32(2.5)}).n_layers == 7


def test_every_figure_has_its_own_key_and_label() -> None:
    labels = [RunMetrics.label(name) for name in KEYS]
    assert len(set(KEYS.values())) == len(KEYS) and len(set(labels)) == len(labels)
    assert all(RunMetrics.model_fields[name].description for name in KEYS)


def test_a_figure_of_the_wrong_type_is_refused_by_name() -> None:
    with pytest.raises(ValueError, match="n_layers"):
        RunMetrics.of({"n_layers": "many"})


def test_the_docs_list_every_figure_with_its_key_and_meaning() -> None:
    from pathlib import Path

    docs = (Path(__file__).resolve().parents[2] / "docs" / "outputs.md").read_text()
    for name, key in KEYS.items():
        row = f"| `{name}` | `{key}` | {RunMetrics.label(name)} | {RunMetrics.model_fields[name].description} |"
        assert row in docs, row
