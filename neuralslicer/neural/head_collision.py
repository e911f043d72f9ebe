"""Global collision term L_GC: the print head placed at each printed point along its LPD must not
reach material printed before that point, nor the platform.

The solid is represented by a fixed pool of points (a jittered grid inside ``H <= 0`` plus surface
samples). A pool point ``x`` collides with the head at pool point ``p`` when it lies in the head
placed at ``p`` along ``d_p`` (cone + holder, the geometry the motion planner's exact check uses)
and is printed earlier, ``G(x) < G(p)``. Per pair the penalty is a product of two hinges,

    c(p, x) = relu(s(x - p - m d_p, d_p)) * relu((G(p) - G(x)) / |grad G(x)| + m),

with ``s`` the (approximate) signed depth of ``x`` inside the head grown by a clearance sideways and
at the top (> 0 inside; the bottom stays at ``min_height`` above the tip, where the previous
layer lies under the nozzle), and ``m`` the front margin (mm): material between pool points is
printed up to ``m`` ahead of the last pool point behind the front, so points up to ``m`` ahead count
as printed, while the head is lifted by ``m`` along its axis so that a point straight ahead of the
tip never does (for a locally planar field the two conditions exclude each other). It is exactly
zero for a collision-free field with its margins, and its gradient moves the head axis ``d_p``
(tilting the head away) and the print order ``G`` (printing ``x`` later or ``p`` earlier). The
head's lowest point below the platform adds ``relu(c_p - (z_low - platform_z))^2`` with the
platform clearance ``c_p = min(clearance, cone_length / 2)``, the head's axis turned toward +z by as much
as the motion planner turns axes at the platform (``toolpath.collision_tilt_deg``, 15°) first (the platform
is exact: only the tip between pool points and the tool axis blur it, and a vertical head at the platform, whose rim is
``cone_length`` above its tip, must stay free). The same penalty, with a 0.5 mm margin and weighted by volume,
holds at every cage tet that has solid within the head's reach of the platform (``FloorTets``), placed at the
tet's lowest solid point along the tet's LPD: exact for the field's discretisation, where pool points are a cell
apart.

The pairs of pool points within the head's reach of each other are found once (a KD-tree pair
query); every ``optim.check_every`` steps they are tested against the current field in vectorised chunks and
those near collision (within generous margins) form the active set. Between refreshes only the
active set is evaluated, so a step costs a few vector operations over the active pairs.

A three-axis printer's head never tilts: with ``vertical`` (``loss.gc_vertical_head``) the head is placed along
+z at every point instead of along ``d_p``, and only the print order ``G`` moves the penalty.

Refinement (:func:`refine_pool`): where the motion planner's exact check finds colliding waypoints that the
pool missed (struts thinner than its spacing), points of a finer jittered lattice inside the solid are added
around each colliding waypoint and each point of material it hit. They are printed points and obstacles like
the base points, but they are paired only along *links*: the points near a colliding waypoint with those near
the material it hit, and the points near each of the two among themselves (every pair within the head's
reach among 20k added points would be 400 M pairs; the links keep the pairs the exact check named).
"""
from __future__ import annotations

import math
import warnings
from dataclasses import dataclass

import numpy as np
import torch
from scipy.spatial import cKDTree

from neuralslicer.motion.profile import Nozzle


@dataclass(frozen=True)
class HeadShape:
    """Print head in its own frame: cone (apex at the tip) of half angle ``half_angle`` (rad) and
    length ``cone_length``, then a holder cylinder of ``holder_radius`` and ``holder_length``;
    material closer than ``min_height`` to the tip along the axis is ignored (the bead itself)."""

    half_angle: float
    cone_length: float
    holder_radius: float
    holder_length: float
    min_height: float

    @classmethod
    def from_nozzle(cls, nozzle: Nozzle, min_height: float) -> "HeadShape":
        """The head of a machine profile's nozzle."""
        return cls(math.radians(nozzle.cone_half_angle_deg), nozzle.cone_length, nozzle.holder_radius,
                   nozzle.holder_length, min_height)

    @property
    def reach(self) -> float:
        """Distance from the tip to the farthest point of the head."""
        top = self.cone_length + self.holder_length
        return float(max(math.hypot(self.cone_length, self.cone_length * math.tan(self.half_angle)),
                         math.hypot(top, self.holder_radius if self.holder_length > 0 else 0.0)))

    def depth(self, offset: torch.Tensor, axis: torch.Tensor, inflate: float = 0.0) -> torch.Tensor:
        """Signed depth (k,) of points at ``offset = x - tip`` (k,3) inside the head along unit ``axis``
        (k,3): > 0 inside, < 0 outside (the distance to the nearest boundary piece, exact for each
        convex part away from their junction; the union takes the deeper part). ``inflate`` grows the
        head by that much sideways and at the top, never below ``min_height`` (the bead under the tip)."""
        h = (offset * axis).sum(dim=1)
        r = ((offset * offset).sum(dim=1) - h * h).clamp_min(0.0).add(1e-12).sqrt()
        L, ta, ca = self.cone_length, math.tan(self.half_angle), math.cos(self.half_angle)
        cone = torch.minimum(torch.minimum(h - self.min_height, L + inflate - h), (h * ta - r) * ca + inflate)
        if self.holder_length <= 0:
            return cone
        bottom = max(L - inflate, self.min_height)
        holder = torch.minimum(torch.minimum(h - bottom, L + self.holder_length + inflate - h),
                               self.holder_radius + inflate - r)
        return torch.maximum(cone, holder)

    def lowest(self, axis: torch.Tensor, turn: float = 0.0) -> torch.Tensor:
        """Height of the lowest rim of the head (cone base, holder ends) above its tip (k,) for unit
        axes (k,3); the head reaches below its tip iff this is negative (exact). ``turn`` (rad): each axis
        first turned toward +z by up to this much, azimuth kept, as the motion planner turns axes whose head
        would dip below the platform (``motion.reorient.clamp_to_platform``); the rim depends on the tilt alone."""
        az = axis[:, 2].clamp(-1.0, 1.0)
        horiz = (1.0 - az * az).clamp_min(0.0).add(1e-12).sqrt()
        if turn > 0:
            tilt = (torch.atan2(horiz, az) - turn).clamp_min(0.0)
            az, horiz = torch.cos(tilt), torch.sin(tilt)
        L = self.cone_length
        low = L * az - L * math.tan(self.half_angle) * horiz
        if self.holder_length > 0:
            for h in (L, L + self.holder_length):
                low = torch.minimum(low, h * az - self.holder_radius * horiz)
        return low


#: margin (mm) of the floor term: the head's lowest rim at least this far above the platform at every floor tet
FLOOR_CLEARANCE = 0.5


@dataclass
class FloorTets:
    """Cage tets that hold solid within the head's reach of the platform (the floor of L_GC's platform term):
    tet indices (f,), the lowest z of solid in each (its lowest vertex, not below the platform) and volumes.
    Their LPD is constant per tet, so a head clear of the platform at a tet's lowest point is clear at all of it:
    the term is exact for the field's discretisation, where pool points near the platform are a cell apart."""

    tets: np.ndarray
    z_low: np.ndarray
    volumes: np.ndarray

    @classmethod
    def empty(cls) -> "FloorTets":
        """No floor (no platform, or no solid near it)."""
        return cls(np.zeros(0, np.int64), np.zeros(0), np.zeros(0))

    @classmethod
    def of(cls, vertices: np.ndarray, tets: np.ndarray, volumes: np.ndarray, solid: np.ndarray, platform_z: float,
           head: HeadShape) -> "FloorTets":
        """The tets flagged ``solid`` (m,) whose lowest vertex lies within the head's reach below its tip
        (holder radius + cone length, any tilt) of the platform."""
        zmin = np.asarray(vertices, float)[np.asarray(tets)].min(axis=1)[:, 2]
        reach = head.holder_radius + head.cone_length + head.cone_length * math.tan(head.half_angle)
        idx = np.flatnonzero(np.asarray(solid, bool) & (zmin < platform_z + reach))
        return cls(idx.astype(np.int64), np.maximum(zmin[idx], platform_z), np.asarray(volumes, float)[idx])


@dataclass
class CollisionPool:
    """Points (k,3) that stand for the solid in L_GC, and the spacing (mm) of the grid they come from.

    A refined pool (:func:`refine_pool`) has its base points first (``n_base`` of them; None: all) and the
    added points after them; ``links`` (l,2,3) are pairs of centres (a colliding waypoint and the material it
    hit, or a centre and itself) whose neighbourhoods of radius ``link_radius`` (mm) are paired in L_GC;
    ``fine_spacing`` (mm) is the spacing of the lattice the added points come from.
    """

    points: np.ndarray
    spacing: float
    n_base: int | None = None
    links: np.ndarray | None = None
    link_radius: float = 0.0
    fine_spacing: float | None = None

    def __post_init__(self) -> None:
        self.points = np.asarray(self.points, np.float64).reshape(-1, 3)
        self.n_base = len(self.points) if self.n_base is None else int(self.n_base)
        self.links = np.zeros((0, 2, 3)) if self.links is None else np.asarray(self.links, np.float64).reshape(-1, 2, 3)

    @property
    def n_refined(self) -> int:
        """Number of points added by refinement."""
        return len(self.points) - int(self.n_base)


def collision_pool(H, bounds: np.ndarray, volume: float, surface_points: np.ndarray, n_points: int,
                   spacing: float | None = None, seed: int = 0) -> CollisionPool:
    """The solid as points: a jittered grid inside ``H < 0`` (spacing ``(volume / n_points)^(1/3)``
    unless given) and the surface samples thinned to one per grid cell."""
    spacing = float(spacing or (volume / n_points) ** (1.0 / 3.0))
    rng = np.random.default_rng(seed)
    lo, hi = np.asarray(bounds[0], float), np.asarray(bounds[1], float)
    axes = [np.arange(a + 0.5 * spacing, b, spacing) for a, b in zip(lo, hi)]
    grid = np.stack(np.meshgrid(*axes, indexing="ij"), axis=-1).reshape(-1, 3)
    grid = grid + rng.uniform(-0.35 * spacing, 0.35 * spacing, grid.shape)
    inside = grid[np.asarray(H(grid)) < 0] if len(grid) else grid
    surf = np.asarray(surface_points, float).reshape(-1, 3)
    if len(surf):
        _, first = np.unique(np.floor((surf - lo) / spacing).astype(np.int64), axis=0, return_index=True)
        surf = surf[np.sort(first)]
    return CollisionPool(np.concatenate([inside, surf]), spacing)


def refine_pool(pool: CollisionPool, hits: np.ndarray, witnesses: np.ndarray | None, H,
                spacing: float | None = None, radius: float | None = None, max_points: int = 20_000,
                seed: int = 0) -> CollisionPool:
    """The pool with points of a finer lattice added inside the solid around collisions the exact check found.

    Parameters
    ----------
    pool : the pool to refine (a base pool or an already refined one).
    hits : (k, 3) float -- positions of colliding waypoints (the head's tip there hit something).
    witnesses : (k, 3) float or None -- a point of the material each of them hit (rows with NaN, e.g. a
        platform collision reported without one, and an empty array or None give no witness).
    H : the implicit solid, ``H(points (n,3)) -> (n,)``, < 0 inside.
    spacing : spacing (mm) of the fine lattice (default: the pool's earlier fine spacing, else a third of
        its spacing).
    radius : how far (mm) from each hit and witness points are added (default: the earlier link radius,
        else two pool spacings).
    max_points : at most this many points are added; the ones nearest to a hit or witness come first.
    seed : seed of the lattice's jitter.

    The lattice has nodes at integer multiples of ``spacing``, each jittered by up to 0.35 spacings by a
    hash of its index and ``seed``: the same node always gives the same point, so refining twice around the
    same collision adds it once (points within a quarter spacing of a pool point are left out). Nodes within
    ``radius`` of a hit or witness, inside the solid (``H < 0``), are added in order of that distance. The
    links (each hit with its witness, and each hit and witness with itself) are thinned to one per cell of
    half the radius in the six coordinates of the two centres (the neighbouring waypoints of one colliding
    stretch become one link), together with the pool's own (which come first).
    """
    hits = np.asarray(hits, np.float64).reshape(-1, 3)
    wit = np.zeros((0, 3)) if witnesses is None else np.asarray(witnesses, np.float64).reshape(-1, 3)
    if len(wit) and len(wit) != len(hits):
        raise ValueError(f"witnesses ({len(wit)}) must be empty or one per hit ({len(hits)})")
    fine = float(spacing or pool.fine_spacing or pool.spacing / 3.0)
    r = float(radius or pool.link_radius or 2.0 * pool.spacing)
    has_hit = np.isfinite(hits).all(axis=1)
    has_wit = np.isfinite(wit).all(axis=1)
    paired = has_hit & has_wit if len(wit) else np.zeros(len(hits), bool)
    centres = np.concatenate([hits[has_hit], wit[has_wit]])
    if not len(centres):
        return CollisionPool(pool.points.copy(), pool.spacing, pool.n_base, pool.links.copy(), pool.link_radius,
                             pool.fine_spacing)
    links = np.concatenate([np.stack([hits[paired], wit[paired]], axis=1), np.stack([centres, centres], axis=1)])
    links = _thin_links(np.concatenate([pool.links, links]), 0.5 * r)
    added = _lattice_points_near(centres, pool.points, H, fine, r, max_points, seed)
    return CollisionPool(np.concatenate([pool.points, added]), pool.spacing, pool.n_base, links, r, fine)


def _thin_links(links: np.ndarray, cell: float) -> np.ndarray:
    """One link (l,2,3) per cell of size ``cell`` in the six coordinates of its two centres, in input order."""
    keys = np.floor(links.reshape(-1, 6) / cell).astype(np.int64)
    _, first = np.unique(keys, axis=0, return_index=True)
    return links[np.sort(first)]


def _node_jitter(nodes: np.ndarray, seed: int) -> np.ndarray:
    """A fixed pseudo-random offset in [-0.35, 0.35)^3 (in lattice units) per integer node (k,3): a splitmix64
    hash of the node's index and the seed, so the same node always moves the same way."""
    with np.errstate(over="ignore"):
        h = np.full(len(nodes), np.uint64(seed % 2**64) * np.uint64(0x9E3779B97F4A7C15) + np.uint64(0x632BE59BD9B4E019))
        out = np.empty((len(nodes), 3))
        for axis in range(3):
            h = (h ^ nodes[:, axis].astype(np.uint64)) * np.uint64(0xBF58476D1CE4E5B9)
            h ^= h >> np.uint64(31)
            h *= np.uint64(0x94D049BB133111EB)
            h ^= h >> np.uint64(29)
            out[:, axis] = (h >> np.uint64(11)).astype(np.float64) / float(1 << 53)
    return 0.7 * out - 0.35


def _lattice_points_near(centres: np.ndarray, existing: np.ndarray, H, spacing: float, radius: float,
                         max_points: int, seed: int, chunk: int = 50_000) -> np.ndarray:
    """Jittered lattice points (a,3), a <= max_points, within ``radius`` of a centre (c,3), inside ``H < 0``
    and farther than a quarter spacing from ``existing`` points, nearest to a centre first."""
    # candidate nodes: the lattice in blocks about one radius wide around the centres' blocks
    per_block = max(1, int(math.ceil(radius / spacing)))
    blocks = np.unique(np.floor(centres / (per_block * spacing)).astype(np.int64), axis=0)
    around = np.stack(np.meshgrid(*[np.arange(-1, 2)] * 3, indexing="ij"), axis=-1).reshape(-1, 3)
    blocks = np.unique((blocks[:, None, :] + around[None]).reshape(-1, 3), axis=0)
    inner = np.stack(np.meshgrid(*[np.arange(per_block)] * 3, indexing="ij"), axis=-1).reshape(-1, 3)
    nodes = (blocks[:, None, :] * per_block + inner[None]).reshape(-1, 3)
    points = (nodes + _node_jitter(nodes, seed)) * spacing
    dist, _ = cKDTree(centres).query(points, distance_upper_bound=radius)
    near = dist <= radius
    if len(existing):
        gap, _ = cKDTree(existing).query(points[near], distance_upper_bound=0.25 * spacing)
        near[np.flatnonzero(near)[np.isfinite(gap)]] = False
    candidates = np.flatnonzero(near)
    candidates = candidates[np.argsort(dist[candidates], kind="stable")]
    out: list[np.ndarray] = []
    found = 0
    for start in range(0, len(candidates), chunk):
        if found >= max_points:
            break
        pts = points[candidates[start:start + chunk]]
        pts = pts[np.asarray(H(pts)) < 0][:max_points - found]
        out.append(pts)
        found += len(pts)
    return np.concatenate(out) if out else np.zeros((0, 3))


def link_pairs(points: np.ndarray, n_base: int, links: np.ndarray, radius: float, reach: float,
               max_pairs: int, seed: int = 0) -> tuple[np.ndarray, int]:
    """The ordered pairs of pool points (e,2) that a refined pool's links add, and how many links were thinned.

    For each link (a, b) of ``links`` (l,2,3): every pool point within ``radius`` of a with every pool point
    within ``radius`` of b, both ways, within ``reach`` of each other, distinct, and at least one of them an
    added point (index >= ``n_base``: pairs of base points are the base query's). When all of them would be
    more than ``max_pairs``, every link keeps a share: the candidate pairs (points near a times points near b)
    are water-filled to a common cap, and a link above it keeps a seeded random subset of the points on each
    side (the square root of its share), so each colliding site the exact check named stays in the loss.
    """
    empty = np.zeros((0, 2), np.int64)
    if not len(links) or n_base >= len(points):
        return empty, 0
    tree = cKDTree(points)
    near_a = [np.asarray(i, np.int64) for i in tree.query_ball_point(links[:, 0], radius)]
    near_b = [np.asarray(i, np.int64) for i in tree.query_ball_point(links[:, 1], radius)]
    sizes = np.array([len(ia) * len(ib) for ia, ib in zip(near_a, near_b)], np.float64)
    cap = _water_level(sizes, max_pairs / 2.0)
    rng = np.random.default_rng(seed)
    out: list[np.ndarray] = []
    thinned = 0
    for ia, ib, size in zip(near_a, near_b, sizes):
        if size > cap:
            keep = math.sqrt(cap / size)
            ia = ia[rng.random(len(ia)) < keep]
            ib = ib[rng.random(len(ib)) < keep]
            thinned += 1
        p, x = np.repeat(ia, len(ib)), np.tile(ib, len(ia))
        keep_pair = ((p >= n_base) | (x >= n_base)) & (p != x)
        p, x = p[keep_pair], x[keep_pair]
        keep_pair = ((points[p] - points[x]) ** 2).sum(axis=1) <= reach * reach
        pairs = np.stack([p[keep_pair], x[keep_pair]], axis=1)
        out += [pairs, pairs[:, ::-1]]
    pairs = np.concatenate(out)
    if not len(pairs):
        return empty, thinned
    code = np.unique(pairs @ np.array([len(points), 1], np.int64))
    pairs = np.stack([code // len(points), code % len(points)], axis=1)
    if len(pairs) > max_pairs:  # the random subsets' sizes may overshoot their mean by a little
        pairs = pairs[np.sort(rng.choice(len(pairs), max_pairs, replace=False))]
    return pairs, thinned


def _kept(mask: torch.Tensor, *columns: torch.Tensor) -> list[torch.Tensor]:
    """The rows of each of columns (a,...) where mask (a,) holds, in order."""
    idx = torch.nonzero(mask).flatten()
    return [c.index_select(0, idx) for c in columns]


def _water_level(sizes: np.ndarray, budget: float) -> float:
    """The cap c with sum(min(sizes, c)) = budget (inf when all of sizes fit in the budget)."""
    if sizes.sum() <= budget:
        return math.inf
    s = np.sort(sizes)
    below = np.concatenate([[0.0], np.cumsum(s)[:-1]])  # sum of the sizes under each
    levels = (budget - below) / (len(s) - np.arange(len(s)))  # cap if the first i sizes fit whole
    i = int(np.flatnonzero(levels <= s)[0])
    return float(levels[i])


class HeadCollision:
    """L_GC on a fixed pool of points located in the cage (see the module docstring).

    points : (k,3) pool; tets : (k,) containing cage tet; bary : (k,4) barycentric coordinates;
    cage_tets : (m,4); head; platform_z (None: no platform term); clearance and lift (the front
    margin ``m``) of the hinges, mm; length : normalisation (the pool spacing); margin : how far
    (mm) outside both hinges a pair may be and still be kept in the active set.
    A refined pool (see :class:`CollisionPool`): n_base : the first n_base points are the base pool
    (None: all), paired by the KD-tree query; links, link_radius : the added points are paired along
    them (:func:`link_pairs`, at most max_link_pairs ordered pairs). The loss is normalised by n_base,
    so refinement does not dilute the base pool's penalties. platform_turn (rad): the platform and floor
    terms judge each head with its axis turned toward +z by up to this much, as the motion planner turns axes
    that would dip below the platform (0: the LPD itself). vertical: the head's axis is +z at every point instead
    of the LPD (a three-axis printer, whose nozzle never tilts); the print order still follows G.
    """

    def __init__(self, points: np.ndarray, tets: np.ndarray, bary: np.ndarray, cage_tets: np.ndarray,
                 head: HeadShape, platform_z: float | None, clearance: float, lift: float,
                 length: float, margin: float, device: torch.device, dtype: torch.dtype, *,
                 n_base: int | None = None, links: np.ndarray | None = None, link_radius: float = 0.0,
                 max_link_pairs: int = 10_000_000, floor: FloorTets | None = None,
                 floor_weight: float = 1.0, platform_turn: float = 0.0, vertical: bool = False) -> None:
        self.points = np.asarray(points, np.float64)
        self.n_base = len(self.points) if n_base is None else int(n_base)
        reach = head.reach + clearance + lift + margin
        near = cKDTree(self.points[:self.n_base]).query_pairs(reach, output_type="ndarray")
        near = np.concatenate([near, near[:, ::-1]])
        links = np.zeros((0, 2, 3)) if links is None else np.asarray(links, np.float64).reshape(-1, 2, 3)
        extra, self.links_thinned = link_pairs(self.points, self.n_base, links, link_radius, reach, max_link_pairs)
        self.n_links, self.n_link_pairs = len(links), len(extra)
        if self.links_thinned:
            warnings.warn(f"L_GC refinement: {self.links_thinned:,} of {len(links):,} links thinned to a random "
                          f"share of their pairs (refine.max_pairs = {max_link_pairs:,} in all)",
                          RuntimeWarning, stacklevel=2)
        # (2,k): each column's indices contiguous, as the pair search gathers them
        self._near = torch.as_tensor(np.ascontiguousarray(np.concatenate([near, extra]).T), device=device)
        self.head, self.platform_z = head, platform_z
        self.clearance, self.lift, self.length, self.margin = clearance, lift, length, margin
        self.platform_clearance = min(clearance, 0.5 * head.cone_length)
        self.platform_turn = float(platform_turn)
        self.vertical = bool(vertical)
        self.device, self.dtype = device, dtype
        self.tet = np.asarray(tets, np.int64)
        self.vertex_ids = torch.as_tensor(np.asarray(cage_tets, np.int64)[self.tet], device=device)
        self.tet_t = torch.as_tensor(self.tet, device=device)
        self.bary_t = torch.as_tensor(np.asarray(bary), dtype=dtype, device=device)
        self.points_t = torch.as_tensor(self.points, dtype=dtype, device=device)
        self._extent = float(np.abs(self.points).max(initial=0.0))   # coordinates' size: the height bound's margin
        self.pairs = torch.zeros((0, 2), dtype=torch.int64, device=device)
        self.pair_offsets = torch.zeros((0, 3), dtype=dtype, device=device)  # x - p per active pair (p, x)
        self.low_points = torch.zeros(0, dtype=torch.int64, device=device)
        floor = floor if floor is not None and platform_z is not None else FloorTets.empty()
        self.n_floor = len(floor.tets)
        self.floor_tets = torch.as_tensor(floor.tets, device=device)
        self.floor_z = torch.as_tensor(floor.z_low - (platform_z or 0.0), dtype=dtype, device=device)
        self.floor_weights = torch.as_tensor(floor_weight * floor.volumes / length ** 3, dtype=dtype, device=device)
        self.floor_clearance = min(self.platform_clearance, FLOOR_CLEARANCE)

    def __len__(self) -> int:
        return len(self.points)

    def values(self, G: torch.Tensor, grad: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
        """(G at the pool points (k,), the head's unit axis (k,3): the LPD, or +z for a vertical head, |grad G|
        (k,)) from G at the cage vertices (n,) and its per-tet gradient (m,3)."""
        g = (self.bary_t * G.index_select(0, self.vertex_ids.reshape(-1)).view(self.vertex_ids.shape)).sum(dim=1)
        d = grad.index_select(0, self.tet_t)
        norm = d.norm(dim=1, keepdim=True).clamp_min(1e-12)
        return g, self._axis(d / norm), norm[:, 0]

    def _axis(self, lpd: torch.Tensor) -> torch.Tensor:
        """The head's axis (k,3) at points with these unit LPDs (k,3): themselves, or +z for a vertical head."""
        if not self.vertical:
            return lpd
        return torch.tensor([0.0, 0.0, 1.0], dtype=lpd.dtype, device=lpd.device).expand_as(lpd)

    def _offsets(self, p: torch.Tensor, x: torch.Tensor) -> torch.Tensor:
        """x - p (a,3) per pair (p, x) of pool points (indices (a,) each)."""
        return self.points_t.index_select(0, x) - self.points_t.index_select(0, p)

    def _depth(self, p: torch.Tensor, x: torch.Tensor, d: torch.Tensor, inflate: float, lift: float,
               offsets: torch.Tensor | None = None) -> torch.Tensor:
        """Depth of x in the head at p, grown by inflate and lifted by lift along d_p, per pair (p, x) (``offsets``:
        their x - p, when known)."""
        offsets = self._offsets(p, x) if offsets is None else offsets
        return self.head.depth(offsets - lift * d.index_select(0, p), d.index_select(0, p), inflate)

    @staticmethod
    def _early(p: torch.Tensor, x: torch.Tensor, g: torch.Tensor, norm: torch.Tensor, lift: float) -> torch.Tensor:
        """How far (mm) x is printed before p, plus lift, per pair (p, x)."""
        return (g.index_select(0, p) - g.index_select(0, x)) / norm.index_select(0, x) + lift

    def _select(self, g: torch.Tensor, d: torch.Tensor, norm: torch.Tensor, inflate: float, lift: float,
                chunk: int = 2_000_000) -> torch.Tensor:
        """Pairs (p, x) within reach whose two hinge arguments are both positive.

        The head's depth is computed only for the pairs whose x can lie above ``min_height`` along d_p from the
        lifted tip: the depth is at most that height less ``min_height`` (cone and holder alike, whatever the
        inflation), so no other pair is in the set. The height is bounded apart from :meth:`_depth`, with a margin
        far above the rounding of either; the set and its order are those of the depth test on every pair, at a
        fraction of its cost (a few % of the pairs in reach pass)."""
        out = []
        floor = self.head.min_height - 1e-4 * (1.0 + self._extent + abs(lift))
        for start in range(0, self._near.shape[1], chunk):
            p, x = self._near[0, start:start + chunk], self._near[1, start:start + chunk]
            p, x = _kept(self._early(p, x, g, norm, lift) > 0, p, x)
            offsets = self._offsets(p, x)
            p, x, offsets = _kept((offsets * d.index_select(0, p)).sum(dim=1) - lift > floor, p, x, offsets)
            p, x = _kept(self._depth(p, x, d, inflate, lift, offsets) > 0, p, x)
            out.append(torch.stack([p, x], dim=1))
        return torch.cat(out) if out else self.near[:0]

    @property
    def near(self) -> torch.Tensor:
        """The ordered pairs (p, x) of pool points within the head's reach of each other (k,2)."""
        return self._near.t()

    @torch.no_grad()
    def refresh(self, G: torch.Tensor, grad: torch.Tensor) -> int:
        """Find the active pairs (near or in collision) for the current field; returns their number."""
        g, d, norm = self.values(G, grad)
        self.pairs = self._select(g, d, norm, self.clearance + self.margin, self.lift + self.margin)
        self.pair_offsets = self._offsets(self.pairs[:, 0], self.pairs[:, 1])
        if self.platform_z is not None:
            clear = self.points_t[:, 2] + self.head.lowest(d, self.platform_turn) - self.platform_z
            self.low_points = torch.nonzero(clear < self.platform_clearance + self.margin).flatten()
        return int(len(self.pairs))

    def floor_clear(self, grad: torch.Tensor) -> torch.Tensor:
        """Height above the platform (mm) of the head's lowest rim at the lowest solid point of each floor tet,
        along that tet's LPD (f,): negative where the head reaches below the platform there."""
        d = grad[self.floor_tets]
        return self.floor_z + self.head.lowest(self._axis(d / d.norm(dim=1, keepdim=True).clamp_min(1e-12)),
                                               self.platform_turn)

    def penalties(self, G: torch.Tensor, grad: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        """(per active pair c(p, x) (a,), per platform candidate penalty (b,): pool points, then floor tets
        weighted by their volume in pool cells), differentiable."""
        g, d, norm = self.values(G, grad)
        p, x = self.pairs[:, 0], self.pairs[:, 1]
        pair = (torch.relu(self._depth(p, x, d, self.clearance, self.lift, self.pair_offsets))
                * torch.relu(self._early(p, x, g, norm, self.lift)))
        plat = [G.new_zeros(0)]
        low = self.low_points
        if self.platform_z is not None and len(low):
            clear = self.points_t[low, 2] + self.head.lowest(d[low], self.platform_turn) - self.platform_z
            plat.append(torch.relu(self.platform_clearance - clear) ** 2)
        if self.n_floor:
            plat.append(self.floor_weights * torch.relu(self.floor_clearance - self.floor_clear(grad)) ** 2)
        return pair, torch.cat(plat)

    def loss(self, G: torch.Tensor, grad: torch.Tensor) -> torch.Tensor:
        """L_GC = (sum of pair and platform penalties) / (base pool size * spacing^2), unit-free."""
        pair, plat = self.penalties(G, grad)
        return (pair.sum() + plat.sum()) / (self.n_base * self.length ** 2)

    @torch.no_grad()
    def count(self, G: torch.Tensor, grad: torch.Tensor, inflate: float = 0.0) -> dict[str, int]:
        """Collisions over the whole pool, with the head grown by ``inflate`` (no order margin):
        colliding (p, x) pairs (head samples in earlier material), pool points whose head hits
        something (``refined_points_hit``: among the added ones), and points whose head is below the platform."""
        g, d, norm = self.values(G, grad)
        bad = self._select(g, d, norm, inflate, 0.0)
        hit = torch.zeros(len(self.points), dtype=torch.bool, device=self.device)
        hit[bad[:, 0]] = True
        n_pairs = len(bad)
        n_low = 0
        if self.platform_z is not None:
            low = self.points_t[:, 2] + self.head.lowest(d, self.platform_turn) - self.platform_z < inflate
            n_low = int(low.sum())
            hit |= low
        n_floor = int((self.floor_clear(grad) < inflate).sum()) if self.n_floor else 0
        return {"colliding_pairs": n_pairs, "colliding_points": int(hit.sum()), "platform_points": n_low,
                "floor_tets_hit": n_floor, "floor_tets": self.n_floor,
                "pool_points": len(self.points), "refined_points": len(self.points) - self.n_base,
                "refined_points_hit": int(hit[self.n_base:].sum())}

