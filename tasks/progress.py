"""What a run shows while it works: a rich bar on a terminal, plain lines on stderr every tenth of the way
(of this run's own work: a resumed optimisation counts from its checkpoint) or every ``line_every_s``
seconds (so a run whose output goes to a file or a scheduler's log can be followed too), and the same lines
as Prefect INFO logs."""
from __future__ import annotations

import logging
import os
import sys
import time
from types import TracebackType
from typing import Any
from uuid import UUID

import rich.console
import rich.progress
from prefect import get_run_logger
from prefect.artifacts import create_progress_artifact, update_progress_artifact
from prefect.context import FlowRunContext, TaskRunContext

#: seconds between plain progress lines (besides one per tenth of the work)
LINE_EVERY_S = 10.0
#: the logger of a step's work outside a Prefect run (a step in a process of its own: ``tasks/isolate.py`` sends its
#: records to the run's log)
STEP_LOGGER = "neuralslicer.step"
#: ``0`` in a step's own process whose run prints its INFO records on the console: progress lines are not printed
#: twice
PROGRESS_CONSOLE_ENV = "NEURALSLICER_PROGRESS_CONSOLE"


def run_logger() -> logging.Logger | logging.LoggerAdapter:
    """Prefect's run logger in a flow or task run; elsewhere (a step in a process of its own) ``STEP_LOGGER``."""
    try:
        return get_run_logger()
    except Exception:  # noqa: BLE001 - outside a flow or task run there is no run logger
        return logging.getLogger(STEP_LOGGER)


def console_prints_info(logger: logging.Logger) -> bool:
    """True when an INFO record of ``logger`` reaches a Prefect console handler that prints it (a worker's or a served
    run's output, Prefect's default; not the command line's, whose console handler shows warnings only)."""
    from prefect.logging.handlers import PrefectConsoleHandler

    if not logger.isEnabledFor(logging.INFO):
        return False
    node: logging.Logger | None = logger
    while node is not None:
        if any(isinstance(h, PrefectConsoleHandler) and h.level <= logging.INFO for h in node.handlers):
            return True
        node = node.parent if node.propagate else None
    return False


def say(message: str) -> None:
    """One line in the Prefect run log (INFO) and on stderr (plain text when it is not a terminal), once: where
    Prefect's console prints the run log's INFO records, that line is the terminal's. Outside a run the line goes to
    ``STEP_LOGGER`` (whose handlers, in a step's own process, send it to the run) and to stderr."""
    logger = run_logger()
    shown_elsewhere = (os.environ.get(PROGRESS_CONSOLE_ENV, "1") == "0" if isinstance(logger, logging.Logger)
                       else console_prints_info(logger.logger))
    if not shown_elsewhere:
        rich.console.Console(stderr=True, highlight=False, soft_wrap=True).print(message, markup=False)
    logger.info(message)


class Progress:
    """Context manager: `update(done, total, **fields)` moves the bar and prints/logs progress lines."""

    def __init__(self, description: str, total: int, line_every_s: float = LINE_EVERY_S) -> None:
        """A bar named `description` with `total` units of work."""
        self.description = description
        self.total = max(int(total), 1)
        self.line_every_s = line_every_s
        self._bar = rich.progress.Progress(
            rich.progress.TextColumn("[bold]{task.description}"),
            rich.progress.BarColumn(),
            rich.progress.MofNCompleteColumn(),
            rich.progress.TimeElapsedColumn(),
            rich.progress.TextColumn("{task.fields[info]}"),
            transient=True,
            console=rich.console.Console(stderr=True),
            disable=not sys.stderr.isatty(),
        )
        self._task = self._bar.add_task(description, total=self.total, info="")
        self._next_fraction = 0.1
        self._start = self._last_line = time.perf_counter()
        self._artifact: UUID | None = None
        self._origin: int | None = None

    def __enter__(self) -> Progress:
        """Start the bar (and a Prefect progress artifact inside a flow or task run)."""
        self._bar.start()
        if FlowRunContext.get() is None and TaskRunContext.get() is None:
            return self                            # no run to attach an artifact to
        try:
            self._artifact = create_progress_artifact(0.0, description=f"{self.description}: starting")
        except Exception:  # noqa: BLE001 - outside a flow or task run, or no API: the bar and lines suffice
            self._artifact = None
        return self

    def __exit__(self, *exc: type[BaseException] | BaseException | TracebackType | None) -> None:
        """Stop the bar; the progress artifact says the step ended."""
        self._bar.stop()
        self._publish(100.0, f"{self.description}: done in {time.perf_counter() - self._start:.0f} s")

    def _publish(self, percent: float, line: str) -> None:
        """Move the Prefect progress artifact (when there is one) to ``percent`` with ``line`` as its text."""
        if self._artifact is None:
            return
        try:
            update_progress_artifact(self._artifact, min(max(percent, 0.0), 100.0), description=line)
        except Exception:  # noqa: BLE001 - a lost API connection must not stop the work
            self._artifact = None

    def update(self, done: int, total: int | None = None, /, **fields: Any) -> None:
        """Advance to `done` of `total` (positional: a field may be called total, as the total loss is); extra
        fields (e.g. loss terms) are shown, printed and logged."""
        if total is not None:
            self.total = max(int(total), 1)
        info = " ".join(f"{k}={v:.4g}" if isinstance(v, float) else f"{k}={v}" for k, v in fields.items())
        self._bar.update(self._task, completed=done, total=self.total, info=info)
        now = time.perf_counter()
        first = self._origin is None
        if first:                   # where this run starts: 0, or a resumed run's checkpoint (its first update is one past)
            self._origin = max(min(done, self.total) - 1, 0)
        span = max(self.total - self._origin, 1)
        fraction = (done - self._origin) / span     # a tenth of the way is a tenth of this run's own work
        if first or fraction >= self._next_fraction or done == self.total or now - self._last_line >= self.line_every_s:
            rate = (done - self._origin) / max(now - self._start, 1e-9)
            settled = done - self._origin >= max(5, 0.02 * span)     # the rate of the first steps says little
            left = (f", at most {(self.total - done) / rate:.0f} s left"
                    if settled and rate > 0 and done < self.total else "")
            line = f"{self.description}: {done}/{self.total} ({rate:.3g}/s, {now - self._start:.0f} s{left}) {info}"
            say(line)
            self._publish(100.0 * done / self.total, line)
            self._next_fraction = (int(fraction * 10) + 1) / 10
            self._last_line = now
