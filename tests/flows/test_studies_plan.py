"""Study planning without running the pipeline: branches, user fields, task runners, command-line errors."""
from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
from prefect.task_runners import ThreadPoolTaskRunner

from neuralslicer.flows.branch import make_user_field
from neuralslicer.tasks.codec import store_user_field
from prefect_dask import DaskTaskRunner
from neuralslicer.flows.studies import (StudyOptions, ablation_branches, batch_branches, cage_branches, initial_guess_branches,
                           methods_branches, task_runner)
from neuralslicer.flows.study_report import markdown_table, table_rows
from neuralslicer.cli.main import main as studies_main
from neuralslicer.errors import InputError
from neuralslicer.neural.initial_guess import user_field_on_cage
from neuralslicer.storage import ArtifactStore
from studies_common import tiny_config, torus_file


def test_cage_branches_vary_only_the_element_count(tmp_path: Path) -> None:
    """One branch per count, each with the shared configuration except cage.n_elements, one shared store."""
    options = StudyOptions(out_dir=str(tmp_path / "s"), config=tiny_config())
    branches = cage_branches(str(tmp_path / "m.stl"), options, [4000, 8000])
    assert [b.name for b in branches] == ["cage_4000", "cage_8000"]
    assert [b.config.cage.n_elements for b in branches] == [4000, 8000]
    a, b = (x.config.model_dump() for x in branches)
    a["cage"].pop("n_elements"), b["cage"].pop("n_elements")
    assert a == b
    assert branches[0].store == branches[1].store == str((tmp_path / "s" / "store.zarr").resolve())
    assert branches[1].out_dir == str(tmp_path / "s" / "cage_8000")
    with pytest.raises(InputError):
        cage_branches("m.stl", options, [])


def test_methods_branches_print_each_method_as_computed(tmp_path: Path) -> None:
    """neural / s3 / s3_oneshot / planar on one store, each printing its own field (no re-optimisation, no planar blend)."""
    model = torus_file(tmp_path)
    branches = methods_branches(str(model), StudyOptions(out_dir=str(tmp_path / "m"), config=tiny_config()))
    assert [(b.name, b.config.method) for b in branches] == [("neural", "neural"), ("s3", "s3"),
                                                                  ("s3_oneshot", "s3_oneshot"), ("planar", "neural")]
    assert branches[3].config.objectives == [] and branches[0].config.objectives == tiny_config().objectives
    assert all(b.config.collision_retries == 0 and b.config.collision_refinements == 0 and b.config.collision_fallback == "none" for b in branches)
    assert len({b.store for b in branches}) == 1


def test_ablation_branches_switch_one_thing_each(tmp_path: Path) -> None:
    """full / no PO / per-element q, s (/ no SR when SR is on), from the objectives asked for or the defaults."""
    model = torus_file(tmp_path)
    branches = ablation_branches(str(model), StudyOptions(out_dir=str(tmp_path / "a"),
                                                          config=tiny_config(objectives=["sf", "po", "sr"])))
    assert {b.name: (b.config.objectives, b.config.neural.network) for b in branches} == {
        "full": (["sf", "po", "sr"], "small"), "no_po": (["sf", "sr"], "small"),
        "per_element": (["sf", "po", "sr"], "per_element"), "no_sr": (["sf", "po"], "small")}
    unset = tiny_config().model_copy(update={"objectives": None})
    defaults = ablation_branches(str(model), StudyOptions(out_dir=str(tmp_path / "b"), config=unset))
    assert [b.name for b in defaults] == ["full", "no_po", "per_element"]  # the torus has no FEA block: no SR
    assert defaults[0].config.objectives == ["sf", "po", "gc", "ca"]
    with pytest.raises(InputError, match="objectives"):
        ablation_branches(str(model), StudyOptions(out_dir=str(tmp_path / "c"), config=tiny_config(objectives=[])))


def test_initial_guess_branches_and_generated_user_field(tmp_path: Path) -> None:
    """height/heat/user branches; the user branch gets a generated smooth field over the model's bounds."""
    model = torus_file(tmp_path)
    options = StudyOptions(out_dir=str(tmp_path / "ig"), config=tiny_config())
    branches = initial_guess_branches(str(model), options)
    assert [(b.name, b.config.neural.init.kind) for b in branches] == [("height", "height"), ("heat", "heat"), ("user", "user")]
    assert branches[0].user_field is None and branches[2].user_field == str(tmp_path / "ig" / "user_field.npz")
    with np.load(branches[2].user_field) as f:
        points, values = f["points"], f["values"]
    # the torus (radius 14 in x/y, 4 in z) lies inside the sampled box
    assert points.min(axis=0)[0] < -14 and points.max(axis=0)[2] > 4
    # a smooth field: linear interpolation between the grid points reproduces it closely at the centre
    centre = np.zeros((1, 3))
    z_here = user_field_on_cage(centre, values, points)[0]
    assert abs(z_here - 0.0) < 0.5  # z + 0.5 (x - cx) + a sin(...) is 0 at the centre of the torus
    with pytest.raises(InputError, match="objectives"):
        initial_guess_branches(str(model), StudyOptions(out_dir=str(tmp_path / "x"), config=tiny_config(objectives=[])))
    with pytest.raises(InputError, match="unknown initial guess"):
        initial_guess_branches(str(model), options, ["height", "warm"])


def test_user_field_goes_to_the_store_by_content(tmp_path: Path) -> None:
    """The same field file content gives the same store group; bad files are input errors."""
    path = make_user_field(np.array([[0.0, 0, 0], [10, 10, 5]]), tmp_path / "f.npz", n=5)
    store = str(tmp_path / "store.zarr")
    ref = store_user_field(store, "m", str(path))
    copy = tmp_path / "copy.npz"
    copy.write_bytes(path.read_bytes())
    assert store_user_field(store, "m", str(copy)) == ref
    arrays, _ = ArtifactStore(store).read(ref.path)
    assert arrays["points"].shape == (125, 3) and arrays["values"].shape == (125,)
    np.savez(tmp_path / "bad.npz", points=np.zeros((4, 2)), values=np.zeros(4))
    with pytest.raises(InputError):
        store_user_field(store, "m", str(tmp_path / "bad.npz"))


def test_batch_branch_names_are_unique(tmp_path: Path) -> None:
    """Two models with the same stem get distinct folders."""
    options = StudyOptions(out_dir=str(tmp_path / "b"))
    branches = batch_branches(["a/part.stl", "b/part.stl", "c/model.yaml"], options)
    assert [b.name for b in branches] == ["part", "part_2", "c_model"]


def test_task_runner_choice() -> None:
    """Threads by default (one per branch unless limited), Dask for an address or 'local'."""
    assert isinstance(task_runner(None, 3), ThreadPoolTaskRunner)
    assert task_runner(None, 3)._max_workers == 3 and task_runner(None, 3, max_workers=1)._max_workers == 1
    remote = task_runner("tcp://127.0.0.1:8786", 3)
    assert isinstance(remote, DaskTaskRunner) and remote.address == "tcp://127.0.0.1:8786"
    local = task_runner("local", 3, dask_workers=4)
    assert local.cluster_kwargs["n_workers"] == 4 and local.cluster_kwargs["processes"] is True


def test_study_table_has_a_row_per_branch() -> None:
    """Completed and failed branches both appear; the failed one with its error."""
    ok = {"name": "a", "status": "completed", "parameters": {"init": "height"}, "cage": {"n_elements": 900, "genus": 1},
          "field": {"steps": 5, "s_per_step": 0.1}, "final_loss": {"total": 0.5, "sf": 0.4, "sr": 0.0},
          "satisfaction": {"sf_supported_fraction": 0.9}, "metrics": {"n_layers": 7}, "wall_s": 3.0,
          "worker": {"pid": 12}}
    bad = {"name": "b", "status": "failed", "parameters": {"init": "heat"}, "error": "RuntimeError: x"}
    rows = table_rows({"branches": [ok, bad]})
    assert rows[0]["L_total"] == 0.5 and "L_sr" not in rows[0] and rows[0]["SF supported"] == 0.9
    text = markdown_table(rows)
    assert "| a | completed | height | 900 | 1 |" in text and "RuntimeError: x" in text


def test_study_command_input_errors(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    """Bad options exit 2 with a one-line error naming the option, and create no output folder."""
    model = torus_file(tmp_path)
    out = tmp_path / "out"
    assert studies_main(["study", "cages", str(model), "--cage-elements", "4000,x", "--out", str(out)]) == 2
    assert "--cage-elements" in capsys.readouterr().err and not out.exists()
    assert studies_main(["study", "initial-guess", str(tmp_path / "none.stl"), "--out", str(out)]) == 2
    assert "no such file" in capsys.readouterr().err and not out.exists()
    assert studies_main(["study", "batch", str(model), "--out", str(out), "--dask", "nowhere"]) == 2
    assert "--dask" in capsys.readouterr().err
    assert studies_main(["study", "initial-guess", str(model), "--out", str(out), "--objectives", "none"]) == 2
    assert "objectives" in capsys.readouterr().err and not out.exists()
