"""Nozzle collision checks against the printed part and the platform (build frame).

The print head is a cone (apex at the tool tip, axis along the tool axis, half angle and length
from the profile) topped by a holder cylinder. The printed material is represented by the
waypoints of all *previous* layers (points on the top surfaces of the deposited beads), kept in
a log-structured set of KD-trees (Bentley-Saxe: O(log L) trees, amortised O(N log N) building).
For every waypoint, a material point inside the largest ball in the cone certifies a hit with one
nearest-neighbour query; for the poses left, the holder is tested against cells of material (whole
cells inside it or outside it at once, the points of the cells on its boundary one by one), and the
points inside balls that together enclose the cone (slabs about as long as wide) are fetched from the
trees (counted first in C, so poses with nothing nearby cost one query each) and tested exactly.
Poses whose head lies wholly above the material's highest point (``head_lowest_z``) are skipped, and
the trees are built only when a pose is left to query: on a part printed bottom-up with a vertical
tool, a planar part, the check costs a few array operations per waypoint.
The platform test is exact: the lowest point of the cone and of the holder against z = platform_z.
"""
from __future__ import annotations

from dataclasses import dataclass
from itertools import chain
from typing import Iterator

import numpy as np
from scipy.spatial import cKDTree

from neuralslicer.motion.profile import Nozzle
from neuralslicer.toolpath.types import Toolpaths
from neuralslicer.types import BoolArray, FloatArray, IndexArray

PART, PLATFORM, TRAVEL_PATH = 0, 1, 2


@dataclass
class CollisionReport:
    """Collisions found: waypoint indices, a colliding location each, and the kind (PART/PLATFORM at the
    waypoint, TRAVEL_PATH: somewhere along the non-printing move arriving at it)."""

    indices: IndexArray
    locations: FloatArray
    kind: np.ndarray

    @property
    def count(self) -> int:
        """Number of colliding waypoints."""
        return int(len(self.indices))

    def replaced(self, checked: IndexArray, again: "CollisionReport") -> "CollisionReport":
        """This report with the waypoints ``checked`` again replaced by what the new check found there."""
        keep = ~np.isin(self.indices, checked)
        idx = np.concatenate([self.indices[keep], again.indices])
        order = np.argsort(idx, kind="stable")
        return CollisionReport(idx[order], np.concatenate([self.locations[keep], again.locations])[order],
                               np.concatenate([self.kind[keep], again.kind])[order])

    def subset(self, mask: BoolArray) -> "CollisionReport":
        """The collisions selected by a boolean mask over this report's entries."""
        return CollisionReport(self.indices[mask], self.locations[mask], self.kind[mask])

    def summary(self) -> dict:
        """JSON-able counts."""
        return {"n_collisions": self.count, "n_part_collisions": int((self.kind == PART).sum()),
                "n_platform_collisions": int((self.kind == PLATFORM).sum()),
                "n_travel_collisions": int((self.kind == TRAVEL_PATH).sum()),
                "first_collision_waypoints": [int(i) for i in self.indices[:20]]}


def _inside_head(d: FloatArray, axis: FloatArray, nozzle: Nozzle, min_height: float) -> BoolArray:
    """Exact membership of offsets ``d = point - tip`` (k,3) in the head along ``axis`` (k,3)."""
    h = np.einsum("ij,ij->i", d, axis)
    radial = np.sqrt(np.maximum(np.einsum("ij,ij->i", d, d) - h * h, 0.0))
    L = nozzle.cone_length
    cone = (h >= min_height) & (h <= L) & (radial <= h * np.tan(np.radians(nozzle.cone_half_angle_deg)))
    return cone | _holder_test(h, radial, nozzle)


def _holder_test(h: FloatArray, radial: FloatArray, nozzle: Nozzle) -> BoolArray:
    """In the holder: above the cone (strictly), up to its top, within its radius."""
    L = nozzle.cone_length
    return (h > L) & (h <= L + nozzle.holder_length) & (radial <= nozzle.holder_radius)


def _in_holder(d: FloatArray, axis: FloatArray, nozzle: Nozzle) -> BoolArray:
    """Exact membership of offsets ``d`` (k,3) in the holder along ``axis`` (k,3) (the head's own rule)."""
    h = np.einsum("ij,ij->i", d, axis)
    return _holder_test(h, np.sqrt(np.maximum(np.einsum("ij,ij->i", d, d) - h * h, 0.0)), nozzle)


def _frustum_ball(a: float, b: float, ra: float, rb: float) -> tuple[float, float]:
    """Smallest ball centred on the axis enclosing the frustum between heights a < b (rim radii ra, rb)."""
    c = float(np.clip((b * b + rb * rb - a * a - ra * ra) / (2 * (b - a) + 1e-300), a, b))
    return c, float(max(np.hypot(c - a, ra), np.hypot(b - c, rb)))


def head_parts(nozzle: Nozzle, min_height: float, holder: bool = True) -> list[tuple[float, float]]:
    """(height of the centre on the axis, radius) of balls that together enclose the head above min_height
    (the cone only with ``holder=False``).

    The cone frustum and the holder are cut into slabs about as long as they are wide, each in its own
    ball, so the candidate points fetched per pose stay close to the head's volume.
    """
    L = nozzle.cone_length
    h0 = min(max(min_height, 0.0), L)
    ta = np.tan(np.radians(nozzle.cone_half_angle_deg))
    parts = []
    n_cone = max(1, int(np.ceil((L - h0) / max(2.0 * L * ta, 1e-9))))
    cuts = np.linspace(h0, L, n_cone + 1)
    parts += [_frustum_ball(a, b, a * ta, b * ta) for a, b in zip(cuts[:-1], cuts[1:])]
    if holder and nozzle.holder_length > 0:
        R = nozzle.holder_radius
        n_hold = max(1, int(np.ceil(nozzle.holder_length / max(R, 1e-9))))
        cuts = np.linspace(L, L + nozzle.holder_length, n_hold + 1)
        parts += [(0.5 * (a + b), float(np.hypot(0.5 * (b - a), R))) for a, b in zip(cuts[:-1], cuts[1:])]
    return parts


def head_cores(nozzle: Nozzle, min_height: float) -> list[tuple[float, float]]:
    """(height of the centre on the axis, radius) of balls inside the cone: a point in one is a hit. The holder has
    none: its cells (``_holder_hits``) classify whole cells inside it at once, and a ball query of the holder's size
    (15 mm on the default head) near dense material cost most of the check while finding what the cells find
    (topopt_new4, 50 layers, 558k waypoints: 33.5 s with a holder core, 19.2 s without, the same hits)."""
    L = nozzle.cone_length
    sa = np.sin(np.radians(nozzle.cone_half_angle_deg))
    c = L / (1.0 + sa)                      # largest ball in the cone below its base: r = c sin(a), c + r = L
    return [(float(c), float(c * sa))] if c - c * sa >= min_height else []


def platform_clearance(xyz: FloatArray, axis: FloatArray, nozzle: Nozzle, platform_z: float) -> FloatArray:
    """Height of the lowest point of the head above the platform, per waypoint (n,) (exact)."""
    az = np.clip(axis[:, 2], -1.0, 1.0)
    horiz = np.sqrt(np.maximum(0.0, 1.0 - az ** 2))
    L, ta = nozzle.cone_length, np.tan(np.radians(nozzle.cone_half_angle_deg))
    cone_base_low = L * az - L * ta * horiz
    low = np.minimum(0.0, cone_base_low)
    if nozzle.holder_length > 0:
        for h in (L, L + nozzle.holder_length):
            low = np.minimum(low, h * az - nozzle.holder_radius * horiz)
    return xyz[:, 2] + low - platform_z


#: threads of the KD-tree queries (-1: one per core; the queries are independent per pose)
QUERY_WORKERS = -1

#: edge (mm) of the cells that stand for the material in the holder test
CELL_SIZE = 3.0


@dataclass
class _Cells:
    """Material points binned in cubes of ``CELL_SIZE``: per non-empty cell the centroid, the largest distance
    of its points from it, and its points (``order[start[c]:start[c] + count[c]]``), with a KD-tree over the
    centroids. A cell whose bounding ball lies in the holder is a hit, one outside it is skipped, and only the
    points of cells on the holder's boundary are tested one by one."""

    centroid: FloatArray
    radius: FloatArray
    start: IndexArray
    count: IndexArray
    order: IndexArray
    tree: cKDTree

    @classmethod
    def of(cls, pts: FloatArray, size: float = CELL_SIZE) -> "_Cells":
        """Cells of points (k, 3)."""
        key = np.floor(pts / size).astype(np.int64)
        key -= key.min(axis=0)
        span = key.max(axis=0) + 1
        flat = (key[:, 0] * span[1] + key[:, 1]) * span[2] + key[:, 2]
        order = np.argsort(flat, kind="stable")
        flat_sorted = flat[order]
        first = np.flatnonzero(np.r_[True, flat_sorted[1:] != flat_sorted[:-1]])
        count = np.diff(np.r_[first, len(flat)])
        cell_of = np.repeat(np.arange(len(first)), count)
        sorted_pts = pts[order]
        centroid = np.add.reduceat(sorted_pts, first, axis=0) / count[:, None]
        dist = np.linalg.norm(sorted_pts - centroid[cell_of], axis=1)
        return cls(centroid, np.maximum.reduceat(dist, first), first.astype(np.int64), count.astype(np.int64),
                   order.astype(np.int64), cKDTree(centroid))


class _TreeSet:
    """Points added in batches (a layer at a time), queried as a union of two KD-trees: one over the bulk and one
    over the batches added since the bulk was last rebuilt (rebuilt on each query after an add). Every query
    visits each tree, and a query costs about as much on a tree of 50k points as on one of millions, so two
    trees beat the logarithmic method's up to 2 log2(layers) (the 200 mm bunny's 411 curved layers, layer 150:
    the cone's ball counts 3.4 s over five trees, 1.1 s over two). The bulk is rebuilt once the recent points
    exceed ``RECENT_FRACTION`` of it, so the rebuilds cost a few times one tree over all points. The trees are
    built on the first query (``blocks``), so material that no pose can reach (``top``) costs no tree."""

    #: the recent points are merged into the bulk once there are more than this fraction of it (or MIN_RECENT)
    RECENT_FRACTION = 0.15
    MIN_RECENT = 100_000

    def __init__(self) -> None:
        self._bulk: tuple[FloatArray, cKDTree, _Cells] | None = None
        self._recent: list[FloatArray] = []
        self._recent_tree: tuple[FloatArray, cKDTree, _Cells] | None = None
        self._dirty = False
        #: highest z of all points added (-inf when empty)
        self.top = -np.inf

    def add(self, pts: FloatArray) -> None:
        """Add a batch of points (k, 3); the trees take it in on the next query."""
        if len(pts) == 0:
            return
        self._recent.append(np.asarray(pts, np.float64))
        self._dirty = True
        self.top = max(self.top, float(pts[:, 2].max()))

    @staticmethod
    def _tree(pts: FloatArray) -> tuple[FloatArray, cKDTree, _Cells]:
        return pts, cKDTree(pts), _Cells.of(pts)

    def _flush(self) -> None:
        if not self._dirty:
            return
        self._dirty = False
        recent = np.concatenate(self._recent) if len(self._recent) > 1 else self._recent[0]
        self._recent = [recent]
        bulk_n = 0 if self._bulk is None else len(self._bulk[0])
        if len(recent) > max(self.RECENT_FRACTION * bulk_n, self.MIN_RECENT):
            self._bulk = self._tree(recent if self._bulk is None else np.concatenate([self._bulk[0], recent]))
            self._recent, self._recent_tree = [], None
        else:
            self._recent_tree = self._tree(recent)

    def _trees(self) -> list[tuple[FloatArray, cKDTree, _Cells]]:
        self._flush()
        return [t for t in (self._bulk, self._recent_tree) if t is not None]

    @property
    def blocks(self) -> list[tuple[FloatArray, cKDTree]]:
        """(points (k, 3), KD-tree) per tree."""
        return [(pts, tree) for pts, tree, _ in self._trees()]

    @property
    def cells(self) -> list[_Cells]:
        """The cells of each tree's points (``_Cells``), in the order of ``blocks``."""
        return [cells for _, _, cells in self._trees()]


def head_lowest_z(xyz: FloatArray, axis: FloatArray, nozzle: Nozzle, min_height: float) -> FloatArray:
    """Lowest z (n,) of the part of the head above ``min_height`` along the tool axis (what ``_inside_head``
    counts), for tips ``xyz`` (n, 3) and unit axes (n, 3); exact up to rounding. The cone frustum and the
    holder are linear in the height along the axis, so the lowest point lies on one of their end rims."""
    az = np.clip(axis[:, 2], -1.0, 1.0)
    horiz = np.sqrt(np.maximum(0.0, 1.0 - az ** 2))
    L, ta = nozzle.cone_length, np.tan(np.radians(nozzle.cone_half_angle_deg))
    h0 = min(max(min_height, 0.0), L)
    low = np.minimum(h0 * (az - ta * horiz), L * (az - ta * horiz))
    if nozzle.holder_length > 0:
        for h in (L, L + nozzle.holder_length):
            low = np.minimum(low, h * az - nozzle.holder_radius * horiz)
    return xyz[:, 2] + low


#: margin (mm) of the reach test: rounding in the exact tests moves points by far less
_REACH_TOL = 1e-6


def _may_reach(material: _TreeSet, xyz: FloatArray, axis: FloatArray, nozzle: Nozzle,
               min_height: float) -> BoolArray:
    """Poses (n,) whose head may hold material: those with the head's lowest point (``head_lowest_z``) not above
    the material's top; poses with an axis that is not of unit length are always kept."""
    unit = np.abs(np.einsum("ij,ij->i", axis, axis) - 1.0) < 1e-9
    return ~unit | (head_lowest_z(xyz, axis, nozzle, min_height) <= material.top + _REACH_TOL)


def _holder_distance(d: FloatArray, axis: FloatArray, nozzle: Nozzle) -> FloatArray:
    """Signed distance (k,) of offsets ``d = point - tip`` (k, 3) to the holder cylinder along ``axis`` (k, 3)."""
    h = np.einsum("ij,ij->i", d, axis)
    radial = np.sqrt(np.maximum(np.einsum("ij,ij->i", d, d) - h * h, 0.0))
    half = 0.5 * nozzle.holder_length
    dr = radial - nozzle.holder_radius
    dh = np.abs(h - (nozzle.cone_length + half)) - half
    return np.minimum(np.maximum(dr, dh), 0.0) + np.hypot(np.maximum(dr, 0.0), np.maximum(dh, 0.0))


def earlier_material(tp: Toolpaths, layer: int) -> _TreeSet:
    """The material the head can meet while printing ``layer``: every earlier layer's printing waypoints."""
    first = int(np.flatnonzero(tp.layer == layer)[0])
    material = _TreeSet()
    material.add(tp.xyz[:first][tp.path[:first] >= 0])
    return material


def _open_queries(material: _TreeSet, hit: BoolArray, xyz: FloatArray, axis: FloatArray,
                  balls: list[tuple[float, float]]) -> Iterator[tuple[FloatArray, cKDTree, FloatArray, float, IndexArray]]:
    """(points, tree, ball centres, radius, poses not yet hit) for each ball of the head and each tree."""
    for hc, rc in balls:
        centres = xyz + hc * axis
        for pts, tree in material.blocks:
            todo = np.flatnonzero(~hit)
            if len(todo) == 0:
                return
            yield pts, tree, centres, rc, todo


def _ball_pairs(tree: cKDTree, centres: FloatArray, radius: float, budget: int
                ) -> Iterator[tuple[IndexArray, IndexArray]]:
    """(row, point) pairs of tree points within ``radius`` of ``centres`` (k, 3), rows indexing the centres, in
    chunks of about ``budget`` pairs (counted first in C, so centres with nothing near cost one query each)."""
    counts = tree.query_ball_point(centres, radius, return_length=True, workers=QUERY_WORKERS)
    rows = np.flatnonzero(counts > 0)
    counts = counts[rows]
    bounds = np.searchsorted(np.cumsum(counts), np.arange(budget, counts.sum() + budget, budget))
    start = 0
    for stop in np.unique(np.concatenate([bounds + 1, [len(rows)]])):
        stop = int(min(max(stop, start + 1), len(rows)))
        if stop <= start:
            continue
        ids = rows[start:stop]
        start = stop
        lists = tree.query_ball_point(centres[ids], radius, return_sorted=False, workers=QUERY_WORKERS)
        n_c = np.fromiter((len(x) for x in lists), np.int64, len(lists))
        yield np.repeat(ids, n_c), np.fromiter(chain.from_iterable(lists), np.int64, int(n_c.sum()))


def _mark(hit: BoolArray, loc: FloatArray, pose: IndexArray, witness: FloatArray) -> None:
    """Mark the poses not hit yet among ``pose`` (k,), each with its first witness point (k, 3)."""
    first = np.unique(pose, return_index=True)[1]
    new = ~hit[pose[first]]
    hit[pose[first][new]] = True
    loc[pose[first][new]] = witness[first][new]


def _head_hits(material: _TreeSet, xyz: FloatArray, axis: FloatArray, nozzle: Nozzle, min_height: float,
               budget: int = 2_000_000) -> tuple[BoolArray, FloatArray]:
    """Exact test of material points against the head at each pose, candidates from ball queries."""
    hit = np.zeros(len(xyz), bool)
    loc = np.zeros((len(xyz), 3))
    if len(xyz) == 0 or material.top == -np.inf:
        return hit, loc
    near = np.flatnonzero(_may_reach(material, xyz, axis, nozzle, min_height))
    if len(near) < len(xyz):                      # the others' heads lie wholly above the material
        if len(near):
            hit[near], loc[near] = _head_hits(material, xyz[near], axis[near], nozzle, min_height, budget)
        return hit, loc
    for pts, tree, centres, rc, todo in _open_queries(material, hit, xyz, axis, head_cores(nozzle, min_height)):
        dist, near = tree.query(centres[todo], k=1, distance_upper_bound=rc, workers=QUERY_WORKERS)
        found = np.isfinite(dist)
        hit[todo[found]] = True
        loc[todo[found]] = pts[near[found]]
    if nozzle.holder_length > 0:
        _holder_hits(material, xyz, axis, nozzle, hit, loc, budget)
    for pts, tree, centres, rc, todo in _open_queries(material, hit, xyz, axis, head_parts(nozzle, min_height, False)):
        for row, cand in _ball_pairs(tree, centres[todo], rc, budget):
            pose = todo[row]
            inside = _inside_head(pts[cand] - xyz[pose], axis[pose], nozzle, min_height)
            _mark(hit, loc, pose[inside], pts[cand[inside]])
    return hit, loc


#: every this many-th pose left after the cone's core test is an anchor of the holder test: its holder is tested with
#: a clearance bound, which clears the poses near it along the path without a query of their own
HOLDER_ANCHOR_EVERY = 8
#: how far (mm) beyond the holder an anchor's test looks for material (the most clearance it can certify)
HOLDER_MARGIN = 5.0


def _holder_hits(material: _TreeSet, xyz: FloatArray, axis: FloatArray, nozzle: Nozzle, hit: BoolArray,
                 loc: FloatArray, budget: int) -> None:
    """Mark the poses whose holder cylinder holds material (``hit``/``loc`` updated in place), exactly.

    Anchor poses (every ``HOLDER_ANCHOR_EVERY``-th) are tested with a lower bound ``D`` on the distance from their
    holder to any material. A pose whose tip is ``delta`` from an anchor's and whose axis is ``gamma`` (rad) from it
    has its holder within ``delta + gamma * reach`` (``reach``: the holder's farthest point from the tip) of the
    anchor's, so it is clear where ``D`` exceeds that; the others are tested one by one (consecutive waypoints lie
    about half a millimetre apart with nearly the same axis, so most poses are cleared by an anchor)."""
    todo = np.flatnonzero(~hit)
    if len(todo) >= 4 * HOLDER_ANCHOR_EVERY:
        anchors = todo[::HOLDER_ANCHOR_EVERY]
        clear = _holder_scan(material, xyz, axis, nozzle, anchors, hit, loc, budget, HOLDER_MARGIN)
        reach = float(np.hypot(nozzle.cone_length + nozzle.holder_length, nozzle.holder_radius))
        rank = np.arange(len(todo))
        rest = np.flatnonzero(rank % HOLDER_ANCHOR_EVERY)
        cleared = np.zeros(len(rest), bool)
        for k in (rest // HOLDER_ANCHOR_EVERY, np.minimum(rest // HOLDER_ANCHOR_EVERY + 1, len(anchors) - 1)):
            a, j = anchors[k], todo[rest]
            delta = np.linalg.norm(xyz[j] - xyz[a], axis=1)
            gamma = np.arccos(np.clip(np.einsum("ij,ij->i", axis[j], axis[a]), -1.0, 1.0))
            cleared |= clear[k] > delta + gamma * reach + _REACH_TOL
        todo = todo[rest[~cleared]]
    _holder_scan(material, xyz, axis, nozzle, todo, hit, loc, budget, 0.0)


def _holder_scan(material: _TreeSet, xyz: FloatArray, axis: FloatArray, nozzle: Nozzle, poses: IndexArray,
                 hit: BoolArray, loc: FloatArray, budget: int, margin: float) -> FloatArray:
    """Test the holder at ``poses`` exactly (``hit``/``loc`` updated in place): cells near the holder are fetched by
    their centroids, classified by the holder's signed distance against their radius, and only the points of cells
    on its boundary are tested one by one. Returns per pose a lower bound on the distance from its holder to the
    material, at most ``margin`` (-inf where hit; with ``margin`` 0 only the hits are wanted)."""
    half = 0.5 * nozzle.holder_length
    centre_h = nozzle.cone_length + half
    reach = float(np.hypot(half, nozzle.holder_radius))
    clear = np.full(len(xyz), margin)
    for (pts, _), cells in zip(material.blocks, material.cells):
        todo = poses[~hit[poses]]
        if not len(todo):
            break
        rb = reach + float(cells.radius.max(initial=0.0)) + margin
        centres = xyz[todo] + centre_h * axis[todo]
        for row, cell in _ball_pairs(cells.tree, centres, rb, max(budget // 64, 1)):
            pose = todo[row]
            sd = _holder_distance(cells.centroid[cell] - xyz[pose], axis[pose], nozzle)
            full = sd < -cells.radius[cell]                               # the cell's ball lies in the holder
            _mark(hit, loc, pose[full], pts[cells.order[cells.start[cell[full]]]])
            edge = (np.abs(sd) <= cells.radius[cell]) & ~hit[pose]
            if margin > 0:
                far = ~edge & ~full
                np.minimum.at(clear, pose[far], sd[far] - cells.radius[cell[far]])
            if not edge.any():
                continue
            e_cell, e_pose = cell[edge], pose[edge]
            n_p = cells.count[e_cell]
            offset = np.arange(int(n_p.sum())) - np.repeat(np.cumsum(n_p) - n_p, n_p)
            point = cells.order[np.repeat(cells.start[e_cell], n_p) + offset]
            p_pose = np.repeat(e_pose, n_p)
            d = pts[point] - xyz[p_pose]
            inside = _in_holder(d, axis[p_pose], nozzle)
            _mark(hit, loc, p_pose[inside], pts[point[inside]])
            if margin > 0:
                np.minimum.at(clear, p_pose[~inside], _holder_distance(d[~inside], axis[p_pose[~inside]], nozzle))
    clear[hit] = -np.inf
    return clear[poses]


def head_collisions(xyz: FloatArray, axis: FloatArray, material: FloatArray, nozzle: Nozzle,
                    min_height: float = 0.5) -> tuple[BoolArray, FloatArray]:
    """Which tool poses (n,3)+(n,3) have material points (k,3) inside the head, and one such point."""
    tree = _TreeSet()
    tree.add(np.asarray(material, np.float64).reshape(-1, 3))
    return _head_hits(tree, np.asarray(xyz, np.float64).reshape(-1, 3), np.asarray(axis, np.float64).reshape(-1, 3),
                      nozzle, min_height)


def default_min_height(tp: Toolpaths) -> float:
    """Material closer to the tip than this along the axis is the bead being laid: the largest line width, at least 0.3 mm."""
    return max(0.3, float(tp.width.max(initial=0.0)))


def travel_samples(tp: Toolpaths, spacing: float) -> tuple[FloatArray, FloatArray, IndexArray]:
    """Poses inside the non-printing moves (into a waypoint that does not extrude), every ``spacing`` mm:
    tool tip, tool axis (interpolated) and the waypoint each move arrives at."""
    if spacing <= 0 or len(tp) < 2:
        return np.zeros((0, 3)), np.zeros((0, 3)), np.zeros(0, np.int64)
    seg = np.linalg.norm(np.diff(tp.xyz, axis=0), axis=1)
    n_in = np.where(~tp.extrude[1:], np.floor(seg / spacing).astype(np.int64), 0)
    n_in[seg <= spacing] = 0
    if not n_in.sum():
        return np.zeros((0, 3)), np.zeros((0, 3)), np.zeros(0, np.int64)
    i = np.repeat(np.arange(len(seg)), n_in)
    k = np.arange(len(i)) - np.repeat(np.cumsum(n_in) - n_in, n_in) + 1
    t = (k / (n_in[i] + 1))[:, None]
    axis = (1 - t) * tp.axis[i] + t * tp.axis[i + 1]
    axis /= np.linalg.norm(axis, axis=1, keepdims=True)
    return (1 - t) * tp.xyz[i] + t * tp.xyz[i + 1], axis, i + 1


def check_collisions(tp: Toolpaths, nozzle: Nozzle, platform_z: float, min_height: float | None = None,
                     platform_tolerance: float = 1e-6, only: IndexArray | None = None,
                     travel_spacing: float = 2.0) -> CollisionReport:
    """Waypoints where the head hits earlier layers' material or the platform (see module doc), and
    non-printing moves whose inside does (poses every ``travel_spacing`` mm, 0: off; reported at the
    waypoint the move arrives at).

    min_height : material closer than this to the tip along the axis is ignored (default: the
    largest line width, at least 0.3 mm), so the beads touching the nozzle are not counted;
    only : check just these waypoints (and the moves arriving at them; the material is still every
    earlier layer's).
    """
    n = len(tp)
    if n == 0:
        return CollisionReport(np.zeros(0, np.int64), np.zeros((0, 3)), np.zeros(0, np.int8))
    if min_height is None:
        min_height = default_min_height(tp)
    wanted = np.ones(n, bool) if only is None else np.isin(np.arange(n), only)
    hit = np.zeros(n, bool)
    loc = np.zeros((n, 3))
    kind = np.zeros(n, np.int8)
    # platform (exact)
    clear = platform_clearance(tp.xyz, tp.axis, nozzle, platform_z)
    plat = (clear < -platform_tolerance) & wanted
    hit |= plat
    loc[plat] = np.c_[tp.xyz[plat, :2], np.full(int(plat.sum()), platform_z)]
    kind[plat] = PLATFORM
    s_xyz, s_axis, s_to = travel_samples(tp, travel_spacing)
    keep = wanted[s_to]
    s_xyz, s_axis, s_to = s_xyz[keep], s_axis[keep], s_to[keep]
    s_layer = tp.layer[s_to]
    # part: material of previous layers
    order = np.argsort(tp.layer, kind="stable")
    layers = tp.layer[order]
    bounds = np.flatnonzero(np.diff(layers)) + 1
    material = _TreeSet()
    for grp in np.split(order, bounds):
        ask = grp[wanted[grp]]
        if material.top > -np.inf and len(ask):
            g_hit, g_loc = _head_hits(material, tp.xyz[ask], tp.axis[ask], nozzle, min_height)
            new = g_hit & ~hit[ask]
            hit[ask[new]] = True
            loc[ask[new]] = g_loc[new]
            kind[ask[new]] = PART
        if material.top > -np.inf and len(s_to):
            sel = np.flatnonzero(s_layer == tp.layer[grp[0]])
            if len(sel):
                t_hit, t_loc = _head_hits(material, s_xyz[sel], s_axis[sel], nozzle, min_height)
                to, where = s_to[sel][t_hit], t_loc[t_hit]
                first = np.unique(to, return_index=True)[1]
                to, where = to[first], where[first]
                new = ~hit[to]
                hit[to[new]] = True
                loc[to[new]] = where[new]
                kind[to[new]] = TRAVEL_PATH
        on_layer = grp[tp.path[grp] >= 0]
        material.add(tp.xyz[on_layer])
    idx = np.flatnonzero(hit)
    return CollisionReport(idx.astype(np.int64), loc[idx], kind[idx])
