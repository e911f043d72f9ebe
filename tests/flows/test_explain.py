"""`neuralslicer explain RUN`: which steps of a run reused a result, and why the others computed one."""
from __future__ import annotations

import json
from pathlib import Path

import pytest
import yaml

from conftest import fast_config
from neuralslicer.cli.main import main


def _explain(capsys: pytest.CaptureFixture[str], run: Path) -> dict[str, dict]:
    """The steps of `explain --json`, by task name (the last task run of a name)."""
    assert main(["explain", str(run), "--json"]) == 0
    return {s["task"]: s for s in json.loads(capsys.readouterr().out)["steps"]}


@pytest.mark.slow   # three small slices (~30 s)
def test_explain_says_what_a_run_reused_and_what_made_each_step_compute(prefect_server: None, small_part: Path,
                                                                        tmp_path: Path, capsys) -> None:
    store = tmp_path / "store.zarr"

    def slice_(out: str, in_store: Path = store, **layers: float) -> Path:
        cfg = tmp_path / f"{out}.yaml"
        config = fast_config()
        config["layers"] = {**config["layers"], **layers}
        cfg.write_text(yaml.safe_dump(config))
        assert main(["slice", str(small_part), "--out", str(tmp_path / out), "--config", str(cfg), "--objectives",
                     "none", "--store", str(in_store)]) == 0
        capsys.readouterr()   # the slice's own output
        return tmp_path / out

    first = _explain(capsys, slice_("a"))
    assert first and all(s["computed"] for s in first.values())
    assert first["layers"]["reason"] == "no earlier result of this step for this model in the store"
    again = _explain(capsys, slice_("b"))   # the same inputs, another folder: only the export is new
    assert [t for t, s in again.items() if s["computed"]] == ["export"]
    assert again["layers"]["reason"].startswith("reused from the store: made by flow run ")
    thicker = _explain(capsys, slice_("c", layer_height=0.9))
    computed = {t for t, s in thicker.items() if s["computed"]}
    assert {"layers", "toolpaths", "motion", "program", "export"} <= computed
    assert not computed & {"model", "surface", "samples", "cage", "field"}
    assert "config.layer_height: 1.0 -> 0.9" in thicker["layers"]["reason"]
    assert "its input layers is another result" in thicker["toolpaths"]["reason"]
    # another store on this machine: every step computed, the cage taken from the machine's cage cache
    elsewhere = _explain(capsys, slice_("d", in_store=tmp_path / "other.zarr"))
    assert all(s["computed"] for s in elsewhere.values())
    assert elsewhere["cage"]["reason"].startswith("taken from the machine's cage cache, not built; no earlier result")
    assert "cage cache" not in elsewhere["samples"]["reason"]


def test_explain_refuses_a_folder_that_is_not_a_run(tmp_path: Path, capsys) -> None:
    assert main(["explain", str(tmp_path)]) == 2
    assert "run.json: no such file" in capsys.readouterr().err
