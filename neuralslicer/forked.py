"""Independent jobs shared between this process and one forked helper process (two cores, one step).

A step whose work splits into independent jobs (the report's figures, the layers' batches, the patches of every
layer) runs them on both cores: a helper process forked at :class:`SharedJobs`' construction takes jobs at once, this
process joins in at :meth:`SharedJobs.finish` (after work of its own, if any), each taking the next job until none is
left; results come back in the jobs' order whoever did them. The helper inherits everything by fork (no pickling of
the inputs; each result is pickled back), so the jobs compute exactly what they would here. Without a helper (not
Linux, one core, ``NEURALSLICER_FORK=0``) this process does every job; a job that failed in the helper, or that the
helper did not finish because it died, is done again here, so that its error is raised here and the results are the
same either way.
"""
from __future__ import annotations

import multiprocessing
import os
import sys
import threading
import warnings
from collections.abc import Callable, Sequence
from typing import Any, Generic, TypeVar

T = TypeVar("T")

#: ``NEURALSLICER_FORK=0``: every job in this process, one after the other
FORK_ENV = "NEURALSLICER_FORK"
#: seconds this process waits for the helper's last job before it does that job itself
HELPER_TIMEOUT_S = 600.0


def helper_wanted() -> bool:
    """Whether a forked helper process can share jobs here: Linux (fork is safe with the libraries this project
    loads), more than one core to run on, and not turned off (``NEURALSLICER_FORK=0``)."""
    if os.environ.get(FORK_ENV, "1").strip().lower() in ("0", "false", "no", "off"):
        return False
    if not sys.platform.startswith("linux") or "fork" not in multiprocessing.get_all_start_methods():
        return False
    try:
        return len(os.sched_getaffinity(0)) > 1
    except (AttributeError, OSError):
        return (os.cpu_count() or 1) > 1


class SharedJobs(Generic[T]):
    """Jobs shared with a forked helper process; see the module's description."""

    def __init__(self, jobs: Sequence[Callable[[], T]], costs: Sequence[float] | None = None,
                 helper: bool | None = None) -> None:
        """Start the helper (where one can run) on ``jobs``; ``costs``: rough relative costs, by which the longest
        jobs are taken first (default: in order); ``helper``: False to do every job here."""
        self.jobs = list(jobs)
        self.order = (sorted(range(len(self.jobs)), key=lambda i: -costs[i]) if costs is not None
                      else list(range(len(self.jobs))))
        self.results: dict[int, T] = {}
        self.process: Any = None
        self.claimed: Any = None
        self._taken = 0
        if len(self.jobs) < 2 or not (helper_wanted() if helper is None else helper):
            return
        try:
            ctx = multiprocessing.get_context("fork")
            self.claimed = ctx.Value("i", 0)
            self.reader, writer = ctx.Pipe(duplex=False)
            self.process = ctx.Process(target=self._helper, args=(writer,), daemon=True, name="neuralslicer-helper")
            with warnings.catch_warnings():  # Python 3.12+ warns of fork with threads running (Prefect's); the
                warnings.simplefilter("ignore", DeprecationWarning)  # helper only computes and writes files
                self.process.start()
            writer.close()
        except (OSError, AssertionError):  # no process to be had (limits), or this one is a daemon (a Dask worker's,
            self.process = self.claimed = None  # a helper's), which may not have children: every job here
            return
        # the helper's results are received as they come (a result larger than the pipe's buffer would otherwise
        # hold the helper until this process has done its own share)
        self._failed: list[str] = []
        self._receiver = threading.Thread(target=self._receive, name="neuralslicer-helper-results", daemon=True)
        self._receiver.start()

    def _receive(self) -> None:
        """The helper's results, until it closes its end of the pipe."""
        try:
            while True:
                i, status, value = self.reader.recv()
                if status == "ok":
                    self.results[i] = value
                else:
                    self._failed.append(value)
        except (EOFError, OSError):
            pass

    def _next(self) -> int | None:
        """The next job to do (an index into ``jobs``), or None when every job is taken."""
        if self.claimed is None:
            k, self._taken = self._taken, self._taken + 1
        else:
            with self.claimed.get_lock():
                k = self.claimed.value
                self.claimed.value = k + 1
        return self.order[k] if k < len(self.order) else None

    def _helper(self, conn: Any) -> None:
        """The helper process: take jobs until none is left, sending back each one's result (or its error); then
        leave at once (``os._exit``): the exit handlers it inherited are the parent's (Prefect's services, the local
        server's), not its own."""
        status = 1
        try:
            while (i := self._next()) is not None:
                try:
                    conn.send((i, "ok", self.jobs[i]()))
                except Exception as exc:  # noqa: BLE001 - done again by the parent, which raises it
                    conn.send((i, "error", f"{type(exc).__name__}: {exc}"))
            status = 0
        finally:
            conn.close()
            os._exit(status)

    def finish(self) -> list[T]:
        """Do jobs here until none is left, wait for the helper's, do again what it failed or left; every job's
        result, in the jobs' order."""
        while (i := self._next()) is not None:
            self.results[i] = self.jobs[i]()
        if self.process is not None:
            self._collect()
        for i in range(len(self.jobs)):   # what the helper failed or left undone
            if i not in self.results:
                self.results[i] = self.jobs[i]()
        return [self.results[i] for i in range(len(self.jobs))]

    def _collect(self) -> None:
        """Wait for the helper's last result (until the timeout, when the helper is stopped)."""
        process, self.process = self.process, None
        self._receiver.join(HELPER_TIMEOUT_S)
        process.join(timeout=5.0)
        if process.is_alive():
            process.kill()
            process.join()
        self._receiver.join(5.0)
        self.reader.close()
        if self._failed or process.exitcode not in (0, None):
            reason = "; ".join(self._failed) or f"it ended with status {process.exitcode}"
            warnings.warn(f"the helper process failed ({reason}); doing its jobs here", stacklevel=3)


def shared_map(jobs: Sequence[Callable[[], T]], costs: Sequence[float] | None = None) -> list[T]:
    """Every job's result in order, the jobs shared with a forked helper process (:class:`SharedJobs`)."""
    return SharedJobs(jobs, costs).finish()
