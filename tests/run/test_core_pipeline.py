"""The whole pipeline from the core package alone, as a notebook would run it: no Prefect, no store."""
from __future__ import annotations

import pytest

import json
import subprocess
import sys
from pathlib import Path

from conftest import REPO, fast_config

NOTEBOOK = r'''
import sys
sys.modules["prefect"] = None   # the core must not need the workflow engine
sys.modules["neuralslicer.storage"] = None   # nor the artifact store
import json
from pathlib import Path

from neuralslicer.config import SliceConfig
from neuralslicer.model.spec import spec_for_file
from neuralslicer.run.in_process import slice_model

model, out = Path(sys.argv[1]), Path(sys.argv[2])
config = SliceConfig.model_validate(json.loads(sys.argv[3]))
chain, metrics = slice_model(spec_for_file(model, "z"), config, out)
outer = ("prefect", "neuralslicer.storage", "neuralslicer.tasks", "neuralslicer.flows", "neuralslicer.cli")
loaded = sorted(m for m in sys.modules if m.startswith(outer) and sys.modules[m] is not None)
print(json.dumps({"modules": loaded, "metrics": metrics, "gcode": len(bytes(chain.program))}, default=float))
'''


@pytest.mark.slow   # over 10 s: the full suite runs it, `make test-fast` does not
def test_the_pipeline_runs_from_the_core_alone(tmp_path: Path, small_part: Path) -> None:
    """Mesh in, G-code and report out through core calls only, with Prefect and the store unimportable."""
    config = fast_config(neural={"optim": {"max_steps": 40}}, objectives=["sf", "po", "gc", "ca"])
    done = subprocess.run([sys.executable, "-c", NOTEBOOK, str(small_part), str(tmp_path / "out"), json.dumps(config)],
                          cwd=REPO,
                          capture_output=True, text=True, timeout=900)
    assert done.returncode == 0, done.stderr[-3000:]
    report = json.loads(done.stdout.strip().splitlines()[-1])
    assert report["modules"] == []
    m = report["metrics"]
    assert m["n_layers"] > 5 and m["n_waypoints"] > 100 and m["loss.ca_violating_pairs"] == 0
    assert m["sf.overhang_area_fraction"] < m["sf.overhang_area_fraction_planar"]
    assert (tmp_path / "out" / "print.gcode").stat().st_size == report["gcode"]
    for name in ("print.gcode", "metrics.json", "report.md", "field.vtu", "model.ply", "figures/layers.png"):
        assert (tmp_path / "out" / name).is_file(), name
