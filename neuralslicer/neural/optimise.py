"""Resumable optimisation of the deformation fields q, s (SPEC steps 5-9).

``optimise_field`` takes the cage, the surface samples B (and stress samples T) and a
:class:`NeuralConfig`, reports progress and checkpoints through callbacks, and returns a
:class:`FieldResult`. It knows nothing of the artifact store or Prefect. The problem (losses,
constraints met) is :mod:`neuralslicer.neural.problem`, the DC3 corrections of L_CA are
:mod:`neuralslicer.neural.constraints`; this module is the loop and its checkpointable state.
"""
from __future__ import annotations

import contextlib
import copy
import io
import math
import pickle
import random
import time
import warnings
from dataclasses import dataclass, field
from typing import Any, Callable, Iterator, Mapping

import numpy as np
import torch
from scipy.spatial import cKDTree

from neuralslicer.errors import InputError
from neuralslicer.fea.samples import StressSamples
from neuralslicer.neural import losses as L
from neuralslicer.neural.config import NeuralConfig
from neuralslicer.neural.constraints import (corrected_evaluation, enforce_collision_constraint, enforce_tilt_bound,
                                             violating_pairs)
from neuralslicer.neural.device import device_record
from neuralslicer.model.solid import Solid
from neuralslicer.neural.head_collision import CollisionPool, collision_pool, refine_pool
from neuralslicer.neural.initial_guess import heat_geodesic, height_matched, platform_vertices, user_field_on_cage
from neuralslicer.neural.networks import DeformationFields
from neuralslicer.neural.problem import FieldProblem, tilt_angles_deg
from neuralslicer.samples import SurfaceSamples
from neuralslicer.tetmesh import TetLocator

TERMS = ("sf", "sr", "po", "hs", "hq", "gc", "ca")  # every run's terms; "tb" too with a tilt bound
WEIGHTS = "weights"  # the group of the network weights in FieldResult.to_arrays
CHECKPOINT_VERSION = 2  # 2: tensors and plain values only (weights_only loading)
ProgressFn = Callable[[int, dict], None]
Scheduler = torch.optim.lr_scheduler.ReduceLROnPlateau


@dataclass
class FieldResult:
    """Result of the neural optimisation.

    deformed_vertices : (n, 3) cage vertices after deformation; G : (n,) field at cage vertices
    (= deformed z); lpd : (m, 3) unit LPD per cage tet; quaternions : (m, 4); scales : (m, 3);
    history : per-step arrays ('total', each term after the DC3 correction, 'corrections' made
    before the step, 'lr'); final : the loss
    terms at the end; pretrain_history : MSE per pre-training step; weights : the final network
    weights, one array per state-dict key (what a warm start reads back, see :meth:`weights_of`).
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
    weights: dict[str, np.ndarray] = field(default_factory=dict)

    def to_arrays(self) -> tuple[dict[str, np.ndarray], dict]:
        """(arrays, json attrs) for a zarr group; history as 'history/<name>' arrays, the network weights as
        'weights/<state-dict key>' arrays (plain float arrays)."""
        arrays = {
            "deformed_vertices": self.deformed_vertices,
            "G": self.G,
            "lpd": self.lpd,
            "quaternions": self.quaternions,
            "scales": self.scales,
            "pretrain_history": self.pretrain_history,
        }
        arrays.update({f"history/{k}": v for k, v in self.history.items()})
        arrays.update({f"{WEIGHTS}/{k}": v for k, v in self.weights.items()})
        attrs = dict(self.attrs)
        attrs.update(
            final=self.final, steps=self.steps, converged=self.converged,
            wall_time_s=self.wall_time_s, satisfaction=self.satisfaction,
        )
        return arrays, attrs

    @staticmethod
    def weights_of(arrays: Mapping[str, np.ndarray]) -> dict[str, np.ndarray] | None:
        """The network weights among a stored field's arrays (the 'weights/<key>' written by to_arrays), for
        ``optimise_field(warm_start=...)``; None when the field has none (written by older code, or not neural)."""
        prefix = WEIGHTS + "/"
        out = {k[len(prefix):]: np.asarray(v) for k, v in arrays.items() if k.startswith(prefix)}
        return out or None


@dataclass
class Refinement:
    """What a refinement of L_GC's pool starts from (see ``optimise_for_solid``).

    hits : (k, 3) positions of the waypoints the exact check found colliding; witnesses : (k, 3) a point of
    the material each hit (``CollisionReport.locations``; NaN rows or an empty array: none), which the pairs
    of the refined pool follow; weights : the earlier result's network weights (``FieldResult.weights`` or
    ``FieldResult.weights_of(arrays)``) to start from, None to start afresh with the refined pool. A second
    round passes the hits and witnesses of both rounds: the refined pool is rebuilt from them.
    """

    hits: np.ndarray
    witnesses: np.ndarray | None = None
    weights: dict[str, np.ndarray] | None = None

    @classmethod
    def of_prints(cls, found: list[tuple[np.ndarray, np.ndarray]], weights: dict[str, np.ndarray] | None
                  ) -> "Refinement":
        """The refinement around the (hits, witnesses) of several prints (``part_collisions`` of each)."""
        return cls(np.concatenate([h for h, _ in found]), np.concatenate([w for _, w in found]), weights)


@dataclass
class LoopState:
    """Everything the loop carries from step to step, and everything a checkpoint holds.

    best_state is the best iterate (loss, weights, Adam state; a diverging step goes back to it);
    trend the running smoothed loss exp(EMA(log L)) per step, which the scheduler and the stall
    test see; best the running minimum of the raw total per step; final_corrections the DC3 steps
    on the final weights; grad_scale the running average of the (capped) gradient norms.
    """

    fields: DeformationFields
    optimizer: torch.optim.Adam
    scheduler: Scheduler
    history: dict[str, list[float]]
    step: int = 0
    converged: bool = False
    best_state: dict | None = None
    rollbacks: int = 0
    trend: list[float] = field(default_factory=list)
    best: list[float] = field(default_factory=list)
    final_corrections: int = 0
    pretrain_history: np.ndarray = field(default_factory=lambda: np.zeros(0))
    grad_scale: float | None = None
    #: correction steps of the final weights toward the tilt bound (loss.tilt_bound_deg)
    tilt_corrections: int = 0
    #: (step, overhang fraction of B, pool points whose head hits) every optim.progress_every steps near the
    #: progress stall test's window
    progress: list[tuple[int, float, int]] = field(default_factory=list)
    #: what ended the run: budget, constraints (met), loss (stall test or target), progress (stall test)
    stop: str = "budget"

    @classmethod
    def start(cls, problem: FieldProblem) -> LoopState:
        """Seeded fresh networks, Adam and scheduler, empty history."""
        seed_everything(problem.config.optim.seed)
        fields = problem.new_fields()
        return cls(fields, *new_optimizer(fields, problem.config),
                   {k: [] for k in ("total", *problem.terms(), "corrections", "lr")})

    def to_bytes(self, config: NeuralConfig) -> bytes:
        """The complete state (with the RNG states) as a checkpoint."""
        buf = io.BytesIO()
        torch.save({
            "version": CHECKPOINT_VERSION, "fields": self.fields.state_dict(),
            "optimizer": self.optimizer.state_dict(), "scheduler": self.scheduler.state_dict(),
            "step": self.step, "converged": self.converged, "history": self.history,
            "final_corrections": self.final_corrections, "tilt_corrections": self.tilt_corrections,
            "best": self.best_state, "rollbacks": self.rollbacks,
            "trend": self.trend, "pretrain_history": torch.from_numpy(np.asarray(self.pretrain_history, np.float64)),
            "rng": _rng_state(),
            "grad_scale": self.grad_scale,
            "progress": [list(r) for r in self.progress], "stop": self.stop,
            "seed": config.optim.seed, "config": config.model_dump(mode="json"),
        }, buf)
        return buf.getvalue()

    def restore(self, blob: bytes, device: torch.device) -> bool:
        """Continue from a checkpoint written by to_bytes (also the RNG states); False (and nothing
        restored) for a checkpoint of an older format. Only tensors and plain values are read
        (``weights_only``): a planted checkpoint cannot run code."""
        try:
            state = torch.load(io.BytesIO(blob), map_location=device, weights_only=True)
        except pickle.UnpicklingError:
            return False
        if state.get("version") != CHECKPOINT_VERSION:
            return False
        self.fields.load_state_dict(state["fields"])
        self.optimizer.load_state_dict(state["optimizer"])
        self.scheduler.load_state_dict(state["scheduler"])
        self.step, self.converged = int(state["step"]), bool(state["converged"])
        self.final_corrections = int(state.get("final_corrections", 0))
        self.tilt_corrections = int(state.get("tilt_corrections", 0))
        self.best_state, self.rollbacks = state.get("best"), int(state.get("rollbacks", 0))
        self.trend = list(state.get("trend", []))
        self.history = {k: list(v) for k, v in state["history"].items()}
        self.pretrain_history = state["pretrain_history"].cpu().numpy()
        self.grad_scale = state.get("grad_scale")
        self.progress = [(int(r[0]), float(r[1]), int(r[2])) for r in state.get("progress", [])]
        self.stop = str(state.get("stop", "budget"))
        _set_rng_state(state["rng"])
        return True

    def prepare(self, weight: float) -> None:
        """Running minimum and (for old checkpoints) the smoothed trend of the history so far."""
        self.best = []
        for v in self.history["total"]:
            self.best.append(min(self.best[-1], v) if self.best else v)
        if not self.trend and self.history["total"]:
            self.trend = _trend_of(self.history["total"], weight)

    @property
    def lr(self) -> float:
        """The current learning rate."""
        return self.optimizer.param_groups[0]["lr"]


def new_optimizer(fields: DeformationFields, config: NeuralConfig) -> tuple[torch.optim.Adam, Scheduler]:
    """Fresh Adam (no moments) and plateau scheduler."""
    oc = config.optim
    opt = torch.optim.Adam(fields.parameters(), lr=oc.lr, betas=tuple(oc.betas))
    return opt, Scheduler(opt, mode="min", factor=oc.plateau_factor, patience=oc.plateau_patience, min_lr=oc.min_lr)


def load_weights(fields: DeformationFields, weights: Mapping[str, np.ndarray]) -> None:
    """Set the networks' weights (and buffers) from plain arrays keyed by state-dict key (a warm start)."""
    own = fields.state_dict()
    if set(weights) != set(own) or any(tuple(np.shape(weights[k])) != tuple(own[k].shape) for k in own):
        raise InputError("warm_start", "the weights do not fit the networks (another network preset or size, or "
                         "per-element values for another cage): start without them")
    fields.load_state_dict({k: torch.as_tensor(np.asarray(weights[k])) for k in own})


def loss_of(problem: FieldProblem, fields: DeformationFields, weights: dict) -> float:
    """Total loss of other weights, evaluated on a copy of the networks (the fields and the graph of their last
    evaluation are left as they were)."""
    other = copy.deepcopy(fields)
    other.load_state_dict(weights)
    with torch.no_grad():
        return float(problem.evaluate(other, remember=False)[0])


def stale_collisions(problem: FieldProblem, fields: DeformationFields) -> bool:
    """Search L_GC's pairs afresh for the current weights; True when the head still collides."""
    problem.refresh_collisions(fields)
    with torch.no_grad():
        return float(problem.evaluate(fields)[1]["gc"]) > 0


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
    """RNG states of torch, numpy and python, as tensors and plain values (loadable with weights_only)."""
    kind, keys, pos, has_gauss, gauss = np.random.get_state()
    return {"torch": torch.get_rng_state(), "python": random.getstate(),
            "numpy": {"kind": kind, "keys": torch.from_numpy(keys.astype(np.int64)), "pos": int(pos),
                      "has_gauss": int(has_gauss), "gauss": float(gauss)}}


def _set_rng_state(state: dict) -> None:
    """Restore the RNG states saved by _rng_state."""
    torch.set_rng_state(state["torch"])
    n = state["numpy"]
    np.random.set_state((n["kind"], n["keys"].numpy().astype(np.uint32), n["pos"], n["has_gauss"], n["gauss"]))
    random.setstate(state["python"])


def seed_everything(seed: int) -> None:
    """Seed torch, numpy and python RNGs."""
    torch.manual_seed(seed)
    np.random.seed(seed % (2**32))
    random.seed(seed)


def optimise_field(
    cage_vertices: np.ndarray,
    cage_tets: np.ndarray,
    samples: SurfaceSamples,
    stress_samples: StressSamples | None = None,
    config: NeuralConfig | None = None,
    platform_z: float | None = None,
    user_field: np.ndarray | None = None,
    user_field_points: np.ndarray | None = None,
    progress: ProgressFn | None = None,
    save_checkpoint: Callable[[bytes, int], None] | None = None,
    load_checkpoint: Callable[[], bytes | None] | None = None,
    collision_pool: CollisionPool | None = None,
    warm_start: Mapping[str, np.ndarray] | None = None,
    solid_tets: np.ndarray | None = None,
) -> FieldResult:
    """Optimise the SIREN fields q, s so that G = deformed z meets the SF/SR/PO/GC objectives.

    Parameters
    ----------
    cage_vertices : (n, 3) float64, cage_tets : (m, 4) int64 -- the cage C (build frame).
    samples : the surface samples B (points on the platform are kept as kNN positions and left
        out of L_SF and L_PO); stress_samples : the stress samples T (optional).
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
    warm_start : network weights to start from (``FieldResult.weights``, plain arrays per state-dict
        key) instead of the identity and the initial guess, which is then not pre-trained. The constraint
        stop of a warm-started run accepts the overhang it starts from plus ``optim.refine.overhang_slack``.
        A checkpoint, when there is one, still wins.
    solid_tets : (m,) bool, the cage tets that hold solid: with the tets holding B or pool points they make the
        floor of L_GC's platform term (the tets within the head's reach of the platform).
    """
    config = config or NeuralConfig()
    t0 = time.perf_counter()
    with deterministic_algorithms():
        problem = FieldProblem(cage_vertices, cage_tets, samples, stress_samples, config, platform_z, collision_pool,
                               solid_tets)
        st = LoopState.start(problem)
        if warm_start is not None:
            load_weights(st.fields, warm_start)
            problem.overhang_floor = problem.overhang(problem.field(st.fields)[1]) + config.optim.refine.overhang_slack
        blob = load_checkpoint() if load_checkpoint is not None else None
        if blob and not st.restore(blob, problem.device):
            warnings.warn("a checkpoint of an older format was ignored: the optimisation starts over", RuntimeWarning,
                          stacklevel=2)
            blob = None
        if not blob and warm_start is None:
            target = initial_target(problem, user_field, user_field_points)
            if target is not None:
                st.pretrain_history = pretrain(problem, st.fields, target, progress)
                st.optimizer, st.scheduler = new_optimizer(st.fields, config)  # no moments carried over from the fit
        save = (lambda: save_checkpoint(st.to_bytes(config), st.step)) if save_checkpoint is not None else (lambda: None)
        run_loop(problem, st, save, progress, t0)
        if config.optim.return_best and st.best_state is not None:
            st.fields.load_state_dict(st.best_state["fields"])
        final_corrections(problem, st)
        save()
        return field_result(problem, st, t0)


def final_corrections(problem: FieldProblem, st: LoopState, rounds: int = 3) -> None:
    """Correct the final weights: the hard constraint L_CA = 0 holds for the field that is returned, not only
    before each step; with a tilt bound, no solid tet's LPD beyond it either (the two in turn, up to ``rounds``
    times, until both hold)."""
    cl = problem.config.loss
    if problem.tilt_bound is None:
        if cl.collision:
            st.final_corrections += enforce_collision_constraint(problem, st.fields)
        return
    for _ in range(rounds):
        st.tilt_corrections += enforce_tilt_bound(problem, st.fields)
        if cl.collision:
            st.final_corrections += enforce_collision_constraint(problem, st.fields)
        if not (problem.tilt_angles64(st.fields) > cl.tilt_bound_deg).any():
            break


def optimise_for_solid(solid: Solid, cage_vertices: np.ndarray, cage_tets: np.ndarray, samples: SurfaceSamples,
                       stress_samples: StressSamples | None, objectives: list[str], config: NeuralConfig,
                       refine: Refinement | None = None, warm_start: Mapping[str, np.ndarray] | None = None,
                       **options: Any) -> FieldResult:
    """The field step: ``optimise_field`` for the objectives asked for, with L_GC's pool of points drawn
    from the solid when gc is one of them; ``options`` are optimise_field's (initial guess, callbacks).

    refine : collisions the exact check found in an earlier result's print: the pool is refined around them
    (:func:`~neuralslicer.neural.head_collision.refine_pool` with ``optim.refine``'s spacing, radius and cap)
    and, with the earlier weights, the run starts from them for at most ``optim.refine.steps`` steps (at
    ``optim.refine.lr``); without weights it starts afresh on the refined pool. Needs the gc objective.
    ``result.attrs["refinement"]`` records what was added. warm_start : weights to start from without a
    refinement (a strength round: new stress samples, at most min(optim.refine.steps, optim.max_steps) steps at
    optim.refine.lr).
    """
    cfg = config.for_objectives(objectives)
    pool = None
    if cfg.loss.w_gc > 0:
        pool = collision_pool(solid.H, solid.bounds, solid.volume(), samples.points, cfg.loss.gc_points,
                              cfg.loss.gc_spacing, seed=cfg.optim.seed)
    record = None
    if refine is not None:
        if pool is None:
            raise InputError("objectives", "refining L_GC's pool needs the gc objective")
        rc = cfg.optim.refine
        base = len(pool.points)
        pool = refine_pool(pool, refine.hits, refine.witnesses, solid.H, spacing=rc.spacing_factor * pool.spacing,
                           radius=rc.radius_factor * pool.spacing, max_points=rc.max_points, seed=cfg.optim.seed)
        warm_start = refine.weights
        witnesses = np.zeros((0, 3)) if refine.witnesses is None else np.asarray(refine.witnesses, float).reshape(-1, 3)
        record = {"hits": int(len(np.asarray(refine.hits).reshape(-1, 3))),
                  "witnesses": int(np.isfinite(witnesses).all(axis=1).sum()),
                  "base_points": base, "added_points": pool.n_refined, "links": int(len(pool.links)),
                  "fine_spacing": pool.fine_spacing, "radius": pool.link_radius,
                  "warm_start": refine.weights is not None}
    if warm_start is not None:
        # a refinement keeps its own budget; a strength round at most the step budget asked for
        rc = cfg.optim.refine
        steps = rc.steps if refine is not None else min(rc.steps, cfg.optim.max_steps)
        cfg = cfg.model_copy(update={"optim": cfg.optim.model_copy(update={"max_steps": steps,
                                                                              "lr": rc.lr or cfg.optim.lr})})
        options["warm_start"] = warm_start
    if pool is not None or cfg.loss.tilt_bound_deg is not None:
        options["solid_tets"] = solid_tets(solid, cage_vertices, cage_tets)
    result = optimise_field(cage_vertices, cage_tets, samples, stress_samples, config=cfg, platform_z=solid.platform_z,
                            collision_pool=pool, **options)
    result.attrs.update(objectives=list(objectives), kind="neural")
    if cfg.loss.tilt_bound_deg is not None:
        held = heldout_tilt(solid, cage_vertices, cage_tets, result.lpd, cfg.loss.tilt_bound_deg, cfg.optim.seed)
        result.attrs["tilt_bound"].update(held)
        result.final["tilt_bound_violation_frac"] = held["heldout_violation_fraction"]
    if record is not None:
        result.attrs["refinement"] = record
    return result


def heldout_tilt(solid: Solid, cage_vertices: np.ndarray, cage_tets: np.ndarray, lpd: np.ndarray, bound_deg: float,
                 seed: int = 0, n_points: int = 20_000) -> dict[str, float]:
    """The tilt of a field's LPD (m,3) per cage tet at held-out points of the solid (a jittered grid of about
    ``n_points`` inside ``H < 0``, drawn apart from L_GC's pool): the fraction beyond ``bound_deg`` from +z, the
    largest angle and its 99th percentile (deg), as ``heldout_*``."""
    points = collision_pool(solid.H, solid.bounds, solid.volume(), np.zeros((0, 3)), n_points,
                            seed=seed + 1_000_003).points
    V, T = np.asarray(cage_vertices, np.float64), np.asarray(cage_tets, np.int64)
    tet, _ = TetLocator(V, T).locate(points)
    outside = tet < 0
    if outside.any():  # the cage encloses the solid; a point on its boundary takes the nearest tet
        tet[outside] = cKDTree(V[T].mean(axis=1)).query(points[outside])[1]
    angles = tilt_angles_deg(np.asarray(lpd, np.float64)[tet])
    if not len(angles):
        return {"heldout_points": 0, "heldout_violation_fraction": 0.0, "heldout_max_deg": 0.0, "heldout_p99_deg": 0.0}
    return {"heldout_points": int(len(angles)), "heldout_violation_fraction": float(np.mean(angles > bound_deg)),
            "heldout_max_deg": float(angles.max()), "heldout_p99_deg": float(np.percentile(angles, 99))}


def solid_tets(solid: Solid, vertices: np.ndarray, tets: np.ndarray) -> np.ndarray:
    """Cage tets (m,) that hold solid: H <= 0 at a vertex or the centroid."""
    vertices, tets = np.asarray(vertices, np.float64), np.asarray(tets, np.int64)
    inside_v = np.asarray(solid.H(vertices)) <= 0
    inside_c = np.asarray(solid.H(vertices[tets].mean(axis=1))) <= 0
    return inside_v[tets].any(axis=1) | inside_c


def run_loop(problem: FieldProblem, st: LoopState, save: Callable[[], None], progress: ProgressFn | None,
             t0: float) -> None:
    """Step until the budget, convergence or the constraints are met; checkpoint every checkpoint_every steps."""
    oc = problem.config.optim
    st.prepare(oc.trend_smoothing)
    first = True  # a resumed run searches L_GC's pairs before its first step (checkpoints sit on check steps)
    while st.step < oc.max_steps and not st.converged:
        n_viol = iterate(problem, st, first)
        first = False
        if n_viol is None:
            break
        if progress is not None:
            info = {k: st.history[k][-1] for k in st.history}
            info.update(elapsed_s=time.perf_counter() - t0, phase="optimise", ca_violating_pairs=n_viol,
                        best=st.best[-1], rollbacks=st.rollbacks, **problem.last_check)
            progress(st.step, info)
        if st.step % oc.checkpoint_every == 0 and st.step < oc.max_steps and not st.converged:
            save()


def iterate(problem: FieldProblem, st: LoopState, first: bool) -> int | None:
    """One step: refresh L_GC's pairs on check steps, DC3-corrected evaluation, then either stop (the
    constraints are met: None), roll back to the best iterate (divergence) or take an Adam step;
    record it and test convergence. Returns the pairs still violating L_CA."""
    oc = problem.config.optim
    check = st.step % oc.check_every == 0
    refresh = problem.head is not None and (check or first)
    if refresh:  # on the first evaluation's field, before its terms
        problem.schedule_refresh()
    total, terms, n_corr, n_viol = corrected_evaluation(problem, st.fields)
    if refresh and st.best_state is not None:  # the best loss again, on the new pairs
        st.best_state["loss"] = loss_of(problem, st.fields, st.best_state["fields"])
    if check and st.step > 0 and n_viol == 0 and problem.constraints_met(st.fields, st.step):
        st.converged, st.best_state, st.stop = True, None, "constraints"  # this (corrected) iterate is the result
        return None
    tv = float(total.detach())
    take_step(st, oc, total, tv)
    st.step += 1
    st.history["total"].append(tv)
    for k in problem.terms():
        st.history[k].append(float(terms[k].detach()))
    st.history["corrections"].append(float(n_corr))
    st.history["lr"].append(st.lr)
    st.best.append(min(st.best[-1], tv) if st.best else tv)
    if converged(problem, st):
        st.converged, st.stop = True, "loss"
    elif stalled_progress(problem, st):
        st.converged, st.stop = True, "progress"
    return n_viol


def stalled_progress(problem: FieldProblem, st: LoopState) -> bool:
    """The progress stall test (``optim.progress_window``): from ``late_after`` on, True once neither the
    overhang of B nor the pool's head hits have improved over the window (measured every progress_every
    steps, from a window before late_after)."""
    oc = problem.config.optim
    w = oc.progress_window
    if not problem.watches_progress() or st.step % oc.progress_every or st.step < oc.late_after - w:
        return False
    over, hits = problem.progress(st.fields)
    st.progress.append((st.step, over, hits))
    if st.step < oc.late_after:
        return False
    before = [r for r in st.progress if r[0] <= st.step - w]
    within = [r for r in st.progress if r[0] > st.step - w]
    if not before:
        return False
    best_over, best_hits = min(r[1] for r in before), min(r[2] for r in before)
    gained = min(r[1] for r in within) < (1.0 - oc.progress_rtol) * best_over
    cleared = min(r[2] for r in within) < best_hits
    return not gained and not cleared


def take_step(st: LoopState, oc, total: torch.Tensor, tv: float) -> bool:
    """Adam step (keeping the best iterate), or roll back when the loss diverged; then the scheduler
    on the smoothed trend (restarting from the best iterate when it lowers the rate). True on roll-back."""
    lr = st.lr
    diverged = (oc.divergence_factor > 0 and st.best_state is not None
                and not tv <= oc.divergence_factor * st.best_state["loss"])
    if diverged:
        # undo: back to the best iterate with its Adam moments, at a lower learning rate
        _restore(st.fields, st.optimizer, st.best_state, max(lr * oc.plateau_factor, oc.min_lr))
        st.rollbacks += 1
    else:
        if st.best_state is None or tv < st.best_state["loss"]:
            st.best_state = {"loss": tv, "step": st.step, "fields": _clone_state(st.fields.state_dict()),
                             "optimizer": _clone_state(st.optimizer.state_dict())}
        st.optimizer.zero_grad()
        total.backward()
        cap_gradient(st, oc.grad_clip)
        st.optimizer.step()
    st.trend.append(_smooth(st.trend[-1] if st.trend else None, tv, oc.trend_smoothing, diverged))
    if not diverged:
        st.scheduler.step(st.trend[-1])
        if oc.restart_from_best and st.lr < lr and st.best_state is not None:
            _restore(st.fields, st.optimizer, st.best_state, st.lr)
    return diverged


def cap_gradient(st: LoopState, clip: float, weight: float = 0.1) -> None:
    """Scale the gradient down to ``clip`` times the running average of the recent norms when it is
    larger (a spike), then update that average with the capped norm (EMA with ``weight``)."""
    if clip <= 0:
        return
    grads = [p.grad for p in st.fields.parameters() if p.grad is not None]
    norm = float(torch.linalg.vector_norm(torch.stack([torch.linalg.vector_norm(g) for g in grads])))
    if not math.isfinite(norm):
        return
    if st.grad_scale is not None and norm > clip * st.grad_scale:
        for g in grads:
            g.mul_(clip * st.grad_scale / norm)
        norm = clip * st.grad_scale
    st.grad_scale = norm if st.grad_scale is None else st.grad_scale + weight * (norm - st.grad_scale)


def converged(problem: FieldProblem, st: LoopState) -> bool:
    """The stall test on the smoothed trend over convergence_window steps, or the loss target (unless
    L_GC's pairs were outdated: then the best loss is forgotten and the run goes on)."""
    oc = problem.config.optim
    done = False
    w = oc.convergence_window
    if len(st.trend) > w:
        old, new = min(st.trend[:-w]), min(st.trend)
        done = (old - new) <= oc.convergence_rtol * abs(old) + oc.convergence_atol
        if st.lr <= oc.min_lr * (1 + 1e-9):
            done = done or (old - new) <= 1e-9 * abs(old)
    if oc.target_loss > 0 and st.best[-1] <= oc.target_loss:
        done = True
        if problem.head is not None and stale_collisions(problem, st.fields):
            # the best loss was measured on an outdated set of pairs: forget it and go on
            done, st.best_state, st.best[-1] = False, None, math.inf
    return done


@contextlib.contextmanager
def deterministic_algorithms() -> Iterator[None]:
    """Use torch's deterministic kernels (reproducible runs and resumes), restoring the settings. The memory of a
    new tensor is not filled with NaN first (torch's default with deterministic kernels, a debugging aid: every
    operation here writes all of its output, so the values are the same, without a pass over each new array)."""
    enabled = torch.are_deterministic_algorithms_enabled()
    warn_only = torch.is_deterministic_algorithms_warn_only_enabled()
    fill = torch.utils.deterministic.fill_uninitialized_memory
    torch.use_deterministic_algorithms(True, warn_only=True)
    torch.utils.deterministic.fill_uninitialized_memory = False
    try:
        yield
    finally:
        torch.use_deterministic_algorithms(enabled, warn_only=warn_only)
        torch.utils.deterministic.fill_uninitialized_memory = fill




def tilt_record(problem: FieldProblem, st: LoopState, grad: np.ndarray) -> dict:
    """The tilt bound as the result holds it (empty without one): the solid cage tets whose LPD (grad G per tet
    (m,3), float64) is beyond it, their volume fraction, the largest angle from +z and its 99th percentile (deg,
    over the tets), the final corrections made."""
    if problem.tilt_bound is None:
        return {}
    bound = problem.config.loss.tilt_bound_deg
    idx = problem.tilt_tets
    angles = tilt_angles_deg(grad[idx])
    volumes = problem.geometry.volumes[idx]
    over = angles > bound
    return {"bound_deg": bound, "tets": int(len(idx)), "violating_tets": int(over.sum()),
            "violating_volume_fraction": float(volumes[over].sum() / max(volumes.sum(), 1e-300)),
            "max_deg": float(angles.max()) if len(angles) else 0.0,
            "p99_deg": float(np.percentile(angles, 99)) if len(angles) else 0.0,
            "corrections": st.tilt_corrections}


def field_result(problem: FieldProblem, st: LoopState, t0: float) -> FieldResult:
    """The result: the float64 deformation of the final weights, the stored field's L_CA and L_GC,
    satisfaction against planar layers, the history and the run's record."""
    problem.refresh_collisions(st.fields)  # L_GC of the result on a fresh set of pairs
    with torch.no_grad():
        q, s = st.fields(problem.centroids_t)
        V = problem.arap.deform(q.double(), s.double()).cpu().numpy()
        G = V[:, 2].copy()
        total, terms = problem.evaluate(st.fields)
    excess64 = problem.excess_of(G)
    n_viol = violating_pairs(excess64, problem.config.loss.correction_tol)
    collision = {
        "enforced": bool(problem.config.loss.collision), "phi_deg": problem.config.apex_deg(),
        "ca": float(np.maximum(excess64, 0).mean()) if len(excess64) else 0.0,
        "violating_pairs": n_viol, "n_pairs": int(len(excess64)),
        "max_excess_rad": float(excess64.max()) if len(excess64) else 0.0,
        "tol_rad": problem.config.loss.correction_tol, "margin_rad": problem.config.loss.correction_margin,
        "final_corrections": st.final_corrections,
    }
    if n_viol and problem.config.loss.collision:
        warnings.warn(f"L_CA = 0 not reached: {n_viol} adjacent pairs still violate "
                      f"(max excess {collision['max_excess_rad']:.2e} rad)", RuntimeWarning, stacklevel=3)
    gradG = np.einsum("ei,eij->ej", G[problem.geometry.tets], problem.geometry.bary_grads)
    lpd = gradG / np.maximum(np.linalg.norm(gradG, axis=1, keepdims=True), 1e-300)
    sat = {k: v for k, v in problem.satisfaction(lpd).items()}
    sat.update({f"planar_{k}": v for k, v in problem.planar_lpd_satisfaction().items()})
    final = {k: float(v) for k, v in terms.items()}
    final["total"] = float(total)
    if problem.config.loss.collision:  # the constraint as stored: the float64 field, pairs counted
        final["ca"] = collision["ca"]
        final["ca_violating_pairs"] = float(n_viol)
    tilt = tilt_record(problem, st, gradG)
    if tilt:
        final["tb_violating_tets"] = float(tilt["violating_tets"])
    head = problem.head_collisions(G)
    if head:
        final["gc_colliding_pairs"] = float(head["colliding_pairs"])
        head.update(weight=problem.config.loss.w_gc, spacing=problem.head.length, clearance=problem.head.clearance,
                    links=problem.head.n_links, links_thinned=problem.head.links_thinned,
                    link_pairs=problem.head.n_link_pairs)
    return FieldResult(
        deformed_vertices=V, G=G, lpd=lpd, quaternions=q.double().cpu().numpy(),
        scales=s.double().cpu().numpy(),
        history={k: np.asarray(v, dtype=np.float64) for k, v in st.history.items()},
        final=final, steps=st.step, converged=st.converged,
        wall_time_s=time.perf_counter() - t0, satisfaction=sat, pretrain_history=st.pretrain_history,
        weights={k: v.detach().cpu().numpy().copy() for k, v in st.fields.state_dict().items()},
        attrs={"config": problem.config.model_dump(mode="json"), "seed": problem.config.optim.seed,
               "solver_backend": problem.arap.backend, **device_record(problem.device),
               "po_length": problem.po_length, "schema_version": 1, "collision": collision,
               "head_collision": head, **({"tilt_bound": tilt} if tilt else {}),
               "rollbacks": st.rollbacks, "stalled_progress": st.stop == "progress", "stop": st.stop,
               "progress": [{"step": r[0], "overhang": r[1], "head_hits": r[2]} for r in st.progress],
               "best_step": None if st.best_state is None else int(st.best_state["step"]) + 1},
    )
