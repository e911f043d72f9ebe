"""What the preview shows of a machine program: its moves back-plotted in the part frame, their colours, decimated.

The tool tip and tool axis of every move come from the program's machine coordinates through the profile's forward
kinematics (``ProgramMoves.forward``), so the page shows what the machine will do, not what the planner meant.
Retract and prime moves (the extruder alone) are left out. The rest is simplified as a polyline in the manner of
Douglas and Peucker: the first and last move of every run of one kind on one layer and the colliding moves are kept;
then, round by round, every stretch between kept moves farther than ``FLOOR_MM`` from its chord is split at its
farthest move and at its middle one (which keeps the rounds few), each taking its distance from the chord as its
significance. The page keeps the most significant moves, then repairs what that misjudged (the farthest move of every
stretch still far from its chord, the farthest first) up to ``max_points``, and says how far the moves left out lie
from the lines drawn. A kept move stands for the moves merged into it: its feed is their length over their time, its
bead width their length-weighted mean. Coarser nested levels (each the most significant half of the one before, the
last within the draw budget; or every other layer where the runs' ends alone are too many) let a view of many layers
draw few moves and a view of a few layers every kept one.
"""
from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass

import numpy as np

from neuralslicer.motion.planning import RETRACT, ProgramMoves
from neuralslicer.preview import DEFAULT_DRAW_BUDGET, DEFAULT_MAX_POINTS
from neuralslicer.toolpath.types import segment_lengths
from neuralslicer.types import BoolArray, FloatArray, IndexArray

#: at most this many coarser levels
MAX_LEVELS = 8
#: at most one in this many kept moves is marked as colliding (a sample of them where more collide)
MARKED_SHARE = 4
#: moves within this distance (mm) of the lines drawn are always left out
FLOOR_MM = 0.01
#: at most this many rounds of the simplification (each splits every stretch still farther than the floor once)
MAX_ROUNDS = 64
#: the share of ``max_points`` left to the repair (:func:`repaired`), and its rounds
REPAIR_SHARE, REPAIR_ROUNDS = 0.15, 8
#: moves per chunk of the simplification: chunks meet at kept moves, so the result does not depend on it; the memory
#: of its temporaries does (about 200 bytes a move)
CHUNK_MOVES = 250_000


@dataclass
class MoveAttributes:
    """Per-move values of a program, in execution order (n moves).

    tip, axis : (n, 3) float64 tool tip and unit tool axis in the part (build) frame, by forward kinematics;
    kind : (n,) int8 TRAVEL/PRINT/RETRACT; layer : (n,) int64; time_s : (n,) planned duration;
    length_mm : (n,) length of the move arriving at each pose (0 for the first); width_mm : (n,) bead width of the
    toolpath waypoint the move belongs to; tilt_deg : (n,) angle of the tool axis from +z.
    """

    tip: FloatArray
    axis: FloatArray
    kind: np.ndarray
    layer: IndexArray
    time_s: FloatArray
    length_mm: FloatArray
    width_mm: FloatArray
    tilt_deg: FloatArray

    def axes_at(self, moves: IndexArray) -> tuple[FloatArray, FloatArray]:
        """Tool axes (k, 3) and tilts (k,) of the moves ``moves``."""
        return self.axis[moves], self.tilt_deg[moves]


@dataclass
class Drawable:
    """The moves a preview can draw (a program's moves without its retractions: d of ``n_moves``), in execution
    order: ``move`` (d,) int64 their indices in the program, ``tip`` (d, 3) float64 their tool tips, ``kind`` (d,)
    int8, ``layer`` (d,) int64."""

    move: IndexArray
    tip: FloatArray
    kind: np.ndarray
    layer: IndexArray
    n_moves: int


#: per drawable move in [a, b) (indices into a :class:`Drawable`): the length of the move arriving there, its bead
#: width and its planned time, each (b - a,) float64 and the caller's to change
MoveValues = Callable[[int, int], tuple[FloatArray, FloatArray, FloatArray]]


@dataclass
class PreviewData:
    """The moves a preview draws (k kept of ``n_moves``), in execution order.

    move : (k,) int64 index of each kept move in the program; tip, axis : (k, 3) float64; layer : (k,) int64; kind :
    (k,) int8; tilt_deg, feed_mm_s, width_mm : (k,) float64 (feed and width over the merged moves); level : (k,)
    uint8 the coarsest detail level each kept move is drawn at (:func:`detail_levels`); collisions : (c,) int64
    indices into the kept moves of those whose head collides; max_deviation_mm, mean_deviation_mm: how far the moves
    left out lie from the drawn lines; n_moves, n_drawable: the program's moves, and those that move the tip
    (retractions left out); draw_budget: the most moves one view draws; n_collided: the colliding moves
    (``collisions`` marks them all, or an even sample of ``max_points / MARKED_SHARE`` where there are more).
    """

    move: IndexArray
    tip: FloatArray
    axis: FloatArray
    layer: IndexArray
    kind: np.ndarray
    tilt_deg: FloatArray
    feed_mm_s: FloatArray
    width_mm: FloatArray
    level: np.ndarray
    collisions: IndexArray
    max_deviation_mm: float
    mean_deviation_mm: float
    n_moves: int
    n_drawable: int
    draw_budget: int = DEFAULT_DRAW_BUDGET
    n_collided: int = 0

    def __len__(self) -> int:
        """Number of kept moves."""
        return int(len(self.move))

    @property
    def factor(self) -> float:
        """Decimation factor: drawable moves per kept move (1 when nothing is left out)."""
        return self.n_drawable / max(len(self), 1)

    def summary(self) -> dict[str, float | int]:
        """JSON-able figures of the decimation."""
        return {"n_moves": self.n_moves, "n_drawable": self.n_drawable, "n_drawn": len(self),
                "factor": round(self.factor, 3), "max_deviation_mm": round(self.max_deviation_mm, 4),
                "mean_deviation_mm": round(self.mean_deviation_mm, 5), "n_collisions": int(len(self.collisions)),
                "n_collided": self.n_collided,
                "draw_budget": self.draw_budget, "levels": [int((self.level >= v).sum()) for v in
                                                            range(int(self.level.max(initial=0)) + 1)]}


def waypoint_values(source: IndexArray, values: FloatArray) -> FloatArray:
    """Per-move value (n,) of the toolpath waypoint each move belongs to: its own ``source`` or, for inserted moves
    (source -1: rotary splits, retract/prime, the approach), the next move's waypoint (the last one's for the end)."""
    n = len(source)
    if n == 0 or len(values) == 0:
        return np.zeros(n)
    pos = np.flatnonzero(source >= 0)
    if len(pos) == 0:
        return np.zeros(n)
    nxt = np.searchsorted(pos, np.arange(n))          # the first move at or after each one with a waypoint
    return np.asarray(values, np.float64)[source[pos[np.minimum(nxt, len(pos) - 1)]]]


def move_attributes(program: ProgramMoves, widths: FloatArray) -> MoveAttributes:
    """Every move's tip and axis by forward kinematics, and its length, bead width and tilt (``widths``: (w,) the
    toolpaths' width per waypoint). What the preview draws is :func:`preview_data`'s, which makes these only where it
    needs them."""
    tip, axis = program.forward()
    tip, axis = np.asarray(tip, np.float64), np.asarray(axis, np.float64)
    return MoveAttributes(tip, axis, np.asarray(program.kind, np.int8), np.asarray(program.layer, np.int64),
                          np.asarray(program.time_s, np.float64), segment_lengths(tip),
                          waypoint_values(np.asarray(program.source, np.int64), widths), tilt_degrees(axis))


def drawable_moves(program: ProgramMoves) -> Drawable:
    """The program's drawable moves with their tips by forward kinematics, :data:`CHUNK_MOVES` at a time (no array
    of every move's tip: 24 bytes a move less)."""
    kind = np.asarray(program.kind, np.int8)
    draw = np.flatnonzero(kind != RETRACT)
    tip = np.empty((len(draw), 3))
    for a in range(0, len(draw), CHUNK_MOVES):
        tip[a:a + CHUNK_MOVES] = program.forward(draw[a:a + CHUNK_MOVES])[0]
    return Drawable(draw, tip, kind[draw], np.asarray(program.layer)[draw].astype(np.int64, copy=False), len(kind))


def program_axes(program: ProgramMoves, moves: IndexArray) -> tuple[FloatArray, FloatArray]:
    """Tool axes (k, 3) and tilts (k,) of the program's moves ``moves`` by forward kinematics."""
    axis = program.forward(moves)[1]
    return axis, tilt_degrees(axis)


def program_values(program: ProgramMoves, widths: FloatArray, drawable: Drawable) -> MoveValues:
    """:data:`MoveValues` of the drawable moves from the program, a range at a time: what
    ``segment_lengths`` of every move's tip, :func:`waypoint_values` and the program's times give at them."""
    source = np.asarray(program.source, np.int64)
    draw, tip = drawable.move, drawable.tip
    reversed_sourced = source[::-1] >= 0
    last = len(source) - 1 - int(reversed_sourced.argmax()) if reversed_sourced.any() else -1   # the last with one
    del reversed_sourced

    def values(a: int, b: int) -> tuple[FloatArray, FloatArray, FloatArray]:
        """Length, width and time of the drawable moves [a, b)."""
        rows, at = draw[a:b], np.arange(a, b)
        before = np.empty((b - a, 3))
        inner = (at > 0) & (draw[np.maximum(at - 1, 0)] == rows - 1)   # the move before is drawable: its tip is here
        before[inner] = tip[at[inner] - 1]
        outer = np.flatnonzero(~inner)                                 # after a retraction, or the program's first
        first = rows[outer] == 0
        before[outer[first]] = tip[a + outer[first]]
        if (~first).any():
            before[outer[~first]] = program.forward(rows[outer[~first]] - 1)[0]
        length = np.linalg.norm(tip[a:b] - before, axis=1)
        return length, _widths_at(source, widths, rows, last), np.asarray(program.time_s)[rows].astype(np.float64, copy=False)

    return values


def _widths_at(source: IndexArray, widths: FloatArray, rows: IndexArray, last: int) -> FloatArray:
    """:func:`waypoint_values` of ``widths`` at the moves ``rows`` (sorted): each the width of the first move at or
    after it with a waypoint (``last``, the last such move, for those after it), found within their span."""
    if last < 0 or not len(rows):
        return np.zeros(len(rows))
    lo, hi = int(rows[0]), int(rows[-1]) + 1
    while hi <= last and source[hi - 1] < 0:            # the span ends on a move with a waypoint (or past the last)
        hi += 1
    span = source[lo:hi]
    at = np.where(span >= 0, np.arange(lo, hi), last)
    nxt = np.minimum.accumulate(at[::-1])[::-1]
    return np.asarray(widths, np.float64)[source[np.minimum(nxt[rows - lo], last)]]


def tilt_degrees(axis: FloatArray) -> FloatArray:
    """Angle (k,) of tool axes (k, 3) from +z, in degrees."""
    return np.degrees(np.arccos(np.clip(axis[:, 2] / np.maximum(np.linalg.norm(axis, axis=1), 1e-300), -1.0, 1.0)))


def colliding_moves(source: IndexArray, waypoints: IndexArray) -> IndexArray:
    """Indices of the moves (sorted) that reach the colliding toolpath waypoints ``waypoints``."""
    hit = np.asarray(waypoints, np.int64)
    if len(hit) == 0 or len(source) == 0:
        return np.zeros(0, np.int64)
    return np.flatnonzero(np.isin(source, hit))


def run_ends(kind: np.ndarray, layer: IndexArray) -> BoolArray:
    """Moves (m,) that start or end a run of one kind on one layer."""
    m = len(kind)
    ends = np.zeros(m, bool)
    if m:
        ends[0] = ends[-1] = True
        change = (kind[1:] != kind[:-1]) | (layer[1:] != layer[:-1])
        ends[1:] |= change
        ends[:-1] |= change
    return ends


def deviations(tip: FloatArray, keep: BoolArray) -> FloatArray:
    """Distance (m,) of every point from the segment between the kept points around it (0 at kept points)."""
    m = len(tip)
    idx = np.arange(m)
    prev = np.maximum.accumulate(np.where(keep, idx, 0))
    nxt = np.minimum.accumulate(np.where(keep, idx, m - 1)[::-1])[::-1]
    a, b = tip[prev], tip[nxt]
    ab = b - a
    t = np.einsum("ij,ij->i", tip - a, ab) / np.maximum(np.einsum("ij,ij->i", ab, ab), 1e-300)
    closest = a + np.clip(t, 0.0, 1.0)[:, None] * ab
    return np.linalg.norm(tip - closest, axis=1)


def spans(fixed: BoolArray, size: int | None = None) -> list[tuple[int, int]]:
    """Chunks (first, last), inclusive, of about ``size`` (default :data:`CHUNK_MOVES`) points that cover a polyline
    of ``len(fixed)`` points: each ends at a ``fixed`` point (or the polyline's last) where the next one starts, so
    no stretch between fixed points crosses two chunks."""
    size = CHUNK_MOVES if size is None else size
    m = len(fixed)
    if m == 0:
        return []
    at = np.flatnonzero(fixed)
    bounds = at[np.searchsorted(at, np.arange(size, m - 1, size))] if len(at) else np.zeros(0, np.int64)
    bounds = np.unique(np.r_[0, bounds[bounds < m - 1], m - 1])
    return [(int(a), int(e)) for a, e in zip(bounds[:-1], bounds[1:], strict=True)] or [(0, m - 1)]


def deviation_summary(tip: FloatArray, keep: BoolArray, chunks: list[tuple[int, int]]) -> tuple[float, float]:
    """The largest and the mean of :func:`deviations`, a chunk (:func:`spans`, meeting at kept points) at a time."""
    largest, total = 0.0, 0.0
    for a, e in chunks:
        dev = deviations(tip[a:e + 1], keep[a:e + 1])
        largest, total = max(largest, float(dev.max())), total + float(dev.sum())
    return largest, total / max(len(tip), 1)


def _distances(p: FloatArray, a: FloatArray, b: FloatArray) -> FloatArray:
    """Distance (k,) of points ``p`` from the segments ``a``-``b`` (each (k, 3))."""
    ab = b - a
    t = np.einsum("ij,ij->i", p - a, ab) / np.maximum(np.einsum("ij,ij->i", ab, ab), 1e-300)
    return np.linalg.norm(p - (a + np.clip(t, 0.0, 1.0)[:, None] * ab), axis=1)


def farthest_per_stretch(tip: FloatArray, keep: BoolArray, candidates: IndexArray
                         ) -> tuple[IndexArray, FloatArray, IndexArray, FloatArray, IndexArray]:
    """For each stretch between consecutive kept points holding some of ``candidates`` (sorted, none kept): its
    candidate farthest from the stretch's chord and that distance, its middle candidate and that one's distance; and
    the stretch (0, 1, ...) of every candidate."""
    m = len(tip)
    idx = np.arange(m)
    prev = np.maximum.accumulate(np.where(keep, idx, 0))
    nxt = np.minimum.accumulate(np.where(keep, idx, m - 1)[::-1])[::-1]
    start = prev[candidates]
    d = _distances(tip[candidates], tip[start], tip[nxt[candidates]])
    new = np.r_[True, start[1:] != start[:-1]]
    first = np.flatnonzero(new)
    stretch = np.cumsum(new) - 1
    far = np.maximum.reduceat(d, first)
    at = np.flatnonzero(d == far[stretch])
    at = at[np.r_[True, stretch[at][1:] != stretch[at][:-1]]]       # the first farthest of each stretch
    mid = first + np.diff(np.r_[first, len(candidates)]) // 2
    return candidates[at], far, candidates[mid], d[mid], stretch


def significance(tip: FloatArray, fixed: BoolArray, floor_mm: float = FLOOR_MM, max_rounds: int = MAX_ROUNDS,
                 chunks: list[tuple[int, int]] | None = None) -> FloatArray:
    """How much each point of a polyline matters (m,): inf for the ``fixed`` ones and its ends; else its distance
    from the chord of the stretch it split when the simplification (see the module) took it; 0 for those it left
    within ``floor_mm`` of the lines. ``chunks`` (:func:`spans` of ``fixed``): computed a chunk at a time, the same
    result in a chunk's memory."""
    if chunks is not None and len(chunks) > 1:
        sig = np.empty(len(tip))
        for a, e in chunks:
            sig[a:e + 1] = significance(tip[a:e + 1], fixed[a:e + 1], floor_mm, max_rounds)
        return sig
    m = len(tip)
    sig = np.zeros(m)
    keep = fixed.copy()
    if m:
        keep[0] = keep[-1] = True
    sig[keep] = np.inf
    open_ = np.flatnonzero(~keep)                        # points of stretches still farther than the floor
    for _ in range(max_rounds):
        if not len(open_):
            break
        far_pts, far, mid_pts, mid, stretch = farthest_per_stretch(tip, keep, open_)
        split = far > floor_mm
        open_ = open_[split[stretch]]
        for pts, dist in ((mid_pts[split], mid[split]), (far_pts[split], far[split])):
            sig[pts] = np.maximum(dist, np.finfo(float).tiny)
            keep[pts] = True
        open_ = open_[~keep[open_]]
    return sig


def most_significant(sig: FloatArray, budget: int) -> BoolArray:
    """The points to keep (m,): every one of infinite significance, and of the others (significance > 0) the most
    significant while at most ``budget`` are kept in all."""
    keep = np.isinf(sig)
    rest = np.flatnonzero((sig > 0) & ~keep)
    room = budget - int(keep.sum())
    if room >= len(rest):
        keep[rest] = True
    elif room > 0:
        keep[rest[np.argpartition(-sig[rest], room - 1)[:room]]] = True
    return keep


def repaired(tip: FloatArray, sig: FloatArray, keep: BoolArray, max_points: int, floor_mm: float = FLOOR_MM,
             rounds: int = REPAIR_ROUNDS, chunks: list[tuple[int, int]] | None = None) -> BoolArray:
    """``keep`` with, round by round, the farthest point of every stretch between kept points farther than
    ``floor_mm`` from its chord added (the farthest stretches first), while at most ``max_points`` are kept: what
    the significance misjudged (a point taken early against a chord that the threshold dropped). Raises ``sig`` of the
    points added to their distance (in place), so that the coarser levels rank them by it. ``chunks``
    (:func:`spans`, meeting at kept points): the stretches found a chunk at a time, the same result."""
    keep = keep.copy()
    chunks = chunks or [(0, len(tip) - 1)]
    for _ in range(rounds):
        room = max_points - int(keep.sum())
        if room <= 0:
            break
        found = []
        for a, e in chunks:
            open_ = np.flatnonzero(~keep[a:e + 1])
            if len(open_):
                pts, far, _, _, _ = farthest_per_stretch(tip[a:e + 1], keep[a:e + 1], open_)
                found.append((pts[far > floor_mm] + a, far[far > floor_mm]))
        if not found:
            break
        pts, far = np.concatenate([p for p, _ in found]), np.concatenate([f for _, f in found])
        if len(pts) > room:
            top = np.argpartition(-far, room - 1)[:room]
            pts, far = pts[top], far[top]
        if not len(pts):
            break
        keep[pts] = True
        sig[pts] = np.maximum(sig[pts], far)
    return keep


def every_other_layer(layer: IndexArray) -> BoolArray:
    """Points (m,) on every other layer of those present, counted from the last one down (the top stays)."""
    present = np.unique(layer)
    kept = present[::-1][::2]
    return np.isin(layer, kept)


def detail_levels(sig: FloatArray, layer: IndexArray, keep_also: BoolArray, draw_budget: int) -> np.ndarray:
    """Nested coarser subsets of the kept points, for views that would draw more than ``draw_budget``: (k,) uint8,
    the coarsest level each point belongs to. Level 0 is the kept points; level l + 1 keeps the most significant half
    of level l (``sig``: :func:`significance`), or, where the runs' ends alone exceed that, every other layer of level
    l whole; ``keep_also`` stays in every level; the last level fits ``draw_budget`` (or is the
    :data:`MAX_LEVELS`-th)."""
    level = np.zeros(len(sig), np.uint8)
    current = np.ones(len(sig), bool)
    while current.sum() > draw_budget and level.max() < MAX_LEVELS:
        size = int(current.sum())
        if (np.isinf(sig) & current).sum() > 0.75 * size:
            coarser = current & (every_other_layer(np.where(current, layer, -1)) | keep_also)
        else:
            coarser = most_significant(np.where(current, sig, 0.0), max(draw_budget, size // 2))
        if coarser.sum() == size:
            break
        current = coarser
        level[current] += 1
    return level


def decimate(attrs: MoveAttributes, collided: IndexArray, max_points: int = DEFAULT_MAX_POINTS,
             draw_budget: int = DEFAULT_DRAW_BUDGET) -> PreviewData:
    """The moves to draw of every move's attributes (:func:`simplify`; ``collided``: the colliding moves)."""
    draw = np.flatnonzero(attrs.kind != RETRACT)

    def values(a: int, b: int) -> tuple[FloatArray, FloatArray, FloatArray]:
        """Length, width and time of the drawable moves [a, b)."""
        rows = draw[a:b]
        return attrs.length_mm[rows], attrs.width_mm[rows], attrs.time_s[rows]

    drawable = Drawable(draw, attrs.tip[draw], attrs.kind[draw], attrs.layer[draw], len(attrs.tip))
    return simplify(drawable, collided, values, attrs.axes_at, max_points, draw_budget)


def simplify(drawable: Drawable, collided: IndexArray, values: MoveValues,
             axes_at: Callable[[IndexArray], tuple[FloatArray, FloatArray]], max_points: int = DEFAULT_MAX_POINTS,
             draw_budget: int = DEFAULT_DRAW_BUDGET) -> PreviewData:
    """The moves to draw (see the module): at most ``max_points`` (more only where the runs' ends and the
    collisions alone exceed it), with coarser nested levels of at most ``draw_budget`` for wide views. ``collided``:
    the program's colliding moves; ``values``: the drawable moves' lengths, widths and times; ``axes_at``: the tool
    axes and tilts of program moves (asked for the kept ones only)."""
    draw, tip, kind, layer = drawable.move, drawable.tip, drawable.kind, drawable.layer
    hit = np.zeros(len(draw), bool)
    marked = collided[np.isin(collided, draw)]
    n_collided = len(marked)
    if n_collided > max_points // MARKED_SHARE:           # a print that hits everywhere: mark a sample, evenly
        marked = marked[np.linspace(0, n_collided - 1, max_points // MARKED_SHARE).astype(np.int64)]
    hit[np.searchsorted(draw, marked)] = True
    fixed = run_ends(kind, layer) | hit
    chunks = spans(fixed)
    sig = significance(tip, fixed, chunks=chunks)
    del fixed
    keep = repaired(tip, sig, most_significant(sig, int(max_points * (1 - REPAIR_SHARE))), max_points, chunks=chunks)
    max_dev, mean_dev = deviation_summary(tip, keep, chunks)
    kept = np.flatnonzero(keep)
    del keep
    moves = draw[kept]
    span, width, dt, own_width = merged_values(values, kept, len(draw))
    width = np.divide(width, span, out=own_width, where=span > 1e-12)
    feed = np.divide(span, dt, out=np.zeros(len(kept)), where=dt > 1e-12)
    level = detail_levels(sig[kept], layer[kept], hit[kept], draw_budget)
    axis, tilt = axes_at(moves)
    return PreviewData(move=moves.astype(np.int64), tip=tip[kept], axis=axis, layer=layer[kept],
                       kind=kind[kept], tilt_deg=tilt, feed_mm_s=feed, width_mm=width,
                       level=level, collisions=np.flatnonzero(hit[kept]).astype(np.int64),
                       max_deviation_mm=max_dev, mean_deviation_mm=mean_dev, n_moves=drawable.n_moves,
                       n_drawable=len(draw), draw_budget=draw_budget, n_collided=n_collided)


def merged_values(values: MoveValues, kept: IndexArray, n: int) -> tuple[FloatArray, FloatArray, FloatArray, FloatArray]:
    """Per kept move (k,) of ``n`` drawable ones: the length, the length-weighted width and the time of the moves
    merged into it (after the kept move before, up to this one; the first drawable move's length and time count as
    0), and its own width;
    :data:`CHUNK_MOVES` drawable moves at a time (each chunk ends at a kept move: the same sums as the whole's)."""
    span, width, dt, own = (np.zeros(len(kept)) for _ in range(4))
    if not len(kept):
        return span, width, dt, own
    cuts = np.unique(np.r_[0, np.searchsorted(kept, np.arange(CHUNK_MOVES, n, CHUNK_MOVES)), len(kept)])
    for i, j in zip(cuts[:-1], cuts[1:], strict=True):
        a, b = (int(kept[i - 1]) + 1 if i else int(kept[0])), int(kept[j - 1]) + 1
        length, w, t = values(a, b)
        if a == 0:
            length[0] = t[0] = 0.0
        starts = np.r_[a, kept[i:j - 1] + 1] - a
        span[i:j] = np.add.reduceat(length, starts)
        width[i:j] = np.add.reduceat(length * w, starts)
        dt[i:j] = np.add.reduceat(t, starts)
        own[i:j] = w[kept[i:j] - a]
    return span, width, dt, own


def preview_data(program: ProgramMoves, widths: FloatArray, collided_waypoints: IndexArray,
                 max_points: int = DEFAULT_MAX_POINTS, draw_budget: int = DEFAULT_DRAW_BUDGET) -> PreviewData:
    """The decimated moves of a program to draw: ``widths`` (w,) the toolpaths' bead width per waypoint,
    ``collided_waypoints`` the toolpath waypoint indices whose head collides (``CollisionReport.indices``). The tips
    are made for the drawable moves only, their lengths, widths and times a chunk at a time, the axes for the kept
    moves: the same as :func:`decimate` of every move's attributes, in about 45 bytes a move instead of 100."""
    drawable = drawable_moves(program)
    return simplify(drawable, colliding_moves(np.asarray(program.source, np.int64), collided_waypoints),
                    program_values(program, widths, drawable), lambda moves: program_axes(program, moves),
                    max_points, draw_budget)
