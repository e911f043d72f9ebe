"""The two runners of the slicing chain agree: the Prefect flow (the command) and the in-process one
(``neuralslicer.run.in_process.slice_model``, what a notebook or a benchmark runs) on the Ring with defaults."""
from __future__ import annotations

import json
from pathlib import Path

import pytest

from neuralslicer.run.compare import values_equal

#: entries that differ between any two runs and say nothing about the result: wall times, and what only the command
#: records (its provenance, its run's tasks)
VOLATILE = ("wall_s.", "provenance.", "timings_s")


def _kept(metrics: dict) -> dict:
    """The metrics without the volatile entries."""
    return {k: v for k, v in metrics.items() if not k.startswith(VOLATILE) and not k.endswith("timings_s")}


@pytest.mark.slow   # two slices of the Ring with defaults (~2 min): the full suite runs it, `make test-fast` does not
def test_the_flow_and_the_in_process_chain_give_the_same_metrics_and_gcode(prefect_server: None, ring_path: Path,
                                                                          tmp_path: Path,
                                                                          monkeypatch: pytest.MonkeyPatch) -> None:
    from neuralslicer.cli.main import main
    from neuralslicer.config import SliceConfig
    from neuralslicer.model.spec import spec_for_file
    from neuralslicer.run.in_process import slice_model

    flow_out, core_out = tmp_path / "flow", tmp_path / "core"
    # the flow's motion, program and export steps in processes of their own, as a large print's are
    monkeypatch.setenv("NEURALSLICER_ISOLATE", "always")
    assert main(["slice", str(ring_path), "--up", "y", "--out", str(flow_out)]) == 0
    slice_model(spec_for_file(ring_path, "y"), SliceConfig(), core_out)
    flow = _kept(json.loads((flow_out / "metrics.json").read_text()))
    core = _kept(json.loads((core_out / "metrics.json").read_text()))
    assert set(flow) == set(core) and len(flow) > 60, set(flow) ^ set(core)
    differ = {k: (flow[k], core[k]) for k in flow if not values_equal(flow[k], core[k])}
    assert differ == {}
    assert flow["field.steps"] > 0 and flow["n_collisions"] == 0
    assert (flow_out / "print.gcode").read_bytes() == (core_out / "print.gcode").read_bytes()
