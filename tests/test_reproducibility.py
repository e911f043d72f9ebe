"""The same input, configuration and versions give the same program: two fresh runs of the ring (each its own
process, store, cage cache and Prefect home, run at the same time) write byte-identical G-code."""
from __future__ import annotations

import hashlib
import json
import os
import subprocess
import sys
from pathlib import Path

import pytest

from conftest import REPO

#: per-run figures that are not results: the steps' wall times, and the commit, which hashes the working tree (that a
#: developer may edit while the runs run)
NOT_RESULTS = ("wall_s.", "provenance.code.git_commit")


def _start(ring: Path, folder: Path) -> subprocess.Popen:
    """`neuralslicer slice ring.tet --up y` into ``folder`` with nothing shared with any other run."""
    folder.mkdir()
    env = {**os.environ, "PREFECT_HOME": str(folder / "prefect"), "NEURALSLICER_CACHE_DIR": str(folder / "cache")}
    cmd = [sys.executable, "-m", "neuralslicer.cli", "slice", str(ring), "--up", "y", "--out", str(folder / "out"),
           "--store", str(folder / "store.zarr")]
    return subprocess.Popen(cmd, cwd=REPO, env=env, stdout=subprocess.DEVNULL, stderr=subprocess.PIPE, text=True)


def _results(metrics: dict) -> dict:
    """The metrics less the run's own times."""
    return {k: v for k, v in metrics.items() if not k.startswith(NOT_RESULTS)}


@pytest.mark.slow
@pytest.mark.skipif(not sys.platform.startswith("linux"), reason="fTetWild's draw is seeded on Linux only")
def test_two_fresh_ring_runs_write_the_same_gcode(tmp_path, ring_path):
    runs = {name: _start(ring_path, tmp_path / name) for name in ("a", "b")}
    for name, run in runs.items():
        _, err = run.communicate(timeout=1800)
        assert run.returncode == 0, f"run {name}: {err[-2000:]}"
    outs = [tmp_path / name / "out" for name in runs]
    digests = [hashlib.sha256((out / "print.gcode").read_bytes()).hexdigest() for out in outs]
    assert digests[0] == digests[1]
    metrics = [json.loads((out / "metrics.json").read_text()) for out in outs]
    assert _results(metrics[0]) == _results(metrics[1])
