"""One Prefect task per step of the table (``neuralslicer/run/step_table.py``), made from its entry: each input read from
the store by the kind of its group (``tasks/codec.py: decode``), the step's core function called, its output written
as the group the task is named after."""
from __future__ import annotations

import contextlib
import inspect
from collections.abc import Iterable, Iterator
from typing import Any

import numpy as np

from neuralslicer.run.step_table import STEPS, Record, Step, StepContext, Update
from neuralslicer.storage import ArrayStream, ArtifactRef, ArtifactStore
from neuralslicer.storage.content_cache import ContentCache, cache_root
from neuralslicer.tasks.checkpoints import StoreCheckpoints
from neuralslicer.tasks.codec import decode
from neuralslicer.tasks.common import pipeline_task
from neuralslicer.tasks.isolate import large_print
from neuralslicer.tasks.progress import Progress, run_logger, say


@contextlib.contextmanager
def _bar(description: str, total: int) -> Iterator[Update]:
    """A progress bar on the terminal and in the run's log (``tasks/progress.py``)."""
    with Progress(description, total) as bar:
        yield bar.update


def step_context(out: ArtifactRef, s: Step) -> StepContext:
    """What a step's core call gets in a task: the run's log, progress bars, and the checkpoints of a resumable step
    beside its output (``<model>/checkpoints/<digest>``); its inputs are read for it alone; its scratch folder is the
    store's own (on the store's disk, not in a temporary folder that may be memory)."""
    checkpoints = (StoreCheckpoints(ArtifactStore(out.store), f"{out.model}/checkpoints/{out.digest}")
                   if s.resumable else None)
    return StepContext(log=run_logger(), progress=_bar, say=say, checkpoints=checkpoints, owns_inputs=True,
                       scratch=ArtifactStore(out.store, create=False).scratch())


def _read(value: Any) -> Any:
    """A parameter as the core call takes it: a stored artifact read (a list of them each), anything else as it is."""
    if isinstance(value, ArtifactRef):
        return decode(value)
    if isinstance(value, list) and value and all(isinstance(v, ArtifactRef) for v in value):
        return [decode(v) for v in value]
    return value


def _storable(arrays: dict[str, Any]) -> dict[str, Any]:
    """The arrays as the store writes them: one given as an iterable of byte chunks (the G-code) streamed."""
    def one(v: Any) -> Any:
        if isinstance(v, (np.ndarray, ArrayStream, list, tuple, str, bytes)) or not isinstance(v, Iterable):
            return v
        return ArrayStream(np.dtype(np.uint8), (np.frombuffer(chunk, np.uint8) for chunk in v))

    return {k: one(v) for k, v in arrays.items()}


def _from_content_cache(s: Step, out: ArtifactRef) -> Record | None:
    """A content-cached step's output of these inputs from the machine's cache (None when absent or not intact)."""
    cache = ContentCache(cache_root())
    hit = cache.load(s.name, out.digest)
    if hit is None or not s.content_cached(hit):
        return None
    say(f"{s.name}: the {s.name} of these inputs from the {s.name} cache ({cache.root})")
    arrays, attrs = hit
    return arrays, {**{k: v for k, v in attrs.items() if k != "cache_key"}, f"from_{s.name}_cache": True}


def _body(s: Step) -> Any:
    """The task body of a step: read the inputs, call the core function, return what to store."""

    def body(out: ArtifactRef, store: str, **parameters: Any) -> Record:
        if s.content_cached is not None:
            hit = _from_content_cache(s, out)
            if hit is not None:
                return hit
        kept = {k: _read(v) for k, v in parameters.items() if k not in s.key}
        arrays, attrs = s.encode(s.compute(**kept, ctx=step_context(out, s)))
        if s.content_cached is not None:   # the same inputs reuse it in any store on this machine
            ContentCache(cache_root()).save(s.name, out.digest, arrays, attrs)
        return _storable(arrays), attrs

    compute = inspect.signature(s.compute)
    plain = inspect.Parameter.POSITIONAL_OR_KEYWORD
    head = [inspect.Parameter(n, plain) for n in ("out", "store", *s.key)]
    params = [p.replace(kind=plain, annotation=inspect.Parameter.empty)
              for n, p in compute.parameters.items() if n != "ctx"]
    body.__signature__ = inspect.Signature(head + params)  # type: ignore[attr-defined]
    body.__name__ = body.__qualname__ = f"{s.name}_task"    # Prefect's task key; how a step's own process finds it
    body.__module__ = __name__
    body.__doc__ = (s.compute.__doc__ or s.name).split("\n")[0]
    return body


def step_task(s: Step) -> Any:
    """The Prefect task of a step of the table."""
    options = {} if s.retries is None else {"retries": s.retries}
    return pipeline_task(s.name, s.version, exclude=s.exclude, isolate=large_print(*s.large) if s.large else None,
                         key_names=s.key_names, **options)(_body(s))


#: the task of every step, by the step's name
TASKS: dict[str, Any] = {s.name: step_task(s) for s in STEPS}


def __getattr__(name: str) -> Any:
    """``<step>_task``: the task of a step (``from neuralslicer.tasks.steps import layers_task``)."""
    if name.endswith("_task") and name.removesuffix("_task") in TASKS:
        return TASKS[name.removesuffix("_task")]
    raise AttributeError(f"module {__name__!r} has no attribute {name!r}")
