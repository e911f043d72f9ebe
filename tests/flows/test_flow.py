"""The slicing flow end to end: output contract, cache hits, selective reruns, resume after a kill."""
from __future__ import annotations

import contextlib
import json
import os
import signal
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import pytest
import trimesh
import yaml

from conftest import REPO, fast_config
from neuralslicer.storage import ArtifactStore
from neuralslicer.cli.main import main

pytestmark = [pytest.mark.usefixtures("prefect_server"), pytest.mark.slow]   # end to end: not in `make test-fast`


def slice_cmd(model: Path, out: Path, cfg: Path, *extra: str) -> list[str]:
    """Arguments of `neuralslicer slice` for a small, fast run."""
    return ["slice", str(model), "--out", str(out), "--config", str(cfg), *extra]


def write_config(path: Path, **overrides: object) -> Path:
    """A fast configuration file."""
    path.write_text(yaml.safe_dump(fast_config(**overrides)))
    return path


def states(out: Path) -> dict[str, str]:
    """Task -> state of the last run in out."""
    return {r["task"]: r["state"] for r in json.loads((out / "run.json").read_text())["tasks"]}


def test_output_contract_cache_hit_and_selective_rerun(tmp_path, small_part, capsys):
    cfg = write_config(tmp_path / "cfg.yaml")
    out = tmp_path / "run"
    assert main(slice_cmd(small_part, out, cfg, "--objectives", "none")) == 0
    # the last lines name the files a user opens, with their paths (a preview where one was written)
    last = capsys.readouterr().out.strip().splitlines()[-3:]
    named = [line.split()[-1] for line in last if line.split()[-1].endswith(("print.gcode", "preview.html",
                                                                             "report.md"))]
    assert named[0] == str(out.resolve() / "print.gcode") and named[-1] == str(out.resolve() / "report.md")
    assert len(named) == (3 if (out / "preview.html").is_file() else 2)
    first = states(out)
    assert set(first.values()) == {"Completed"}
    for name in ("model.ply", "field.vtu", "metrics.json", "report.md", "samples_B.ply", "print.gcode",
                 "toolpaths/waypoints.csv", "toolpaths.vtp", "figures/layers.png", "figures/sf_histogram.png"):
        assert (out / name).is_file(), name
    layers = sorted((out / "layers").glob("layer_*.ply"))
    metrics = json.loads((out / "metrics.json").read_text())
    assert len(layers) == metrics["n_layers"] > 10
    for key in ("n_cage_elements", "sf.overhang_area_fraction", "sf.overhang_area_fraction_planar", "wall_s.cage",
                "model_genus", "cage_genus", "toolpath_length_mm", "n_waypoints", "estimated_print_time_s",
                "material_mm3", "n_collisions"):
        assert key in metrics, key
    # the identity field gives planar layers: the same overhang as planar, layers at increasing heights
    assert metrics["sf.overhang_area_fraction"] == pytest.approx(metrics["sf.overhang_area_fraction_planar"])
    # held out (the surface mesh, apart from B): the field's, the layers' and planar overhang agree as well
    held = [metrics[f"sf.heldout.overhang_area_fraction{k}"] for k in ("", "_layers", "_planar")]
    assert held[0] == pytest.approx(held[2], abs=1e-9) and held[1] == pytest.approx(held[2], abs=0.01)
    assert held[2] == pytest.approx(metrics["sf.overhang_area_fraction_planar"], abs=0.02)
    # the arm's underside (12 x 10 mm² of the 992 mm² of surface off the platform) overhangs
    assert metrics["sf.overhang_area_fraction_planar"] == pytest.approx(120 / 992, rel=0.1)
    z = [trimesh.load(p).vertices[:, 2].mean() for p in layers]
    assert np.all(np.diff(z) > 0)
    model = trimesh.load(out / "model.ply")
    assert model.is_watertight and model.volume == pytest.approx(1760.0, rel=1e-6)
    # the flow run is named after the model and the output folder, and publishes the report
    run = json.loads((out / "run.json").read_text())
    assert run["flow_run_name"] == "slice-lpart-run" and run["report_artifact"] == "slice-lpart"
    # run.json names the group of every step, and each is in the store
    from neuralslicer.storage import ArtifactStore

    assert {"model", "surface", "samples", "cage", "field", "layers", "toolpaths", "motion", "program"} <= set(run["groups"])
    assert all(ArtifactStore(run["store"], create=False).exists(g) for g in run["groups"].values())
    from prefect.client.orchestration import get_client
    from prefect.client.schemas.filters import ArtifactFilter, ArtifactFilterKey, ArtifactFilterType

    with get_client(sync_client=True) as client:
        arts = client.read_artifacts(artifact_filter=ArtifactFilter(key=ArtifactFilterKey(any_=["slice-lpart"])))
    assert arts and "Neural Slicer report" in str(arts[0].data)
    with get_client(sync_client=True) as client:   # and a progress artifact per step with a bar, ended at 100 %
        bars = client.read_artifacts(artifact_filter=ArtifactFilter(type=ArtifactFilterType(any_=["progress"])))
    assert any(a.data == 100 and "layers: done in" in (a.description or "") for a in bars), bars[-3:]

    assert main(slice_cmd(small_part, out, cfg, "--objectives", "none")) == 0
    assert set(states(out).values()) == {"Cached"}

    assert main(slice_cmd(small_part, out, cfg, "--objectives", "none", "--layer-height", "0.7")) == 0
    after = states(out)
    assert [t for t, s in after.items() if s == "Cached"] == ["model", "surface", "samples", "cage", "field"]
    assert [t for t, s in after.items() if s == "Completed"] == ["layers", "toolpaths", "motion", "program", "export"]
    assert json.loads((out / "metrics.json").read_text())["n_layers"] > metrics["n_layers"]
    assert len(list((out / "layers").glob("layer_*.ply"))) == json.loads((out / "metrics.json").read_text())["n_layers"]


def test_a_large_prints_export_in_two_rounds_writes_the_same_files(tmp_path, small_part, monkeypatch):
    """The export of a stored print shared in two rounds (the program's moves, then the toolpaths: a large print's
    way, here with the threshold at 0) writes the same preview, CSV, VTP, G-code and report as in one round."""
    import neuralslicer.run.outputs as outputs

    cfg = write_config(tmp_path / "cfg.yaml")
    assert main(slice_cmd(small_part, tmp_path / "one", cfg, "--objectives", "none")) == 0
    rounds: list[int] = []
    real = outputs.ExportJobs
    monkeypatch.setattr(outputs, "ExportJobs", lambda jobs: rounds.append(len(jobs)) or real(jobs))
    monkeypatch.setattr(outputs, "TWO_ROUNDS_WAYPOINTS", 0)
    assert main(slice_cmd(small_part, tmp_path / "two", cfg, "--objectives", "none",
                          "--store", str(tmp_path / "one" / "store.zarr"))) == 0
    assert len(rounds) == 2 and rounds[1] == 4            # the VTP and the three figures that draw the waypoints
    for name in ("preview.html", "toolpaths/waypoints.csv", "toolpaths.vtp", "print.gcode", "report.md"):
        assert (tmp_path / "one" / name).read_bytes() == (tmp_path / "two" / name).read_bytes(), name
    assert sorted(p.name for p in (tmp_path / "one" / "figures").iterdir()) == sorted(
        p.name for p in (tmp_path / "two" / "figures").iterdir())


def test_layers_lie_inside_the_solid(tmp_path, small_part):
    cfg = write_config(tmp_path / "cfg.yaml")
    out = tmp_path / "run"
    assert main(slice_cmd(small_part, out, cfg, "--objectives", "sf", "--max-steps", "10")) == 0
    from neuralslicer.model import implicit_solid, spec_for_file

    solid = implicit_solid(spec_for_file(small_part))
    for path in sorted((out / "layers").glob("layer_*.ply")):
        v = trimesh.load(path, process=False).vertices
        assert solid.H(v).max() <= 1e-6, path.name


def test_the_store_is_the_one_cache(tmp_path, small_part):
    from prefect.settings import PREFECT_LOCAL_STORAGE_PATH

    cfg = write_config(tmp_path / "cfg.yaml")
    out = tmp_path / "run"
    results = Path(PREFECT_LOCAL_STORAGE_PATH.value())
    before = set(results.rglob("*")) if results.exists() else set()
    assert main(slice_cmd(small_part, out, cfg, "--objectives", "none")) == 0
    # Prefect keeps no record of a step's result (nothing a planted file could turn into code), here or by the store
    assert (set(results.rglob("*")) if results.exists() else set()) == before
    assert not list(out.glob(".*prefect-results"))
    # a group gone from the store is computed again, and only that step: its digest (the later steps' keys) is the same
    run = json.loads((out / "run.json").read_text())
    ArtifactStore(run["store"]).remove(run["groups"]["cage"])
    assert main(slice_cmd(small_part, out, cfg, "--objectives", "none")) == 0
    after = states(out)
    assert after["cage"] == "Completed" and after["field"] == "Cached" and after["samples"] == "Cached"
    assert ArtifactStore(run["store"]).exists(run["groups"]["cage"])


def test_kill_and_resume(tmp_path, small_part):
    cfg = write_config(
        tmp_path / "cfg.yaml",
        # no early stop on met constraints: the run must still be going when it is killed
        neural={"optim": {"max_steps": 60, "checkpoint_every": 2, "convergence_window": 1000, "target_overhang": 0}},
    )
    out = tmp_path / "run"
    env = {**os.environ, "PREFECT_HOME": str(tmp_path / "prefect-home")}
    cmd = [sys.executable, "-m", "neuralslicer.cli", *slice_cmd(small_part, out, cfg, "--objectives", "sf,po")]
    proc = subprocess.Popen(cmd, cwd=REPO, env=env, stdout=subprocess.DEVNULL, stderr=subprocess.PIPE,
                            start_new_session=True)  # its own process group: the kill takes its Prefect server too
    ckpt_root = out / "store.zarr" / "lpart" / "checkpoints"
    deadline = time.monotonic() + 240
    try:
        while time.monotonic() < deadline and proc.poll() is None:
            steps = [p for p in ckpt_root.glob("*/step_*") if (p / "zarr.json").is_file()] if ckpt_root.exists() else []
            if len(steps) >= 2:
                break
            time.sleep(0.2)
        assert proc.poll() is None, f"the run ended before it could be killed: {proc.stderr.read().decode()[-2000:]}"
    finally:
        with contextlib.suppress(ProcessLookupError):
            os.killpg(proc.pid, signal.SIGKILL)
        proc.wait(timeout=30)
    assert not (out / "metrics.json").exists()
    rerun = subprocess.run(cmd, cwd=REPO, env=env, capture_output=True, text=True, timeout=600)
    assert rerun.returncode == 0, rerun.stderr[-3000:]
    # output to a pipe (not a terminal): one line as each computed step starts and ends, progress lines
    lines = rerun.stderr.splitlines()
    for step in ("field", "layers", "toolpaths", "motion", "program", "export"):
        assert f"{step}: started" in lines and any(ln.startswith(f"{step}: done in ") for ln in lines), step
    assert not any(ln.startswith("cage: started") for ln in lines)               # cached: no work, no line
    assert sum(ln.startswith("optimise: ") and "/60 (" in ln for ln in lines) >= 10, "\n".join(lines[-60:])
    st = states(out)
    assert [st[t] for t in ("model", "surface", "samples", "cage")] == ["Cached"] * 4
    assert st["field"] == "Completed"
    from neuralslicer.storage import ArtifactStore

    store = ArtifactStore(out / "store.zarr")
    field = [f"lpart/field/{d}" for d in store.children("lpart/field")]
    attrs = store.attrs(field[0])
    assert attrs["resumed_from_step"] >= 2
    assert attrs["steps"] == 60
    assert len(store.read(field[0], ["history/total"])[0]["history/total"]) == 60


BAD = {
    "missing": (None, "no such file"),
    "garbage.stl": (b"this is not a mesh\x00\x01\x02", ""),
    "empty.stl": (b"", ""),
    "nan.tet": (b"4 vertices\n1 tets\n0 0 0\n1 0 0\n0 nan 0\n0 0 1\n4 0 1 2 3\n", "nan"),
    "flat.obj": (b"v 0 0 0\nv 1 0 0\nv 0 1 0\nv 1 1 0\nf 1 2 3\nf 2 4 3\n", ""),
}


@pytest.mark.parametrize("name", sorted(BAD))
def test_bad_input_is_one_line_exit_2_and_no_output(tmp_path, name, capsys):
    content, needle = BAD[name]
    path = tmp_path / name
    if content is not None:
        path.write_bytes(content)
    out = tmp_path / "out"
    code = main(["slice", str(path), "--out", str(out), "--objectives", "none"])
    err = capsys.readouterr().err.strip()
    assert code == 2
    assert len(err.splitlines()) == 1, err
    assert err.startswith("neuralslicer: error: ") and str(path) in err
    assert needle.lower() in err.lower()
    assert not out.exists()


def test_unknown_option_is_one_line_exit_2(tmp_path, small_part, capsys):
    with pytest.raises(SystemExit) as exc:
        main(["slice", str(small_part), "--out", str(tmp_path / "o"), "--frobnicate", "3"])
    assert exc.value.code == 2
    err = capsys.readouterr().err.strip()
    assert len(err.splitlines()) == 1 and "--frobnicate" in err
    assert not (tmp_path / "o").exists()


def test_default_objectives_are_print_head_aware_with_the_local_constraint(tmp_path, small_part):
    # enough steps to leave the planar start on every cage (with 20, a run whose first steps raised
    # the loss returned its best iterate, the planar start); the constraint stop ends it earlier
    # with the command's collision refinements (not the fast configuration's none): the pool is a sample of the
    # solid, so on some cages (fTetWild's are not bit-reproducible) the first print has a stray hit or two that a
    # refinement round clears; the blend and the smoothing retries stay off, so the printed field is optimised
    cfg = write_config(tmp_path / "cfg.yaml", neural={"optim": {"max_steps": 300, "checkpoint_every": 50}},
                       collision_refinements=3)
    out = tmp_path / "run"
    assert main(slice_cmd(small_part, out, cfg)) == 0
    metrics = json.loads((out / "metrics.json").read_text())
    assert metrics["field.objectives"] == "sf,po,gc,ca"
    # L_CA = 0 holds in the stored field, the pool sees no head collision, the program has none
    assert metrics["loss.ca_violating_pairs"] == 0 and metrics["loss.ca"] == 0
    assert metrics["loss.gc_colliding_pairs"] == 0 and "loss.gc" in metrics
    assert metrics["n_collisions"] == 0 and metrics["field.blend_planar"] == 0.0
    # the first print is clean or nearly so (stray hits only: the pool saw the head's reach)
    assert metrics.get("collision_resolution.0.collisions", 0) <= 10
    assert metrics["sf.overhang_area_fraction"] < metrics["sf.overhang_area_fraction_planar"]
    assert (out / "figures" / "collisions.png").is_file()


def test_collisions_fall_back_to_a_collision_free_blend(tmp_path, small_part):
    # a print head whose wide cone grazes the part as soon as the tool tilts: the optimised field collides
    from neuralslicer.motion import load_profile

    profile = load_profile("table_bc_linuxcnc").model_dump(mode="json")
    profile["nozzle"] = {"cone_half_angle_deg": 85.0, "cone_length": 3.0, "holder_radius": 1.0, "holder_length": 1.0}
    machine = tmp_path / "wide_nozzle.yaml"
    machine.write_text(yaml.safe_dump(profile))
    out = tmp_path / "run"
    keep = write_config(tmp_path / "keep.yaml", machine=str(machine))
    assert main(slice_cmd(small_part, out, keep, "--objectives", "sf")) == 0
    colliding = json.loads((out / "metrics.json").read_text())
    colliding_gcode = (out / "print.gcode").read_bytes()
    assert colliding["n_collisions"] > 0 and colliding["field.blend_planar"] == 0.0
    assert colliding["sf.overhang_area_fraction"] < colliding["sf.overhang_area_fraction_planar"]

    # the paper's fallback: one re-optimisation with larger harmonic weights and CA, reported after the first
    retry = write_config(tmp_path / "retry.yaml", machine=str(machine), collision_retries=1, collision_fallback="none")
    assert main(slice_cmd(small_part, out, retry, "--objectives", "sf", "--keep-attempts")) == 0
    from neuralslicer.storage import ArtifactStore
    from neuralslicer.tasks.release import RELEASED

    store = ArtifactStore(str(out / "store.zarr"), create=False)
    motions = [store.attrs(f"lpart/motion/{d}") for d in store.children("lpart/motion")]
    assert len(motions) == 2 and not any(RELEASED in a for a in motions)   # --keep-attempts: both whole
    metrics = json.loads((out / "metrics.json").read_text())
    runs = json.loads((out / "run.json").read_text())["tasks"]
    assert [r["state"] for r in runs if r["task"] == "field"] == ["Cached", "Completed"]
    assert metrics["collision_resolution.0.collisions"] == colliding["n_collisions"]
    assert metrics["collision_resolution.1.stage"].startswith("re-optimised, harmonic x")
    assert metrics["n_collisions"] == metrics["collision_resolution.1.collisions"]
    assert metrics["field.objectives"] == "ca,sf"  # the retry adds the local collision constraint

    # the last resort: the smallest blend toward planar layers whose print is collision-free
    blend = write_config(tmp_path / "blend.yaml", machine=str(machine), collision_retries=0, collision_fallback="blend",
                         collision_blend_steps=2)
    assert main(slice_cmd(small_part, out, blend, "--objectives", "sf")) == 0
    metrics = json.loads((out / "metrics.json").read_text())
    tasks = [r["task"] for r in json.loads((out / "run.json").read_text())["tasks"]]
    assert metrics["n_collisions"] == 0 and 0.0 < metrics["field.blend_planar"] <= 1.0
    assert tasks.count("field") == 1 and tasks.count("field_blend") >= 2
    # every field printed on the way is reported: the first is the colliding run above, the blends follow
    stages = sorted({int(k.split(".")[1]) for k in metrics if k.startswith("collision_resolution.")})
    rows = [{f: metrics[f"collision_resolution.{i}.{f}"] for f in ("stage", "collisions", "overhang_area_fraction")}
            for i in stages]
    assert len(rows) == 1 + tasks.count("field_blend")
    assert rows[0]["stage"] == "optimised" and rows[0]["collisions"] == colliding["n_collisions"]
    assert rows[0]["overhang_area_fraction"] == pytest.approx(colliding["sf.overhang_area_fraction"], abs=1e-12)
    assert all(r["stage"].startswith("planar blend t = ") for r in rows[1:])
    chosen = [r for r in rows if r["stage"].startswith(f"planar blend t = {metrics['field.blend_planar']:.4g}")]
    assert chosen and chosen[-1]["collisions"] == 0
    assert chosen[-1]["overhang_area_fraction"] == pytest.approx(metrics["sf.overhang_area_fraction"], abs=1e-12)
    report = (out / "report.md").read_text()
    assert "## Collision resolution" in report and "figures/collisions.png" in report
    assert (out / "figures" / "collisions.png").is_file()
    assert metrics["field.objectives"] == "sf"
    # the blend keeps part of the optimised field's gain unless it had to go all the way to planar layers
    if metrics["field.blend_planar"] < 1.0:
        assert metrics["sf.overhang_area_fraction"] <= metrics["sf.overhang_area_fraction_planar"]

    # the prints not kept were released from the store (their metrics and collisions stay, the report above read
    # them): whole are only the retry's print, kept by the second run, and the chosen blend's
    for step in ("toolpaths", "motion"):
        groups = [store.attrs(f"lpart/{step}/{d}") for d in store.children(f"lpart/{step}")]
        assert len(groups) == 2 + tasks.count("field_blend") and sum(RELEASED not in a for a in groups) == 2
    # the first run again: its print, released by the second, is printed again, whole and the same
    assert main(slice_cmd(small_part, out, keep, "--objectives", "sf")) == 0
    runs = json.loads((out / "run.json").read_text())["tasks"]
    assert [r["state"] for r in runs if r["task"] in ("toolpaths", "motion")] == ["Cached"] * 2 + ["Completed"] * 2
    assert (out / "print.gcode").read_bytes() == colliding_gcode
    assert json.loads((out / "metrics.json").read_text())["n_collisions"] == colliding["n_collisions"]


@pytest.mark.parametrize("model", ["spec.yaml", "part_scan.pcd"])
def test_point_clouds_slice_end_to_end(tmp_path, model):
    """The shipped point clouds (with normals, through a spec; a noisy scan without normals, as a bare file) slice
    from points to G-code: the optimised field takes the part's overhangs away and its print is complete."""
    source = REPO / "neuralslicer" / "examples" / "points" / model
    cfg = write_config(tmp_path / "cfg.yaml", neural={"optim": {"max_steps": 20, "checkpoint_every": 5}})
    out = tmp_path / "run"
    assert main(slice_cmd(source, out, cfg, "--objectives", "sf,po")) == 0
    metrics = json.loads((out / "metrics.json").read_text())
    assert metrics["model_genus"] == 1  # the block's through hole survives the reconstruction
    assert metrics["n_layers"] > 5 and metrics["n_waypoints"] > 1000 and (out / "print.gcode").stat().st_size > 0
    assert metrics["sf.overhang_area_fraction"] <= metrics["sf.overhang_area_fraction_planar"]


def test_collisions_of_the_print_refine_the_collision_term(tmp_path, small_part):
    """A colliding print's collisions refine L_GC's pool there (field step with refine_prints), warm-started from
    the weights of the field that printed it; the flow takes this path whenever gc is an objective."""
    from neuralslicer.config import SliceConfig
    from neuralslicer.motion import load_profile
    from neuralslicer.storage import ArtifactRef, ArtifactStore
    from neuralslicer.tasks.codec import read_part_collisions
    from neuralslicer.tasks.steps import field_task

    profile = load_profile("table_bc_linuxcnc").model_dump(mode="json")
    profile["nozzle"] = {"cone_half_angle_deg": 85.0, "cone_length": 3.0, "holder_radius": 1.0, "holder_length": 1.0}
    machine = tmp_path / "wide_nozzle.yaml"
    machine.write_text(yaml.safe_dump(profile))
    cfg = write_config(tmp_path / "cfg.yaml", machine=str(machine),
                       neural={"optim": {"max_steps": 20, "checkpoint_every": 5, "refine": {"steps": 10}}})
    out = tmp_path / "run"
    assert main(slice_cmd(small_part, out, cfg, "--objectives", "sf")) == 0  # blind to the head: it collides
    metrics = json.loads((out / "metrics.json").read_text())
    assert metrics["n_part_collisions"] + metrics["n_platform_collisions"] > 0
    root = str(out / "store.zarr")
    store = ArtifactStore(root, create=False)
    ref = {step: ArtifactRef(root, f"lpart/{step}/{d}", d)
           for step in ("model", "samples", "cage", "field", "motion") for d in store.children(f"lpart/{step}")}
    hits, witnesses = read_part_collisions(ref["motion"])
    assert len(hits) > 0 and np.isfinite(witnesses).all()
    neural = SliceConfig.from_yaml(cfg).neural
    refined = field_task(store=root, model=ref["model"], cage=ref["cage"], samples=ref["samples"], stress_samples=None,
                         objectives=["sf", "gc"], config=neural, refine_prints=[ref["motion"]], warm_start=ref["field"])
    attrs = store.attrs(refined.path)
    record = attrs["refinement"]
    assert record["warm_start"] and record["hits"] == len(hits) and record["added_points"] > 0
    assert attrs["steps"] <= 10  # the refinement budget, from the earlier weights


def test_refinement_rounds_do_not_use_up_the_retries(tmp_path, small_part):
    """With gc and a head that still hits after the first optimisation, the flow refines L_GC around the hits
    (collision_refinements rounds, from the field that printed them) even with no smoothing retry allowed, then
    stops there; every print on the way is reported."""
    from neuralslicer.motion import load_profile

    profile = load_profile("table_bc_linuxcnc").model_dump(mode="json")
    profile["nozzle"] = {"cone_half_angle_deg": 85.0, "cone_length": 3.0, "holder_radius": 1.0, "holder_length": 1.0}
    machine = tmp_path / "wide_nozzle.yaml"
    machine.write_text(yaml.safe_dump(profile))
    # a weak head term (w_gc 1e-6): the field leaves its saddle as the SF-only one does, and still collides
    cfg = write_config(tmp_path / "cfg.yaml", machine=str(machine), collision_refinements=1, collision_retries=0,
                       neural={"optim": {"max_steps": 20, "checkpoint_every": 5, "refine": {"steps": 5}},
                               "loss": {"w_gc": 1e-6}})
    out = tmp_path / "run"
    assert main(slice_cmd(small_part, out, cfg, "--objectives", "sf,gc")) == 0
    metrics = json.loads((out / "metrics.json").read_text())
    fields = [r for r in json.loads((out / "run.json").read_text())["tasks"] if r["task"] == "field"]
    assert len(fields) == 2 and metrics["collision_resolution.0.collisions"] > 0
    assert metrics["collision_resolution.0.stage"] == "optimised"
    # heads below the platform in the first print: the refined field's floor (platform) term weighs 3x more
    assert metrics["collision_resolution.0.platform_collisions"] > 0
    assert metrics["collision_resolution.1.stage"] == "refined around the collisions of 1 print(s), floor weight x3"
    assert "collision_resolution.2.stage" not in metrics and metrics["field.steps"] <= 5
    from neuralslicer.storage import ArtifactStore
    store = ArtifactStore(str(out / "store.zarr"), create=False)
    weights = sorted(store.attrs(f"lpart/field/{d}")["config"]["loss"]["gc_floor_weight"]
                     for d in store.children("lpart/field"))
    from neuralslicer.neural.config import LossConfig, RefineConfig
    w = LossConfig().gc_floor_weight
    assert weights == [w, w * RefineConfig().floor_weight_factor]
