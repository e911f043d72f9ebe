"""The optimisation step's shortcuts (issue 42) give the step they replace, bit for bit: the field shared by a
check step's pair search, evaluation and constraint check, the best loss evaluated on a copy of the networks, the
excess of L_CA with a graph only when a correction follows, the height from the rotations' third rows."""
from __future__ import annotations

import copy

import numpy as np
import pytest
import torch

from neuralslicer.neural import NeuralConfig
from neuralslicer.neural import losses as L
from neuralslicer.neural.constraints import corrected_evaluation
from neuralslicer.neural.deformation import ArapDeformation
from neuralslicer.neural.head_collision import CollisionPool
from neuralslicer.neural.networks import quaternion_to_matrix
from neuralslicer.neural.optimise import (LoopState, deterministic_algorithms, initial_target, iterate, loss_of,
                                          pretrain, take_step)
from neuralslicer.neural.problem import FieldProblem
from neuralslicer.neural.synthetic import sphere_samples
from neuralslicer.tetmesh import box_tet_grid

STEPS = 14


def _config() -> NeuralConfig:
    """Small networks, L_GC with a small head (pairs to follow), L_CA with a wide cone (corrections), a valley guess."""
    return NeuralConfig.model_validate({
        "network": "small", "device": "cpu",
        "optim": {"max_steps": STEPS, "check_every": 3, "convergence_window": 1000, "target_overhang": 0,
                  "lr": 5e-3},
        "loss": {"w_gc": 1.0, "phi_deg": 120.0, "head_min_height": 0.3,
                 "head": {"cone_half_angle_deg": 30, "cone_length": 1, "holder_radius": 6, "holder_length": 6}},
        "init": {"kind": "user", "pretrain_steps": 40, "pretrain_lr": 3e-3},
    })


def _problem() -> FieldProblem:
    """A 10 mm box cage around a sphere's samples, a pool of points inside the sphere."""
    V, T = box_tet_grid((4, 4, 4), np.zeros(3), np.full(3, 10.0))
    axis = np.arange(1.0, 9.5, 1.5)
    grid = np.stack(np.meshgrid(axis, axis, axis, indexing="ij"), -1).reshape(-1, 3)
    pool = CollisionPool(grid[np.linalg.norm(grid - 5.0, axis=1) < 4.0], 1.5)
    return FieldProblem(V, T, sphere_samples(), None, _config(), 0.0, pool)


def _start(problem: FieldProblem) -> LoopState:
    """The seeded start, pre-trained to a V-shaped valley (whose creases violate L_CA = 0)."""
    V = problem.geometry.vertices
    st = LoopState.start(problem)
    pretrain(problem, st.fields, initial_target(problem, V[:, 2] - np.abs(V[:, 0] - 5.0), None))
    return st


def _loss_in_place(problem: FieldProblem, fields, weights: dict) -> float:
    """The best loss as the loop evaluated it before: the weights loaded into the live networks and back."""
    current = copy.deepcopy(fields.state_dict())
    fields.load_state_dict(weights)
    with torch.no_grad():
        total = float(problem.evaluate(fields)[0])
    fields.load_state_dict(current)
    return total


def _reference_iterate(problem: FieldProblem, st: LoopState, first: bool) -> None:
    """The loop's step without the shortcuts: L_GC's pairs searched on a field of their own before the evaluation,
    the best loss on the live networks, the constraint check on a field of its own."""
    oc = problem.config.optim
    check = st.step % oc.check_every == 0
    if check or first:
        problem.refresh_collisions(st.fields)
        if st.best_state is not None:
            st.best_state["loss"] = _loss_in_place(problem, st.fields, st.best_state["fields"])
    total, terms, n_corr, n_viol = corrected_evaluation(problem, st.fields)
    if check and st.step > 0 and n_viol == 0:
        problem.constraints_met(st.fields, st.step)
    tv = float(total.detach())
    take_step(st, oc, total, tv)
    st.step += 1
    st.history["total"].append(tv)
    for k in problem.terms():
        st.history[k].append(float(terms[k].detach()))
    st.history["corrections"].append(float(n_corr))


@pytest.fixture(scope="module")
def runs() -> tuple[LoopState, LoopState]:
    """(the loop's states, the reference's) after STEPS steps from the same start."""
    out = []
    for step in (iterate, _reference_iterate):
        problem = _problem()
        if step is _reference_iterate:  # no field kept: every field computed afresh
            problem._remember_field = lambda fields, G, grad: (G.detach(), grad.detach())
        with deterministic_algorithms():
            st = _start(problem)
            for i in range(STEPS):
                step(problem, st, i == 0)
        out.append(st)
    return out[0], out[1]


def test_the_steps_are_those_of_the_reference_bit_for_bit(runs):
    fast, ref = runs
    assert sum(ref.history["corrections"]) > 0 and max(ref.history["gc"]) > 0  # both shortcuts were exercised
    for k in ("total", "sf", "po", "hs", "hq", "gc", "ca", "corrections"):
        assert fast.history[k] == ref.history[k], k
    a, b = fast.fields.state_dict(), ref.fields.state_dict()
    assert all(torch.equal(a[k], b[k]) for k in a)


def test_the_field_is_computed_again_whenever_a_weight_changes():
    problem = _problem()
    st = LoopState.start(problem)
    calls = []
    height = problem.height
    problem.height = lambda fields: calls.append(1) or height(fields)

    def fresh(fields):
        with torch.no_grad():
            return height(fields)[0]

    G, _ = problem.field(st.fields)
    assert problem.field(st.fields)[0] is G and len(calls) == 1        # the same weights: kept
    with torch.no_grad():
        st.fields.q_net.head.bias.add_(0.1)                              # an in-place change (Adam, DC3)
    G2, _ = problem.field(st.fields)
    assert len(calls) == 2 and torch.equal(G2, fresh(st.fields)) and not torch.equal(G2, G)
    other = copy.deepcopy(st.fields)                                    # other networks, the same weights
    problem.field(other)
    assert len(calls) == 3
    st.fields.load_state_dict(LoopState.start(problem).fields.state_dict())   # a state dict loaded
    assert torch.equal(problem.field(st.fields)[0], fresh(st.fields)) and len(calls) == 4
    problem.evaluate(st.fields)                                          # an evaluation's field is kept
    G5, _ = problem.field(st.fields)
    assert len(calls) == 5 and torch.equal(G5, fresh(st.fields))


def test_the_best_loss_leaves_the_networks_and_their_graph_alone():
    problem = _problem()
    with deterministic_algorithms():
        st = _start(problem)
        other = copy.deepcopy(st.fields.state_dict())
        with torch.no_grad():
            st.fields.q_net.head.bias.add_(0.05)
        before = copy.deepcopy(st.fields.state_dict())
        total, _ = problem.evaluate(st.fields)
        best = loss_of(problem, st.fields, other)
        total.backward()                                                 # the graph is intact
        assert best == _loss_in_place(problem, st.fields, other)
        after = st.fields.state_dict()
        assert all(torch.equal(before[k], after[k]) for k in before)


def test_the_excess_has_a_graph_only_when_a_pair_violates():
    problem = _problem()
    with deterministic_algorithms():
        st = LoopState.start(problem)                                    # planar: no crease
        _, _, excess = problem.evaluate_with_excess(st.fields)
        assert not excess.requires_grad and (excess <= problem.config.loss.correction_tol).all()
        st = _start(problem)                                             # the valley
        _, _, excess = problem.evaluate_with_excess(st.fields)
        assert excess.requires_grad and (excess > problem.config.loss.correction_tol).any()
        G, grad = problem.field(st.fields)
        direct = L.collision_excess(grad, problem.pairs_t, problem.pair_normals_t, problem.phi)
        assert torch.equal(excess.detach(), direct)


def test_the_height_from_third_rows_is_that_of_the_full_rotations():
    V, T = box_tet_grid((3, 3, 3), np.zeros(3), np.full(3, 10.0))
    arap = ArapDeformation(V, T, platform_z=0.0)
    gen = torch.Generator().manual_seed(0)
    q0 = torch.nn.functional.normalize(torch.randn(len(T), 4, generator=gen), dim=1)
    s0 = 0.5 + torch.rand(len(T), 3, generator=gen)
    w = torch.randn(len(V), generator=gen)
    out = []
    for height in (arap.deformed_height, lambda q, s: arap.solve_z(arap.rhs_z(quaternion_to_matrix(q), s))):
        q, s = q0.clone().requires_grad_(), s0.clone().requires_grad_()
        G = height(q, s)
        (G * w).sum().backward()
        out.append((G.detach(), q.grad, s.grad))
    for a, b in zip(*out):
        assert torch.equal(a, b)
