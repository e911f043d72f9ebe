"""The table of steps (neuralslicer/run/step_table.py): both runners made from it, the cache keys of the hand-written tasks
it replaced kept, and a step added to it running both ways."""
from __future__ import annotations

from pathlib import Path
from typing import Any

import numpy as np
import pytest

from neuralslicer.config import SliceConfig
from neuralslicer.motion.profile import load_profile
from neuralslicer.run.step_table import BY_NAME, STEPS, Step, StepContext
from neuralslicer.storage import ArtifactRef, ArtifactStore
from neuralslicer.storage.layout import DIMENSIONS
from neuralslicer.tasks.codec import DECODERS
from neuralslicer.tasks.steps import TASKS, step_task

#: the output group of every step for fixed parameters, as the hand-written tasks before the table computed it: the
#: table keeps every cache key (a store written before it is reused as it is)
KEYS_BEFORE = {
    "cage": "part/cage/1c0b6c2eda6c9c1b378f", "fea": "part/fea/5692cb1a22916ef08630",
    "fea_printed": "part/fea_printed/925cde241224c880e102", "field": "part/field/7ebecc50100f283aca9a",
    "field_blend": "part/field_blend/55aa37d3998ad6fbbcfa", "field_s3": "part/field_s3/bc0e8fafd62fa8e3deec",
    "field_s3_oneshot": "part/field_s3_oneshot/84cfceb9306011105b9a", "layers": "part/layers/6d421e1622fcf804183e",
    "model": "part/model/6652941b9703ef57133e", "motion": "part/motion/1490ed8281721064e472",
    "program": "part/program/a71a125c70ec2d8318e3", "samples": "part/samples/661cef373de5ccb30d5d",
    "stress_samples": "part/stress_samples/848992dbed65bb3d69d0", "surface": "part/surface/2686f91370d2143d7c45",
    "toolpaths": "part/toolpaths/c1354bc5d5f71d0041e6", "verify": "part/verify/8ee178f7be0767d8bbdf",
}


def _ref(kind: str) -> ArtifactRef:
    """A made-up input of this kind (its digest named after it)."""
    return ArtifactRef("/s", f"part/{kind}/d{kind}", f"d{kind}")


def _parameters() -> dict[str, dict[str, Any]]:
    """Fixed parameters of every step (inputs as refs of made-up digests, the default settings)."""
    c = SliceConfig()
    machine = load_profile(c.machine)
    r = _ref
    fea_of = {"model": r("model"), "fea": r("fea"), "cage": r("cage"), "field": r("field")}
    field_in = {"model": r("model"), "cage": r("cage"), "samples": r("samples"), "stress_samples": None}
    return {
        "model": {"name": "part", "spec": None, "content": "abc"}, "surface": {"model": r("model")},
        "samples": {"model": r("model"), "config": c.samples},
        "cage": {"model": r("model"), "samples": r("samples"), "config": c.cage}, "fea": {"model": r("model")},
        "stress_samples": {"model": r("model"), "fea": r("fea")},
        "field": {**field_in, "objectives": ["sf", "gc"], "config": c.neural},
        "field_s3": {**field_in, "objectives": ["sf"], "config": c.s3},
        "field_s3_oneshot": {**field_in, "objectives": ["sf"], "config": c.s3_oneshot},
        "field_blend": {"cage": r("cage"), "field": r("field"), "planar": 0.25},
        "layers": {"model": r("model"), "cage": r("cage"), "field": r("field"), "config": c.layers},
        "toolpaths": {"model": r("model"), "layers": r("layers"), "config": c.toolpath, "machine": machine,
                      "t_max": c.layers.t_max, "fea": None},
        "motion": {"model": r("model"), "toolpaths": r("toolpaths"), "config": c.toolpath, "machine": machine},
        "program": {"motion": r("motion")},
        "fea_printed": {**fea_of, "motion": r("motion")},
        "verify": {**fea_of, "motion": r("motion"), "layer_config": c.layers, "toolpath_config": c.toolpath},
    }


def test_every_step_keeps_the_cache_key_of_its_hand_written_task() -> None:
    parameters = _parameters()
    assert set(parameters) == set(BY_NAME) == set(TASKS)
    made = {name: TASKS[name].pipeline.output({"store": "/s", **p}).path for name, p in parameters.items()}
    assert made == KEYS_BEFORE


#: the field steps' and the export's keys with stress samples T given, from before T's parameter was renamed from
#: ``stress`` to ``stress_samples`` (the keys still name it ``stress``)
KEYS_WITH_T = {"field": "part/field/0311b337d9c9110ada35", "field_s3": "part/field_s3/d75fea3b5eb81746451f",
               "field_s3_oneshot": "part/field_s3_oneshot/29df056f8e77ae80397b",
               "export": "part/export/2c50068da4b861399fd3"}


def test_a_renamed_parameter_keeps_its_key() -> None:
    from neuralslicer.tasks.export import export_task

    c = SliceConfig()
    base = {"store": "/s", **{k: _ref(k) for k in ("model", "cage", "samples", "stress_samples")},
            "objectives": ["sf", "sr"]}
    made = {name: TASKS[name].pipeline.output({**base, "config": cfg}).path
            for name, cfg in (("field", c.neural), ("field_s3", c.s3), ("field_s3_oneshot", c.s3_oneshot))}
    export = {"store": "/s", "out_dir": "/o", "verify": None, "robot": False, "alpha_deg": 45.0, "beta_deg": 20.0,
              **{k: _ref(k) for k in ("model", "surface", "samples", "cage", "field", "layers", "motion",
                                      "stress_samples")}}
    made["export"] = export_task.pipeline.output(export).path
    assert made == KEYS_WITH_T
    key = TASKS["field"].pipeline.key_record({**base, "config": c.neural})
    assert key["inputs"]["stress"] == "part/stress_samples/dstress_samples" and "stress_samples" not in key["inputs"]


def test_a_task_has_its_core_functions_parameters_and_every_stored_kind_a_reader() -> None:
    import inspect

    for s in STEPS:
        core = [n for n in inspect.signature(s.compute).parameters if n != "ctx"]
        assert list(TASKS[s.name].pipeline.signature.parameters) == ["store", *s.key, *core], s.name
        assert TASKS[s.name].name == s.name and TASKS[s.name].pipeline.version == s.version
        assert s.name in DIMENSIONS, f"{s.name}: no dimension names in storage/layout.py"
    read = {s.name for s in STEPS} - {"program"}     # the G-code is read by the export only, a chunk at a time
    assert read <= set(DECODERS), read - set(DECODERS)
    with pytest.raises(KeyError, match="no step 'layer'; the steps: model, surface"):
        from neuralslicer.run.step_table import step

        step("layer")


def centre_step(samples: Any, weight: float, *, ctx: StepContext) -> np.ndarray:
    """A made-up step: the area-weighted centre of samples B, scaled."""
    ctx.log.info("centre of %d samples", len(samples.points))
    return weight * np.average(samples.points, axis=0, weights=samples.areas)


@pytest.mark.slow   # a Prefect server and a flow (~15 s): the full suite runs it, `make test-fast` does not
def test_a_step_added_to_the_table_runs_both_ways(prefect_server: None, small_part: Path, tmp_path: Path,
                                                  monkeypatch: pytest.MonkeyPatch) -> None:
    from prefect import flow

    from neuralslicer.flows.slice import RunLog, TaskSteps
    from neuralslicer.model.spec import spec_for_file
    from neuralslicer.run.in_process import InProcessSteps

    new = Step("centre", "the centre of B (a test)", "1", centre_step,
               lambda c: ({"centre": np.asarray(c)[None]}, {"units": "mm"}))
    monkeypatch.setitem(BY_NAME, "centre", new)
    monkeypatch.setitem(TASKS, "centre", step_task(new))
    monkeypatch.setitem(DIMENSIONS, "centre", {"centre": ("row", "spatial")})
    config = SliceConfig().samples.model_copy(update={"n_samples": 400})

    steps = InProcessSteps()
    model = steps.run("model", spec=spec_for_file(small_part))
    here = steps.run("centre", samples=steps.run("samples", model=model, config=config), weight=2.0)
    assert set(steps.wall_s) == {"model", "samples", "centre"}

    store = str(tmp_path / "store.zarr")

    @flow
    def centre_flow() -> tuple[ArtifactRef, list[str]]:
        log = RunLog()
        task_steps = TaskSteps(log, store)
        samples = task_steps.run("samples", model=task_steps.run("model", spec=spec_for_file(small_part)),
                                 config=config)
        ref = task_steps.run("centre", samples=samples, weight=2.0)
        assert task_steps.run("centre", samples=samples, weight=2.0) == ref     # the store holds it: reused
        return ref, [t.state for t in log.tasks]

    ref, states = centre_flow()
    assert states == ["Completed", "Completed", "Completed", "Cached"]
    arrays, attrs = ArtifactStore(store, create=False).read(ref.path)
    assert ref.path.startswith("lpart/centre/") and attrs["units"] == "mm" and attrs["key"]["version"] == "1"
    np.testing.assert_allclose(arrays["centre"][0], here, rtol=0, atol=1e-12)
    assert attrs["key"]["parameters"]["weight"] == 2.0

