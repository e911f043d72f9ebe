"""A step of a large print runs in a process of its own (tasks/isolate.py): the same group as in this process, its
log records back in the run's log, its errors raised here with their type, a killed process named as such."""
from __future__ import annotations

import logging
import os
import signal
from pathlib import Path

import numpy as np
import pytest

from neuralslicer.errors import InputError
from neuralslicer.storage import ArtifactStore
from neuralslicer.tasks.common import pipeline_task
from neuralslicer.tasks.isolate import (ISOLATE_ENV, StepProcessError, isolation_mode, large_print, n_waypoints,
                                        run_isolated)
from neuralslicer.tasks.progress import run_logger, say


@pipeline_task("probe", version="1", exclude=("isolated",), isolate=lambda params: params["isolated"])
def probe_task(out, store: str, name: str, isolated: bool, fail: str = "") -> tuple[dict, dict]:
    """A step that says where it ran (its process id), or fails as asked."""
    if fail == "input":
        raise InputError("probe.yaml", "line 3: no such key")
    if fail == "kill":
        os.kill(os.getpid(), signal.SIGKILL)
    say("probe: halfway")
    run_logger().warning("probe ran in process %d", os.getpid())
    return {"values": np.arange(5.0) * 2}, {"pid": os.getpid()}


class Kept(logging.Handler):
    """Keeps the records a logger gets."""

    def __init__(self) -> None:
        super().__init__()
        self.records: list[logging.LogRecord] = []

    def emit(self, record: logging.LogRecord) -> None:
        self.records.append(record)


def _call(tmp_path: Path, **params):
    """The bound parameters and output ref of one probe call on a store in tmp_path."""
    pipeline = probe_task.pipeline
    bound = pipeline.bind({"store": str(tmp_path / "store.zarr"), "name": "m", **params})
    return pipeline, bound, pipeline.output(bound)


def _logger() -> tuple[logging.Logger, Kept]:
    """A logger that keeps its records (the run's logger stand-in)."""
    logger, kept = logging.getLogger("test-isolate-run"), Kept()
    logger.handlers[:] = [kept]
    logger.setLevel(logging.DEBUG)
    logger.propagate = False
    return logger, kept


def test_a_step_in_its_own_process_writes_the_group_this_process_would(tmp_path: Path) -> None:
    pipeline, bound, out = _call(tmp_path, isolated=True)
    logger, kept = _logger()
    run_isolated(probe_task.__module__, "probe_task", out, bound, {"flow_run": "f-1"}, logger)
    store = ArtifactStore(out.store, create=False)
    arrays, attrs = store.read(out.path)
    assert attrs["pid"] != os.getpid()
    assert attrs["made"] == {"flow_run": "f-1"} and attrs["step"] == "probe" and attrs["wall_s"] >= 0
    np.testing.assert_array_equal(arrays["values"], np.arange(5.0) * 2)
    # the same step in this process: the same arrays and key record, another process id
    other = tmp_path / "here"
    _, bound2, out2 = _call(other, isolated=False)
    pipeline.write(out2, bound2, {"flow_run": "f-1"})
    arrays2, attrs2 = ArtifactStore(out2.store, create=False).read(out2.path)
    np.testing.assert_array_equal(arrays2["values"], arrays["values"])
    assert attrs2["pid"] == os.getpid() and attrs2["key"] == attrs["key"] and out2.digest == out.digest
    # the step's records reach the run's logger, its progress lines included
    messages = [(r.levelno, r.getMessage()) for r in kept.records]
    assert (logging.WARNING, f"probe ran in process {attrs['pid']}") in messages
    assert (logging.INFO, "probe: halfway") in messages and (logging.INFO, "probe: started") in messages


def test_a_steps_error_comes_back_with_its_type_and_nothing_is_written(tmp_path: Path) -> None:
    _, bound, out = _call(tmp_path, isolated=True, fail="input")
    with pytest.raises(InputError) as raised:
        run_isolated(probe_task.__module__, "probe_task", out, bound, {}, _logger()[0])
    assert raised.value.where == "probe.yaml" and raised.value.message == "line 3: no such key"
    assert any("in the step's own process" in note for note in raised.value.__notes__)
    assert not ArtifactStore(out.store).exists(out.path)


def test_a_killed_step_process_is_named_and_nothing_is_written(tmp_path: Path) -> None:
    _, bound, out = _call(tmp_path, isolated=True, fail="kill")
    with pytest.raises(StepProcessError, match="signal 9: killed, perhaps for lack of memory"):
        run_isolated(probe_task.__module__, "probe_task", out, bound, {}, _logger()[0])
    assert not ArtifactStore(out.store).exists(out.path)


def test_the_task_isolates_as_its_rule_says_inside_a_flow(prefect_server: None, tmp_path: Path) -> None:
    from prefect import flow

    from neuralslicer.tasks.common import run_step

    @flow
    def two() -> tuple[int, int]:
        store = str(tmp_path / "store.zarr")
        there = run_step(probe_task, store=store, name="there", isolated=True).result()
        here = run_step(probe_task, store=store, name="here", isolated=False).result()
        st = ArtifactStore(store, create=False)
        return st.attrs(there.path)["pid"], st.attrs(here.path)["pid"]

    there, here = two()
    assert here == os.getpid() and there != os.getpid()


def test_the_isolation_rule_reads_the_mode_and_the_prints_size(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    store = ArtifactStore(str(tmp_path / "s.zarr"))
    store.write("m/toolpaths/abc", {"xyz": np.zeros((7, 3))}, {})
    ref = store.ref("m/toolpaths/abc", "abc")
    assert n_waypoints(ref, "xyz") == 7 and n_waypoints(None, "xyz") == 0
    rule = large_print("toolpaths", "xyz")
    monkeypatch.delenv(ISOLATE_ENV, raising=False)
    assert isolation_mode() == "auto" and not rule({"toolpaths": ref})
    monkeypatch.setattr("neuralslicer.tasks.isolate.MIN_WAYPOINTS", 7)
    assert rule({"toolpaths": ref})
    for value, mode in (("never", "never"), ("0", "never"), ("always", "always"), ("on", "always")):
        monkeypatch.setenv(ISOLATE_ENV, value)
        assert isolation_mode() == mode
    monkeypatch.setenv(ISOLATE_ENV, "never")
    assert not rule({"toolpaths": ref})
    monkeypatch.setenv(ISOLATE_ENV, "sometimes")
    with pytest.raises(ValueError, match="NEURALSLICER_ISOLATE='sometimes': expected auto, always or never"):
        isolation_mode()
