"""A study killed midway (SIGKILL) and rerun: finished branches come from the cache, the interrupted optimisation resumes."""
from __future__ import annotations

import json
import os
import signal
import subprocess
import sys
import time
from pathlib import Path

import pytest
import yaml

from neuralslicer.storage import ArtifactStore
from studies_common import shared_store, tiny_config, torus_file

pytestmark = pytest.mark.slow   # end to end (a Prefect server, the CLI or a cluster): not in `make test-fast`

REPO = Path(__file__).resolve().parents[2]


def _study_command(model: Path, out: Path, store: Path, config: Path) -> list[str]:
    """The study command run by the test (sequential branches: height first, then heat)."""
    return [sys.executable, "-m", "neuralslicer.cli", "study", "initial-guess", str(model), "--kinds",
            "height,heat", "--out", str(out), "--store", str(store), "--config", str(config), "--workers", "1"]


def _env(home: Path) -> dict[str, str]:
    """A private Prefect home, INFO logs (the resume message), no analytics."""
    return {**os.environ, "PREFECT_HOME": str(home), "PREFECT_LOGGING_LEVEL": "INFO",
            "PREFECT_SERVER_ANALYTICS_ENABLED": "false", "DO_NOT_TRACK": "1", "PYTHONUNBUFFERED": "1"}


def _checkpoint_roots(store: Path, model: str) -> dict[str, list[str]]:
    """Checkpoint folders (optimisation digest -> step groups), read from the file system."""
    root = store / model / "checkpoints"
    if not root.is_dir():
        return {}
    return {d.name: sorted(p.name for p in d.iterdir() if (p / "zarr.json").is_file() and p.name.startswith("step_"))
            for d in root.iterdir() if d.is_dir()}


@pytest.mark.slow
def test_killed_study_reuses_finished_branch_and_resumes_checkpoint(
    tmp_path: Path, tmp_path_factory: pytest.TempPathFactory
) -> None:
    """SIGKILL once the first branch finished and the second has checkpoints; the rerun completes from there."""
    model = torus_file(tmp_path_factory.getbasetemp())
    store = shared_store(tmp_path_factory)
    config = tmp_path / "config.yaml"
    max_steps = 60
    config.write_text(yaml.safe_dump(tiny_config(max_steps=max_steps, checkpoint_every=3).model_dump(mode="json")))
    out = tmp_path / "study"
    cmd = _study_command(model, out, store, config)
    before = set(_checkpoint_roots(store, "torus"))  # the shared store may hold other tests' optimisations
    log = open(tmp_path / "first.log", "w")
    proc = subprocess.Popen(cmd, cwd=REPO, env=_env(tmp_path / "home"), stdout=log, stderr=subprocess.STDOUT,
                            start_new_session=True)
    killed_with: dict[str, list[str]] = {}
    try:
        deadline = time.monotonic() + 420
        while time.monotonic() < deadline and proc.poll() is None:
            if (out / "height" / "branch.json").is_file():
                roots = _checkpoint_roots(store, "torus")
                height_field = json.loads((out / "height" / "branch.json").read_text())["field"]["path"].rsplit("/", 1)[1]
                others = {k: v for k, v in roots.items() if k != height_field and k not in before and v}
                if others:
                    killed_with = others
                    break
            time.sleep(0.2)
    finally:
        if proc.poll() is None:
            os.killpg(proc.pid, signal.SIGKILL)
        proc.wait(timeout=60)
        log.close()
    assert killed_with, f"the first run never reached the second branch's checkpoints:\n{(tmp_path / 'first.log').read_text()[-3000:]}"
    assert proc.returncode == -signal.SIGKILL
    assert not (out / "heat" / "metrics.json").is_file()  # the heat branch was interrupted before its export
    (digest, steps), = killed_with.items()
    killed_at = int(steps[-1].removeprefix("step_"))
    assert 0 < killed_at < max_steps

    rerun = subprocess.run(cmd, cwd=REPO, env=_env(tmp_path / "home"), capture_output=True, text=True, timeout=600)
    assert rerun.returncode == 0, rerun.stdout[-3000:] + rerun.stderr[-3000:]
    study = json.loads((out / "study.json").read_text())
    height, heat = study["branches"]
    # the finished branch: every task of its pipeline came from the cache
    assert height["status"] == "completed" and height["all_cached"], height["tasks"]
    # the interrupted branch: its shared steps were cached, the optimisation resumed from the newest checkpoint
    states = {t["task"]: t["state"] for t in heat["tasks"]}
    assert states["cage"] == "Cached" and states["model"] == "Cached"
    assert states["field"] == "Completed"
    assert heat["field"]["path"].endswith(digest)
    resumed = int(heat["field"]["resumed_from_checkpoint"].removeprefix("step_"))
    assert resumed >= killed_at
    assert "resuming the optimisation from" in rerun.stdout + rerun.stderr
    # the optimisation task itself says where it resumed (recorded on the field artifact)
    assert ArtifactStore(store).attrs(heat["field"]["path"])["resumed_from_step"] == resumed
    # the resumed optimisation kept the steps done before the kill: the history covers the whole budget
    history = ArtifactStore(store).read(heat["field"]["path"], ["history/total"])[0]["history/total"]
    assert len(history) == heat["field"]["steps"] == max_steps
    assert json.loads((out / "heat" / "metrics.json").read_text())["field.steps"] == max_steps
