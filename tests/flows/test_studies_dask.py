"""Integration: the initial-guess study fanned out on a two-worker Dask LocalCluster through prefect-dask."""
from __future__ import annotations

import json
import os
from pathlib import Path

import numpy as np
import pytest

from neuralslicer.storage import ArtifactStore
from studies_common import shared_store, tiny_config, torus_file

pytestmark = pytest.mark.slow   # end to end (a Prefect server, the CLI or a cluster): not in `make test-fast`

pytest.importorskip("prefect_dask")


@pytest.mark.slow
def test_initial_guess_study_runs_branches_in_dask_worker_processes(
    prefect_server: None, tmp_path: Path, tmp_path_factory: pytest.TempPathFactory
) -> None:
    """Three branches (height, heat, user) run in the cluster's worker processes; the report overlays three curves."""
    from distributed import Client, LocalCluster

    from neuralslicer.flows.studies import initial_guess_study

    model = torus_file(tmp_path_factory.getbasetemp())
    out = tmp_path / "ig"
    with LocalCluster(n_workers=2, threads_per_worker=1, processes=True, host="127.0.0.1",
                      dashboard_address=None) as cluster, Client(cluster) as client:
        worker_pids = set(client.run(os.getpid).values())
        study = initial_guess_study(model=str(model), out_dir=str(out), store=str(shared_store(tmp_path_factory)),
                                    config=tiny_config(), dask=cluster.scheduler_address)
    assert len(worker_pids) == 2 and os.getpid() not in worker_pids

    recorded = json.loads((out / "study.json").read_text())
    assert [b["name"] for b in recorded["branches"]] == ["height", "heat", "user"]
    assert all(b["status"] == "completed" for b in recorded["branches"]), recorded["branches"]
    pids = {b["worker"]["pid"] for b in recorded["branches"]}
    # every branch ran inside a worker process of the cluster, and the branches used both workers
    assert pids == worker_pids
    assert all(b["worker"].get("dask_address") for b in recorded["branches"])
    # the branches shared one cage, computed once under the store's lock while they ran concurrently
    assert len({b["cage"]["path"] for b in recorded["branches"]}) == 1
    states = [{t["task"]: t["state"] for t in b["tasks"]} for b in recorded["branches"]]
    assert all(s["field"] == "Completed" for s in states)
    staging = Path(shared_store(tmp_path_factory), "_staging")
    assert sorted(p.name for p in staging.iterdir() if not p.name.startswith(("locks", "zarr.json"))) == []
    # the three initial guesses really differ: the pre-trained fields start apart, so the loss curves differ
    store = ArtifactStore(shared_store(tmp_path_factory))
    totals = {b["name"]: store.read(b["field"]["path"], ["history/total"])[0]["history/total"]
              for b in recorded["branches"]}
    assert all(len(v) == 8 for v in totals.values())
    assert not np.allclose(totals["height"], totals["heat"]) and not np.allclose(totals["height"], totals["user"])
    # the report: one overlaid learning-curve figure with the three runs, the table with each branch
    assert recorded["curves"] == ["heat", "height", "user"]
    text = (out / "study.md").read_text()
    assert "![Learning curves (total loss)](figures/learning_curves.png)" in text
    assert (out / "figures" / "learning_curves.png").stat().st_size > 10_000
    for name in ("height", "heat", "user"):
        assert f"| {name} | completed | {name} |" in text
        metrics = json.loads((out / name / "metrics.json").read_text())
        assert metrics["field.steps"] == 8 and "provenance.inputs.spec_sha256" in metrics
        assert (out / name / "report.md").is_file() and (out / name / "provenance.json").is_file()
    assert study["kind"] == "initial-guess"
    # the headline: how alike the three fields are (LPD angles, print-order correlation), every pair once
    pairs = {(r["a"], r["b"]) for r in recorded["agreement"]}
    assert len(pairs) == 3 and all(r["n_points"] > 100 and 0.0 <= r["lpd_angle_median_deg"] <= 180.0
                                   and -1.0 <= r["print_order_spearman"] <= 1.0 for r in recorded["agreement"])
    assert "## How alike the fields are" in text and "LPD angle, median" in text
