"""Progress lines: a tenth of the way is a tenth of this run's own work, fresh or resumed."""
from __future__ import annotations

import pytest

from neuralslicer.tasks import progress


@pytest.mark.parametrize("first_step", [1, 13, 55])
def test_progress_prints_every_tenth_of_the_runs_own_work(monkeypatch, first_step):
    lines: list[str] = []
    monkeypatch.setattr(progress, "say", lines.append)
    with progress.Progress("optimise", total=60, line_every_s=1e9) as bar:
        for step in range(first_step, 61):
            bar.update(step, loss=0.5)
    # the first update, then one line per tenth of the steps left (the last one at 60/60; at most one a step)
    assert len(lines) >= min(10, 61 - first_step) and lines[0].startswith(f"optimise: {first_step}/60 (")
    assert lines[-1].startswith("optimise: 60/60 (") and "loss=0.5" in lines[-1]
    done = [int(ln.split(":")[1].split("/")[0]) for ln in lines]
    assert done == sorted(done) and len(set(done)) == len(done)
