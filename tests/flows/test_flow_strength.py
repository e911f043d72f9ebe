"""Strength in the pipeline: the infill decided per slice, --verify's three parts, strength rounds, bad load cases."""
from __future__ import annotations

import json
from pathlib import Path

import pytest
import trimesh
import yaml

from neuralslicer.cli.main import main
from conftest import fast_config
from neuralslicer.config import SliceConfig
from neuralslicer.model.spec import load_spec
from neuralslicer.run.run_metrics import RunMetrics

pytestmark = [pytest.mark.usefixtures("prefect_server"), pytest.mark.slow]   # end to end: not in `make test-fast`


def beam_spec(tmp_path: Path, force_n: float = -40.0) -> Path:
    """A 40 x 8 x 8 mm cantilever clamped at x = 0, loaded down at its free end."""
    trimesh.creation.box(bounds=[[0, 0, 0], [40, 8, 8]]).export(tmp_path / "beam.stl")
    spec = tmp_path / "beam.yaml"
    spec.write_text(yaml.safe_dump({
        "components": [{"type": "mesh", "file": "beam.stl"}],
        "fea": {"voxels": 8000, "supports": [{"box": [[-1, -1, -1], [0.5, 9, 9]]}],
                "loads": [{"box": [[39.5, -1, -1], [41, 9, 9]], "force_n": [0, 0, force_n]}]}}))
    return spec


def config(tmp_path: Path, **toolpath: object) -> Path:
    """A fast configuration for the beam (line width 0.5: the stress lines need a few per layer)."""
    cfg = fast_config(toolpath={"line_width": 0.5, "n_shells": 1, **toolpath})
    path = tmp_path / "cfg.yaml"
    path.write_text(yaml.safe_dump(cfg))
    return path


def test_the_infill_follows_the_stress_by_default_only_with_a_load_case_and_sr(tmp_path) -> None:
    """auto: stress-following with an fea block and sr among the objectives, else zig-zag; an explicit choice stays."""
    spec = load_spec(beam_spec(tmp_path))
    plain = spec.model_copy(update={"fea": None})
    assert SliceConfig().toolpath_for(spec).infill == "stress"
    assert SliceConfig().toolpath_for(plain).infill == "zigzag"
    assert SliceConfig(objectives=["sf"]).toolpath_for(spec).infill == "zigzag"
    assert SliceConfig.checked({"toolpath": {"infill": "zigzag"}}, "t").toolpath_for(spec).infill == "zigzag"
    assert SliceConfig.checked({"toolpath": {"infill": "stress"}}, "t").needs_fea(plain)


def test_stress_infill_without_a_load_case_is_refused(tmp_path, small_part, capsys) -> None:
    """--infill stress on a model without an fea block: one line naming the spec's missing block, nothing written."""
    assert main(["slice", str(small_part), "--out", str(tmp_path / "out"), "--infill", "stress"]) == 2
    err = capsys.readouterr().err.strip()
    assert len(err.splitlines()) == 1 and "fea" in err and "toolpath.infill: stress" in err, err
    assert not (tmp_path / "out").exists()


def test_a_load_case_without_stress_is_refused_in_one_line(tmp_path, capsys) -> None:
    """A load of 0 N: the FEA would find no stress anywhere; the slice stops before any work, naming the loads."""
    assert main(["slice", str(beam_spec(tmp_path, force_n=0.0)), "--out", str(tmp_path / "out"),
                 "--objectives", "none", "--infill", "stress"]) == 2
    err = capsys.readouterr().err.strip()
    assert len(err.splitlines()) == 1 and "fea.loads" in err, err


def test_stress_nowhere_significant_falls_back_to_zigzag_and_says_so(tmp_path) -> None:
    """No layer with an in-layer stress over the threshold (here set above any): zig-zag throughout, and the report
    says why."""
    out = tmp_path / "run"
    cfg = config(tmp_path, infill="stress", stress_threshold=1e6)
    assert main(["slice", str(beam_spec(tmp_path)), "--out", str(out), "--config", str(cfg), "--objectives", "none"]) == 0
    metrics = json.loads((out / "metrics.json").read_text())
    assert metrics["toolpath.stress_infill_fraction"] == 0.0
    assert "No layer has a significant in-layer stress" in (out / "report.md").read_text()


def test_verify_prints_three_parts_and_strength_rounds_re_optimise_against_the_printed_stress(tmp_path) -> None:
    """A cantilever with sr and two strength rounds: the second round's T comes from the FEA of the first print (a
    second fea_printed and stress_samples run), both rounds are reported with their strain and how far tau_max
    turned, and --verify compares planar + zig-zag, planar + stress infill and the printed program."""
    out = tmp_path / "run"
    assert main(["slice", str(beam_spec(tmp_path)), "--out", str(out), "--config", str(config(tmp_path)),
                 "--objectives", "sf,sr", "--sr-rounds", "2", "--verify"]) == 0
    tasks = [r["task"] for r in json.loads((out / "run.json").read_text())["tasks"]]
    assert tasks.count("fea_printed") == 2 and tasks.count("stress_samples") == 2 and tasks.count("field") == 2
    metrics = json.loads((out / "metrics.json").read_text())
    for i in (0, 1):
        assert metrics[f"sr_rounds.{i}.max_strain"] > 0 and 0 <= metrics[f"sr_rounds.{i}.tau_turn_median_deg"] <= 90
    for part in ("planar_zigzag", "planar_stress", "printed"):
        assert metrics[f"fea.{part}.max_strain"] > 0 and 0 <= metrics[f"fea.{part}.aligned_fraction"] <= 1
    assert metrics["fea.max_strain"] == metrics["fea.printed.max_strain"]
    # a run with sr and --verify has every headline figure the schema names: its keys are the ones runs write
    figures = RunMetrics.of(metrics)
    assert [name for name, value in figures if value is None] == []
    assert figures.max_strain == metrics["fea.max_strain"] and figures.field_steps == metrics["field.steps"]
    # the stress infill along the beam's bending stress beats the zig-zag on the same planar layers
    assert metrics["fea.planar_stress.aligned_fraction"] > 0.8 > metrics["fea.planar_zigzag.aligned_fraction"]
    assert metrics["fea.planar_stress.max_strain_p99"] < metrics["fea.planar_zigzag.max_strain_p99"]
    report = (out / "report.md").read_text()
    assert "## Strength of the printed part" in report and "## Strength rounds" in report
    for name in ("strain_maps.png", "filament_angles.png", "stress_turn.png", "strain_histogram.png"):
        assert (out / "figures" / name).is_file(), name
