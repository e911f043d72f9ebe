"""The whole pipeline from the core package alone, as a notebook would run it: no Prefect, no store."""
from __future__ import annotations

import json
import subprocess
import sys
from pathlib import Path

from conftest import REPO

NOTEBOOK = r'''
import sys
sys.modules["prefect"] = None   # the core must not need the workflow engine
sys.modules["storage"] = None   # nor the artifact store
import json
from pathlib import Path

import numpy as np

from neuralslicer.cage import CageConfig, make_cage
from neuralslicer.layers import LayerConfig, slice_layers
from neuralslicer.model.solid import implicit_solid
from neuralslicer.model.spec import spec_for_file
from neuralslicer.motion import load_profile, plan_print
from neuralslicer.neural import NeuralConfig
from neuralslicer.neural.optimise import optimise_for_solid
from neuralslicer.outputs import RunResults, write_outputs
from neuralslicer.samples import surface_samples
from neuralslicer.scalar_field import ScalarField
from neuralslicer.toolpath.config import ToolpathConfig

model, out = Path(sys.argv[1]), Path(sys.argv[2])
solid = implicit_solid(spec_for_file(model, "z"))
samples = surface_samples(solid, 2000, k=10, seed=0)
cage = make_cage(solid, samples.points, CageConfig(n_elements=1500))
machine = load_profile("table_bc_linuxcnc")
config = NeuralConfig.model_validate({"optim": {"max_steps": 40}}).with_head(machine.nozzle, 1.0)
result = optimise_for_solid(solid, cage.vertices, cage.tets, samples, None, ["sf", "po", "gc", "ca"], config)
field = ScalarField(cage.vertices, cage.tets, result.G, result.attrs | {"final": result.final, "steps": result.steps})
layers = slice_layers(solid, field, LayerConfig(layer_height=1.0, thickness_samples=2000))
tp, program, print_metrics, collisions = plan_print(
    layers.meshes, platform_z=solid.platform_z, solid_H=solid.H, profile=machine,
    toolpath_cfg=ToolpathConfig(line_width=1.0, spacing=1.0, n_shells=1, infill_density=0.5))
run = RunResults(model=model.stem, surface=solid.surface(), surface_attrs=solid.surface_record()[1], samples=samples, cage=cage, cage_attrs=cage.summary(), field=field,
                 field_history=result.history, layers=layers, toolpaths=tp, program=program,
                 print_metrics=print_metrics, collision_maps={"printed": (tp.xyz, np.zeros(len(tp), bool))},
                 wall_s={"field": result.wall_time_s})
metrics = write_outputs(out, run, alpha_deg=45.0, beta_deg=30.0)
print(json.dumps({"modules": sorted(m.split(".")[0] for m in sys.modules if m.split(".")[0] in ("prefect", "storage", "tasks", "flows", "cli") and sys.modules[m] is not None), "metrics": metrics}, default=float))
'''


def test_the_pipeline_runs_from_the_core_alone(tmp_path: Path, small_part: Path) -> None:
    """Mesh in, G-code and report out through core calls only, with Prefect and the store unimportable."""
    done = subprocess.run([sys.executable, "-c", NOTEBOOK, str(small_part), str(tmp_path / "out")], cwd=REPO,
                          capture_output=True, text=True, timeout=900)
    assert done.returncode == 0, done.stderr[-3000:]
    report = json.loads(done.stdout.strip().splitlines()[-1])
    assert report["modules"] == []
    m = report["metrics"]
    assert m["n_layers"] > 5 and m["n_waypoints"] > 100 and m["loss.ca_violating_pairs"] == 0
    assert m["sf.overhang_area_fraction"] < m["sf.overhang_area_fraction_planar"]
    for name in ("print.gcode", "metrics.json", "report.md", "field.vtu", "model.ply", "figures/layers.png"):
        assert (tmp_path / "out" / name).is_file(), name
