"""The local collision constraint L_CA = 0 (paper Sec. 5) and the tilt bound as DC3 corrections of the network
weights."""
from __future__ import annotations

import math

import numpy as np
import torch

from neuralslicer.neural.networks import DeformationFields
from neuralslicer.neural.problem import FieldProblem


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


def enforce_tilt_bound(problem: FieldProblem, fields: DeformationFields) -> int:
    """Correct the final weights until no tet of the solid has its LPD beyond ``loss.tilt_bound_deg`` from +z in
    the float64 field the result stores (at most ``loss.tilt_correction_steps`` steps, each toward LPDs
    ``loss.tilt_margin_deg`` inside the bound); returns the steps made (0 without a bound)."""
    cl = problem.config.loss
    if problem.tilt_bound is None or not len(problem.tilt_tets):
        return 0
    done = 0
    while done < cl.tilt_correction_steps and (problem.tilt_angles64(fields) > cl.tilt_bound_deg).any():
        target = problem.tilt_violation(fields)
        if float(target.detach()) <= 0 or not correction_step(fields, target, cl):
            break
        done += 1
    return done
