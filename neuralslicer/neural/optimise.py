"""Resumable optimisation of the deformation fields q, s (SPEC steps 5-9).

``optimise_field`` takes plain arrays (cage, surface samples B, stress samples T) and a
:class:`NeuralConfig`, reports progress and checkpoints through callbacks, and returns a
:class:`FieldResult`. It knows nothing of the artifact store or Prefect.
"""
from __future__ import annotations

import contextlib
import copy
import io
import math
import random
import time
import warnings
from dataclasses import dataclass, field
from typing import Callable, Iterator

import numpy as np
import torch

from neuralslicer.metrics import overhang_area_fraction, strength_satisfaction
from neuralslicer.neural import losses as L
from neuralslicer.neural.config import NeuralConfig
from neuralslicer.neural.deformation import ArapDeformation
from neuralslicer.neural.device import resolve_device, resolve_dtype
from neuralslicer.neural.field import CageGeometry, field_gradient, unit
from neuralslicer.neural.head_collision import CollisionPool, HeadCollision, HeadShape
from neuralslicer.neural.initial_guess import (
    heat_geodesic,
    height_matched,
    platform_vertices,
    user_field_on_cage,
)
from neuralslicer.neural.networks import DeformationFields

TERMS = ("sf", "sr", "po", "hs", "hq", "gc", "ca")
CHECKPOINT_VERSION = 1
ProgressFn = Callable[[int, dict], None]


@dataclass
class FieldResult:
    """Result of the neural optimisation.

    deformed_vertices : (n, 3) cage vertices after deformation; G : (n,) field at cage vertices
    (= deformed z); lpd : (m, 3) unit LPD per cage tet; quaternions : (m, 4); scales : (m, 3);
    history : per-step arrays ('total', each term after the DC3 correction, 'corrections' made
    before the step, 'lr'); final : the loss
    terms at the end; pretrain_history : MSE per pre-training step.
    """

    deformed_vertices: np.ndarray
    G: np.ndarray
    lpd: np.ndarray
    quaternions: np.ndarray
    scales: np.ndarray
    history: dict[str, np.ndarray]
    final: dict[str, float]
    steps: int
    converged: bool
    wall_time_s: float
    satisfaction: dict[str, float]
    pretrain_history: np.ndarray
    attrs: dict = field(default_factory=dict)

    def to_arrays(self) -> tuple[dict[str, np.ndarray], dict]:
        """(arrays, json attrs) for a zarr group; history as 'history/<name>' arrays."""
        arrays = {
            "deformed_vertices": self.deformed_vertices,
            "G": self.G,
            "lpd": self.lpd,
            "quaternions": self.quaternions,
            "scales": self.scales,
            "pretrain_history": self.pretrain_history,
        }
        arrays.update({f"history/{k}": v for k, v in self.history.items()})
        attrs = dict(self.attrs)
        attrs.update(
            final=self.final, steps=self.steps, converged=self.converged,
            wall_time_s=self.wall_time_s, satisfaction=self.satisfaction,
        )
        return arrays, attrs


class FieldProblem:
    """Everything fixed during the optimisation: cage, ARAP factor, samples mapped to cage tets."""

    def __init__(
        self,
        cage_vertices: np.ndarray,
        cage_tets: np.ndarray,
        surface_points: np.ndarray,
        surface_normals: np.ndarray,
        surface_areas: np.ndarray,
        surface_knn: np.ndarray,
        surface_on_platform: np.ndarray | None,
        stress_points: np.ndarray | None,
        stress_volumes: np.ndarray | None,
        stress_tau: np.ndarray | None,
        config: NeuralConfig,
        platform_z: float | None,
        collision_pool: CollisionPool | None = None,
    ) -> None:
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
        pts = np.asarray(surface_points, dtype=np.float64).reshape(-1, 3)
        on_pf = (np.zeros(len(pts), bool) if surface_on_platform is None
                 else np.asarray(surface_on_platform, dtype=bool))
        active = np.flatnonzero(~on_pf)
        self.b_active = active
        self.b_tet = g.locate(pts[active])
        self.b_tet_t = T(self.b_tet, torch.int64)
        self.b_points_t = T(pts[active])
        self.b_all_t = T(pts)
        self.b_normals = np.asarray(surface_normals, dtype=np.float64)[active]
        self.b_normals_t = T(self.b_normals)
        self.b_areas = np.asarray(surface_areas, dtype=np.float64)[active]
        self.b_areas_t = T(self.b_areas)
        knn = np.asarray(surface_knn, dtype=np.int64)
        self.b_knn_t = T(knn[active], torch.int64)
        if len(active) and knn.size:
            dist = np.linalg.norm(pts[knn[active]] - pts[active][:, None, :], axis=2)
            self.po_length = float(max(dist.mean(), 1e-12))
        else:
            self.po_length = 1.0
        # stress samples T
        if stress_points is not None and len(stress_points):
            sp_ = np.asarray(stress_points, dtype=np.float64).reshape(-1, 3)
            self.t_tet = g.locate(sp_)
            self.t_tau = np.asarray(stress_tau, dtype=np.float64)
            self.t_volumes = np.asarray(stress_volumes, dtype=np.float64)
        else:
            self.t_tet = np.zeros(0, np.int64)
            self.t_tau = np.zeros((0, 3))
            self.t_volumes = np.zeros(0)
        self.t_tet_t = T(self.t_tet, torch.int64)
        self.t_tau_t = T(self.t_tau)
        self.t_volumes_t = T(self.t_volumes)
        self.head = self._head_collision(collision_pool)

    def _head_collision(self, pool: CollisionPool | None) -> HeadCollision | None:
        """L_GC on the pool of solid points (None when its weight is 0); the pool is required then."""
        cl = self.config.loss
        if cl.w_gc <= 0:
            return None
        if pool is None or len(pool.points) == 0:
            raise ValueError("the global collision term (w_gc > 0) needs a collision_pool of points in the solid")
        tet, bary = self.geometry.barycentric(pool.points)
        head = HeadShape.from_nozzle(cl.head, cl.head_min_height)
        clearance = cl.gc_clearance if cl.gc_clearance is not None else min(1.5 * pool.spacing, cl.head.cone_length)
        return HeadCollision(pool.points, tet, bary, self.geometry.tets, head, self.platform_z, clearance,
                             cl.gc_front_margin, pool.spacing, 0.5 * pool.spacing, self.device, self.dtype)

    def field(self, fields: DeformationFields) -> tuple[torch.Tensor, torch.Tensor]:
        """(G at the cage vertices (n,), grad G per tet (m,3)) for the current weights, without a graph."""
        with torch.no_grad():
            G, _, _ = self.height(fields)
            return G, field_gradient(G, self.tets_t, self.bary_grads_t)

    def refresh_collisions(self, fields: DeformationFields) -> int:
        """Search the pairs near collision for the current weights (L_GC's active set); their number."""
        return 0 if self.head is None else self.head.refresh(*self.field(fields))

    def head_collisions(self, G: np.ndarray) -> dict[str, int]:
        """Collisions of the head over the whole pool for a field G (n,) at the cage vertices."""
        if self.head is None:
            return {}
        Gt = torch.as_tensor(G, dtype=self.dtype, device=self.device)
        return self.head.count(Gt, field_gradient(Gt, self.tets_t, self.bary_grads_t))

    def new_fields(self) -> DeformationFields:
        """Fresh identity-initialised networks (uses the torch RNG) on the problem's device/dtype."""
        bounds = np.stack([self.geometry.vertices.min(0), self.geometry.vertices.max(0)])
        return DeformationFields(self.config.network_config(), bounds).to(self.device, self.dtype)

    def height(self, fields: DeformationFields) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
        """(G at cage vertices (n,), unit quaternions (m,4), scales (m,3)) for the current weights."""
        q, s = fields(self.centroids_t)
        return self.arap.deformed_height(q, s), q, s

    def evaluate(self, fields: DeformationFields) -> tuple[torch.Tensor, dict[str, torch.Tensor]]:
        """(total weighted loss, every term incl. L_CA) for the current network weights."""
        total, terms, _ = self.evaluate_with_excess(fields)
        return total, terms

    def evaluate_with_excess(
        self, fields: DeformationFields
    ) -> tuple[torch.Tensor, dict[str, torch.Tensor], torch.Tensor | None]:
        """(total, terms, per-pair collision excess angle (None when the collision term is off))."""
        cl = self.config.loss
        G, q, s = self.height(fields)
        grad = field_gradient(G, self.tets_t, self.bary_grads_t)
        d = unit(grad)
        terms: dict[str, torch.Tensor] = {}
        zero = G.new_zeros(())
        d_b = d[self.b_tet_t]
        terms["sf"] = (L.support_free_loss(d_b, self.b_normals_t, self.b_areas_t,
                                           math.radians(cl.alpha_deg), cl.k_sf)
                       if cl.w_sf > 0 else zero)
        terms["sr"] = (L.strength_loss(d[self.t_tet_t], self.t_tau_t, self.t_volumes_t,
                                       math.radians(cl.beta_deg), cl.k_sr)
                       if cl.w_sr > 0 and len(self.t_tet) else zero)
        terms["po"] = (L.point_overhang_loss(d_b, self.b_points_t, self.b_knn_t, self.b_all_t,
                                             self.b_areas_t, self.po_length)
                       if cl.w_po > 0 and self.b_knn_t.numel() else zero)
        terms["hs"] = L.harmonic_scale_loss(s, self.pairs_t, self.pair_weights_t) if cl.w_hs > 0 else zero
        terms["hq"] = L.harmonic_quaternion_loss(q, self.pairs_t, self.pair_weights_t) if cl.w_hq > 0 else zero
        terms["gc"] = self.head.loss(G, grad) if self.head is not None else zero
        excess = None
        if cl.collision:
            excess = L.collision_excess(grad, self.pairs_t, self.pair_normals_t, self.phi)
            terms["ca"] = torch.relu(excess).mean() if excess.numel() else zero
        else:
            terms["ca"] = zero
        total = (cl.w_sf * terms["sf"] + cl.w_sr * terms["sr"] + cl.w_po * terms["po"]
                 + cl.w_hs * terms["hs"] + cl.w_hq * terms["hq"] + cl.w_gc * terms["gc"])
        return total, terms, excess

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

    def constraints_met(self, fields: DeformationFields) -> bool:
        """Support-free within ``optim.target_overhang`` (area fraction of B) and no head collision
        (none in the pool with the head grown by half its clearance); never with a strength objective,
        which has no satisfied state (always False when target_overhang is 0 or SF is off). L_CA = 0 is
        the caller's part: the DC3 correction before each evaluation reports it."""
        cl, oc = self.config.loss, self.config.optim
        if oc.target_overhang <= 0 or cl.w_sf <= 0 or cl.w_sr > 0 or not len(self.b_tet):
            return False
        G, grad = self.field(fields)
        d = unit(grad[self.b_tet_t]).double().cpu().numpy()
        if overhang_area_fraction(self.b_normals, self.b_areas, np.zeros(len(d), bool), d,
                                  cl.alpha_deg) > oc.target_overhang:
            return False
        return self.head is None or not self.head.count(G, grad, 0.5 * self.head.clearance)["colliding_points"]

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


def correction_step(fields: DeformationFields, violation: torch.Tensor, config) -> bool:
    """One DC3-style correction of the weights towards the feasible set (in place); False if no step.

    ``violation`` is ``mean(relu(excess + margin))`` over the adjacent pairs (zero iff every pair
    is at least ``margin`` inside the constraint). The step is the first-order (Polyak /
    Gauss-Newton) step to its zero, ``theta -= lr * v / |grad v|^2 * grad v``, its length capped at
    ``max_step * |theta|`` so that a nearly flat constraint cannot throw the weights away.
    """
    params = [p for p in fields.parameters() if p.requires_grad]
    grads = torch.autograd.grad(violation, params, allow_unused=True)
    norm2 = sum(float((g * g).sum()) for g in grads if g is not None)
    if norm2 <= 0 or not math.isfinite(norm2):
        return False
    theta = math.sqrt(sum(float((p.detach() * p.detach()).sum()) for p in params))
    eta = config.correction_lr * float(violation.detach()) / norm2
    eta = min(eta, config.correction_max_step * theta / math.sqrt(norm2))
    with torch.no_grad():
        for p, g in zip(params, grads):
            if g is not None:
                p.sub_(eta * g)
    return True


def violating_pairs(excess: torch.Tensor | np.ndarray | None, tol: float) -> int:
    """Number of adjacent pairs whose excess angle is above tol (0 when the term is off)."""
    if excess is None:
        return 0
    if isinstance(excess, torch.Tensor):
        return int((excess.detach() > tol).sum())
    return int(np.count_nonzero(excess > tol))


def corrected_evaluation(
    problem: FieldProblem, fields: DeformationFields
) -> tuple[torch.Tensor, dict[str, torch.Tensor], int, int]:
    """Evaluate the losses after DC3 corrections: while a pair violates L_CA = 0 (excess above
    ``correction_tol``), at most ``correction_steps`` times, one correction step.

    Returns (total, terms, corrections made, pairs still violating); the terms are those of the
    corrected weights, so a feasible iterate costs one evaluation and each correction one
    backward + one evaluation.
    """
    cl = problem.config.loss
    total, terms, excess = problem.evaluate_with_excess(fields)
    done = 0
    while (excess is not None and done < cl.correction_steps
           and violating_pairs(excess, cl.correction_tol) > 0):
        if not correction_step(fields, torch.relu(excess + cl.correction_margin).mean(), cl):
            break
        done += 1
        total, terms, excess = problem.evaluate_with_excess(fields)
    return total, terms, done, violating_pairs(excess, cl.correction_tol)


def loss_of(problem: FieldProblem, fields: DeformationFields, weights: dict) -> float:
    """Total loss of other weights (the fields' own weights are left as they were)."""
    current = _clone_state(fields.state_dict())
    fields.load_state_dict(weights)
    with torch.no_grad():
        total = float(problem.evaluate(fields)[0])
    fields.load_state_dict(current)
    return total


def stale_collisions(problem: FieldProblem, fields: DeformationFields) -> bool:
    """Search L_GC's pairs afresh for the current weights; True when the head still collides."""
    problem.refresh_collisions(fields)
    with torch.no_grad():
        return float(problem.evaluate(fields)[1]["gc"]) > 0


def enforce_collision_constraint(problem: FieldProblem, fields: DeformationFields) -> int:
    """Correct the final weights until no pair violates L_CA = 0 in the float64 field the result
    stores (at most ``final_correction_steps`` steps); returns the steps made."""
    cl = problem.config.loss
    excess64 = problem.collision_excess64(fields)
    done = 0
    while done < cl.final_correction_steps and violating_pairs(excess64, cl.correction_tol) > 0:
        target = torch.relu(problem.collision_excess(fields) + cl.correction_margin).mean()
        # float32 and float64 excesses differ by ~1e-6 rad, far less than the margin: a zero
        # target here would mean no direction is left to correct along; the result reports it
        if float(target.detach()) <= 0 or not correction_step(fields, target, cl):
            break
        done += 1
        excess64 = problem.collision_excess64(fields)
    return done


def initial_target(problem: FieldProblem, user_values: np.ndarray | None,
                   user_points: np.ndarray | None) -> np.ndarray | None:
    """Target G at cage vertices for the configured initial guess (None for 'height')."""
    init = problem.config.init
    V, Tt = problem.geometry.vertices, problem.geometry.tets
    if init.kind == "height":
        return None
    if init.kind == "heat":
        edges = np.linalg.norm(V[Tt[:, 0]] - V[Tt[:, 1]], axis=1).mean()
        src = platform_vertices(V, problem.platform_z, 0.5 * edges)
        field_ = heat_geodesic(V, Tt, src, init.heat_time_factor)
    else:
        if user_values is None:
            from neuralslicer.errors import InputError

            raise InputError("init.kind", "'user' initial guess needs user_field values")
        field_ = user_field_on_cage(V, user_values, user_points)
    return height_matched(field_, V)


def pretrain(
    problem: FieldProblem,
    fields: DeformationFields,
    target: np.ndarray,
    progress: ProgressFn | None = None,
) -> np.ndarray:
    """Fit G to target (n,) by Adam; returns the MSE (normalised by the z range^2) per step.

    The objective is the MSE plus ``pretrain_harmonic * (w_hs L_HS + w_hq L_HQ)``: many rotation and
    scale fields give the same G, and a plain MSE fit picks rough ones (large L_HS) that the
    optimisation afterwards has to smooth out slowly; with the harmonic terms the guess starts
    as smooth as it can be. ``progress(0, {"phase": "pretrain", "pretrain_step", "pretrain_steps",
    "mse"})`` per step.
    """
    init, cl = problem.config.init, problem.config.loss
    tgt = torch.as_tensor(target, dtype=problem.dtype, device=problem.device)
    scale = float(np.ptp(problem.geometry.vertices[:, 2])) ** 2
    opt = torch.optim.Adam(fields.parameters(), lr=init.pretrain_lr)
    wh = init.pretrain_harmonic
    hist = []
    for _ in range(init.pretrain_steps):
        G, q, s = problem.height(fields)
        mse = ((G - tgt) ** 2).mean() / scale
        loss = mse
        if wh > 0:
            if cl.w_hs > 0:
                loss = loss + wh * cl.w_hs * L.harmonic_scale_loss(s, problem.pairs_t, problem.pair_weights_t)
            if cl.w_hq > 0:
                loss = loss + wh * cl.w_hq * L.harmonic_quaternion_loss(q, problem.pairs_t, problem.pair_weights_t)
        opt.zero_grad()
        loss.backward()
        opt.step()
        hist.append(float(mse.detach()))
        if progress is not None:
            progress(0, {"phase": "pretrain", "pretrain_step": len(hist),
                         "pretrain_steps": init.pretrain_steps, "mse": hist[-1]})
    return np.asarray(hist)


def _clone_state(state: dict) -> dict:
    """A deep copy of a (network or optimiser) state dict, tensors cloned."""
    return copy.deepcopy(state)


def _restore(fields: DeformationFields, optimizer: torch.optim.Optimizer, state: dict, lr: float) -> None:
    """Weights and Adam state of a saved iterate, with the learning rate set to lr."""
    fields.load_state_dict(state["fields"])
    # a copy: Adam updates its moments in place and would alter the saved state
    optimizer.load_state_dict(_clone_state(state["optimizer"]))
    for group in optimizer.param_groups:
        group["lr"] = lr


def _smooth(previous: float | None, value: float, weight: float, skip: bool = False) -> float:
    """Next smoothed loss: exp of the exponential moving average of log(loss); unchanged on skip."""
    if previous is None:
        return value
    if skip or not (value > 0 and math.isfinite(value)) or previous <= 0:
        return previous
    return math.exp(math.log(previous) + weight * (math.log(value) - math.log(previous)))


def _trend_of(totals: list[float], weight: float) -> list[float]:
    """Smoothed losses of a history (for checkpoints written without them)."""
    out: list[float] = []
    for v in totals:
        out.append(_smooth(out[-1] if out else None, v, weight))
    return out


def _rng_state() -> dict:
    """RNG states of torch, numpy and python."""
    return {"torch": torch.get_rng_state(), "numpy": np.random.get_state(), "python": random.getstate()}


def _set_rng_state(state: dict) -> None:
    """Restore the RNG states saved by _rng_state."""
    torch.set_rng_state(state["torch"])
    np.random.set_state(state["numpy"])
    random.setstate(state["python"])


def seed_everything(seed: int) -> None:
    """Seed torch, numpy and python RNGs."""
    torch.manual_seed(seed)
    np.random.seed(seed % (2**32))
    random.seed(seed)


def optimise_field(
    cage_vertices: np.ndarray,
    cage_tets: np.ndarray,
    surface_points: np.ndarray,
    surface_normals: np.ndarray,
    surface_areas: np.ndarray,
    surface_knn: np.ndarray,
    surface_on_platform: np.ndarray | None = None,
    stress_points: np.ndarray | None = None,
    stress_volumes: np.ndarray | None = None,
    stress_tau: np.ndarray | None = None,
    config: NeuralConfig | None = None,
    platform_z: float | None = None,
    user_field: np.ndarray | None = None,
    user_field_points: np.ndarray | None = None,
    progress: ProgressFn | None = None,
    save_checkpoint: Callable[[bytes, int], None] | None = None,
    load_checkpoint: Callable[[], bytes | None] | None = None,
    collision_pool: CollisionPool | None = None,
) -> FieldResult:
    """Optimise the SIREN fields q, s so that G = deformed z meets the SF/SR/PO objectives.

    Parameters
    ----------
    cage_vertices : (n, 3) float64, cage_tets : (m, 4) int64 -- the cage C (build frame).
    surface_points, surface_normals : (nb, 3) -- B with outward unit normals; surface_areas : (nb,)
        |A_p|; surface_knn : (nb, k) int64 neighbour ids into B; surface_on_platform : (nb,) bool,
        points excluded from L_SF and L_PO.
    stress_points : (nt, 3), stress_volumes : (nt,), stress_tau : (nt, 3) unit -- T (optional).
    config : NeuralConfig (defaults documented there); platform_z : platform height (pinning,
        heat-method source); user_field / user_field_points : the 'user' initial guess, values at
        cage vertices (n,) or at the given points.
    progress(step, info) : called after every step with the loss terms, lr, corrections and
        elapsed time (info["phase"] == "optimise"); during pre-training with step 0 and
        info["phase"] == "pretrain".
    save_checkpoint(bytes, step) : called every ``optim.checkpoint_every`` steps and at the end.
    load_checkpoint() -> bytes | None : a previous checkpoint to resume from.
    collision_pool : points inside the solid that stand for it in the global collision term L_GC
        (see :func:`neuralslicer.neural.head_collision.collision_pool`); needed when ``loss.w_gc > 0``.
    """
    config = config or NeuralConfig()
    with deterministic_algorithms():
        return _optimise_field(
            cage_vertices, cage_tets, surface_points, surface_normals, surface_areas, surface_knn,
            surface_on_platform, stress_points, stress_volumes, stress_tau, config, platform_z,
            user_field, user_field_points, progress, save_checkpoint, load_checkpoint, collision_pool,
        )


@contextlib.contextmanager
def deterministic_algorithms() -> Iterator[None]:
    """Use torch's deterministic kernels (reproducible runs and resumes), restoring the setting."""
    enabled = torch.are_deterministic_algorithms_enabled()
    warn_only = torch.is_deterministic_algorithms_warn_only_enabled()
    torch.use_deterministic_algorithms(True, warn_only=True)
    try:
        yield
    finally:
        torch.use_deterministic_algorithms(enabled, warn_only=warn_only)


def _optimise_field(
    cage_vertices: np.ndarray,
    cage_tets: np.ndarray,
    surface_points: np.ndarray,
    surface_normals: np.ndarray,
    surface_areas: np.ndarray,
    surface_knn: np.ndarray,
    surface_on_platform: np.ndarray | None,
    stress_points: np.ndarray | None,
    stress_volumes: np.ndarray | None,
    stress_tau: np.ndarray | None,
    config: NeuralConfig,
    platform_z: float | None,
    user_field: np.ndarray | None,
    user_field_points: np.ndarray | None,
    progress: ProgressFn | None,
    save_checkpoint: Callable[[bytes, int], None] | None,
    load_checkpoint: Callable[[], bytes | None] | None,
    collision_pool: CollisionPool | None,
) -> FieldResult:
    """optimise_field's body, run under deterministic torch algorithms."""
    t0 = time.perf_counter()
    problem = FieldProblem(
        cage_vertices, cage_tets, surface_points, surface_normals, surface_areas, surface_knn,
        surface_on_platform, stress_points, stress_volumes, stress_tau, config, platform_z, collision_pool,
    )
    oc = config.optim
    seed_everything(oc.seed)
    fields = problem.new_fields()

    def new_optimizer() -> tuple[torch.optim.Adam, torch.optim.lr_scheduler.ReduceLROnPlateau]:
        """Fresh Adam (no moments) and plateau scheduler."""
        opt = torch.optim.Adam(fields.parameters(), lr=oc.lr, betas=tuple(oc.betas))
        return opt, torch.optim.lr_scheduler.ReduceLROnPlateau(
            opt, mode="min", factor=oc.plateau_factor, patience=oc.plateau_patience, min_lr=oc.min_lr
        )

    optimizer, scheduler = new_optimizer()
    # the best iterate: loss, weights and Adam state (a diverging step goes back to it)
    best_state: dict | None = None
    rollbacks = 0
    trend: list[float] = []
    history: dict[str, list[float]] = {k: [] for k in ("total", *TERMS, "corrections", "lr")}
    pretrain_hist = np.zeros(0)
    step = 0
    converged = False
    final_corrections = 0  # DC3 steps on the final weights (kept in the last checkpoint)
    blob = load_checkpoint() if load_checkpoint is not None else None
    if blob:
        state = torch.load(io.BytesIO(blob), map_location=problem.device, weights_only=False)
        fields.load_state_dict(state["fields"])
        optimizer.load_state_dict(state["optimizer"])
        scheduler.load_state_dict(state["scheduler"])
        step, converged = int(state["step"]), bool(state["converged"])
        final_corrections = int(state.get("final_corrections", 0))
        best_state, rollbacks = state.get("best"), int(state.get("rollbacks", 0))
        trend = list(state.get("trend", []))
        history = {k: list(v) for k, v in state["history"].items()}
        for k in TERMS:  # checkpoints written before a term existed
            history.setdefault(k, [0.0] * len(history["total"]))
        pretrain_hist = np.asarray(state["pretrain_history"])
        _set_rng_state(state["rng"])
    else:
        target = initial_target(problem, user_field, user_field_points)
        if target is not None:
            pretrain_hist = pretrain(problem, fields, target, progress)
            optimizer, scheduler = new_optimizer()  # no moments carried over from the fit

    def checkpoint() -> None:
        """Serialise the complete state and hand it to save_checkpoint."""
        if save_checkpoint is None:
            return
        buf = io.BytesIO()
        torch.save({
            "version": CHECKPOINT_VERSION, "fields": fields.state_dict(),
            "optimizer": optimizer.state_dict(), "scheduler": scheduler.state_dict(),
            "step": step, "converged": converged, "history": history,
            "final_corrections": final_corrections, "best": best_state, "rollbacks": rollbacks,
            "trend": trend,
            "pretrain_history": pretrain_hist, "rng": _rng_state(), "seed": oc.seed,
            "config": config.model_dump(mode="json"),
        }, buf)
        save_checkpoint(buf.getvalue(), step)

    best: list[float] = []
    for v in history["total"]:
        best.append(min(best[-1], v) if best else v)
    # running minimum of the smoothed loss exp(EMA(log L)) per step: what the scheduler and the
    # stall test see (roll-back steps leave it unchanged)
    if not trend:
        trend = _trend_of(history["total"], oc.trend_smoothing) if history["total"] else []
    first = True  # a resumed run searches L_GC's pairs before its first step (checkpoints sit on check steps)
    while step < oc.max_steps and not converged:
        check = step % oc.check_every == 0
        if problem.head is not None and (check or first):
            problem.refresh_collisions(fields)
            if best_state is not None:  # the best loss again, on the new pairs
                best_state["loss"] = loss_of(problem, fields, best_state["fields"])
        first = False
        total, terms, n_corr, n_viol = corrected_evaluation(problem, fields)
        if check and step > 0 and n_viol == 0 and problem.constraints_met(fields):
            converged, best_state = True, None  # this (corrected) iterate is the result
            break
        tv = float(total.detach())
        lr = optimizer.param_groups[0]["lr"]
        diverged = (oc.divergence_factor > 0 and best_state is not None
                    and not tv <= oc.divergence_factor * best_state["loss"])
        if diverged:
            # undo: back to the best iterate with its Adam moments, at a lower learning rate
            _restore(fields, optimizer, best_state, max(lr * oc.plateau_factor, oc.min_lr))
            rollbacks += 1
        else:
            if best_state is None or tv < best_state["loss"]:
                best_state = {"loss": tv, "step": step, "fields": _clone_state(fields.state_dict()),
                              "optimizer": _clone_state(optimizer.state_dict())}
            optimizer.zero_grad()
            total.backward()
            optimizer.step()
        smoothed = _smooth(trend[-1] if trend else None, tv, oc.trend_smoothing, diverged)
        trend.append(smoothed)
        if not diverged:
            scheduler.step(smoothed)
            new_lr = optimizer.param_groups[0]["lr"]
            if oc.restart_from_best and new_lr < lr and best_state is not None:
                _restore(fields, optimizer, best_state, new_lr)
        step += 1
        history["total"].append(tv)
        for k in TERMS:
            history[k].append(float(terms[k].detach()))
        history["corrections"].append(float(n_corr))
        history["lr"].append(optimizer.param_groups[0]["lr"])
        best.append(min(best[-1], tv) if best else tv)
        w = oc.convergence_window
        if len(trend) > w:
            old, new = min(trend[:-w]), min(trend)
            converged = (old - new) <= oc.convergence_rtol * abs(old) + oc.convergence_atol
            if optimizer.param_groups[0]["lr"] <= oc.min_lr * (1 + 1e-9):
                converged = converged or (old - new) <= 1e-9 * abs(old)
        if oc.target_loss > 0 and best[-1] <= oc.target_loss:
            converged = True
            if problem.head is not None and stale_collisions(problem, fields):
                # the best loss was measured on an outdated set of pairs: forget it and go on
                converged, best_state, best[-1] = False, None, math.inf
        if progress is not None:
            info = {k: history[k][-1] for k in history}
            info["elapsed_s"] = time.perf_counter() - t0
            info["phase"] = "optimise"
            info["ca_violating_pairs"] = n_viol
            info["best"] = best[-1]
            info["rollbacks"] = rollbacks
            progress(step, info)
        if step % oc.checkpoint_every == 0 and step < oc.max_steps and not converged:
            checkpoint()
    if oc.return_best and best_state is not None:
        fields.load_state_dict(best_state["fields"])
    if config.loss.collision:
        # the hard constraint holds for the field that is returned, not only before each step
        final_corrections += enforce_collision_constraint(problem, fields)
    checkpoint()

    problem.refresh_collisions(fields)  # L_GC of the result on a fresh set of pairs
    with torch.no_grad():
        q, s = fields(problem.centroids_t)
        V = problem.arap.deform(q.double(), s.double()).cpu().numpy()
        G = V[:, 2].copy()
        total, terms = problem.evaluate(fields)
    excess64 = problem.excess_of(G)
    n_viol = violating_pairs(excess64, config.loss.correction_tol)
    collision = {
        "enforced": bool(config.loss.collision), "phi_deg": config.apex_deg(),
        "ca": float(np.maximum(excess64, 0).mean()) if len(excess64) else 0.0,
        "violating_pairs": n_viol, "n_pairs": int(len(excess64)),
        "max_excess_rad": float(excess64.max()) if len(excess64) else 0.0,
        "tol_rad": config.loss.correction_tol, "margin_rad": config.loss.correction_margin,
        "final_corrections": final_corrections,
    }
    if n_viol and config.loss.collision:
        warnings.warn(f"L_CA = 0 not reached: {n_viol} adjacent pairs still violate "
                      f"(max excess {collision['max_excess_rad']:.2e} rad)", RuntimeWarning, stacklevel=2)
    gradG = np.einsum("ei,eij->ej", G[problem.geometry.tets], problem.geometry.bary_grads)
    lpd = gradG / np.maximum(np.linalg.norm(gradG, axis=1, keepdims=True), 1e-300)
    sat = {k: v for k, v in problem.satisfaction(lpd).items()}
    sat.update({f"planar_{k}": v for k, v in problem.planar_lpd_satisfaction().items()})
    final = {k: float(v) for k, v in terms.items()}
    final["total"] = float(total)
    if config.loss.collision:  # the constraint as stored: the float64 field, pairs counted
        final["ca"] = collision["ca"]
        final["ca_violating_pairs"] = float(n_viol)
    head = problem.head_collisions(G)
    if head:
        final["gc_colliding_pairs"] = float(head["colliding_pairs"])
        head.update(weight=config.loss.w_gc, spacing=problem.head.length, clearance=problem.head.clearance)
    return FieldResult(
        deformed_vertices=V, G=G, lpd=lpd, quaternions=q.double().cpu().numpy(),
        scales=s.double().cpu().numpy(),
        history={k: np.asarray(v, dtype=np.float64) for k, v in history.items()},
        final=final, steps=step, converged=converged,
        wall_time_s=time.perf_counter() - t0, satisfaction=sat, pretrain_history=pretrain_hist,
        attrs={"config": config.model_dump(mode="json"), "seed": oc.seed,
               "solver_backend": problem.arap.backend, "device": str(problem.device),
               "po_length": problem.po_length, "schema_version": 1, "collision": collision,
               "head_collision": head,
               "rollbacks": rollbacks, "best_step": None if best_state is None else int(best_state["step"]) + 1},
    )
