"""S3-Slicer baseline (Zhang et al. 2022) as the Neural Slicer paper describes it (its Sec. 1, Fig. 2).

S3-Slicer optimises a rotation per element so that the manufacturing objectives hold in the
*deformed* space, where the layers are the planes ``z = const`` and the printing direction is +z:

- ``L_SF = sum_B |A_p| sigma(k_SF (-(R_e n_p).z - sin a)) / sum_B |A_p|``: the rotated outward
  normal ``R_e n_p`` of each surface sample judged against the vertical;
- ``L_SR = sum_T |V_e| sigma(k_SR (|(R_e tau).z| - sin b)) / sum_T |V_e|``: the rotated max-stress
  direction judged against the horizontal plane;
- ``L_H = L^2 sum_(i,j) w_ij |q_i - q_j|^2 / |c_i - c_j|^2 / sum w_ij``: the harmonic (Dirichlet)
  energy of the quaternion field over adjacent tets, ``w_ij = (|V_i| + |V_j|) / 2``, made unit-free
  and independent of the cage's resolution by the centroid distances and ``L = (cage volume)^(1/3)``.

Since ``(R_e v).z = v.(R_e^T z)``, L_SF and L_SR are the Neural Slicer's losses
(:mod:`neuralslicer.neural.losses`) with the LPD replaced by the direction ``R_e^T z`` that the
rotation *intends*. Only after the optimisation is the field realised: the cage follows the rotations
by the scale-controlled ARAP deformation with ``s = 1`` (the neural method's factored system) and
``G`` is the height of the deformed cage at the cage vertices. The objectives never see ``grad G``, so
where the rotations are not compatible the ARAP compromise distorts the layers and the realised LPDs
can overhang in the model space although the rotated normals do not -- the difference the paper's
comparison measures. Collision terms and the point-overhang loss are not part of S3 and are ignored.
"""
from __future__ import annotations

import math
import time
from dataclasses import dataclass, field
from typing import Callable, Iterable

import numpy as np
import torch

from neuralslicer.fea.samples import StressSamples
from neuralslicer.neural import losses as L
from neuralslicer.neural.device import device_record
from neuralslicer.baselines.s3_config import S3Config
from neuralslicer.neural.networks import quaternion_to_matrix
from neuralslicer.neural.problem import FieldProblem
from neuralslicer.samples import SurfaceSamples

ProgressFn = Callable[[int, dict], None]
TERMS = ("sf", "sr", "smooth")
#: objectives S3-Slicer has; any other one asked for is recorded as ignored
S3_OBJECTIVES = ("sf", "sr")


def unit_quaternions(raw: torch.Tensor) -> torch.Tensor:
    """Rows of raw (m,4) scaled to unit quaternions (w first)."""
    return raw / raw.norm(dim=1, keepdim=True).clamp_min(1e-12)


def intended_lpd(quaternions: torch.Tensor) -> torch.Tensor:
    """The printing direction R_e^T z that each rotation intends in the model space (m,3): the third
    row of R(q_e), since (R_e v).z = v.(R_e^T z)."""
    return quaternion_to_matrix(quaternions)[:, 2, :]


class S3Objective:
    """The S3 loss of per-element quaternions: the objectives in the deformed space and L_H."""

    def __init__(self, problem: FieldProblem, config: S3Config) -> None:
        """Sample tensors from the problem; the pair coefficients of L_H."""
        self.problem, self.config = problem, config
        g = problem.geometry
        d2 = np.sum((g.centroids[g.pairs[:, 0]] - g.centroids[g.pairs[:, 1]]) ** 2, axis=1)
        w = 0.5 * (g.volumes[g.pairs[:, 0]] + g.volumes[g.pairs[:, 1]])
        length2 = float(g.volumes.sum()) ** (2.0 / 3.0)
        coef = length2 * w / np.maximum(d2, 1e-300) / max(float(w.sum()), 1e-300)
        self.pair_coef = torch.as_tensor(coef, dtype=problem.dtype, device=problem.device)

    def __call__(self, raw: torch.Tensor) -> tuple[torch.Tensor, dict[str, torch.Tensor]]:
        """(total weighted loss, terms 'sf', 'sr', 'smooth') for raw per-element quaternions (m,4)."""
        p, c = self.problem, self.config
        q = unit_quaternions(raw)
        d = intended_lpd(q)
        zero = q.new_zeros(())
        terms = {
            "sf": (L.support_free_loss(d[p.b_tet_t], p.b_normals_t, p.b_areas_t, math.radians(c.alpha_deg), c.k_sf)
                   if c.w_sf > 0 and len(p.b_tet) else zero),
            "sr": (L.strength_loss(d[p.t_tet_t], p.t_tau_t, p.t_volumes_t, math.radians(c.beta_deg), c.k_sr)
                   if c.w_sr > 0 and len(p.t_tet) else zero),
        }
        diff = q[p.pairs_t[:, 0]] - q[p.pairs_t[:, 1]]
        terms["smooth"] = (self.pair_coef * (diff * diff).sum(dim=1)).sum() if len(self.pair_coef) else zero
        total = c.w_sf * terms["sf"] + c.w_sr * terms["sr"] + c.w_smooth * terms["smooth"]
        return total, terms


@dataclass
class S3Result:
    """Result of the S3 baseline, with the neural field's output contract.

    G : (n,) float64 field at the cage vertices (= z of the deformed cage); deformed_vertices : (n, 3);
    quaternions : (m, 4) unit, per cage tet; lpd : (m, 3) realised unit grad G per tet; intended_lpd :
    (m, 3) R_e^T z, the direction the rotations meant; history : per-step 'total', 'sf', 'sr',
    'smooth' (before each step); final : the loss terms of the returned rotations; satisfaction : of
    the realised field, with 'deformed_space_' (the intended directions) and 'planar_' counterparts.
    """

    G: np.ndarray
    deformed_vertices: np.ndarray
    quaternions: np.ndarray
    lpd: np.ndarray
    intended_lpd: np.ndarray
    history: dict[str, list[float]]
    final: dict[str, float]
    steps: int
    converged: bool
    wall_time_s: float
    satisfaction: dict[str, float]
    attrs: dict = field(default_factory=dict)

    def summary(self) -> dict:
        """JSON-ready figures: steps, convergence, time, final losses, satisfaction, sizes, objectives."""
        return {"method": "s3", "steps": self.steps, "converged": self.converged, "wall_time_s": self.wall_time_s,
                "final": dict(self.final), "satisfaction": dict(self.satisfaction),
                "n_vertices": int(len(self.G)), "n_tets": int(len(self.quaternions)),
                "objectives": list(self.attrs.get("objectives", [])),
                "ignored_objectives": list(self.attrs.get("ignored_objectives", []))}

    def to_arrays(self) -> tuple[dict[str, np.ndarray], dict]:
        """(arrays, json attrs) for a zarr group, as FieldResult.to_arrays; history as 'history/<name>'."""
        arrays = {"G": self.G, "deformed_vertices": self.deformed_vertices, "lpd": self.lpd,
                  "quaternions": self.quaternions, "intended_lpd": self.intended_lpd}
        arrays.update({f"history/{k}": np.asarray(v, dtype=np.float64) for k, v in self.history.items()})
        attrs = dict(self.attrs)
        attrs.update(self.summary(), kind="s3", schema_version=1)
        return arrays, attrs


def _stalled(best: list[float], window: int, tol: float) -> bool:
    """The running minimum improved by less than tol (relative) over the last window steps."""
    if len(best) <= window:
        return False
    old, new = best[-window - 1], best[-1]
    return old - new <= tol * abs(old)


def optimise_s3(
    cage_vertices: np.ndarray,
    cage_tets: np.ndarray,
    samples: SurfaceSamples,
    stress_samples: StressSamples | None = None,
    objectives: Iterable[str] = ("sf",),
    config: S3Config | None = None,
    platform_z: float | None = None,
    progress: ProgressFn | None = None,
) -> S3Result:
    """S3-Slicer's field on the cage: per-element rotations optimised in the deformed space, realised by ARAP.

    Parameters
    ----------
    cage_vertices : (n, 3) float64, cage_tets : (m, 4) int64 -- the cage C (build frame, z up).
    samples : the surface samples B (platform points are left out of L_SF); stress_samples : the stress
        samples T (optional, used by 'sr').
    objectives : 'sf' and/or 'sr'; others (po, gc, ca) are not S3's and are recorded as ignored.
    config : S3Config (defaults documented there); platform_z : platform height (ARAP pinning only).
    progress(step, info) : after every step, with the loss terms, lr, best loss and elapsed time
        (info["phase"] == "s3").

    Returns an :class:`S3Result` whose ``G`` (n,) is the deformed height at the cage vertices, as the
    neural field's; with ``config.steps == 0`` the rotations are the identity and ``G = z``.
    """
    t0 = time.perf_counter()
    objectives = list(objectives)
    config = (config or S3Config()).for_objectives(objectives)
    problem = FieldProblem(cage_vertices, cage_tets, samples, stress_samples, config.neural_config(), platform_z)
    objective = S3Objective(problem, config)
    m = len(problem.geometry.tets)
    raw = torch.zeros((m, 4), dtype=problem.dtype, device=problem.device)
    raw[:, 0] = 1.0
    if config.steps > 0 and config.jitter > 0:
        # one small tilt about a random horizontal axis for every element: coherent, so the smoothness term keeps it
        angle = np.random.default_rng(config.seed).uniform(0.0, 2.0 * np.pi)
        axis = torch.tensor([np.cos(angle), np.sin(angle), 0.0], dtype=raw.dtype, device=raw.device)
        raw[:, 1:] = 0.5 * config.jitter * axis
    raw.requires_grad_(True)
    optimizer = torch.optim.Adam([raw], lr=config.lr)
    history: dict[str, list[float]] = {k: [] for k in ("total", *TERMS)}
    best_loss, best_raw, best = math.inf, raw.detach().clone(), []
    converged = False
    step = 0
    while step < config.steps and not converged:
        total, terms = objective(raw)
        tv = float(total.detach())
        if tv < best_loss:
            best_loss, best_raw = tv, raw.detach().clone()
        optimizer.zero_grad()
        total.backward()
        optimizer.step()
        step += 1
        history["total"].append(tv)
        for k in TERMS:
            history[k].append(float(terms[k].detach()))
        best.append(best_loss)
        converged = _stalled(best, config.window, config.tol)
        if progress is not None:
            info = {k: v[-1] for k, v in history.items()}
            progress(step, dict(info, lr=config.lr, best=best_loss, elapsed_s=time.perf_counter() - t0, phase="s3"))
    with torch.no_grad():
        if step:  # the iterate after the last step has not been evaluated yet
            last = float(objective(raw)[0])
            if last < best_loss:
                best_raw = raw.detach().clone()
        return _result(problem, objective, best_raw, history, step, converged, objectives, t0)


def _result(problem: FieldProblem, objective: S3Objective, raw: torch.Tensor, history: dict[str, list[float]],
            steps: int, converged: bool, objectives: list[str], t0: float) -> S3Result:
    """Realise the rotations (float64 ARAP, s = 1), judge the field and record the run."""
    total, terms = objective(raw)
    q = unit_quaternions(raw.double())
    V = problem.arap.deform(q, torch.ones((len(q), 3), dtype=torch.float64, device=q.device)).cpu().numpy()
    G = V[:, 2].copy()
    g = problem.geometry
    grad = np.einsum("ei,eij->ej", G[g.tets], g.bary_grads)
    lpd = grad / np.maximum(np.linalg.norm(grad, axis=1, keepdims=True), 1e-300)
    intended = intended_lpd(q).cpu().numpy()
    sat = problem.satisfaction(lpd)
    sat.update({f"deformed_space_{k}": v for k, v in problem.satisfaction(intended).items()})
    sat.update({f"planar_{k}": v for k, v in problem.planar_lpd_satisfaction().items()})
    final = {k: float(v) for k, v in terms.items()}
    final["total"] = float(total)
    config = objective.config
    return S3Result(
        G=G, deformed_vertices=V, quaternions=q.cpu().numpy(), lpd=lpd, intended_lpd=intended, history=history,
        final=final, steps=steps, converged=converged, wall_time_s=time.perf_counter() - t0, satisfaction=sat,
        attrs={"config": config.model_dump(mode="json"), "objectives": objectives,
               "ignored_objectives": [o for o in objectives if o not in S3_OBJECTIVES],
               "solver_backend": problem.arap.backend, **device_record(problem.device)},
    )
