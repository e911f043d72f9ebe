"""The collision policy on its own: which field comes after which print, with no Prefect and no slicing."""
from __future__ import annotations

from collections.abc import Sequence

import pytest

from neuralslicer.config import SliceConfig
from neuralslicer.neural.config import NeuralConfig
from neuralslicer.run.collision_policy import (CollisionPolicy, FieldRequest, PlanarBlend, PrintAttempt, Refine,
                                               Smoother, run_policy)

OBJECTIVES = ["sf", "po", "gc", "ca"]


def policy(**config: object) -> CollisionPolicy:
    """The policy of a slice configuration with the default neural settings."""
    cfg = SliceConfig.model_validate(config)
    return CollisionPolicy.for_config(cfg, cfg.neural, config.get("objectives", OBJECTIVES))  # type: ignore[arg-type]


def play(p: CollisionPolicy, outcomes: Sequence[tuple[int, int, int]] | None = None,
         clean_from: float | None = None, released: list[tuple[int, int]] | None = None
         ) -> tuple[list[PrintAttempt], int]:
    """Run the policy against scripted prints: optimised fields collide as ``outcomes`` says ((collisions, head
    hits, platform hits) each, clean once they run out); a blend t is clean when t >= ``clean_from``. Each print
    released is appended to ``released`` as (its index, the prints made by then)."""
    script = list(outcomes or [])
    made: list[int] = []

    def attempt(request: FieldRequest, earlier: Sequence[int]) -> tuple[int, PrintAttempt]:
        made.append(len(earlier))
        if request.blend is not None:
            clean = clean_from is not None and request.blend[0] >= clean_from
            return len(earlier), PrintAttempt(request, 0 if clean else 3, 3, 0)
        n, head, platform = script.pop(0) if script else (0, 0, 0)
        return len(earlier), PrintAttempt(request, n, head, platform)

    _, attempts, kept = run_policy(p, attempt, None if released is None else lambda i: released.append((i, len(made))))
    return attempts, kept


@pytest.mark.parametrize(("config", "outcomes", "clean_from"), [
    ({}, [], None),                                                          # clean at once
    ({"collision_refinements": 3}, [(5, 5, 0), (4, 4, 0)], None),            # refined until clean
    ({"collision_refinements": 1, "collision_retries": 1, "collision_fallback": "none"}, [(5, 5, 0)] * 3, None),
    ({"collision_refinements": 0, "collision_retries": 0, "collision_blend_steps": 4}, [(5, 5, 0)], 0.3),
    ({"collision_refinements": 1, "collision_retries": 0, "collision_blend_steps": 2}, [(5, 5, 0)] * 2, None),
])
def test_every_print_but_the_kept_one_is_released_once_as_soon_as_it_cannot_be_kept(
        config: dict, outcomes: list, clean_from: float | None) -> None:
    """The kept print is never released; every other one is, once, and no later than when the next print is made
    (a clean blend stays until a smaller clean one is found)."""
    released: list[tuple[int, int]] = []
    attempts, kept = play(policy(**config), outcomes, clean_from, released)
    indices = [i for i, _ in released]
    assert sorted(indices) == [i for i in range(len(attempts)) if i != kept] and len(set(indices)) == len(indices)
    for i, made in released:
        a = attempts[i]
        if a.request.blend is None:
            assert made == i + 2      # an optimised print is kept until the next one
        elif not a.clean:   # a colliding blend goes at once when a clean one was found, else with the next print
            found = any(b.clean and b.request.blend is not None for b in attempts[:i])
            assert made == (i + 1 if found else i + 2)
    blends = [(i, made) for i, made in released if attempts[i].clean and attempts[i].request.blend is not None]
    assert all(attempts[i].request.blend[0] > attempts[kept].request.blend[0] for i, _ in blends)


def test_a_clean_first_print_is_the_answer() -> None:
    attempts, kept = play(policy())
    assert [a.request.label for a in attempts] == ["optimised"] and kept == 0


def test_refinements_accumulate_the_prints_and_start_from_the_last_field() -> None:
    attempts, kept = play(policy(collision_refinements=3), [(5, 5, 0), (4, 4, 0), (2, 2, 0)])
    assert [a.request.by for a in attempts] == ["first", "refine", "refine", "refine"]
    assert [a.request.refine_on for a in attempts] == [(), (0,), (0, 1), (0, 1, 2)]
    assert [a.request.warm_start for a in attempts] == [None, 0, 1, 2]
    assert attempts[-1].request.label == "refined around the collisions of 3 print(s)" and kept == 3


def test_heads_below_the_platform_firm_up_the_floor_from_then_on() -> None:
    p = policy(collision_refinements=3)
    base = p.first.neural.loss.gc_floor_weight
    factor = p.first.neural.optim.refine.floor_weight_factor
    attempts, _ = play(p, [(5, 5, 2), (4, 4, 0)])
    floors = [a.request.neural.loss.gc_floor_weight for a in attempts]
    assert floors == pytest.approx([base, base * factor, base * factor])
    assert attempts[1].request.label.endswith(f"floor weight x{factor:g}")


def test_only_travel_collisions_skip_the_refinement() -> None:
    """Collisions with no head hit at a waypoint give L_GC nothing to refine around: smoother fields come next."""
    attempts, _ = play(policy(collision_refinements=3, collision_retries=1, collision_fallback="none"), [(4, 0, 0)])
    assert [a.request.by for a in attempts] == ["first", "smoother"]


def test_smoother_fields_after_the_refinements_keep_their_pool_and_start() -> None:
    p = policy(collision_refinements=1, collision_retries=2, collision_smoothness_factor=10.0, collision_fallback="none")
    attempts, kept = play(p, [(5, 5, 0), (4, 4, 0), (3, 3, 0), (2, 2, 0)])
    assert [a.request.by for a in attempts] == ["first", "refine", "smoother", "smoother"]
    w = p.first.neural.loss.w_hs
    assert [a.request.neural.loss.w_hs for a in attempts] == pytest.approx([w, w, 10 * w, 100 * w])
    assert attempts[2].request.refine_on == (0,) and attempts[2].request.warm_start == 0   # the refinement's
    assert "ca" in attempts[2].request.objectives and attempts[3].request.label == "re-optimised, harmonic x100 + CA"
    assert kept == 3   # no blend: the last print, colliding, is the result


def test_the_blend_bisects_to_the_smallest_clean_weight() -> None:
    p = policy(collision_refinements=0, collision_retries=0, collision_blend_steps=4)
    attempts, kept = play(p, [(5, 5, 0)], clean_from=0.3)
    ts = [a.request.blend[0] for a in attempts[1:]]
    assert ts == [0.5, 0.25, 0.375, 0.3125]
    assert all(a.request.blend[1] == 0 for a in attempts[1:])
    assert kept == 4 and attempts[kept].request.blend[0] == 0.3125 and attempts[kept].clean


def test_planar_layers_when_no_blend_is_clean() -> None:
    attempts, kept = play(policy(collision_refinements=0, collision_retries=0, collision_blend_steps=2), [(5, 5, 0)])
    assert [a.request.blend[0] for a in attempts[1:]] == [0.5, 0.75, 1.0]
    assert attempts[kept].request.label == "planar blend t = 1 (planar layers)"


def test_s3_goes_straight_to_the_blend_and_no_objectives_to_nothing() -> None:
    attempts, _ = play(policy(method="s3", collision_blend_steps=1), [(5, 5, 0)], clean_from=0.0)
    assert [a.request.by for a in attempts] == ["first", "blend"] and attempts[0].request.neural is None
    attempts, kept = play(policy(objectives=[]), [(5, 5, 0)])
    assert len(attempts) == 1 and kept == 0


def test_strategies_answer_alone() -> None:
    """Each strategy is a function of the attempts: it offers nothing when the last print is clean or its budget
    is spent."""
    first = FieldRequest("optimised", "first", neural=NeuralConfig(), objectives=("sf", "gc"))
    clean, hit = PrintAttempt(first, 0), PrintAttempt(first, 3, 3, 0)
    for strategy in (Refine(1, 2.0, 1.0), Smoother(1, 10.0), PlanarBlend(2)):
        assert strategy.next_request([clean]) is None
        assert strategy.next_request([hit]) is not None
    refined = PrintAttempt(Refine(1, 2.0, 1.0).next_request([hit]), 2, 2, 0)
    assert Refine(1, 2.0, 1.0).next_request([hit, refined]) is None
