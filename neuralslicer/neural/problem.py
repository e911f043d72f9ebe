"""The optimisation problem: the cage, its ARAP factor, B and T mapped to cage tets, and every loss term."""
from __future__ import annotations

import math
import weakref

import numpy as np
import torch

from neuralslicer.fea.samples import StressSamples
from neuralslicer.metrics import overhang_area_fraction, strength_satisfaction
from neuralslicer.neural import losses as L
from neuralslicer.neural.config import NeuralConfig
from neuralslicer.neural.deformation import ArapDeformation
from neuralslicer.neural.device import resolve_device, resolve_dtype
from neuralslicer.neural.field import CageGeometry, field_gradient, unit
from neuralslicer.neural.head_collision import CollisionPool, FloorTets, HeadCollision, HeadShape
from neuralslicer.neural.networks import DeformationFields
from neuralslicer.samples import SurfaceSamples


class FieldProblem:
    """Everything fixed during the optimisation: cage, ARAP factor, samples mapped to cage tets."""

    def __init__(self, cage_vertices: np.ndarray, cage_tets: np.ndarray, samples: SurfaceSamples,
                 stress_samples: StressSamples | None, config: NeuralConfig, platform_z: float | None,
                 collision_pool: CollisionPool | None = None, solid_tets: np.ndarray | None = None) -> None:
        """Map B (and T) to the cage, factor the ARAP system, build the collision terms. ``solid_tets``: the cage
        tets that hold solid (m,) bool, for L_GC's floor term (besides the tets holding B or pool points)."""
        self.config = config
        self.phi = math.radians(config.apex_deg())
        self.device = resolve_device(config.device)
        self.dtype = resolve_dtype(config.dtype)
        self.geometry = CageGeometry.build(cage_vertices, cage_tets)
        g = self.geometry
        self.platform_z = float(platform_z) if platform_z is not None else None
        self.arap = ArapDeformation(g.vertices, g.tets, config.deformation, self.platform_z)
        dev, dt = self.device, self.dtype

        def T(a: np.ndarray, dtype: torch.dtype = dt) -> torch.Tensor:
            """Array -> tensor on the problem's device."""
            return torch.as_tensor(np.asarray(a), dtype=dtype, device=dev)

        self.tets_t = T(g.tets, torch.int64)
        self.bary_grads_t = T(g.bary_grads)
        self.centroids_t = T(g.centroids)
        self.pairs_t = T(g.pairs, torch.int64)
        self.pair_normals_t = T(g.pair_normals)
        self.pair_weights_t = T(0.5 * (g.volumes[g.pairs[:, 0]] + g.volumes[g.pairs[:, 1]]))
        # surface samples B (platform points kept as kNN positions, excluded from SF/PO)
        pts = np.asarray(samples.points, dtype=np.float64).reshape(-1, 3)
        on_pf = np.asarray(samples.on_platform, dtype=bool)
        active = np.flatnonzero(~on_pf)
        self.b_active = active
        self.b_tet = g.locate(pts[active])
        self.b_tet_t = T(self.b_tet, torch.int64)
        self.b_platform_tet = g.locate(pts[on_pf])
        self.b_points_t = T(pts[active])
        self.b_all_t = T(pts)
        self.b_normals = np.asarray(samples.normals, dtype=np.float64)[active]
        self.b_normals_t = T(self.b_normals)
        self.b_areas = np.asarray(samples.areas, dtype=np.float64)[active]
        self.b_areas_t = T(self.b_areas)
        knn = np.asarray(samples.knn, dtype=np.int64)
        self.b_knn_t = T(knn[active], torch.int64)
        self.b_offsets_t = (L.neighbour_offsets(self.b_points_t, self.b_knn_t, self.b_all_t)  # L_PO's, fixed
                            if self.b_knn_t.numel() else None)
        if len(active) and knn.size:
            dist = np.linalg.norm(pts[knn[active]] - pts[active][:, None, :], axis=2)
            self.po_length = float(max(dist.mean(), 1e-12))
        else:
            self.po_length = 1.0
        # stress samples T
        if stress_samples is not None and len(stress_samples.points):
            self.t_tet = g.locate(np.asarray(stress_samples.points, dtype=np.float64).reshape(-1, 3))
            self.t_tau = np.asarray(stress_samples.tau_max, dtype=np.float64)
            self.t_volumes = np.asarray(stress_samples.volumes, dtype=np.float64)
        else:
            self.t_tet = np.zeros(0, np.int64)
            self.t_tau = np.zeros((0, 3))
            self.t_volumes = np.zeros(0)
        self.t_tet_t = T(self.t_tet, torch.int64)
        self.t_tau_t = T(self.t_tau)
        self.t_volumes_t = T(self.t_volumes)
        self.head = self._head_collision(collision_pool, solid_tets)
        self._tilt_set(solid_tets)
        #: what the last constraint check measured (overhang, its target, pool points whose head hits), for progress
        self.last_check: dict[str, float] = {}
        #: the constraint stop accepts at least this overhang fraction (a warm start's own, see optimise_field)
        self.overhang_floor = 0.0
        #: (networks, their weights' versions, G, grad G) of the last field computed (see :meth:`field`)
        self._last_field: tuple[weakref.ref, tuple[int, ...], torch.Tensor, torch.Tensor] | None = None
        #: search L_GC's pairs on the next evaluation's own field, before its terms (see :meth:`schedule_refresh`)
        self._refresh_due = False

    def _head_collision(self, pool: CollisionPool | None, solid_tets: np.ndarray | None) -> HeadCollision | None:
        """L_GC on the pool of solid points and the floor tets (None when its weight is 0); the pool is required
        then."""
        cl = self.config.loss
        if cl.w_gc <= 0:
            return None
        if pool is None or len(pool.points) == 0:
            raise ValueError("the global collision term (w_gc > 0) needs a collision_pool of points in the solid")
        tet, bary = self.geometry.barycentric(pool.points)
        head = HeadShape.from_nozzle(cl.head, cl.head_min_height)
        floor = None
        if self.platform_z is not None and cl.gc_floor:
            g = self.geometry
            solid = np.zeros(len(g.tets), bool) if solid_tets is None else np.asarray(solid_tets, bool).copy()
            solid[tet] = True
            solid[self.b_tet] = True
            solid[self.b_platform_tet] = True
            floor = FloorTets.of(g.vertices, g.tets, g.volumes, solid, self.platform_z, head)
        clearance = cl.gc_clearance if cl.gc_clearance is not None else min(1.5 * pool.spacing, cl.head.cone_length)
        return HeadCollision(pool.points, tet, bary, self.geometry.tets, head, self.platform_z, clearance,
                             cl.gc_front_margin, pool.spacing, 0.5 * pool.spacing, self.device, self.dtype,
                             n_base=pool.n_base, links=pool.links, link_radius=pool.link_radius,
                             max_link_pairs=self.config.optim.refine.max_pairs, floor=floor,
                             floor_weight=cl.gc_floor_weight, platform_turn=math.radians(cl.gc_platform_turn_deg),
                             vertical=cl.gc_vertical_head)

    def _tilt_set(self, solid_tets: np.ndarray | None) -> None:
        """The cage tets where the tilt bound holds (the solid: ``solid_tets`` with the tets holding B, T or L_GC's
        pool points) and their volumes, the weights of L_TB; none without a bound."""
        g = self.geometry
        self.tilt_bound = (math.radians(self.config.loss.tilt_bound_deg)
                           if self.config.loss.tilt_bound_deg is not None else None)
        solid = np.zeros(len(g.tets), bool)
        if self.tilt_bound is not None:
            if solid_tets is not None:
                solid |= np.asarray(solid_tets, bool)
            pool = self.head.tet if self.head is not None else np.zeros(0, np.int64)
            for tets in (self.b_tet, self.b_platform_tet, self.t_tet, pool):
                solid[tets[tets >= 0]] = True
        self.tilt_tets = np.flatnonzero(solid)
        self.tilt_tets_t = torch.as_tensor(self.tilt_tets, dtype=torch.int64, device=self.device)
        self.tilt_weights_t = torch.as_tensor(g.volumes[self.tilt_tets], dtype=self.dtype, device=self.device)

    def terms(self) -> tuple[str, ...]:
        """The loss terms this problem evaluates (the history's keys): L_TB only with a tilt bound."""
        base = ("sf", "sr", "po", "hs", "hq", "gc", "ca")
        return base + ("tb",) if self.tilt_bound is not None else base

    def field(self, fields: DeformationFields) -> tuple[torch.Tensor, torch.Tensor]:
        """(G at the cage vertices (n,), grad G per tet (m,3)) for the current weights, without a graph; the last
        field computed (here or by an evaluation) again while the weights are unchanged (a check step asks for it
        up to three times)."""
        last = self._last_field
        if last is not None and last[0]() is fields and last[1] == weights_version(fields):
            return last[2], last[3]
        with torch.no_grad():
            G, _, _ = self.height(fields)
            grad = field_gradient(G, self.tets_t, self.bary_grads_t)
        return self._remember_field(fields, G, grad)

    def _remember_field(self, fields: DeformationFields, G: torch.Tensor, grad: torch.Tensor
                        ) -> tuple[torch.Tensor, torch.Tensor]:
        """Keep G (n,) and grad G (m,3) of these networks' current weights for :meth:`field`; them, detached."""
        self._last_field = (weakref.ref(fields), weights_version(fields), G.detach(), grad.detach())
        return self._last_field[2], self._last_field[3]

    def refresh_collisions(self, fields: DeformationFields) -> int:
        """Search the pairs near collision for the current weights (L_GC's active set); their number."""
        self._refresh_due = False
        return 0 if self.head is None else self.head.refresh(*self.field(fields))

    def schedule_refresh(self) -> None:
        """Search L_GC's pairs on the field of the next evaluation (before its terms, as refresh_collisions before
        it would, without a forward pass of its own)."""
        self._refresh_due = self.head is not None

    def head_collisions(self, G: np.ndarray) -> dict[str, int]:
        """Collisions of the head over the whole pool for a field G (n,) at the cage vertices."""
        if self.head is None:
            return {}
        Gt = torch.as_tensor(G, dtype=self.dtype, device=self.device)
        return self.head.count(Gt, field_gradient(Gt, self.tets_t, self.bary_grads_t))

    def new_fields(self) -> DeformationFields:
        """Fresh identity-initialised networks (uses the torch RNG) on the problem's device/dtype."""
        bounds = np.stack([self.geometry.vertices.min(0), self.geometry.vertices.max(0)])
        return DeformationFields(self.config.network_config(), bounds, len(self.geometry.tets)).to(
            self.device, self.dtype)

    def height(self, fields: DeformationFields) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
        """(G at cage vertices (n,), unit quaternions (m,4), scales (m,3)) for the current weights."""
        q, s = fields(self.centroids_t)
        return self.arap.deformed_height(q, s), q, s

    def evaluate(self, fields: DeformationFields, remember: bool = True
                 ) -> tuple[torch.Tensor, dict[str, torch.Tensor]]:
        """(total weighted loss, every term incl. L_CA) for the current network weights (``remember``: its field is
        the one :meth:`field` gives back while the weights stay as they are)."""
        total, terms, _ = self.evaluate_with_excess(fields, remember)
        return total, terms

    def evaluate_with_excess(
        self, fields: DeformationFields, remember: bool = True
    ) -> tuple[torch.Tensor, dict[str, torch.Tensor], torch.Tensor | None]:
        """(total, terms, per-pair collision excess angle (None when the collision term is off)). The excess has a
        graph only when a pair violates L_CA = 0 (beyond ``loss.correction_tol``: the DC3 correction follows), the
        total is free of it. A scheduled search for L_GC's pairs runs on this field first."""
        cl = self.config.loss
        G, q, s = self.height(fields)
        grad = field_gradient(G, self.tets_t, self.bary_grads_t)
        if remember:
            self._remember_field(fields, G, grad)
        if self._refresh_due:
            self._refresh_due = False
            self.head.refresh(G.detach(), grad.detach())
        d = unit(grad)
        terms: dict[str, torch.Tensor] = {}
        zero = G.new_zeros(())
        d_b = d.index_select(0, self.b_tet_t)
        terms["sf"] = (L.support_free_loss(d_b, self.b_normals_t, self.b_areas_t,
                                           math.radians(cl.alpha_deg), cl.k_sf)
                       if cl.w_sf > 0 else zero)
        terms["sr"] = (L.strength_loss(d[self.t_tet_t], self.t_tau_t, self.t_volumes_t,
                                       math.radians(cl.beta_deg), cl.k_sr)
                       if cl.w_sr > 0 and len(self.t_tet) else zero)
        terms["po"] = (L.point_overhang_loss(d_b, self.b_points_t, self.b_knn_t, self.b_all_t,
                                             self.b_areas_t, self.po_length, self.b_offsets_t)
                       if cl.w_po > 0 and self.b_knn_t.numel() else zero)
        terms["hs"] = L.harmonic_scale_loss(s, self.pairs_t, self.pair_weights_t) if cl.w_hs > 0 else zero
        terms["hq"] = L.harmonic_quaternion_loss(q, self.pairs_t, self.pair_weights_t) if cl.w_hq > 0 else zero
        terms["gc"] = self.head.loss(G, grad) if self.head is not None else zero
        excess = None
        if cl.collision:
            with torch.no_grad():
                excess = L.collision_excess(grad, self.pairs_t, self.pair_normals_t, self.phi)
            if bool((excess > cl.correction_tol).any()):  # a correction follows: the excess with its graph
                excess = L.collision_excess(grad, self.pairs_t, self.pair_normals_t, self.phi)
            terms["ca"] = torch.relu(excess).mean() if excess.numel() else zero
        else:
            terms["ca"] = zero
        total = (cl.w_sf * terms["sf"] + cl.w_sr * terms["sr"] + cl.w_po * terms["po"]
                 + cl.w_hs * terms["hs"] + cl.w_hq * terms["hq"] + cl.w_gc * terms["gc"])
        if self.tilt_bound is not None:
            terms["tb"] = L.tilt_bound_loss(grad[self.tilt_tets_t], self.tilt_weights_t, self.tilt_bound)
            total = total + cl.w_tb * terms["tb"]
        return total, terms, excess

    def tilt_violation(self, fields: DeformationFields) -> torch.Tensor:
        """``sum |V_e| relu(cos(b - margin) - d_z) / sum |V_e|`` over the tilt set, with its graph: zero iff every
        solid tet's LPD is at least ``loss.tilt_margin_deg`` inside the bound b (the final correction's target)."""
        G, _, _ = self.height(fields)
        grad = field_gradient(G, self.tets_t, self.bary_grads_t)
        bound = max(self.tilt_bound - math.radians(self.config.loss.tilt_margin_deg), 0.0)
        x = torch.relu(L.tilt_excess(grad[self.tilt_tets_t], bound))
        return (x * self.tilt_weights_t).sum() / self.tilt_weights_t.sum().clamp_min(1e-300)

    def tilt_angles64(self, fields: DeformationFields) -> np.ndarray:
        """Angle (deg) between +z and the LPD of each tet of the tilt set, in the float64 field the result
        stores."""
        with torch.no_grad():
            q, s = fields(self.centroids_t)
            G = self.arap.deformed_height(q.double(), s.double()).cpu().numpy()
        g = self.geometry
        grad = np.einsum("ei,eij->ej", G[g.tets[self.tilt_tets]], g.bary_grads[self.tilt_tets])
        return tilt_angles_deg(grad)

    def collision_excess(self, fields: DeformationFields) -> torch.Tensor:
        """Per-pair collision excess angle (rad, > 0 violates) in the working dtype, with its graph."""
        G, _, _ = self.height(fields)
        grad = field_gradient(G, self.tets_t, self.bary_grads_t)
        return L.collision_excess(grad, self.pairs_t, self.pair_normals_t, self.phi)

    def collision_excess64(self, fields: DeformationFields) -> np.ndarray:
        """Per-pair collision excess angle of the field the result stores (float64 deformation)."""
        with torch.no_grad():
            q, s = fields(self.centroids_t)
            G = self.arap.deformed_height(q.double(), s.double()).cpu().numpy()
        return self.excess_of(G)

    def excess_of(self, G: np.ndarray) -> np.ndarray:
        """Per-pair collision excess angle (rad, float64) of a field G (n,) at the cage vertices."""
        g = self.geometry
        grad = np.einsum("ei,eij->ej", np.asarray(G, dtype=np.float64)[g.tets], g.bary_grads)
        e = L.collision_excess(torch.from_numpy(grad), torch.from_numpy(g.pairs),
                               torch.from_numpy(g.pair_normals), self.phi)
        return e.numpy()

    def overhang(self, grad: torch.Tensor) -> float:
        """Overhang area fraction of B for the per-tet gradient of G (m,3)."""
        d = unit(grad[self.b_tet_t]).double().cpu().numpy()
        return overhang_area_fraction(self.b_normals, self.b_areas, np.zeros(len(d), bool), d,
                                      self.config.loss.alpha_deg)

    def constraints_met(self, fields: DeformationFields, step: int = 0) -> bool:
        """Support-free within ``optim.target_overhang`` (area fraction of B; ``target_overhang_late`` from
        step ``late_after`` on; at least ``overhang_floor``) and no head collision (none in the pool, refined
        points included, with the head grown by ``optim.stop_head_growth`` times its clearance); never with a
        strength objective, which has no satisfied state (always False when target_overhang is 0 or SF is
        off). L_CA = 0 is the caller's part: the DC3 correction before each evaluation reports it."""
        oc = self.config.optim
        if not self.has_satisfied_state():
            return False
        target = max(oc.target_overhang, oc.target_overhang_late) if step >= oc.late_after else oc.target_overhang
        target = max(target, self.overhang_floor)
        G, grad = self.field(fields)
        over = self.overhang(grad)
        self.last_check = {"overhang": over, "overhang_target": target}
        if over > target:
            return False
        if self.head is None:
            return True
        # the pool's points judge: the floor's lowest solid point is a bound (up to a cage cell below the solid), so
        # its tets can stay "hit" where the solid itself is clear; counted here, 11 such tets kept a torus standing
        # on the platform from stopping within 600 steps, its print clean (the floor term still acts in the loss)
        hits = self.head.count(G, grad, oc.stop_head_growth * self.head.clearance)["colliding_points"]
        self.last_check["head_hits"] = hits
        return not hits

    def has_satisfied_state(self) -> bool:
        """Whether the constraint stop can fire: an overhang target, SF on, samples B, no strength objective."""
        cl, oc = self.config.loss, self.config.optim
        return oc.target_overhang > 0 and cl.w_sf > 0 and cl.w_sr <= 0 and len(self.b_tet) > 0

    def watches_progress(self) -> bool:
        """Whether the progress stall test applies: it is on and the constraint stop can fire."""
        return self.config.optim.progress_window > 0 and self.has_satisfied_state()

    def progress(self, fields: DeformationFields) -> tuple[float, int]:
        """(overhang area fraction of B, pool points whose head hits, grown as the constraint stop's) now."""
        G, grad = self.field(fields)
        hits = 0
        if self.head is not None:
            growth = self.config.optim.stop_head_growth * self.head.clearance
            count = self.head.count(G, grad, growth)
            hits = int(count["colliding_points"] + count["floor_tets_hit"])
        return self.overhang(grad), hits

    def planar_lpd_satisfaction(self) -> dict[str, float]:
        """SF/SR satisfaction of planar layers (d = +z)."""
        m = len(self.geometry.tets)
        return self.satisfaction(np.tile([0.0, 0.0, 1.0], (m, 1)))

    def satisfaction(self, lpd: np.ndarray) -> dict[str, float]:
        """Fraction of B area supported (-n.d <= sin a), overhang fraction, fraction of T volume
        with |d.tau| <= sin b, for per-tet unit LPDs (m,3)."""
        cl = self.config.loss
        out: dict[str, float] = {}
        if len(self.b_tet):  # B holds the non-platform samples only
            over = overhang_area_fraction(self.b_normals, self.b_areas, np.zeros(len(self.b_tet), bool),
                                          lpd[self.b_tet], cl.alpha_deg)
            out["sf_supported_fraction"] = 1.0 - over
            out["overhang_area_fraction"] = over
        if len(self.t_tet):
            out["sr_satisfied_fraction"] = strength_satisfaction(self.t_tau, self.t_volumes, lpd[self.t_tet], cl.beta_deg)
        return out


def weights_version(fields: DeformationFields) -> tuple[int, ...]:
    """The version counters of the networks' parameters and buffers: any change of a weight in place (an Adam or
    DC3 step, a state dict loaded) changes them."""
    return tuple(t._version for t in (*fields.parameters(), *fields.buffers()))


def tilt_angles_deg(directions: np.ndarray) -> np.ndarray:
    """Angle (deg) between +z and each direction (n,3) (any length; a zero vector counts as 180)."""
    d = np.asarray(directions, np.float64).reshape(-1, 3)
    norm = np.linalg.norm(d, axis=1)
    cos = np.where(norm > 0, d[:, 2] / np.maximum(norm, 1e-300), -1.0)
    return np.degrees(np.arccos(np.clip(cos, -1.0, 1.0)))
