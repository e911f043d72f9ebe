"""Releasing a print the collision policy will not keep: what later steps read of it is the same before and after,
its waypoints are gone (a clear error where a step would read them), and the disk check names the store."""
from __future__ import annotations

from collections import namedtuple

import numpy as np
import pytest

from neuralslicer.errors import InputError
from neuralslicer.motion.collision import PART, PLATFORM, TRAVEL_PATH
from neuralslicer.motion.output import print_hits
from neuralslicer.storage import ArtifactStore
from neuralslicer.tasks import release as rel
from neuralslicer.tasks.codec import (StoredMotion, read_collision_map, read_machine_program, read_part_collisions,
                                      read_toolpaths)

N = 200_000


def _print(tmp_path, locations: bool = True):
    """A store with one print's toolpaths and motion groups (random waypoints, 300 collisions of each kind; without
    ``locations``, a print from before they were stored)."""
    rng = np.random.default_rng(7)
    store = ArtifactStore(str(tmp_path / "store.zarr"))
    xyz, axis = rng.normal(size=(N, 3)) * 50, np.tile([0.0, 0.0, 1.0], (N, 1))
    columns = {"xyz": xyz, "axis": axis, "layer": rng.integers(0, 50, N).astype(np.int32),
               "path": np.arange(N, dtype=np.int64) // 100, "thickness": np.full(N, 0.3), "width": np.full(N, 0.5),
               "extrude": rng.random(N) > 0.1}
    indices = np.sort(rng.choice(N, 900, replace=False))
    kind = np.repeat(np.array([PART, PLATFORM, TRAVEL_PATH], np.int8), 300)[rng.permutation(900)]
    store.write("m/toolpaths/t0", columns, {"n": N})
    motion = {**{f"toolpaths/{k}": v for k, v in columns.items()},
              "program/machine": rng.normal(size=(N, 5)), "program/time_s": rng.random(N),
              "collisions/indices": indices, "collisions/kind": kind,
              **({"collisions/locations": xyz[indices] + 0.1} if locations else {})}
    store.write("m/motion/m0", motion, {"metrics": {"n_collisions": 900, "n_platform_collisions": 300},
                                         "toolpaths": {}, "program": {}})
    return store, store.ref("m/toolpaths/t0", "t0"), store.ref("m/motion/m0", "m0")


def test_a_released_print_answers_as_before_without_its_waypoints(tmp_path):
    store, toolpaths, motion = _print(tmp_path)
    before = (read_part_collisions(motion), read_collision_map(motion), print_hits(StoredMotion(motion)))
    size = rel.disk_bytes(motion) + rel.disk_bytes(toolpaths)
    freed = rel.release_toolpaths(toolpaths) + rel.release_motion(motion)
    assert rel.released(motion) and rel.released(toolpaths) and freed > 0.9 * size
    assert rel.release_motion(motion) == 0 and rel.release_toolpaths(toolpaths) == 0   # once only
    hits, witnesses = read_part_collisions(motion)
    np.testing.assert_array_equal(hits, before[0][0])
    np.testing.assert_array_equal(witnesses, before[0][1])
    cmap = read_collision_map(motion)
    for name in ("clear", "hit", "bounds"):
        np.testing.assert_array_equal(getattr(cmap, name), getattr(before[1], name))
    assert (cmap.n_waypoints, cmap.n_hit) == (before[1].n_waypoints, before[1].n_hit) == (N, 900)
    assert print_hits(StoredMotion(motion)) == before[2] == (900, 600, 300)
    assert store.attrs(motion.path)["metrics"]["n_collisions"] == 900
    # what is left: the collisions and the map; the sizes it had, for the disk check of the next print
    assert sorted(store.array_names(motion.path)) == sorted(
        ["collisions/indices", "collisions/kind", "collisions/locations", rel.HIT_XYZ, rel.MAP_CLEAR, rel.MAP_HIT,
         rel.MAP_BOUNDS])
    assert rel.group_bytes(motion)[0] >= rel.disk_bytes(motion) * 10 and rel.group_bytes(toolpaths)[1] > N * 50
    # a step that would read its waypoints says so in one line
    for read in (read_toolpaths, lambda r: StoredMotion(r).toolpaths, read_machine_program):
        with pytest.raises(InputError, match="released"):
            read(toolpaths if read is read_toolpaths else motion)
    # restoring removes what is left, so the steps make the groups again
    assert rel.forget_released([toolpaths, motion]) and not store.exists(motion.path)
    assert not rel.forget_released([toolpaths, motion])


def test_the_next_print_needs_room_on_the_stores_disk(tmp_path, monkeypatch):
    store, toolpaths, motion = _print(tmp_path)
    need = rel.disk_bytes(toolpaths) + rel.disk_bytes(motion) + store.nbytes(toolpaths.path) + rel.ROOM_SLACK
    usage = namedtuple("usage", "total used free")
    monkeypatch.setattr(rel.shutil, "disk_usage", lambda path: usage(10 * need, 9 * need, need + 1))
    rel.check_room([toolpaths, motion], unpacked=toolpaths)
    monkeypatch.setattr(rel.shutil, "disk_usage", lambda path: usage(10 * need, 9 * need, need - 1))
    with pytest.raises(InputError) as exc:
        rel.check_room([toolpaths, motion], unpacked=toolpaths)
    assert exc.value.where == store.root and "free on the store's disk" in exc.value.message
    # a released print asks for the room it took before it was released
    rel.release_toolpaths(toolpaths)
    rel.release_motion(motion)
    with pytest.raises(InputError):
        rel.check_room([toolpaths, motion], unpacked=toolpaths)


def test_a_print_from_before_stored_locations_is_released_too(tmp_path):
    _, toolpaths, motion = _print(tmp_path, locations=False)
    hits, witnesses = read_part_collisions(motion)
    rel.release_motion(motion)
    again = read_part_collisions(motion)
    np.testing.assert_array_equal(again[0], hits)
    assert len(hits) == 600 and np.isnan(witnesses).all() and np.isnan(again[1]).all()
