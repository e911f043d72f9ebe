"""The artifact store: one zarr v3 store per workspace, a group per model and step, written atomically."""
from __future__ import annotations

import contextlib
import json
import os
import shutil
import socket
import threading
import time
import uuid
import warnings
from collections.abc import Callable, Iterable, Iterator, Mapping
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
import zarr

from neuralslicer.fileio import to_json
from neuralslicer.storage.layout import CHUNK_BYTES, chunk_shape, compressor, group_dimensions, group_kind

COMPLETE = "_complete"
STAGING = "_staging"


def default_store(out_dir: str | Path) -> str:
    """Where a run keeps its artifacts when no store is given: ``OUT/store.zarr``."""
    return str(Path(out_dir) / "store.zarr")


@dataclass(frozen=True)
class ArtifactRef:
    """A reference to one complete group of the store: what tasks pass instead of arrays."""

    store: str
    path: str
    digest: str

    @property
    def model(self) -> str:
        """The model name (first component of the group path)."""
        return self.path.split("/", 1)[0]


def groups_used(refs: Mapping[str, ArtifactRef | None]) -> dict[str, str]:
    """The group path of each step a run used (the steps it skipped left out): what run.json can list so that a
    reader opens the run's arrays (``xarray.open_zarr(store, group=path)``) without searching the store."""
    return {step: ref.path for step, ref in refs.items() if ref is not None}


@dataclass(frozen=True)
class ArrayStream:
    """A 1-D array written as it is produced: ``parts`` concatenated, each part written as soon as a chunk fills (a
    G-code program of any size, never whole in memory). The group's attributes are taken after its arrays are
    written, so the producer may complete them (its wall time) when its parts run out."""

    dtype: np.dtype
    parts: Iterable[np.ndarray]

    def write_into(self, group: zarr.Group, name: str, dimension: str) -> None:
        """Create the array ``name`` in ``group`` and append the parts, whole chunks at a time."""
        dtype = np.dtype(self.dtype)
        rows = max(1, CHUNK_BYTES // dtype.itemsize)
        array = group.create_array(name, shape=(0,), dtype=dtype, dimension_names=(dimension,), chunks=(rows,),
                                   compressors=compressor(dtype), overwrite=True)
        pending: list[np.ndarray] = []
        n_pending = 0
        for part in self.parts:
            pending.append(np.asarray(part, dtype).ravel())
            n_pending += len(pending[-1])
            if n_pending >= rows:
                joined = np.concatenate(pending)
                full = len(joined) - len(joined) % rows
                array.append(joined[:full])
                pending, n_pending = [joined[full:]], len(joined) - full
        if n_pending:
            array.append(np.concatenate(pending))


class ArtifactStore:
    """A zarr v3 store on a local path or an fsspec URL; groups become visible only when complete."""

    def __init__(self, root: str | Path, create: bool = True) -> None:
        """Open the store at a local path or fsspec URL, creating it when ``create`` (readers pass False: a
        reader never leaves an empty store behind, and a missing one is a FileNotFoundError naming it)."""
        root = str(root)
        self.is_local = "://" not in root or root.startswith("file://")
        self.root = str(Path(root.removeprefix("file://")).resolve()) if self.is_local else root.rstrip("/")
        if not create:
            try:
                zarr.open_group(self.root, mode="r")
            except (FileNotFoundError, zarr.errors.GroupNotFoundError) as exc:
                raise FileNotFoundError(f"{self.root}: no artifact store there") from exc
            return
        if self.is_local:
            Path(self.root).mkdir(parents=True, exist_ok=True)
        self._ensure_group("")

    def scratch(self) -> Path | None:
        """A folder on the store's own disk for a step's temporary files (its staging folder), None for a remote store."""
        if not self.is_local:
            return None
        folder = Path(self.root, STAGING)
        folder.mkdir(parents=True, exist_ok=True)
        return folder

    def _ensure_group(self, path: str) -> None:
        """Create a group unless it exists, safe against another process creating it at the same moment
        (zarr's mode "a" checks, then creates: the loser of that race sees ContainsGroupError)."""
        try:
            zarr.open_group(self.root, mode="a", path=path)
        except zarr.errors.ContainsGroupError:
            zarr.open_group(self.root, mode="r+", path=path)

    def _group(self, path: str, mode: str = "r") -> zarr.Group:
        """Open a group of the store."""
        return zarr.open_group(self.root, mode=mode, path=path)

    def ref(self, path: str, digest: str) -> ArtifactRef:
        """An ArtifactRef to a group of this store."""
        return ArtifactRef(store=self.root, path=path, digest=digest)

    def exists(self, path: str) -> bool:
        """True when the group exists and was completely written."""
        try:
            return bool(self._group(path).attrs.get(COMPLETE, False))
        except (FileNotFoundError, KeyError, zarr.errors.GroupNotFoundError, ValueError):
            return False

    def write(self, path: str, arrays: Mapping[str, np.ndarray | ArrayStream], attrs: Mapping[str, Any] | None = None
              ) -> None:
        """Write a group atomically: staged and renamed into place locally, marked complete last.

        Two processes that may write the same path hold `lock(path)` around the write.
        """
        attrs = {} if attrs is None else attrs
        if not self.is_local:
            self._write_group(path, arrays, attrs, group_kind(path))
            return
        staging = f"{STAGING}/{uuid.uuid4().hex}"
        self._write_group(staging, arrays, attrs, group_kind(path))
        src, dst = Path(self.root, staging), Path(self.root, path)
        if dst.exists():  # replacing: readers see the old or the new group, never a mix
            trash = Path(self.root, STAGING, f"old-{uuid.uuid4().hex}")
            os.replace(dst, trash)
            os.replace(src, dst)
            shutil.rmtree(trash, ignore_errors=True)
        else:
            if "/" in path:
                self._ensure_group(path.rsplit("/", 1)[0])
            os.replace(src, dst)

    def _write_group(self, path: str, arrays: Mapping[str, np.ndarray | ArrayStream], attrs: Mapping[str, Any],
                     kind: str) -> None:
        """Write arrays (named dimensions of a group of this ``kind``, chosen chunks and codecs; streams as they come)
        then attributes (read only now), then the group's consolidated metadata, the completion flag last."""
        group = zarr.open_group(self.root, mode="w", path=path)
        streams = {name: value for name, value in arrays.items() if isinstance(value, ArrayStream)}
        data = {name: np.ascontiguousarray(value) for name, value in arrays.items() if name not in streams}
        dims = group_dimensions(kind, {**{name: d.shape for name, d in data.items()}, **{name: (0,) for name in streams}})
        for name, stream in streams.items():
            stream.write_into(group, name, dims[name][0])
        for name, d in data.items():
            if d.dtype == object:
                raise TypeError(f"array {name!r} has dtype object")
            group.create_array(name, data=d, dimension_names=dims[name], chunks=chunk_shape(d.shape, d.dtype.itemsize),
                               compressors=compressor(d.dtype), overwrite=True)
        group.attrs.update({**to_json(dict(attrs)), "written_at": time.strftime("%Y-%m-%dT%H:%M:%SZ", time.gmtime()),
                            COMPLETE: False})
        with warnings.catch_warnings():  # zarr: consolidated metadata is not yet in the v3 specification
            warnings.simplefilter("ignore", zarr.errors.ZarrUserWarning)
            group = zarr.consolidate_metadata(self.root, path=path)
        group.attrs[COMPLETE] = True

    def read(self, path: str, names: list[str] | None = None) -> tuple[dict[str, np.ndarray], dict[str, Any]]:
        """All (or the named) arrays of a complete group, and its attributes."""
        if not self.exists(path):
            raise FileNotFoundError(f"{self.root}/{path}: no complete artifact there")
        group = self._group(path)
        keys = self.array_names(path) if names is None else names
        return {k: np.asarray(group[k][...]) for k in keys}, dict(group.attrs)

    def array_names(self, path: str) -> list[str]:
        """Names of the arrays of a complete group (nested ones as ``a/b``)."""
        if not self.exists(path):
            raise FileNotFoundError(f"{self.root}/{path}: no complete artifact there")
        return [k for k, v in self._group(path).members(max_depth=None) if isinstance(v, zarr.Array)]

    def shape(self, path: str, name: str) -> tuple[int, ...]:
        """The shape of an array of a complete group, read from its metadata."""
        if not self.exists(path):
            raise FileNotFoundError(f"{self.root}/{path}: no complete artifact there")
        return tuple(self._group(path)[name].shape)

    def nbytes(self, path: str) -> int:
        """Bytes the arrays of a complete group take uncompressed, read from their metadata."""
        if not self.exists(path):
            raise FileNotFoundError(f"{self.root}/{path}: no complete artifact there")
        group = self._group(path)
        return sum(int(np.prod(a.shape)) * a.dtype.itemsize for _, a in group.members(max_depth=None)
                   if isinstance(a, zarr.Array))

    def read_slices(self, path: str, name: str, length: int) -> Iterator[np.ndarray]:
        """An array of a complete group, ``length`` items along its first axis at a time (a large array read in
        bounded memory)."""
        if not self.exists(path):
            raise FileNotFoundError(f"{self.root}/{path}: no complete artifact there")
        array = self._group(path)[name]
        for start in range(0, array.shape[0], length):
            yield np.asarray(array[start:start + length])

    def attrs(self, path: str) -> dict[str, Any]:
        """Attributes of a complete group."""
        if not self.exists(path):
            raise FileNotFoundError(f"{self.root}/{path}: no complete artifact there")
        return dict(self._group(path).attrs)

    def children(self, path: str) -> list[str]:
        """Names of the complete child groups of a group (empty when it does not exist)."""
        try:
            group = self._group(path)
        except (FileNotFoundError, KeyError, zarr.errors.GroupNotFoundError, ValueError):
            return []
        return sorted(name for name, _ in group.groups() if self.exists(f"{path}/{name}"))

    def remove(self, path: str) -> None:
        """Delete a group (used to prune old checkpoints)."""
        if self.is_local:
            shutil.rmtree(Path(self.root, path), ignore_errors=True)
        else:
            with contextlib.suppress(Exception):
                del zarr.open_group(self.root, mode="a")[path]

    def write_blob(self, path: str, blob: bytes, attrs: Mapping[str, Any] | None = None) -> None:
        """Store opaque bytes (e.g. a torch checkpoint) as a uint8 array in a group."""
        self.write(path, {"blob": np.frombuffer(blob, dtype=np.uint8)}, attrs)

    def read_blob(self, path: str) -> bytes:
        """Bytes stored by write_blob."""
        arrays, _ = self.read(path, ["blob"])
        return arrays["blob"].tobytes()

    def write_once(self, path: str, make: Callable[[], tuple[Mapping[str, np.ndarray], Mapping[str, Any]]],
                   done: Callable[[], bool] | None = None) -> bool:
        """Write the group ``make()`` returns at ``path`` unless ``done()`` (default: the group exists),
        checked again under the path's lock; True if this call wrote it."""
        done = done or (lambda: self.exists(path))
        if done():
            return False
        with self.lock(path):
            if done():
                return False
            arrays, attrs = make()
            self.write(path, arrays, attrs)
        return True

    @contextlib.contextmanager
    def lock(self, path: str, timeout_s: float | None = None) -> Iterator[None]:
        """An exclusive lock on one artifact path across processes and hosts (O_EXCL lock file naming
        host and PID, its time renewed every LOCK_HEARTBEAT_S while held; no-op off local disk).

        A lock is taken over only when it is abandoned: its holder on this host is gone, or its
        heartbeat stopped for LOCK_STALE_S (a holder on another host, or a frozen one). A long step
        keeps its lock however long it runs. ``timeout_s``: give up waiting with an error.
        """
        if not self.is_local:
            yield
            return
        lock_dir = Path(self.root, STAGING, "locks")
        lock_dir.mkdir(parents=True, exist_ok=True)
        lock_file = lock_dir / (path.replace("/", "__") + ".lock")
        start = time.monotonic()
        while True:
            try:
                fd = os.open(lock_file, os.O_CREAT | os.O_EXCL | os.O_WRONLY)
                os.write(fd, json.dumps({"host": socket.gethostname(), "pid": os.getpid()}).encode())
                os.close(fd)
                break
            except FileExistsError:
                if _stale(lock_file):
                    with contextlib.suppress(FileNotFoundError):
                        lock_file.unlink()
                    continue
                if timeout_s is not None and time.monotonic() - start > timeout_s:
                    raise TimeoutError(f"{lock_file}: held by {_holder(lock_file)} for more than {timeout_s:g} s")
                time.sleep(0.1)
        stop = threading.Event()
        beat = threading.Thread(target=_heartbeat, args=(lock_file, stop), daemon=True)
        beat.start()
        try:
            yield
        finally:
            stop.set()
            beat.join()
            with contextlib.suppress(FileNotFoundError):
                lock_file.unlink()


#: a held lock's file time is renewed this often (s) ...
LOCK_HEARTBEAT_S = 10.0
#: ... and a lock whose time is older than this (s) is abandoned
LOCK_STALE_S = 120.0


def _heartbeat(lock_file: Path, stop: threading.Event) -> None:
    """Renew the lock file's time until stop is set."""
    while not stop.wait(LOCK_HEARTBEAT_S):
        with contextlib.suppress(FileNotFoundError):
            os.utime(lock_file)


def _holder(lock_file: Path) -> dict:
    """Host and PID written in a lock file ({} when unreadable; a bare PID from older versions)."""
    try:
        text = lock_file.read_text()
    except FileNotFoundError:
        return {}
    try:
        data = json.loads(text or "{}")
    except ValueError:
        return {}
    return data if isinstance(data, dict) else {"host": socket.gethostname(), "pid": int(data)}


def _stale(lock_file: Path) -> bool:
    """True when a lock is abandoned: its holder on this host no longer exists, or its heartbeat stopped."""
    try:
        age = time.time() - lock_file.stat().st_mtime
    except FileNotFoundError:
        return False
    if age > LOCK_STALE_S:
        return True
    holder = _holder(lock_file)
    pid = int(holder.get("pid", 0) or 0)
    if holder.get("host") != socket.gethostname() or pid <= 0:
        return False
    try:
        os.kill(pid, 0)
    except ProcessLookupError:
        return True
    except PermissionError:
        return False
    return False
