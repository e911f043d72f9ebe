"""preview.html's data: moves back-plotted by forward kinematics, their colours, the decimation; the page's embedded
data read back; `neuralslicer preview RUN_DIR` on a stored run. (The page in a browser: test_preview_browser.py.)"""
from __future__ import annotations

import base64
import json
import re
from pathlib import Path

import numpy as np
import pytest

from neuralslicer.motion import load_profile, plan_print
from neuralslicer.motion.planning import PRINT, RETRACT, TRAVEL
from neuralslicer.preview import PREVIEW_FILE
from neuralslicer.preview.data import (FLOOR_MM, MoveAttributes, colliding_moves, decimate, deviations, move_attributes,
                                       preview_data, waypoint_values)
from neuralslicer.preview.page import PREVIEW_SCHEMA, plotly_js, preview_html, write_preview
from neuralslicer.toolpath.synthetic import cap_stack


@pytest.fixture(scope="module")
def curved():
    """A curved part printed with rotary motion (concentric caps, LPD radial): toolpaths, program, metrics,
    collisions."""
    layers = cap_stack(3, r0=8.0, theta_max_deg=40.0, center=(3.0, -2.0, 0.0), subdivisions=4)
    return plan_print(layers, platform_z=0.0, profile=load_profile("table_bc_linuxcnc"))


def angle_from_z(axis: np.ndarray) -> np.ndarray:
    """Degrees between each row and +z."""
    return np.degrees(np.arccos(np.clip(axis[:, 2] / np.linalg.norm(axis, axis=1), -1, 1)))


def test_moves_are_back_plotted_through_the_profile(curved) -> None:
    """Tips and axes by forward kinematics reach the toolpath waypoints; tilt is the axis' angle from +z; bead widths
    are the waypoints'."""
    tp, prog, _, _ = curved
    attrs = move_attributes(prog, tp.width)
    src = prog.source
    w = src >= 0
    assert np.abs(attrs.tip[w] - tp.xyz[src[w]]).max() < 1e-3
    assert np.abs(attrs.tilt_deg[w] - angle_from_z(tp.axis[src[w]])).max() < 0.05
    assert attrs.tilt_deg.max() > 10.0                       # the caps tilt the tool
    assert np.array_equal(attrs.width_mm[w], tp.width[src[w]])
    assert np.allclose(attrs.length_mm[1:], np.linalg.norm(np.diff(attrs.tip, axis=0), axis=1))


def test_the_preview_turns_axes_only_for_the_moves_it_keeps(curved) -> None:
    """The preview makes the tips of the drawable moves only, their lengths, widths and times a chunk at a time and
    the tool axes and tilts at the moves it keeps: the same moves and values as from every move's attributes, with
    chunks of any size."""
    import neuralslicer.preview.data as data

    tp, prog, _, report = curved
    full = move_attributes(prog, tp.width)
    b = decimate(full, colliding_moves(prog.source, report.indices), max_points=500)
    drawable = data.drawable_moves(prog)
    assert np.array_equal(drawable.tip, full.tip[drawable.move]) and len(drawable.move) < len(prog)
    for chunk in (data.CHUNK_MOVES, 97, 7):
        data.CHUNK_MOVES = chunk
        try:
            a = preview_data(prog, tp.width, report.indices, max_points=500)
        finally:
            data.CHUNK_MOVES = 250_000
        assert 0 < len(a) < len(prog)
        for name in ("move", "tip", "axis", "tilt_deg", "layer", "kind", "feed_mm_s", "width_mm", "level", "collisions"):
            assert np.array_equal(getattr(a, name), getattr(b, name)), (chunk, name)
        assert (a.max_deviation_mm, a.n_moves, a.n_drawable) == (b.max_deviation_mm, b.n_moves, b.n_drawable)
        # the mean deviation is summed a chunk at a time (the chunks' order of addition)
        assert a.mean_deviation_mm == (b.mean_deviation_mm if chunk == 250_000 else pytest.approx(b.mean_deviation_mm,
                                                                                                  rel=1e-12))


def test_the_moves_read_back_draw_what_the_whole_program_draws(curved) -> None:
    """ProgramMoves (the arrays the export reads of a stored program) give the preview the same moves and values."""
    from neuralslicer.motion.planning import MachineProgram, ProgramMoves

    tp, prog, _, _ = curved
    arrays, attrs = prog.to_arrays()
    moves = ProgramMoves.from_arrays(arrays, attrs)
    assert not isinstance(moves, MachineProgram) and len(moves) == len(prog) and moves.attrs == prog.attrs
    assert set(ProgramMoves.ARRAYS) < set(MachineProgram.ARRAYS)
    whole, drawn = preview_data(prog, tp.width, np.array([5])), preview_data(moves, tp.width, np.array([5]))
    for name in ("move", "tip", "axis", "tilt_deg", "feed_mm_s", "width_mm", "level", "collisions"):
        assert np.array_equal(getattr(whole, name), getattr(drawn, name)), name


def test_inserted_moves_take_the_next_waypoints_value() -> None:
    """A move inserted before a waypoint (rotary split, prime, approach) belongs to that waypoint; the last ones to the
    last waypoint."""
    source = np.array([-1, 0, -1, -1, 1, -1])
    assert waypoint_values(source, np.array([10.0, 20.0])).tolist() == [10, 10, 20, 20, 20, 20]


def synthetic_moves(n_turns: int = 3, per_turn: int = 2000, radius: float = 20.0) -> MoveAttributes:
    """A helix printed at 40 mm/s (a travel of 5 moves before each turn, a retraction at its start), widths 0.4 on
    the first half of each turn and 0.6 on the second, one layer per turn; tool axis tilted by 30° about y."""
    tips, kinds, layers, widths = [], [], [], []
    for k in range(n_turns):
        t = np.linspace(0, 2 * np.pi, per_turn, endpoint=False)
        helix = np.column_stack([radius * np.cos(t), radius * np.sin(t), 0.8 * k + 0.8 * t / (2 * np.pi)])
        travel = np.linspace(tips[-1][-1] if tips else helix[0] + [0, 0, 5], helix[0], 6)[1:]
        tips += [travel[:1], travel, helix[1:]]
        kinds += [[RETRACT], [TRAVEL] * 5, [PRINT] * (per_turn - 1)]
        layers += [[k] * (1 + 5 + per_turn - 1)]
        widths += [[0.5] * 6, np.where(t[1:] < np.pi, 0.4, 0.6)]
    tip = np.concatenate(tips)
    kind = np.concatenate([np.asarray(k, np.int8) for k in kinds])
    length = np.r_[0.0, np.linalg.norm(np.diff(tip, axis=0), axis=1)]
    speed = np.where(kind == PRINT, 40.0, 100.0)
    time = np.where(kind == RETRACT, 0.5, length / speed)
    axis = np.tile([np.sin(np.radians(30)), 0.0, np.cos(np.radians(30))], (len(tip), 1))
    return MoveAttributes(tip, axis, kind, np.concatenate(layers).astype(np.int64), time, length,
                          np.concatenate(widths).astype(float), np.full(len(tip), 30.0))


def test_decimation_fits_the_budget_and_keeps_the_shape() -> None:
    """At most max_points kept, every run's ends and every collision kept, retractions left out, the dropped moves
    within the reported deviation of the drawn lines and, on the helix, within a few times the sagitta of an even
    polygon of as many points; merged moves keep their length over their time (40 mm/s) and their length-weighted
    width."""
    attrs = synthetic_moves()
    collided = np.array([100, 2500, 4000])
    data = decimate(attrs, collided, max_points=200, draw_budget=100)
    assert 150 < len(data) <= 200 and data.n_drawable == len(attrs.tip) - 3
    assert not np.any(data.kind == RETRACT)
    assert set(collided) <= set(data.move[data.collisions].tolist())
    drawable = np.flatnonzero(attrs.kind != RETRACT)
    kind = attrs.kind[drawable]
    change = np.flatnonzero(np.diff(kind) != 0)
    assert set(drawable[np.r_[change, change + 1, 0, len(drawable) - 1]]) <= set(data.move.tolist())
    # every dropped move lies within the reported deviation of the polyline of the kept moves (all its segments)
    kept_tip = attrs.tip[data.move]
    a, b = kept_tip[:-1], kept_tip[1:]
    pts = attrs.tip[drawable]
    ab = b - a
    t = np.clip(np.einsum("pij,ij->pi", pts[:, None] - a[None], ab) / np.einsum("ij,ij->i", ab, ab), 0, 1)
    dist = np.linalg.norm(pts[:, None] - (a[None] + t[..., None] * ab[None]), axis=2).min(axis=1)
    assert dist.max() <= data.max_deviation_mm + 1e-9
    per_turn = (data.kind == PRINT).sum() / 3
    assert data.max_deviation_mm <= 4 * 20.0 * (1 - np.cos(np.pi / per_turn))
    printing = (data.kind == PRINT) & (np.r_[0, np.diff(data.move)] > 1)   # prints that stand for several moves
    assert printing.sum() > 100 and np.allclose(data.feed_mm_s[printing], 40.0, rtol=1e-9)
    assert data.width_mm[printing].min() >= 0.4 - 1e-12 and data.width_mm[printing].max() <= 0.6 + 1e-12
    assert np.isclose(data.width_mm[printing].max(), 0.6) and np.isclose(data.width_mm[printing].min(), 0.4)
    assert data.factor == pytest.approx(data.n_drawable / len(data))


def test_decimation_in_chunks_is_the_decimation_of_the_whole(monkeypatch) -> None:
    """Chunks meet at kept moves, so a print simplified a few hundred moves at a time (bounded memory) keeps the same
    moves, levels, values and deviations as one simplified whole; the merged feeds and widths are exact sums."""
    import neuralslicer.preview.data as data

    attrs = synthetic_moves(n_turns=6, per_turn=1500)
    collided = np.array([100, 2500, 7000])
    monkeypatch.setattr(data, "CHUNK_MOVES", 10**9)
    whole = decimate(attrs, collided, max_points=1200, draw_budget=300)
    assert len(data.spans(np.ones(len(attrs.tip), bool))) == 1
    monkeypatch.setattr(data, "CHUNK_MOVES", 700)
    fixed = data.run_ends(attrs.kind, attrs.layer)
    assert len(data.spans(fixed)) > 5                       # chunks end on the runs' ends, several per layer
    chunked = decimate(attrs, collided, max_points=1200, draw_budget=300)
    for name in ("move", "tip", "axis", "layer", "kind", "tilt_deg", "level", "collisions", "feed_mm_s", "width_mm"):
        assert np.array_equal(getattr(whole, name), getattr(chunked, name)), name
    assert whole.max_deviation_mm == chunked.max_deviation_mm
    assert chunked.mean_deviation_mm == pytest.approx(whole.mean_deviation_mm, rel=1e-12)
    import math

    draw = np.flatnonzero(attrs.kind != RETRACT)
    at = np.searchsorted(draw, chunked.move)                   # kept moves among the drawn ones
    for j in range(1, len(at)):                                # each kept move stands for those merged into it
        merged = draw[at[j - 1] + 1:at[j] + 1]
        span, dt = math.fsum(attrs.length_mm[merged]), math.fsum(attrs.time_s[merged])
        assert chunked.feed_mm_s[j] == (pytest.approx(span / dt, rel=1e-12) if dt > 1e-12 else 0.0)
        width = math.fsum(attrs.length_mm[merged] * attrs.width_mm[merged]) / span if span > 1e-12 else attrs.width_mm[
            chunked.move[j]]
        assert chunked.width_mm[j] == pytest.approx(width, rel=1e-12)


def test_spans_cover_the_polyline_and_meet_at_fixed_points() -> None:
    """Consecutive chunks share their boundary point, which is fixed (or the last point); together they cover all."""
    from neuralslicer.preview.data import spans

    fixed = np.zeros(1000, bool)
    fixed[[0, 130, 260, 261, 500, 999]] = True
    chunks = spans(fixed, size=200)
    assert chunks[0][0] == 0 and chunks[-1][1] == 999
    assert all(a < e for a, e in chunks) and all(e == a2 for (_, e), (a2, _) in zip(chunks[:-1], chunks[1:]))
    assert all(fixed[e] for _, e in chunks)
    assert spans(fixed[:1], size=200) == [(0, 0)] and spans(np.zeros(0, bool)) == []


def test_detail_levels_are_nested_and_fit_the_draw_budget() -> None:
    """Each coarser level is a subset of the finer one, the coarsest within the draw budget, every run's ends and the
    collisions in every level; where the runs' ends alone exceed the budget, coarser levels draw every other layer."""
    attrs = synthetic_moves()
    data = decimate(attrs, np.array([2500]), max_points=2000, draw_budget=300)
    counts = [int((data.level >= v).sum()) for v in range(int(data.level.max()) + 1)]
    assert counts[0] == len(data) and all(a > b for a, b in zip(counts, counts[1:])) and counts[-1] <= 300
    top = data.level == data.level.max()
    ends = np.r_[True, data.kind[1:] != data.kind[:-1]] | np.r_[data.kind[1:] != data.kind[:-1], True]
    assert ends.sum() == 12 and top[ends].all() and top[data.collisions].all()
    few = decimate(attrs, np.array([2500]), max_points=2000, draw_budget=10)     # 12 run ends on 3 layers
    coarsest = few.level == few.level.max()
    coarsest[few.collisions] = False
    assert set(few.layer[coarsest]) == {0, 2} and (few.level[few.collisions] == few.level.max()).all()


def test_a_print_that_collides_everywhere_marks_an_even_sample() -> None:
    """More colliding moves than a quarter of max_points: that many marked, spread over the print, all counted."""
    attrs = synthetic_moves()
    collided = np.flatnonzero(attrs.kind == PRINT)
    data = decimate(attrs, collided, max_points=800)
    assert data.n_collided == len(collided) and len(data.collisions) == 200 and len(data) <= 800
    marked = data.move[data.collisions]
    assert set(marked) <= set(collided) and marked[0] == collided[0] and marked[-1] == collided[-1]
    assert np.diff(marked).max() < 3 * len(collided) / 200


def test_within_the_budget_only_moves_on_the_lines_are_left_out() -> None:
    """Below max_points, a move is left out only within FLOOR_MM of the lines drawn; a straight run keeps its ends."""
    attrs = synthetic_moves(n_turns=1, per_turn=300)
    data = decimate(attrs, np.zeros(0, np.int64), max_points=10_000)
    assert 0 < data.max_deviation_mm <= FLOOR_MM and len(data) < data.n_drawable and data.level.max() == 0
    line = np.linspace([0.0, 0, 0], [10.0, 0, 0], 50)
    straight = MoveAttributes(line, np.tile([0.0, 0, 1], (50, 1)), np.full(50, PRINT, np.int8), np.zeros(50, np.int64),
                              np.full(50, 0.01), np.r_[0, np.full(49, 10 / 49)], np.full(50, 0.5), np.zeros(50))
    kept = decimate(straight, np.zeros(0, np.int64))
    assert kept.move.tolist() == [0, 49] and kept.max_deviation_mm < 1e-12
    assert kept.feed_mm_s[1] == pytest.approx(10 / (49 * 0.01))


def test_deviation_of_a_bent_line() -> None:
    """A right angle with its corner dropped: the corner lies half the diagonal from the chord."""
    tip = np.array([[0.0, 0, 0], [1, 0, 0], [1, 1, 0]])
    assert np.allclose(deviations(tip, np.array([True, False, True])), [0, np.sqrt(0.5), 0])


def embedded(html: str) -> dict:
    """The page's data."""
    match = re.search(r'<script type="application/json" id="preview-data">(.*?)</script>', html, re.S)
    assert match is not None
    return json.loads(match.group(1))


def decoded(a: dict) -> np.ndarray:
    """An array of the page's data, dequantised."""
    q = np.frombuffer(base64.b64decode(a["b64"]), np.dtype(a["dtype"]).newbyteorder("<"))
    return a.get("offset", 0.0) + a.get("scale", 1.0) * q.astype(np.float64) if "offset" in a else q


def test_page_is_self_contained_and_its_data_round_trips(curved) -> None:
    """One file: plotly.js from the plotly package inline, no URL to load; the embedded moves decode to the
    decimated ones within half a quantisation step."""
    tp, prog, metrics, _ = curved
    data = preview_data(prog, tp.width, np.array([5, 50]), max_points=5000)
    html = preview_html(data, "caps </script>", prog.profile.nozzle, {"n_layers": 3})
    assert plotly_js()[:2000] in html and len(plotly_js()) > 1_000_000
    ours = html.replace(plotly_js(), "")                   # (plotly.js names CDNs only for maps, never used here)
    assert not re.search(r'<script[^>]+src=|<link[^>]+href=|https?://', ours)
    doc = embedded(html)
    assert doc["schema"] == PREVIEW_SCHEMA and doc["n"] == len(data) and doc["title"] == "caps </script>"
    for k, col in (("x", 0), ("y", 1), ("z", 2)):
        assert np.abs(decoded(doc[k]) - data.tip[:, col]).max() <= 0.5 * doc[k]["scale"] + 1e-9
    assert np.array_equal(decoded(doc["layer"]), data.layer) and np.array_equal(decoded(doc["move"]), data.move)
    assert np.array_equal(decoded(doc["kind"]), data.kind) and np.array_equal(decoded(doc["level"]), data.level)
    assert np.abs(decoded(doc["tilt"]) - data.tilt_deg).max() <= 0.5 * 180 / 65535 + 1e-9
    assert np.abs(decoded(doc["feed"]) - data.feed_mm_s).max() <= 0.5 * doc["feed"]["scale"] + 1e-9
    axis = decoded(doc["axis"]).reshape(-1, 3) * doc["axis"]["scale"]
    assert np.abs(axis - data.axis).max() < 1e-4
    assert decoded(doc["collisions"]).tolist() == data.collisions.tolist()
    assert doc["head"]["cone_length"] == prog.profile.nozzle.cone_length


def test_write_preview_marks_the_colliding_moves(curved, tmp_path: Path) -> None:
    """The colliding waypoints' moves are marked; the file is written whole (no temporary left beside it)."""
    tp, prog, metrics, _ = curved
    hit = np.array([3, 40, len(tp) - 1])
    data = write_preview(tmp_path / PREVIEW_FILE, prog, tp.width, hit, "caps", metrics)
    assert sorted(prog.source[data.move[data.collisions]].tolist()) == hit.tolist()
    assert [p.name for p in tmp_path.iterdir()] == [PREVIEW_FILE]
    doc = embedded((tmp_path / PREVIEW_FILE).read_text())
    assert doc["stats"]["n_layers"] == 3 and doc["stats"]["n_collisions"] == metrics["n_collisions"]


def stored_run(tmp_path: Path, curved) -> Path:
    """An output folder whose run.json names a store holding the print (as `neuralslicer slice` leaves it)."""
    from neuralslicer.motion.collision import CollisionReport
    from neuralslicer.storage import ArtifactStore
    from neuralslicer.motion.output import Motion

    tp, prog, metrics, _ = curved
    hits = CollisionReport(np.array([7, 70]), np.zeros((2, 3)), np.zeros(2, np.int8))
    store = ArtifactStore(tmp_path / "store.zarr")
    group = "caps/motion/0123456789abcdef0123"
    store.write(group, *Motion(tp, prog, metrics, hits).to_arrays())
    run = tmp_path / "run"
    run.mkdir()
    (run / "run.json").write_text(json.dumps({"store": store.root, "groups": {"motion": group}}))
    return run


def test_cli_preview_rewrites_the_page_of_a_stored_run(tmp_path: Path, curved, capsys) -> None:
    """`neuralslicer preview RUN_DIR` writes RUN_DIR/preview.html from the store run.json names; bad folders and
    options end with one line naming them and exit code 2."""
    from neuralslicer.cli.main import main

    run = stored_run(tmp_path, curved)
    assert main(["preview", str(run)]) == 0
    out = capsys.readouterr().out
    assert f"preview: {run / PREVIEW_FILE}" in out and "2 colliding moves" in out
    doc = embedded((run / PREVIEW_FILE).read_text())
    assert doc["title"] == "caps: preview of print.gcode" and len(decoded(doc["collisions"])) == 2
    assert main(["preview", str(run), "--max-points", "500", "--out", str(tmp_path / "small.html")]) == 0
    assert embedded((tmp_path / "small.html").read_text())["n"] <= 500
    for argv, where in ((["preview", str(tmp_path / "none")], "none: no such folder"),
                        (["preview", str(tmp_path)], "run.json: no such file"),
                        (["preview", str(run), "--max-points", "x"], "--max-points: 'x' is not an integer")):
        assert main(argv) == 2
        assert where in capsys.readouterr().err
    (run / "run.json").write_text(json.dumps({"store": str(tmp_path / "gone.zarr"), "groups": {"motion": "a/b/c"}}))
    assert main(["preview", str(run)]) == 2
    assert "gone.zarr: no artifact store there" in capsys.readouterr().err
