"""The last lines of `neuralslicer slice`: the files a user opens next, with their paths."""
from __future__ import annotations

from pathlib import Path

import pytest

from neuralslicer.cli.main import print_summary


@pytest.mark.parametrize("preview", [True, False])
def test_slice_ends_with_the_gcode_preview_and_report_paths(tmp_path: Path, preview: bool, capsys) -> None:
    out = tmp_path / "a rather long folder name" / "run"
    out.mkdir(parents=True)
    names = ["print.gcode", "report.md", "metrics.json"] + (["preview.html"] if preview else [])
    for name in names:
        (out / name).write_text("x")
    print_summary({"tasks": [{"task": "model", "state": "Completed"}], "wall_s": 1.0, "out_dir": str(out)})
    lines = capsys.readouterr().out.rstrip("\n").splitlines()
    expected = [("G-code:", out / "print.gcode")] + ([("preview:", out / "preview.html")] if preview else []) \
        + [("report:", out / "report.md")]
    tail = lines[-len(expected):]
    # one line per file, unwrapped, the full path (with its spaces) after the label
    assert [(line.split()[0], line.split(None, 1)[1]) for line in tail] == [(w, str(p)) for w, p in expected]
    assert all(Path(line.split(None, 1)[1]).is_file() for line in tail)
    assert "preview.html" not in "\n".join(lines[:-len(expected)])
