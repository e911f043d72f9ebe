"""What every pipeline task shares: an output path keyed by the digest of its inputs, parameters and code version, and
the store as its one cache (a task whose group is there computes nothing and ends ``Cached``)."""
from __future__ import annotations

import functools
import inspect
import json
import time
from collections.abc import Callable, Iterable, Iterator, Mapping
from dataclasses import dataclass, field
from typing import Any, TypeVar

from prefect import task
from prefect.cache_policies import NO_CACHE
from prefect.states import Completed, State

from neuralslicer.allocator import release_freed_memory
from neuralslicer.run.provenance import package_versions
from neuralslicer.storage import ArrayStream, ArtifactRef, ArtifactStore, canonical, digest
from neuralslicer.tasks.progress import run_logger, say

T = TypeVar("T")
#: the name of the state of a task whose output the store already held (Prefect's own name for a cache hit)
CACHED = "Cached"


def keyed(parameters: dict[str, Any], exclude: tuple[str, ...] = (),
          key_names: Mapping[str, str] | None = None) -> dict[str, Any]:
    """The parameters a step's output digest covers (not the store, not ``exclude``), each under its name in the key
    (``key_names``: a renamed parameter keeps the name it had, so stores written before keep their keys)."""
    skip = {"store", *exclude}
    names = key_names or {}
    return {names.get(k, k): v for k, v in parameters.items() if k not in skip}


def output_ref(step: str, version: str, parameters: dict[str, Any], exclude: tuple[str, ...] = (),
               key_names: Mapping[str, str] | None = None) -> ArtifactRef:
    """The ref a step writes for these parameters: path `<model>/<step>/<digest>` in the given store."""
    key = digest(step, version, keyed(parameters, exclude, key_names))
    model = parameters.get("name") or next(v.model for v in parameters.values() if isinstance(v, ArtifactRef))
    return ArtifactRef(store=str(parameters["store"]), path=f"{model}/{step}/{key}", digest=key)


@dataclass(frozen=True)
class PipelineStep:
    """How a pipeline task names and writes its output: step name, code version, parameters left out of the key, extra
    validity check, the step's function, when it runs in a process of its own and the parameters keyed under
    another name."""

    step: str
    version: str
    signature: inspect.Signature
    exclude: tuple[str, ...] = ()
    valid: Callable[[ArtifactRef, dict[str, Any]], bool] | None = None
    fn: Callable[..., tuple[dict, dict]] | None = None
    isolate: Callable[[dict[str, Any]], bool] | None = None
    key_names: Mapping[str, str] = field(default_factory=dict, hash=False)

    def bind(self, parameters: dict[str, Any]) -> dict[str, Any]:
        """All parameters of a call, defaults included."""
        bound = self.signature.bind(**parameters)
        bound.apply_defaults()
        return dict(bound.arguments)

    def output(self, parameters: dict[str, Any]) -> ArtifactRef:
        """The output ref for these parameters."""
        return output_ref(self.step, self.version, self.bind(parameters), self.exclude, self.key_names)

    def done(self, parameters: dict[str, Any]) -> bool:
        """True when the output exists in the store (and passes the validity check)."""
        ref = self.output(parameters)
        return ArtifactStore(ref.store).exists(ref.path) and (self.valid is None or self.valid(ref, parameters))

    def key_record(self, parameters: dict[str, Any]) -> dict[str, Any]:
        """What the output's digest covers, kept in its attributes (``neuralslicer explain`` compares two of them):
        the code version, the parameters in canonical form (inputs by digest) and the store path of each input."""
        kept = keyed(self.bind(parameters), self.exclude, self.key_names)
        return {"version": self.version, "parameters": json.loads(json.dumps(canonical(kept), default=str)),
                "inputs": {k: v.path for k, v in kept.items() if isinstance(v, ArtifactRef)}}

    def write(self, out: ArtifactRef, params: dict[str, Any], made: dict[str, Any]) -> None:
        """Compute the step's output for its (bound) parameters and write it as the group ``out.path``, with its wall
        time, the package versions, what its key covers and the flow run that made it (``made``); nothing when it is
        there."""
        step = self.step

        def make() -> tuple[dict, dict]:
            start = time.perf_counter()
            say(f"{step}: started")
            arrays, attrs = self.fn(out=out, **params)
            record = {**attrs, "step": step, "versions": package_versions(), "key": self.key_record(params),
                      "made": made}

            def done() -> None:
                """The step's wall time, once its arrays are made (streamed ones too)."""
                record["wall_s"] = time.perf_counter() - start
                say(f"{step}: done in {record['wall_s']:.1f} s")

            streams = {k: v for k, v in arrays.items() if isinstance(v, ArrayStream)}
            if streams:   # the store writes them first and reads the attributes after
                arrays = {**arrays, **{k: ArrayStream(v.dtype, then(v.parts, done)) for k, v in streams.items()}}
            else:
                done()
            return arrays, record

        try:
            ArtifactStore(out.store).write_once(out.path, make, done=lambda: self.done(params))
        finally:
            release_freed_memory()   # what the step freed goes back to the kernel (neuralslicer/allocator.py)


def run_step(task_: Any, **parameters: Any) -> State:
    """Run a pipeline task and return its final state: ``Cached`` when the store already held its output (the task
    then does no work), ``Completed`` when it computed it."""
    return task_(**parameters, return_state=True)


def made_by() -> dict[str, str | None]:
    """Which flow run wrote a step's output: ``neuralslicer explain`` tells a result a run made from one it reused."""
    from prefect.runtime import flow_run

    run_id = flow_run.id
    return {"flow_run": str(run_id) if run_id else None}


def then(parts: Iterable[T], finish: Callable[[], None]) -> Iterator[T]:
    """``parts``, then ``finish()`` once they run out."""
    yield from parts
    finish()


def pipeline_task(
    step: str,
    version: str,
    exclude: tuple[str, ...] = (),
    valid: Callable[[ArtifactRef, dict[str, Any]], bool] | None = None,
    isolate: Callable[[dict[str, Any]], bool] | None = None,
    key_names: Mapping[str, str] | None = None,
    **task_options: Any,
) -> Callable[[Callable[..., tuple[dict, dict]]], Any]:
    """Prefect task for one pipeline step.

    The wrapped function receives `out` (its output ref) and the step's parameters and returns
    `(arrays, attrs)`; the wrapper writes them atomically as the group `out.path`, with the wall time.
    `version` is the step's code version: bump it when the step's output for the same inputs changes (it enters the
    cache key, so older artifacts are not reused). Parameters named in `exclude` do not enter the cache key (e.g. file paths whose content is hashed
    in another parameter). The task is idempotent: when its output group exists it does no work and its state is ``Cached`` (the store is
    the cache; Prefect keeps no record of the result). `isolate`: for the
    call's parameters, whether the step runs in a process of its own (``neuralslicer/tasks/isolate.py``).
    `key_names`: parameters keyed under an earlier name (a parameter renamed in the code keeps its stores' keys).
    """

    def decorate(fn: Callable[..., tuple[dict, dict]]) -> Any:
        signature = inspect.signature(fn)
        public = signature.replace(parameters=[p for n, p in signature.parameters.items() if n != "out"])
        pipeline = PipelineStep(step, version, public, exclude, valid, fn, isolate, dict(key_names or {}))

        @functools.wraps(fn)
        def body(*args: Any, **kwargs: Any) -> ArtifactRef | State:
            params = pipeline.bind(public.bind(*args, **kwargs).arguments)
            out = pipeline.output(params)
            if pipeline.done(params):    # the store decides: its group is there, so nothing is computed
                return Completed(name=CACHED, data=out, message=f"{step}: reused {out.path} from the store")
            if pipeline.isolate is not None and pipeline.isolate(params):
                from neuralslicer.tasks.isolate import run_isolated

                run_isolated(fn.__module__, fn.__name__, out, params, made_by(), run_logger())
            else:
                pipeline.write(out, params, made_by())
            return out

        body.__signature__ = public  # type: ignore[attr-defined]
        del body.__wrapped__
        # no Prefect cache record: the store's groups are the one cache (the body returns a Cached state)
        options = {"cache_policy": NO_CACHE, "persist_result": False, "name": step, **task_options}
        pipeline_task_ = task(body, **options)
        pipeline_task_.pipeline = pipeline
        return pipeline_task_

    return decorate
