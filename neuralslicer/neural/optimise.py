"""Resumable optimisation of the deformation fields q, s (SPEC steps 5-9).

``optimise_field`` takes plain arrays (cage, surface samples B, stress samples T) and a
:class:`NeuralConfig`, reports progress and checkpoints through callbacks, and returns a
:class:`FieldResult`. It knows nothing of the artifact store or Prefect.
"""
from __future__ import annotations

import contextlib
import io
import math
import random
import time
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
from neuralslicer.neural.initial_guess import (
    heat_geodesic,
    height_matched,
    platform_vertices,
    user_field_on_cage,
)
from neuralslicer.neural.networks import DeformationFields

TERMS = ("sf", "sr", "po", "hs", "hq", "ca")
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
    ) -> None:
        self.config = config
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
        terms["ca"] = (L.collision_loss(grad, self.pairs_t, self.pair_normals_t, math.radians(cl.phi_deg))
                       if cl.collision else zero)
        total = (cl.w_sf * terms["sf"] + cl.w_sr * terms["sr"] + cl.w_po * terms["po"]
                 + cl.w_hs * terms["hs"] + cl.w_hq * terms["hq"])
        return total, terms

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


def correction_step(fields: DeformationFields, ca: torch.Tensor, config) -> bool:
    """One DC3-style correction of the weights towards L_CA = 0 (in place); False if no step.

    The step is the first-order (Polyak / Gauss-Newton) step for the scalar constraint,
    ``theta -= lr * L_CA / |grad L_CA|^2 * grad L_CA``, its length capped at
    ``max_step * |theta|`` so that a nearly flat constraint cannot throw the weights away.
    """
    params = [p for p in fields.parameters() if p.requires_grad]
    grads = torch.autograd.grad(ca, params, allow_unused=True)
    norm2 = sum(float((g * g).sum()) for g in grads if g is not None)
    if norm2 <= 0:
        return False
    theta = math.sqrt(sum(float((p.detach() * p.detach()).sum()) for p in params))
    eta = config.correction_lr * float(ca.detach()) / norm2
    eta = min(eta, config.correction_max_step * theta / math.sqrt(norm2))
    with torch.no_grad():
        for p, g in zip(params, grads):
            if g is not None:
                p.sub_(eta * g)
    return True


def corrected_evaluation(
    problem: FieldProblem, fields: DeformationFields
) -> tuple[torch.Tensor, dict[str, torch.Tensor], int]:
    """Evaluate the losses after up to ``correction_steps`` DC3 corrections (while L_CA > tol).

    Returns (total, terms, corrections made); the terms are those of the corrected weights, so
    a feasible iterate costs one evaluation and each correction one backward + one evaluation.
    """
    cl = problem.config.loss
    total, terms = problem.evaluate(fields)
    done = 0
    while (cl.collision and done < cl.correction_steps
           and float(terms["ca"].detach()) > cl.correction_tol):
        if not correction_step(fields, terms["ca"], cl):
            break
        done += 1
        total, terms = problem.evaluate(fields)
    return total, terms, done


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
    """Fit G to target (n,) by Adam on the MSE (normalised by the z range^2); returns MSE history.

    ``progress(0, {"phase": "pretrain", "pretrain_step", "pretrain_steps", "mse"})`` per step.
    """
    init = problem.config.init
    tgt = torch.as_tensor(target, dtype=problem.dtype, device=problem.device)
    scale = float(np.ptp(problem.geometry.vertices[:, 2])) ** 2
    opt = torch.optim.Adam(fields.parameters(), lr=init.pretrain_lr)
    hist = []
    for _ in range(init.pretrain_steps):
        G, _, _ = problem.height(fields)
        mse = ((G - tgt) ** 2).mean() / scale
        opt.zero_grad()
        mse.backward()
        opt.step()
        hist.append(float(mse.detach()))
        if progress is not None:
            progress(0, {"phase": "pretrain", "pretrain_step": len(hist),
                         "pretrain_steps": init.pretrain_steps, "mse": hist[-1]})
    return np.asarray(hist)


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
    """
    config = config or NeuralConfig()
    with deterministic_algorithms():
        return _optimise_field(
            cage_vertices, cage_tets, surface_points, surface_normals, surface_areas, surface_knn,
            surface_on_platform, stress_points, stress_volumes, stress_tau, config, platform_z,
            user_field, user_field_points, progress, save_checkpoint, load_checkpoint,
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
) -> FieldResult:
    """optimise_field's body, run under deterministic torch algorithms."""
    t0 = time.perf_counter()
    problem = FieldProblem(
        cage_vertices, cage_tets, surface_points, surface_normals, surface_areas, surface_knn,
        surface_on_platform, stress_points, stress_volumes, stress_tau, config, platform_z,
    )
    oc = config.optim
    seed_everything(oc.seed)
    fields = problem.new_fields()
    optimizer = torch.optim.Adam(fields.parameters(), lr=oc.lr)
    scheduler = torch.optim.lr_scheduler.ReduceLROnPlateau(
        optimizer, mode="min", factor=oc.plateau_factor, patience=oc.plateau_patience, min_lr=oc.min_lr
    )
    history: dict[str, list[float]] = {k: [] for k in ("total", *TERMS, "corrections", "lr")}
    pretrain_hist = np.zeros(0)
    step = 0
    converged = False
    blob = load_checkpoint() if load_checkpoint is not None else None
    if blob:
        state = torch.load(io.BytesIO(blob), map_location=problem.device, weights_only=False)
        fields.load_state_dict(state["fields"])
        optimizer.load_state_dict(state["optimizer"])
        scheduler.load_state_dict(state["scheduler"])
        step, converged = int(state["step"]), bool(state["converged"])
        history = {k: list(v) for k, v in state["history"].items()}
        pretrain_hist = np.asarray(state["pretrain_history"])
        _set_rng_state(state["rng"])
    else:
        target = initial_target(problem, user_field, user_field_points)
        if target is not None:
            pretrain_hist = pretrain(problem, fields, target, progress)
            optimizer = torch.optim.Adam(fields.parameters(), lr=oc.lr)
            scheduler = torch.optim.lr_scheduler.ReduceLROnPlateau(
                optimizer, mode="min", factor=oc.plateau_factor, patience=oc.plateau_patience,
                min_lr=oc.min_lr,
            )

    def checkpoint() -> None:
        """Serialise the complete state and hand it to save_checkpoint."""
        if save_checkpoint is None:
            return
        buf = io.BytesIO()
        torch.save({
            "version": CHECKPOINT_VERSION, "fields": fields.state_dict(),
            "optimizer": optimizer.state_dict(), "scheduler": scheduler.state_dict(),
            "step": step, "converged": converged, "history": history,
            "pretrain_history": pretrain_hist, "rng": _rng_state(), "seed": oc.seed,
            "config": config.model_dump(mode="json"),
        }, buf)
        save_checkpoint(buf.getvalue(), step)

    best: list[float] = []
    for v in history["total"]:
        best.append(min(best[-1], v) if best else v)
    while step < oc.max_steps and not converged:
        total, terms, n_corr = corrected_evaluation(problem, fields)
        optimizer.zero_grad()
        total.backward()
        optimizer.step()
        tv = float(total.detach())
        scheduler.step(tv)
        step += 1
        history["total"].append(tv)
        for k in TERMS:
            history[k].append(float(terms[k].detach()))
        history["corrections"].append(float(n_corr))
        history["lr"].append(optimizer.param_groups[0]["lr"])
        best.append(min(best[-1], tv) if best else tv)
        w = oc.convergence_window
        if len(best) > w:
            old = best[-1 - w]
            converged = (old - best[-1]) <= oc.convergence_rtol * abs(old) + oc.convergence_atol
        if optimizer.param_groups[0]["lr"] <= oc.min_lr * (1 + 1e-9) and len(best) > w:
            converged = converged or (best[-1 - w] - best[-1]) <= 1e-9 * abs(best[-1 - w])
        if progress is not None:
            info = {k: history[k][-1] for k in history}
            info["elapsed_s"] = time.perf_counter() - t0
            info["phase"] = "optimise"
            progress(step, info)
        if step % oc.checkpoint_every == 0 and step < oc.max_steps and not converged:
            checkpoint()
    checkpoint()

    with torch.no_grad():
        q, s = fields(problem.centroids_t)
        V = problem.arap.deform(q.double(), s.double()).cpu().numpy()
        G = V[:, 2].copy()
        total, terms = problem.evaluate(fields)
    gradG = np.einsum("ei,eij->ej", G[problem.geometry.tets], problem.geometry.bary_grads)
    lpd = gradG / np.maximum(np.linalg.norm(gradG, axis=1, keepdims=True), 1e-300)
    sat = {k: v for k, v in problem.satisfaction(lpd).items()}
    sat.update({f"planar_{k}": v for k, v in problem.planar_lpd_satisfaction().items()})
    final = {k: float(v) for k, v in terms.items()}
    final["total"] = float(total)
    return FieldResult(
        deformed_vertices=V, G=G, lpd=lpd, quaternions=q.double().cpu().numpy(),
        scales=s.double().cpu().numpy(),
        history={k: np.asarray(v, dtype=np.float64) for k, v in history.items()},
        final=final, steps=step, converged=converged,
        wall_time_s=time.perf_counter() - t0, satisfaction=sat, pretrain_history=pretrain_hist,
        attrs={"config": config.model_dump(mode="json"), "seed": oc.seed,
               "solver_backend": problem.arap.backend, "device": str(problem.device),
               "po_length": problem.po_length, "schema_version": 1},
    )
