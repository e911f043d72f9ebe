"""Nozzle collisions against the printed part and the platform (build frame), exact.

The head is a cone (apex at the tool tip, axis along the tool axis) topped by a holder cylinder
(``motion/head.py``). The material is every bead laid before the pose, its top and its bottom
(``PrintedMaterial``): the earlier layers and the paths of the pose's own layer printed before it. One such
structure, built once for a print, serves the check, the travel lifts and the tilts at every moment of the print.
Per pose, the cone and the holder are scanned separately against it (``motion/scan.py``): coarse cubes empty at
that moment or outside the part are dropped, cubes inside it are hits, the rest is split down to the points.
Poses whose head lies wholly above the highest material laid so far are skipped. The holder is wide, so
every ``HOLDER_ANCHOR_EVERY``-th pose left is an anchor: its scan returns a lower bound on the distance from its
holder to the material (of the latest moment the anchor stands for), which clears the poses near it along the
path without a scan of their own. The platform test is exact: the lowest point of the cone and of the holder
against z = platform_z.
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from neuralslicer.motion.head import _inside_head, head_lowest_z, platform_clearance  # noqa: F401
from neuralslicer.motion.material import PrintedMaterial
from neuralslicer.motion.profile import Nozzle
from neuralslicer.motion.scan import HeadPart, scan
from neuralslicer.toolpath.types import Toolpaths
from neuralslicer.types import BoolArray, FloatArray, IndexArray

PART, PLATFORM, TRAVEL_PATH = 0, 1, 2


#: at most this many clear and this many colliding waypoints of a print are kept for its collision map's figure
MAP_POINTS = 40_000


@dataclass(frozen=True)
class CollisionMap:
    """Where one print's head hits, as much of it as a figure draws: every ``len // MAP_POINTS``-th clear and colliding
    waypoint (evenly along the print), the counts and the bounds of all waypoints. A few MB, where the print's
    waypoints and flags are 25 bytes a waypoint.

    clear, hit : (k, 3), (h, 3) the kept clear and colliding waypoints; n_waypoints, n_hit : the print's counts;
    bounds : (2, 3) the lowest and highest coordinates of all waypoints ((0, 3) for a print without any).
    """

    clear: FloatArray
    hit: FloatArray
    n_waypoints: int
    n_hit: int
    bounds: FloatArray

    @classmethod
    def of(cls, xyz: FloatArray, hit: BoolArray, max_points: int = MAP_POINTS) -> "CollisionMap":
        """The map of waypoints ``xyz`` (n, 3) of which ``hit`` (n,) collide."""
        ok, bad = np.flatnonzero(~hit), np.flatnonzero(hit)
        ok, bad = ok[:: max(1, len(ok) // max_points)], bad[:: max(1, len(bad) // max_points)]
        bounds = np.stack([xyz.min(axis=0), xyz.max(axis=0)]) if len(xyz) else np.zeros((0, 3))
        return cls(xyz[ok], xyz[bad], int(len(hit)), int(hit.sum()), bounds)

    @classmethod
    def of_indices(cls, xyz: FloatArray, indices: IndexArray) -> "CollisionMap":
        """The map of waypoints ``xyz`` (n, 3) of which those at ``indices`` collide."""
        hit = np.zeros(len(xyz), bool)
        hit[np.asarray(indices, np.int64)] = True
        return cls.of(xyz, hit)


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


#: margin (mm) of the reach test: rounding in the exact tests moves points by far less
_REACH_TOL = 1e-6
#: every this many-th pose left after the cone's test is an anchor of the holder test
HOLDER_ANCHOR_EVERY = 8
#: how far (mm) beyond the holder an anchor's scan looks for material (the most clearance it can certify)
HOLDER_MARGIN = 5.0
#: waypoints checked at a time (the check's temporaries, some 300 bytes a waypoint, are a block's)
CHECK_BLOCK = 1 << 18



def part_collisions(xyz: FloatArray, indices: IndexArray, kind: np.ndarray, locations: FloatArray | None = None
                    ) -> tuple[FloatArray, FloatArray]:
    """(hits (k,3), witnesses (k,3)) of a print: the waypoints whose head hit material or the platform and a point it
    hit (NaN without locations); travel collisions are left out (the travel lift is the planner's answer to those,
    the field cannot place the head there)."""
    keep = np.asarray(kind) != TRAVEL_PATH
    idx = np.asarray(indices, np.int64)
    witnesses = (np.asarray(locations, np.float64).reshape(-1, 3)[keep] if locations is not None
                 else np.full((int(keep.sum()), 3), np.nan))
    return np.asarray(xyz, np.float64)[idx[keep]], witnesses


def _may_reach(material: PrintedMaterial, xyz: FloatArray, axis: FloatArray, visible: IndexArray, nozzle: Nozzle,
               min_height: float) -> BoolArray:
    """Poses (n,) whose head may hold material: material laid before them, the head's lowest point
    (``head_lowest_z``) not above its top; poses with an axis that is not of unit length are always kept."""
    unit = np.abs(np.einsum("ij,ij->i", axis, axis) - 1.0) < 1e-9
    top = material.top_before(visible)
    return (visible > 0) & (~unit | (head_lowest_z(xyz, axis, nozzle, min_height) <= top + _REACH_TOL))


def head_hits(material: PrintedMaterial, xyz: FloatArray, axis: FloatArray, visible: IndexArray, nozzle: Nozzle,
              min_height: float) -> tuple[BoolArray, FloatArray]:
    """Which tool poses (tips (n, 3), unit axes (n, 3)) have material laid before ``visible`` (n,) inside the
    head, and one such point each (n, 3)."""
    n = len(xyz)
    hit, loc = np.zeros(n, bool), np.zeros((n, 3))
    near = np.flatnonzero(_may_reach(material, xyz, axis, visible, nozzle, min_height))
    if not len(near):
        return hit, loc
    near = near[np.argsort(visible[near], kind="stable")]       # the anchors need the poses in time order
    tips, axes, vis = xyz[near], axis[near], visible[near]
    cone_hit, witness, _ = scan(material, HeadPart.cone(nozzle, min_height, material), tips, axes, vis)
    if nozzle.holder_length > 0:
        _holder_hits(material, HeadPart.holder(nozzle, material), nozzle, tips, axes, vis, cone_hit, witness)
    hit[near] = cone_hit
    loc[near[cone_hit]] = material.points[witness[cone_hit]]
    return hit, loc


def _holder_hits(material: PrintedMaterial, part: HeadPart, nozzle: Nozzle, tips: FloatArray, axes: FloatArray,
                 visible: IndexArray, hit: BoolArray, witness: IndexArray) -> None:
    """Mark the poses (in time order) whose holder holds material (``hit``/``witness`` updated in place), exactly.

    Anchor poses (every ``HOLDER_ANCHOR_EVERY``-th) get a lower bound ``D`` on the distance from their holder to the
    material laid before the next anchor (so before every pose the anchor stands for). A pose whose tip is ``delta``
    from an anchor's and whose axis is ``gamma`` (rad) from it has its holder within ``delta + gamma * reach``
    (``reach``: the holder's farthest point from the tip) of the anchor's, so it is clear where ``D`` exceeds that;
    the others are scanned one by one (consecutive waypoints lie about half a millimetre apart with nearly the same
    axis, so most poses are cleared by an anchor)."""
    from neuralslicer.motion.scan_kernel import anchor_cleared     # numba only where the holder is scanned

    todo = np.flatnonzero(~hit)
    if len(todo) >= 4 * HOLDER_ANCHOR_EVERY:
        anchors = todo[::HOLDER_ANCHOR_EVERY]
        until = todo[np.minimum(np.arange(0, len(todo), HOLDER_ANCHOR_EVERY) + HOLDER_ANCHOR_EVERY, len(todo) - 1)]
        _, _, clear = scan(material, part, tips[anchors], axes[anchors], visible[until], HOLDER_MARGIN)
        reach = float(np.hypot(nozzle.cone_length + nozzle.holder_length, nozzle.holder_radius))
        cleared = anchor_cleared(tips, axes, todo, clear, HOLDER_ANCHOR_EVERY, reach, _REACH_TOL)
        todo = todo[~cleared]
    h, w, _ = scan(material, part, tips[todo], axes[todo], visible[todo])
    hit[todo[h]] = True
    witness[todo[h]] = w[h]


def head_collisions(xyz: FloatArray, axis: FloatArray, material: FloatArray, nozzle: Nozzle,
                    min_height: float = 0.5) -> tuple[BoolArray, FloatArray]:
    """Which tool poses (n,3)+(n,3) have material points (k,3) inside the head, and one such point."""
    pts = np.asarray(material, np.float64).reshape(-1, 3)
    printed = PrintedMaterial.of_points(pts, np.zeros(len(pts), np.int64), 1)
    xyz, axis = np.asarray(xyz, np.float64).reshape(-1, 3), np.asarray(axis, np.float64).reshape(-1, 3)
    return head_hits(printed, xyz, axis, np.ones(len(xyz), np.int64), nozzle, min_height)


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
                     travel_spacing: float = 2.0, material: PrintedMaterial | None = None) -> CollisionReport:
    """Waypoints where the head hits material laid before them (earlier layers and the paths of their own layer
    printed before them, see module doc) or the platform, and non-printing moves whose inside does (poses every
    ``travel_spacing`` mm, 0: off; reported at the waypoint the move arrives at).

    min_height : material closer than this to the tip along the axis is ignored (default: the
    largest line width, at least 0.3 mm), so the beads touching the nozzle are not counted;
    only : check just these waypoints (and the moves arriving at them; the material is still all of it);
    material : the print's material (``PrintedMaterial.of_toolpaths``), when the caller has it already.
    The waypoints are checked ``CHECK_BLOCK`` at a time (every pose's answer is its own: the same report).
    """
    n = len(tp)
    if n == 0:
        return CollisionReport(np.zeros(0, np.int64), np.zeros((0, 3)), np.zeros(0, np.int8))
    if min_height is None:
        min_height = default_min_height(tp)
    material = PrintedMaterial.of_toolpaths(tp) if material is None else material
    printing = material.printing_of(tp)
    asked = None if only is None else np.unique(np.asarray(only, np.int64))
    found, before = [], 0
    for lo in range(0, n, CHECK_BLOCK):
        hi = min(lo + CHECK_BLOCK, n)
        on = printing[lo:hi].astype(np.int64)
        visible = np.cumsum(on)
        visible += before - on                       # the printing waypoints before each (material.visible_at)
        before = int(visible[-1]) + int(on[-1])
        ask = np.arange(lo, hi) if asked is None else asked[(asked >= lo) & (asked < hi)]
        if len(ask):
            found.append(_check_block(tp, lo, hi, ask, visible, nozzle, platform_z, min_height, platform_tolerance,
                                      travel_spacing, material))
    if not found:
        return CollisionReport(np.zeros(0, np.int64), np.zeros((0, 3)), np.zeros(0, np.int8))
    return CollisionReport(np.concatenate([f.indices for f in found]), np.concatenate([f.locations for f in found]),
                           np.concatenate([f.kind for f in found]))


def _check_block(tp: Toolpaths, lo: int, hi: int, ask: IndexArray, visible: IndexArray, nozzle: Nozzle,
                 platform_z: float, min_height: float, platform_tolerance: float, travel_spacing: float,
                 material: PrintedMaterial) -> CollisionReport:
    """``check_collisions`` of the waypoints ``ask`` (sorted, within [lo, hi)) and the moves arriving at them;
    ``visible`` (hi - lo,): the ranks each waypoint of the block sees."""
    m = hi - lo
    hit, loc, kind = np.zeros(m, bool), np.zeros((m, 3)), np.zeros(m, np.int8)
    local = ask - lo
    # platform (exact), at the waypoints asked about only
    plat = ask[platform_clearance(tp.xyz[ask], tp.axis[ask], nozzle, platform_z) < -platform_tolerance]
    hit[plat - lo] = True
    loc[plat - lo] = np.c_[tp.xyz[plat, :2], np.full(len(plat), platform_z)]
    kind[plat - lo] = PLATFORM
    # the part: the waypoints, then the poses inside the moves arriving at them (from the waypoint before the block)
    first = max(lo - 1, 0)
    s_xyz, s_axis, s_to = travel_samples(tp.rows(first, hi), travel_spacing)
    s_to += first - lo
    wanted = np.zeros(m, bool)
    wanted[local] = True
    keep = wanted[s_to]
    s_xyz, s_axis, s_to = s_xyz[keep], s_axis[keep], s_to[keep]
    p_hit, p_loc = head_hits(material, np.concatenate([tp.xyz[ask], s_xyz]), np.concatenate([tp.axis[ask], s_axis]),
                             visible[np.concatenate([local, s_to])], nozzle, min_height)
    new = p_hit[:len(ask)] & ~hit[local]
    hit[local[new]], loc[local[new]], kind[local[new]] = True, p_loc[:len(ask)][new], PART
    t_hit, t_loc = p_hit[len(ask):], p_loc[len(ask):]
    to, where = s_to[t_hit], t_loc[t_hit]
    first_hit = np.unique(to, return_index=True)[1]
    to, where = to[first_hit], where[first_hit]
    new = ~hit[to]
    hit[to[new]], loc[to[new]], kind[to[new]] = True, where[new], TRAVEL_PATH
    idx = np.flatnonzero(hit)
    return CollisionReport((idx + lo).astype(np.int64), loc[idx], kind[idx])
