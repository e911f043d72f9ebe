"""What to do after a print collides, as data: strategies that, given the attempts so far, name the next field to
print or none (SPEC step 11's fallbacks and the refinement beyond the paper).

The flow and the in-process pipeline only loop: ``request = policy.next_request(attempts)``, print it, append the
attempt, until the policy returns None; ``policy.kept(attempts)`` is the attempt whose print is the result.
"""
from __future__ import annotations

from collections.abc import Callable, Sequence
from dataclasses import dataclass, field, replace
from typing import Protocol, TypeVar

from neuralslicer.config import SliceConfig
from neuralslicer.neural.config import NeuralConfig

T = TypeVar("T")


@dataclass(frozen=True)
class FieldRequest:
    """One field to compute and print.

    label : how the report names the attempt; by : the strategy that asked for it ("first" for the first field);
    neural : the optimisation's settings (None for the S3 methods); objectives : the objectives optimised;
    refine_on : indices of the attempts whose prints' collisions refine L_GC's pool; warm_start : index of the
    attempt whose field's weights start the optimisation; blend : (t, index) for the field of attempt ``index``
    blended toward planar layers, (1 - t) G + t z, instead of an optimisation.
    """

    label: str
    by: str
    method: str = "neural"
    neural: NeuralConfig | None = None
    objectives: tuple[str, ...] = ()
    refine_on: tuple[int, ...] = ()
    warm_start: int | None = None
    blend: tuple[float, int] | None = None


@dataclass(frozen=True)
class PrintAttempt:
    """A printed field: the request and what the exact check of its print found."""

    request: FieldRequest
    collisions: int
    head_hits: int = 0
    platform_hits: int = 0

    @property
    def clean(self) -> bool:
        """True when the print is collision-free."""
        return self.collisions == 0


class Strategy(Protocol):
    """One answer to a colliding print."""

    name: str

    def next_request(self, attempts: Sequence[PrintAttempt]) -> FieldRequest | None:
        """The next field to print after these attempts, or None when this strategy has nothing to offer."""


def _optimised(attempts: Sequence[PrintAttempt]) -> list[PrintAttempt]:
    """The attempts that optimised a field (no blend)."""
    return [a for a in attempts if a.request.blend is None]


def _last_collides(attempts: Sequence[PrintAttempt]) -> bool:
    """True when the last attempt is an optimised field whose print collides."""
    return bool(attempts) and not attempts[-1].clean and attempts[-1].request.blend is None


@dataclass(frozen=True)
class Refine:
    """Refine L_GC's pool around the collisions of every print so far and re-optimise from the last field's weights
    (at most ``rounds`` times); heads below the platform also make the floor term ``floor_factor`` times firmer."""

    rounds: int
    floor_factor: float
    base_floor_weight: float
    name: str = "refine"

    def next_request(self, attempts: Sequence[PrintAttempt]) -> FieldRequest | None:
        """Refine when the last print's head hits the part at a waypoint and rounds are left."""
        done = sum(a.request.by == self.name for a in attempts)
        if not _last_collides(attempts) or done >= self.rounds:
            return None
        last = attempts[-1]
        if last.head_hits == 0 or "gc" not in last.request.objectives or last.request.neural is None:
            return None
        prints = (*last.request.refine_on, len(attempts) - 1)
        neural, label = last.request.neural, f"refined around the collisions of {len(prints)} print(s)"
        if last.platform_hits:
            # the floor's quadratic penalty settled short of the platform against SF: it weighs more from here on
            loss = neural.loss.model_copy(update={"gc_floor_weight": neural.loss.gc_floor_weight * self.floor_factor})
            neural = neural.model_copy(update={"loss": loss})
            label += f", floor weight x{neural.loss.gc_floor_weight / self.base_floor_weight:g}"
        return replace(last.request, label=label, by=self.name, neural=neural, refine_on=prints,
                       warm_start=len(attempts) - 1)


@dataclass(frozen=True)
class Smoother:
    """The paper's fallback: re-optimise with the harmonic weights ``factor`` times larger and the local collision
    term, at most ``retries`` times; the refinement so far (pool, warm start) carries over."""

    retries: int
    factor: float
    name: str = "smoother"

    def next_request(self, attempts: Sequence[PrintAttempt]) -> FieldRequest | None:
        """Smooth when the last print collides and retries are left."""
        done = sum(a.request.by == self.name for a in attempts)
        last = attempts[-1] if attempts else None
        if not _last_collides(attempts) or done >= self.retries or last.request.neural is None:
            return None
        neural = last.request.neural
        loss = neural.loss.model_copy(update={"w_hs": neural.loss.w_hs * self.factor, "w_hq": neural.loss.w_hq * self.factor})
        return replace(last.request, label=f"re-optimised, harmonic x{self.factor ** (done + 1):g} + CA", by=self.name,
                       neural=neural.model_copy(update={"loss": loss}),
                       objectives=tuple(sorted(set(last.request.objectives) | {"ca"})))


@dataclass(frozen=True)
class PlanarBlend:
    """The last resort: the smallest blend t toward planar layers, (1 - t) G + t z of the last optimised field,
    whose print is clean, by bisection to within 2^-steps; planar layers (t = 1) when no smaller t is."""

    steps: int
    name: str = "blend"

    def bisection(self, attempts: Sequence[PrintAttempt]) -> tuple[float, float, float | None, int]:
        """(lo, hi, best clean t, steps taken) after the blends tried so far."""
        lo, hi, best, n = 0.0, 1.0, None, 0
        for a in attempts:
            if a.request.by == self.name and a.request.blend is not None and n < self.steps:
                n += 1
                t = a.request.blend[0]
                if a.clean:
                    hi = best = t
                else:
                    lo = t
        return lo, hi, best, n

    def next_request(self, attempts: Sequence[PrintAttempt]) -> FieldRequest | None:
        """The next blend weight to try, or None once the bisection is done (or nothing collided)."""
        blends = [a for a in attempts if a.request.by == self.name]
        if not blends and not _last_collides(attempts):
            return None
        if not attempts[-1].request.objectives:
            return None
        base = len(attempts) - 1 - len(blends) if not blends else blends[0].request.blend[1]
        lo, hi, best, n = self.bisection(attempts)
        if n < self.steps:
            t = 0.5 * (lo + hi)
        elif best is None and not any(a.request.blend[0] == 1.0 for a in blends):
            t = 1.0
        else:
            return None
        label = "planar blend t = 1 (planar layers)" if t == 1.0 else f"planar blend t = {t:.4g}"
        return replace(attempts[base].request, label=label, by=self.name, blend=(t, base))

    def kept(self, attempts: Sequence[PrintAttempt]) -> int | None:
        """The index of the blend whose print is the result (None when no blend was tried, or while none is clean
        and planar layers are still to be tried)."""
        blends = [i for i, a in enumerate(attempts) if a.request.by == self.name]
        if not blends:
            return None
        _, _, best, _ = self.bisection(attempts)
        t = 1.0 if best is None else best
        return next((i for i in blends if attempts[i].request.blend[0] == t), None)


@dataclass(frozen=True)
class CollisionPolicy:
    """The first field and, while its print collides, the strategies in order: the first with a request wins."""

    first: FieldRequest
    strategies: tuple[Strategy, ...] = field(default_factory=tuple)

    @classmethod
    def for_config(cls, config: SliceConfig, neural: NeuralConfig, objectives: Sequence[str]) -> CollisionPolicy:
        """The policy a slice configuration asks for: refinement and smoother fields for the neural method when it
        has objectives, then the planar blend (``collision_fallback: blend``)."""
        method = config.method
        first = FieldRequest("optimised", "first", method, neural if method == "neural" else None, tuple(objectives))
        strategies: list[Strategy] = []
        if method == "neural" and objectives:
            strategies += [Refine(config.collision_refinements, neural.optim.refine.floor_weight_factor,
                                  neural.loss.gc_floor_weight),
                           Smoother(config.collision_retries, config.collision_smoothness_factor)]
        if config.collision_fallback == "blend" and objectives:
            strategies.append(PlanarBlend(config.collision_blend_steps))
        return cls(first, tuple(strategies))

    def next_request(self, attempts: Sequence[PrintAttempt]) -> FieldRequest | None:
        """The next field to print, or None when the last print is the answer."""
        if not attempts:
            return self.first
        blending = attempts[-1].request.blend is not None
        if attempts[-1].clean and not blending:
            return None
        for strategy in self.strategies:
            if blending and not isinstance(strategy, PlanarBlend):
                continue
            request = strategy.next_request(attempts)
            if request is not None:
                return request
        return None

    def kept(self, attempts: Sequence[PrintAttempt]) -> int:
        """The index of the attempt whose print is the result: the chosen blend, else the last attempt."""
        for strategy in self.strategies:
            if isinstance(strategy, PlanarBlend) and (i := strategy.kept(attempts)) is not None:
                return i
        return len(attempts) - 1


def run_policy(policy: CollisionPolicy, attempt: Callable[[FieldRequest, Sequence[T]], tuple[T, PrintAttempt]],
               release: Callable[[T], None] | None = None) -> tuple[list[T], list[PrintAttempt], int]:
    """Print fields as the policy asks until it is done: ``attempt(request, outputs so far)`` prints one and
    returns its output and PrintAttempt; ``release(output)`` is called once for each print as soon as it can no
    longer be the one kept (the policy's choice only moves on: to a later print, or to a smaller clean blend).
    Returns every output, every attempt and the index of the one kept."""
    outputs: list[T] = []
    attempts: list[PrintAttempt] = []
    released: set[int] = set()
    while (request := policy.next_request(attempts)) is not None:
        out, done = attempt(request, outputs)
        outputs.append(out)
        attempts.append(done)
        if release is not None:
            kept = policy.kept(attempts)
            for i in sorted(set(range(len(outputs))) - released - {kept}):
                release(outputs[i])
                released.add(i)
    return outputs, attempts, policy.kept(attempts)
