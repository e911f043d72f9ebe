"""Prints the collision policy did not keep, released from the store: their toolpaths' and motion's per-waypoint
arrays dropped once a later print replaced them, what later steps read of them kept (the metrics, where the head hit,
the collision map the report draws); and the check that the store's disk has room for the next print."""
from __future__ import annotations

import os
import shutil
import time
from pathlib import Path

import numpy as np

from neuralslicer.errors import InputError
from neuralslicer.motion.collision import CollisionMap
from neuralslicer.storage import ArtifactRef, ArtifactStore

#: the attribute that marks a released group: what it held, when it was released
RELEASED = "released"
#: the arrays a released motion group keeps (``collisions/*`` as written, plus the colliding waypoints and the map)
HIT_XYZ, MAP_CLEAR, MAP_HIT, MAP_BOUNDS = "collisions/xyz", "collision_map/clear", "collision_map/hit", "collision_map/bounds"
#: the room asked for beyond the estimate (bytes): the store's own metadata, logs, a figure
ROOM_SLACK = 256 << 20


def released(ref: ArtifactRef) -> bool:
    """Whether a stored toolpaths or motion group was released (its per-waypoint arrays dropped)."""
    store = ArtifactStore(ref.store, create=False)
    return store.exists(ref.path) and RELEASED in store.attrs(ref.path)


def disk_bytes(ref: ArtifactRef) -> int:
    """Bytes a group of a local store takes on its disk now (0 for a remote store or a missing group)."""
    store = ArtifactStore(ref.store, create=False)
    root = Path(store.root, ref.path)
    if not store.is_local or not root.is_dir():
        return 0
    return sum(Path(d, f).stat().st_size for d, _, files in os.walk(root) for f in files)


def group_bytes(ref: ArtifactRef) -> tuple[int, int]:
    """(bytes on disk, bytes of its arrays uncompressed) of a stored group, as it was before it was released."""
    store = ArtifactStore(ref.store, create=False)
    attrs = store.attrs(ref.path)
    if RELEASED in attrs:
        return int(attrs[RELEASED]["bytes"]), int(attrs[RELEASED]["unpacked"])
    return disk_bytes(ref), store.nbytes(ref.path)


def _release(store: ArtifactStore, ref: ArtifactRef, arrays: dict[str, np.ndarray], extra: dict) -> int:
    """Replace a group by ``arrays`` and its attributes marked released (with ``extra``); bytes freed."""
    (before, unpacked), attrs = group_bytes(ref), store.attrs(ref.path)
    held = store.array_names(ref.path)
    attrs[RELEASED] = {"at": time.strftime("%Y-%m-%dT%H:%M:%SZ", time.gmtime()), "bytes": before,
                       "unpacked": unpacked, "dropped": sorted(set(held) - set(arrays)), **extra}
    store.write(ref.path, arrays, attrs)
    return max(0, before - disk_bytes(ref))


def release_motion(ref: ArtifactRef) -> int:
    """Release a stored print (the motion step's group): keep its attributes, its collisions, the waypoints that
    collide and its collision map, drop the rest; bytes freed (nothing when it was released already)."""
    store = ArtifactStore(ref.store, create=False)
    if released(ref):
        return 0
    names = ["toolpaths/xyz", "collisions/indices", "collisions/kind"]
    have = set(store.array_names(ref.path))
    arrays, _ = store.read(ref.path, names + (["collisions/locations"] if "collisions/locations" in have else []))
    xyz = arrays.pop("toolpaths/xyz")
    indices = np.asarray(arrays["collisions/indices"], np.int64)
    cmap = CollisionMap.of_indices(xyz, indices)
    kept = {**arrays, HIT_XYZ: xyz[indices], MAP_CLEAR: cmap.clear, MAP_HIT: cmap.hit, MAP_BOUNDS: cmap.bounds}
    del xyz
    return _release(store, ref, kept, {"n_waypoints": cmap.n_waypoints, "n_hit": cmap.n_hit})


def release_toolpaths(ref: ArtifactRef) -> int:
    """Release the toolpaths step's group of a print: its attributes alone stay; bytes freed."""
    store = ArtifactStore(ref.store, create=False)
    if released(ref):
        return 0
    return _release(store, ref, {}, {"n_waypoints": int(store.shape(ref.path, "xyz")[0])})


def released_map(ref: ArtifactRef) -> CollisionMap:
    """The collision map a released print kept."""
    arrays, attrs = ArtifactStore(ref.store, create=False).read(ref.path, [MAP_CLEAR, MAP_HIT, MAP_BOUNDS])
    r = attrs[RELEASED]
    return CollisionMap(arrays[MAP_CLEAR], arrays[MAP_HIT], int(r["n_waypoints"]), int(r["n_hit"]), arrays[MAP_BOUNDS])


def forget_released(refs: list[ArtifactRef]) -> bool:
    """Remove those of these groups that were released, so that their steps make them again; whether any was."""
    gone = [r for r in refs if released(r)]
    for r in gone:
        ArtifactStore(r.store, create=False).remove(r.path)
    return bool(gone)


def whole(ref: ArtifactRef) -> ArtifactRef:
    """``ref``, checked not to be released (a clear error where a step would read a released print's waypoints)."""
    if released(ref):
        raise InputError(f"{ref.store}/{ref.path}", "this print was released (it was not the one kept: only its "
                         "metrics and collisions stay); run the slice again to make it whole, or pass "
                         "--keep-attempts to keep every print")
    return ref


def check_room(refs: list[ArtifactRef], unpacked: ArtifactRef | None = None) -> None:
    """Raise a one-line error when the store's disk has less room than another print like these groups takes
    (their bytes on disk, plus ``unpacked``'s arrays uncompressed: the toolpaths the motion step parks beside the
    store while it plans), as they were before any was released."""
    if not refs or not ArtifactStore(refs[0].store, create=False).is_local:
        return
    root = ArtifactStore(refs[0].store, create=False).root
    need = sum(group_bytes(r)[0] for r in refs) + (group_bytes(unpacked)[1] if unpacked is not None else 0) + ROOM_SLACK
    free = shutil.disk_usage(root).free
    if free < need:
        raise InputError(root, f"{free / 1e9:.1f} GB free on the store's disk, and the next print of the collision "
                         f"resolution needs about {need / 1e9:.1f} GB (as much as the last one's layers, toolpaths "
                         "and motion); free some space or put the store on a larger disk (--store), then run the same "
                         "command again: it resumes")
