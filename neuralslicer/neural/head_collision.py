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
platform clearance ``c_p = min(clearance, cone_length / 2)`` (the platform is exact: only the tip
between pool points and the tool axis blur it, and a vertical head at the platform, whose rim is
``cone_length`` above its tip, must stay free).

The pairs of pool points within the head's reach of each other are found once (a KD-tree pair
query); every ``optim.check_every`` steps they are tested against the current field in vectorised chunks and
those near collision (within generous margins) form the active set. Between refreshes only the
active set is evaluated, so a step costs a few vector operations over the active pairs.
"""
from __future__ import annotations

import math
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

    def lowest(self, axis: torch.Tensor) -> torch.Tensor:
        """Height of the lowest rim of the head (cone base, holder ends) above its tip (k,) for unit
        axes (k,3); the head reaches below its tip iff this is negative (exact)."""
        az = axis[:, 2].clamp(-1.0, 1.0)
        horiz = (1.0 - az * az).clamp_min(0.0).add(1e-12).sqrt()
        L = self.cone_length
        low = L * az - L * math.tan(self.half_angle) * horiz
        if self.holder_length > 0:
            for h in (L, L + self.holder_length):
                low = torch.minimum(low, h * az - self.holder_radius * horiz)
        return low


@dataclass
class CollisionPool:
    """Points (k,3) that stand for the solid in L_GC, and the spacing (mm) of the grid they come from."""

    points: np.ndarray
    spacing: float


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


class HeadCollision:
    """L_GC on a fixed pool of points located in the cage (see the module docstring).

    points : (k,3) pool; tets : (k,) containing cage tet; bary : (k,4) barycentric coordinates;
    cage_tets : (m,4); head; platform_z (None: no platform term); clearance and lift (the front
    margin ``m``) of the hinges, mm; length : normalisation (the pool spacing); margin : how far
    (mm) outside both hinges a pair may be and still be kept in the active set.
    """

    def __init__(self, points: np.ndarray, tets: np.ndarray, bary: np.ndarray, cage_tets: np.ndarray,
                 head: HeadShape, platform_z: float | None, clearance: float, lift: float,
                 length: float, margin: float, device: torch.device, dtype: torch.dtype) -> None:
        self.points = np.asarray(points, np.float64)
        near = cKDTree(self.points).query_pairs(head.reach + clearance + lift + margin, output_type="ndarray")
        self.near = torch.as_tensor(np.concatenate([near, near[:, ::-1]]), device=device)
        self.head, self.platform_z = head, platform_z
        self.clearance, self.lift, self.length, self.margin = clearance, lift, length, margin
        self.platform_clearance = min(clearance, 0.5 * head.cone_length)
        self.device, self.dtype = device, dtype
        self.tet = np.asarray(tets, np.int64)
        self.vertex_ids = torch.as_tensor(np.asarray(cage_tets, np.int64)[self.tet], device=device)
        self.tet_t = torch.as_tensor(self.tet, device=device)
        self.bary_t = torch.as_tensor(np.asarray(bary), dtype=dtype, device=device)
        self.points_t = torch.as_tensor(self.points, dtype=dtype, device=device)
        self.pairs = torch.zeros((0, 2), dtype=torch.int64, device=device)
        self.low_points = torch.zeros(0, dtype=torch.int64, device=device)

    def __len__(self) -> int:
        return len(self.points)

    def values(self, G: torch.Tensor, grad: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
        """(G at the pool points (k,), unit LPD (k,3), |grad G| (k,)) from G at the cage vertices (n,)
        and its per-tet gradient (m,3)."""
        g = (self.bary_t * G[self.vertex_ids]).sum(dim=1)
        d = grad[self.tet_t]
        norm = d.norm(dim=1, keepdim=True).clamp_min(1e-12)
        return g, d / norm, norm[:, 0]

    def _depth(self, pairs: torch.Tensor, d: torch.Tensor, inflate: float, lift: float) -> torch.Tensor:
        """Depth of x in the head at p, grown by inflate and lifted by lift along d_p, per pair (p, x)."""
        p, x = pairs[:, 0], pairs[:, 1]
        return self.head.depth(self.points_t[x] - self.points_t[p] - lift * d[p], d[p], inflate)

    @staticmethod
    def _early(pairs: torch.Tensor, g: torch.Tensor, norm: torch.Tensor, lift: float) -> torch.Tensor:
        """How far (mm) x is printed before p, plus lift, per pair (p, x)."""
        return (g[pairs[:, 0]] - g[pairs[:, 1]]) / norm[pairs[:, 1]] + lift

    def _select(self, g: torch.Tensor, d: torch.Tensor, norm: torch.Tensor, inflate: float, lift: float,
                chunk: int = 2_000_000) -> torch.Tensor:
        """Pairs (p, x) within reach whose two hinge arguments are both positive."""
        out = []
        for start in range(0, len(self.near), chunk):
            pairs = self.near[start:start + chunk]
            pairs = pairs[self._early(pairs, g, norm, lift) > 0]
            out.append(pairs[self._depth(pairs, d, inflate, lift) > 0])
        return torch.cat(out) if out else self.near[:0]

    @torch.no_grad()
    def refresh(self, G: torch.Tensor, grad: torch.Tensor) -> int:
        """Find the active pairs (near or in collision) for the current field; returns their number."""
        g, d, norm = self.values(G, grad)
        self.pairs = self._select(g, d, norm, self.clearance + self.margin, self.lift + self.margin)
        if self.platform_z is not None:
            clear = self.points_t[:, 2] + self.head.lowest(d) - self.platform_z
            self.low_points = torch.nonzero(clear < self.platform_clearance + self.margin).flatten()
        return int(len(self.pairs))

    def penalties(self, G: torch.Tensor, grad: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        """(per active pair c(p, x) (a,), per platform candidate penalty (b,)), differentiable."""
        g, d, norm = self.values(G, grad)
        pair = (torch.relu(self._depth(self.pairs, d, self.clearance, self.lift))
                * torch.relu(self._early(self.pairs, g, norm, self.lift)))
        low = self.low_points
        if self.platform_z is None or len(low) == 0:
            return pair, G.new_zeros(0)
        clear = self.points_t[low, 2] + self.head.lowest(d[low]) - self.platform_z
        return pair, torch.relu(self.platform_clearance - clear) ** 2

    def loss(self, G: torch.Tensor, grad: torch.Tensor) -> torch.Tensor:
        """L_GC = (sum of pair and platform penalties) / (pool size * spacing^2), unit-free."""
        pair, plat = self.penalties(G, grad)
        return (pair.sum() + plat.sum()) / (len(self.points) * self.length ** 2)

    @torch.no_grad()
    def count(self, G: torch.Tensor, grad: torch.Tensor, inflate: float = 0.0) -> dict[str, int]:
        """Collisions over the whole pool, with the head grown by ``inflate`` (no order margin):
        colliding (p, x) pairs (head samples in earlier material), pool points whose head hits
        something, and points whose head is below the platform."""
        g, d, norm = self.values(G, grad)
        bad = self._select(g, d, norm, inflate, 0.0)
        hit = torch.zeros(len(self.points), dtype=torch.bool, device=self.device)
        hit[bad[:, 0]] = True
        n_pairs = len(bad)
        n_low = 0
        if self.platform_z is not None:
            low = self.points_t[:, 2] + self.head.lowest(d) - self.platform_z < inflate
            n_low = int(low.sum())
            hit |= low
        return {"colliding_pairs": n_pairs, "colliding_points": int(hit.sum()), "platform_points": n_low,
                "pool_points": len(self.points)}

