"""Reliability where the runs really happen: the same inputs give the same cage and results in fresh stores,
a run killed (SIGKILL) at any step resumes to the uninterrupted result, concurrent runs share one store,
and a run on a machine whose cores are busy completes (its own Prefect server included)."""
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

from conftest import REPO, fast_config, l_part_mesh
from neuralslicer.cli.main import main

pytestmark = [pytest.mark.usefixtures("prefect_server"), pytest.mark.slow]   # end to end: not in `make test-fast`

#: steps killed by SIGKILL as soon as they start: before the optimisation, inside it, after it
KILL_AT = ("cage", "field", "motion")


def comparable(out: Path) -> dict:
    """metrics.json without the wall times (everything else must repeat exactly)."""
    metrics = json.loads((out / "metrics.json").read_text())
    return {k: v for k, v in metrics.items() if not k.startswith("wall_s.")}


@pytest.fixture(scope="module")
def case(tmp_path_factory: pytest.TempPathFactory) -> dict:
    """The L part, a fast configuration with a short optimisation (SF + PO) and one uninterrupted run of it."""
    root = tmp_path_factory.mktemp("reliability")
    model = root / "lpart.stl"
    l_part_mesh().export(model)
    cfg = root / "cfg.yaml"
    cfg.write_text(yaml.safe_dump(fast_config(neural={"optim": {"max_steps": 20, "checkpoint_every": 2}})))
    args = ["slice", str(model), "--config", str(cfg), "--objectives", "sf,po"]
    assert main([*args, "--out", str(root / "reference")]) == 0
    return {"root": root, "model": model, "args": args, "reference": comparable(root / "reference")}


def cli_env(tmp_path: Path, own_server: bool = False) -> dict[str, str]:
    """Environment of a CLI subprocess: the session's Prefect server (a running server is used when
    PREFECT_API_URL names it), or with ``own_server`` an ephemeral one of its own in a fresh PREFECT_HOME (which
    stops with the command: conftest sets NEURALSLICER_API_IDLE_S=0)."""
    from prefect.settings import PREFECT_API_URL

    env = {**os.environ, "PREFECT_HOME": str(tmp_path / "prefect-home")}
    env.pop("PREFECT_API_URL", None)
    if not own_server:
        env["PREFECT_API_URL"] = str(PREFECT_API_URL.value())
    return env


def _as_a_shell_starts_it() -> None:
    """In the command's process before it starts: Ctrl-C's default action and no signal blocked, as a terminal's shell
    starts a command. A child inherits both from this test process, where other tests' libraries may have changed
    them; a command started with SIGINT ignored or blocked (as a shell's background job is) rightly keeps running."""
    signal.signal(signal.SIGINT, signal.SIG_DFL)
    signal.pthread_sigmask(signal.SIG_SETMASK, [])


def cli(args: list[str], env: dict[str, str], **kwargs) -> subprocess.Popen:
    """`python -m neuralslicer.cli ARGS` in its own process group (a kill takes its children too)."""
    return subprocess.Popen([sys.executable, "-m", "neuralslicer.cli", *args], cwd=REPO, env=env, start_new_session=True,
                            stdout=subprocess.DEVNULL, stderr=subprocess.PIPE, text=True,
                            preexec_fn=_as_a_shell_starts_it, **kwargs)


def test_two_fresh_stores_give_the_same_cage_and_metrics(case, tmp_path):
    out = tmp_path / "again"
    assert main([*case["args"], "--out", str(out)]) == 0
    again = comparable(out)
    assert again["provenance.cage_sha256"] == case["reference"]["provenance.cage_sha256"]
    assert again == case["reference"]


def test_the_cage_cache_holds_only_verified_arrays(tmp_path):
    from neuralslicer.storage.content_cache import ContentCache, cache_root

    assert cache_root({"NEURALSLICER_CACHE_DIR": "off"}) is None
    assert cache_root({"XDG_CACHE_HOME": str(tmp_path)}) == tmp_path / "neuralslicer"
    cache = ContentCache(tmp_path / "c")
    assert cache.load("cage", "k1") is None
    assert cache.save("cage", "k1", {"vertices": np.eye(3)}, {"n": 1})
    arrays, attrs = cache.load("cage", "k1")
    assert np.array_equal(arrays["vertices"], np.eye(3)) and attrs["n"] == 1
    # an entry copied under another key, or a pickled object array, is not an entry
    (tmp_path / "c" / "cage" / "k2.json").write_text((tmp_path / "c" / "cage" / "k1.json").read_text())
    (tmp_path / "c" / "cage" / "k2.npz").write_bytes((tmp_path / "c" / "cage" / "k1.npz").read_bytes())
    assert cache.load("cage", "k2") is None
    np.savez(tmp_path / "c" / "cage" / "k3.npz", vertices=np.array([object()], dtype=object))
    (tmp_path / "c" / "cage" / "k3.json").write_text(json.dumps({"cache_key": "k3"}))
    assert cache.load("cage", "k3") is None
    with pytest.raises(ValueError):
        cache.load("cage", "../../etc/passwd")
    assert not ContentCache(None).save("cage", "k", {}, {})


@pytest.mark.parametrize("step", KILL_AT)
def test_sigkill_at_a_step_then_rerun_gives_the_uninterrupted_result(case, tmp_path, step):
    out = tmp_path / "run"
    args = [*case["args"], "--out", str(out)]
    env = cli_env(tmp_path)
    proc = cli(args, env)
    seen: list[str] = []
    try:
        for line in proc.stderr:
            seen.append(line.rstrip())
            if line.startswith(f"{step}: started"):
                break
        assert proc.poll() is None, "the run ended before it could be killed:\n" + "\n".join(seen[-30:])
    finally:
        with contextlib.suppress(ProcessLookupError):
            os.killpg(proc.pid, signal.SIGKILL)
        proc.wait(timeout=30)
    assert proc.returncode == -signal.SIGKILL
    assert not (out / "metrics.json").exists()
    rerun = subprocess.run([sys.executable, "-m", "neuralslicer.cli", *args], cwd=REPO, env=env, capture_output=True, text=True,
                           timeout=600)
    assert rerun.returncode == 0, rerun.stderr[-3000:]
    assert comparable(out) == case["reference"]


def test_ctrl_c_says_one_line_exits_130_and_the_rerun_resumes(case, tmp_path):
    out = tmp_path / "run"
    args = [*case["args"], "--out", str(out)]
    env = cli_env(tmp_path)
    proc = cli(args, env)
    seen: list[str] = []
    for line in proc.stderr:
        seen.append(line.rstrip())
        if line.startswith("optimise: ") and "/20 (" in line:  # inside the optimisation
            break
    proc.send_signal(signal.SIGINT)  # what Ctrl-C sends
    rest = proc.stderr.read().splitlines()
    assert proc.wait(timeout=120) == 130, "\n".join((seen + rest)[-30:])
    assert [ln for ln in rest if ln.startswith("neuralslicer:")] == [
        "neuralslicer: interrupted; run the same command again to resume"]
    assert not any("Traceback" in ln for ln in rest), "\n".join(rest[-30:])
    rerun = subprocess.run([sys.executable, "-m", "neuralslicer.cli", *args], cwd=REPO, env=env, capture_output=True, text=True,
                           timeout=600)
    assert rerun.returncode == 0, rerun.stderr[-3000:]
    assert comparable(out) == case["reference"]


def _resumed_from(out: Path) -> list[int | None]:
    """The step each optimisation of the run's store resumed from (None: started afresh)."""
    from neuralslicer.storage import ArtifactStore

    root = out / "store.zarr"
    model = next(p.name for p in root.iterdir() if p.is_dir() and not p.name.startswith("_"))
    store = ArtifactStore(root)
    return [store.attrs(f"{model}/field/{d}").get("resumed_from_step") for d in store.children(f"{model}/field")]


def test_sigterm_to_the_process_group_stops_like_ctrl_c_exits_143_and_the_rerun_resumes(case, tmp_path):
    """What a scheduler does at its time limit: SIGTERM to the whole process group of a run with its own local
    Prefect server, inside the optimisation. One line, exit 143 within 10 s, no traceback; the server was not in
    the group (the flow reported its end to it) and is gone with the command; the rerun resumes from a checkpoint
    and gives the uninterrupted result."""
    import psutil

    out = tmp_path / "run"
    args = [*case["args"], "--out", str(out)]
    env = cli_env(tmp_path, own_server=True)
    proc = cli(args, env)
    seen: list[str] = []
    for line in proc.stderr:
        seen.append(line.rstrip())
        if line.startswith("optimise: ") and "/20 (" in line and int(line.split()[1].split("/")[0]) >= 6:
            break                                  # checkpoints (every 2 steps) are on disk
    server = [c for c in psutil.Process(proc.pid).children(recursive=True) if "neuralslicer.flows.api_server" in c.cmdline()]
    assert server and all(os.getpgid(c.pid) != proc.pid for c in server), "the local server shares the group"
    sent = time.monotonic()
    os.killpg(proc.pid, signal.SIGTERM)
    rest = proc.stderr.read().splitlines()
    assert proc.wait(timeout=60) == 143, "\n".join((seen + rest)[-30:])
    assert time.monotonic() - sent < 10.0
    assert [ln for ln in rest if not ln.startswith("optimise: ")] == [
        "neuralslicer: terminated (SIGTERM); run the same command again to resume"], "\n".join(rest[-30:])
    psutil.wait_procs(server, timeout=10)
    assert not any(p.is_running() and p.status() != psutil.STATUS_ZOMBIE for p in server)
    assert not (out / "metrics.json").exists()
    rerun = subprocess.run([sys.executable, "-m", "neuralslicer.cli", *args], cwd=REPO, env=env, capture_output=True, text=True,
                           timeout=600)
    assert rerun.returncode == 0, rerun.stderr[-3000:]
    assert any(step for step in _resumed_from(out))
    assert comparable(out) == case["reference"]


def test_a_read_only_working_directory_builds_the_cage(tmp_path, monkeypatch):
    """fTetWild writes a debug file into the working directory; where it cannot (here /proc, read-only even for
    root), the cage is built all the same."""
    from neuralslicer.cage import CageConfig, build_cage

    sphere = trimesh.creation.icosphere(2, 10.0)
    H = lambda x: np.linalg.norm(np.asarray(x), axis=1) - 10.0  # noqa: E731
    monkeypatch.chdir("/proc")
    cage = build_cage(H, np.array([[-10.0] * 3, [10.0] * 3]), 4188.8, CageConfig(n_elements=800),
                      np.asarray(sphere.vertices) * 0.99)
    assert len(cage.tets) > 200


def test_concurrent_runs_share_one_store(case, tmp_path):
    other = tmp_path / "tpart.stl"
    mesh = l_part_mesh()
    mesh.apply_transform(trimesh.transformations.scale_matrix(1.2))  # another model, another name
    mesh.export(other)
    store = tmp_path / "shared.zarr"
    env = cli_env(tmp_path)
    runs = {
        "same_a": [*case["args"], "--out", str(tmp_path / "same_a"), "--store", str(store)],
        "same_b": [*case["args"], "--out", str(tmp_path / "same_b"), "--store", str(store)],
        "other": ["slice", str(other), *case["args"][2:], "--out", str(tmp_path / "other"), "--store", str(store)],
    }
    procs = {name: cli(args, env) for name, args in runs.items()}
    errors = {name: p.communicate(timeout=600)[1] for name, p in procs.items()}
    for name, p in procs.items():
        assert p.returncode == 0, f"{name}: {errors[name][-3000:]}"
    assert comparable(tmp_path / "same_a") == comparable(tmp_path / "same_b") == case["reference"]
    assert comparable(tmp_path / "other")["n_layers"] > 0
    from neuralslicer.storage import ArtifactStore

    shared = ArtifactStore(store, create=False)
    for model in ("lpart", "tpart"):
        for step in ("model", "samples", "cage", "field", "layers", "toolpaths", "motion", "program"):
            groups = shared.children(f"{model}/{step}")
            assert len(groups) == 1, (model, step, groups)  # written once, not twice
            arrays, _ = shared.read(f"{model}/{step}/{groups[0]}")  # complete and readable
            assert arrays or step == "model"
    staging = store / "_staging"
    assert not [p.name for p in staging.iterdir() if p.name not in ("zarr.json", "locks")], "a staged group was left"
    assert not list((staging / "locks").glob("*")), "a lock was left behind"


def test_a_run_on_a_busy_machine_completes(case, tmp_path):
    burners = [subprocess.Popen([sys.executable, "-c", "while True: pass"]) for _ in range(os.cpu_count() or 2)]
    try:
        time.sleep(1.0)
        out = tmp_path / "busy"
        proc = cli([*case["args"], "--out", str(out)], cli_env(tmp_path, own_server=True))
        _, err = proc.communicate(timeout=900)
    finally:
        for b in burners:
            b.kill()
            b.wait()
    assert proc.returncode == 0, err[-3000:]
    assert comparable(out) == case["reference"]
