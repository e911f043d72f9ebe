"""A step of a large print in a process of its own: the memory the command holds does not add to the step's peak,
and everything the step allocated goes back to the machine when it ends.

The command that runs a slice keeps what its earlier steps left (the imports, torch after an optimisation, the
allocator's retained pages: about 1 GB after the bunny's field), and a step on a print of 10M waypoints needs 2.5 to
3 GB of its own on top of that. The motion, program and export steps of such a print therefore run in a fresh
process started with ``spawn``: it imports the step's task module, computes the step's output and writes it to the
store as the task would have, and ends. The run's view is unchanged: the same store group, the same Prefect task
run; the step's log records come back to its run's log, and its progress lines are printed as they come.

``NEURALSLICER_ISOLATE``: ``auto`` (default) isolates a step whose print has at least :data:`MIN_WAYPOINTS`
waypoints, ``always`` every step that may be isolated, ``never`` none. A process that may have no children (a
daemon: a Dask worker's) runs the step itself.
"""
from __future__ import annotations

import importlib
import logging
import multiprocessing
import os
import pickle
import traceback
from collections.abc import Callable
from typing import Any

from neuralslicer.storage import ArtifactRef, ArtifactStore
from neuralslicer.tasks.progress import PROGRESS_CONSOLE_ENV, STEP_LOGGER, console_prints_info

#: the environment variable that says which steps run in a process of their own (``auto``, ``always``, ``never``)
ISOLATE_ENV = "NEURALSLICER_ISOLATE"
#: in ``auto``, a step runs in a process of its own from this many waypoints of its print on
MIN_WAYPOINTS = 2_000_000


class StepProcessError(RuntimeError):
    """A step's own process ended without a result (killed, out of memory)."""


def isolation_mode() -> str:
    """``auto``, ``always`` or ``never`` (``NEURALSLICER_ISOLATE``; 1/0, yes/no, on/off read as always/never)."""
    value = os.environ.get(ISOLATE_ENV, "auto").strip().lower()
    aliases = {"1": "always", "yes": "always", "on": "always", "true": "always",
               "0": "never", "no": "never", "off": "never", "false": "never"}
    value = aliases.get(value, value)
    if value not in ("auto", "always", "never"):
        raise ValueError(f"{ISOLATE_ENV}={os.environ[ISOLATE_ENV]!r}: expected auto, always or never")
    return value


def may_have_children() -> bool:
    """Whether this process may start one (a daemonic process, as a Dask worker's, may not)."""
    return not multiprocessing.current_process().daemon


def n_waypoints(ref: ArtifactRef | None, array: str) -> int:
    """The waypoint count of a stored print: the length of its group's ``array`` (0 when there is none)."""
    if ref is None:
        return 0
    store = ArtifactStore(ref.store, create=False)
    return store.shape(ref.path, array)[0] if store.exists(ref.path) else 0


def large_print(parameter: str, array: str) -> Callable[[dict[str, Any]], bool]:
    """The isolation rule of a step whose print is the group of ``parameter`` (its waypoints: ``array``)."""

    def wanted(parameters: dict[str, Any]) -> bool:
        """True when this call of the step should run in a process of its own."""
        mode = isolation_mode()
        if mode == "never" or not may_have_children():
            return False
        return mode == "always" or n_waypoints(parameters.get(parameter), array) >= MIN_WAYPOINTS

    return wanted


def run_isolated(module: str, name: str, out: ArtifactRef, parameters: dict[str, Any], made: dict[str, Any],
                 logger: logging.Logger | logging.LoggerAdapter) -> None:
    """Run the pipeline task ``module.name`` for ``parameters`` in a spawned process that writes ``out``; its log
    records go to ``logger`` (the run's), its error is raised here."""
    ctx = multiprocessing.get_context("spawn")
    receive, send = ctx.Pipe(duplex=False)
    quiet = console_prints_info(getattr(logger, "logger", logger))
    process = ctx.Process(target=_child, args=(module, name, out, parameters, made, quiet, send),
                          name=f"neuralslicer-{name}", daemon=False)
    process.start()
    send.close()
    try:
        try:
            outcome, records, error = receive.recv()
        except EOFError:
            outcome, records, error = "died", [], None
        process.join()
    except BaseException:
        process.terminate()
        process.join()
        raise
    finally:
        receive.close()
    for level, message in records:
        logger.log(level, message)
    if outcome == "died":
        signal = -process.exitcode if process.exitcode is not None and process.exitcode < 0 else None
        raise StepProcessError(
            f"{out.path}: the step's own process ended without a result (exit code {process.exitcode}"
            + (f", signal {signal}: killed, perhaps for lack of memory" if signal else "") + ")")
    if outcome == "error":
        raise pickle.loads(error)


class _Records(logging.Handler):
    """Keeps the (level, message) of every record, to be sent to the parent's run log."""

    def __init__(self) -> None:
        super().__init__(logging.DEBUG)
        self.records: list[tuple[int, str]] = []

    def emit(self, record: logging.LogRecord) -> None:
        """Keep the record's level and formatted message."""
        self.records.append((record.levelno, record.getMessage()))


def _child(module: str, name: str, out: ArtifactRef, parameters: dict[str, Any], made: dict[str, Any], quiet: bool,
           send: Any) -> None:
    """The spawned process: the step written to the store; ("ok" | "error", records, pickled error) sent back."""
    from neuralslicer.allocator import keep_freed_memory

    keep_freed_memory()
    if quiet:   # the parent's console prints the run log's INFO records: the progress lines come from there
        os.environ[PROGRESS_CONSOLE_ENV] = "0"
    handler = _Records()
    log = logging.getLogger(STEP_LOGGER)
    log.addHandler(handler)
    log.setLevel(logging.DEBUG)
    log.propagate = False
    try:
        task = getattr(importlib.import_module(module), name)
        task.pipeline.write(out, parameters, made)
        send.send(("ok", handler.records, None))
    except BaseException as exc:  # noqa: BLE001 - every error goes back to the parent, which raises it
        exc.add_note(f"in the step's own process:\n{''.join(traceback.format_exception(exc))}")
        try:
            blob = pickle.dumps(exc)
            pickle.loads(blob)
        except Exception:  # noqa: BLE001 - an error that does not pickle comes back as its text
            blob = pickle.dumps(RuntimeError(f"{type(exc).__name__}: {exc}"))
        send.send(("error", handler.records, blob))
    finally:
        send.close()
