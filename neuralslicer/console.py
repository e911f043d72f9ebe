"""The console that tables are printed to: the terminal's width on a terminal, unlimited in a file or a log."""
from __future__ import annotations

import os
import sys
from typing import TYPE_CHECKING

if TYPE_CHECKING:
    from rich.console import Console

#: the width tables get where output goes to a file or a scheduler's log (no terminal to fit)
LOG_WIDTH = 10_000


def table_console(stderr: bool = False) -> Console:
    """A rich Console for tables: on a terminal (or with COLUMNS set) that width; redirected, wide enough that no
    cell is cut ('neur…')."""
    from rich.console import Console

    stream = sys.stderr if stderr else sys.stdout
    return Console(stderr=stderr, width=None if stream.isatty() or "COLUMNS" in os.environ else LOG_WIDTH)
