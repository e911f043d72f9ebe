"""Progress of long steps: a rich bar on the terminal and a Prefect log line every tenth of the way."""
from __future__ import annotations

from types import TracebackType
from typing import Any

import rich.progress
from prefect import get_run_logger


class Progress:
    """Context manager: `update(done, total, **fields)` moves the bar and logs through Prefect."""

    def __init__(self, description: str, total: int) -> None:
        """A bar named `description` with `total` units of work."""
        self.description = description
        self.total = max(int(total), 1)
        self._bar = rich.progress.Progress(
            rich.progress.TextColumn("[bold]{task.description}"),
            rich.progress.BarColumn(),
            rich.progress.MofNCompleteColumn(),
            rich.progress.TimeElapsedColumn(),
            rich.progress.TextColumn("{task.fields[info]}"),
            transient=True,
        )
        self._task = self._bar.add_task(description, total=self.total, info="")
        self._next_log = 0.1

    def __enter__(self) -> Progress:
        """Start the bar."""
        self._bar.start()
        return self

    def __exit__(self, *exc: type[BaseException] | BaseException | TracebackType | None) -> None:
        """Stop the bar."""
        self._bar.stop()

    def update(self, done: int, total: int | None = None, **fields: Any) -> None:
        """Advance to `done` of `total`; extra fields (e.g. loss terms) are shown and logged."""
        if total is not None:
            self.total = max(int(total), 1)
        info = " ".join(f"{k}={v:.4g}" if isinstance(v, float) else f"{k}={v}" for k, v in fields.items())
        self._bar.update(self._task, completed=done, total=self.total, info=info)
        if done / self.total >= self._next_log or done == self.total:
            get_run_logger().info("%s: %d/%d %s", self.description, done, self.total, info)
            self._next_log = (int(done / self.total * 10) + 1) / 10
