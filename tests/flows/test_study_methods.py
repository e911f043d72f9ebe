"""`neuralslicer study methods`: the Neural Slicer, the S3-Slicer baseline and planar layers side by side."""
from __future__ import annotations

import json

import pytest
import yaml

from conftest import fast_config
from neuralslicer.cli.main import main

pytestmark = [pytest.mark.usefixtures("prefect_server"), pytest.mark.slow]   # end to end: not in `make test-fast`


def test_methods_study_on_a_part_with_a_flat_overhang(tmp_path, small_part):
    cfg = tmp_path / "cfg.yaml"
    cfg.write_text(yaml.safe_dump(fast_config(neural={"optim": {"max_steps": 20, "checkpoint_every": 5}})))
    out = tmp_path / "methods"
    assert main(["study", "methods", str(small_part), "--out", str(out), "--config", str(cfg), "--objectives", "sf,po",
                 "--workers", "1"]) == 0
    study = json.loads((out / "study.json").read_text())
    rows = {b["name"]: b for b in study["branches"]}
    assert set(rows) == {"neural", "s3", "s3_oneshot", "planar"} and all(b["status"] == "completed" for b in rows.values())
    m = {name: b["metrics"] for name, b in rows.items()}
    # one cage, one sample set: the planar overhang is the same number in every branch
    assert len({b["cage"]["path"] for b in rows.values()}) == 1
    planar = m["planar"]["sf.heldout.overhang_area_fraction"]
    assert planar > 0.05  # the 12 mm arm's underside
    for method in ("neural", "s3", "s3_oneshot"):  # every method take the flat overhang away, judged on points B never held
        assert m[method]["sf.heldout.overhang_area_fraction"] < 0.5 * planar, method
        assert m[method]["sf.heldout.overhang_area_fraction_layers"] < 0.5 * planar, method
    assert m["s3"]["field.kind"] == "s3" and m["s3"]["field.steps"] > 0 and m["s3"]["field.energy_by_iteration"]
    assert m["s3_oneshot"]["field.kind"] == "s3_oneshot"
    text = (out / "study.md").read_text()
    for column in ("overhang held out", "overhang of the layers", "collisions", "field s"):
        assert f"| {column} |" in text or f" {column} |" in text, column
    assert (out / "figures" / "learning_curves.png").is_file()
